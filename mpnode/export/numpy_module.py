"""`mpnode export MODEL -o OUT.py`: a Python module that rolls the model out with NumPy alone.

The file is the source of `standalone` (the rollout in NumPy) followed by the model on its
graph (`arrays.model_arrays`, arrays as base64 bytes: exact, any dtype) and ``rollout``.
"""
import base64
import inspect
import os

import numpy as np

from mpnode.base.atomic import atomic_path

from . import standalone
from .arrays import model_arrays

_ROLLOUT = '''

MODEL = decode({model})


def rollout(x0, steps=None, u=None):
    """x (B, T+1, N, dx) from x0 (B, N, dx) under controls u (B, T, N, du) (None without
    controls; steps defaults to u's length): see the module docstring."""
    return run(MODEL, x0, steps, u)
'''


def _encoded(value):
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        a = a.astype(a.dtype.newbyteorder("<"))
        return {"base64": base64.b64encode(a.tobytes()).decode("ascii"), "dtype": a.dtype.str, "shape": list(a.shape)}
    return value


def numpy_module_source(model, graph):
    """The text of the module for ``model`` on ``graph`` (an mpnode Graph)."""
    p = {k: _encoded(v) for k, v in model_arrays(model, graph).items()}
    return inspect.getsource(standalone) + _ROLLOUT.format(model=repr(p))


def write_numpy_module(model, graph, path):
    """Write the module atomically to ``path``."""
    text = numpy_module_source(model, graph)
    with atomic_path(os.fspath(path)) as tmp:
        with open(tmp, "w") as f:
            f.write(text)
