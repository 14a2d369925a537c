"""`mpnode export MODEL -o OUT.py`: a Python module that rolls the model out with NumPy alone.

The file is `standalone`'s docstring, the source of the NumPy path's model
(`mpnode.engine.numpy_path.NUMPY_ONLY`: the field and RK4 the library itself runs without
numba) and of `standalone`'s functions, then the model on its graph (`arrays.model_arrays`,
arrays as base64 bytes: exact, any dtype; the default node attributes and edge weights among
them) and ``rollout``.
"""
import base64
import inspect
import os

import numpy as np

from mpnode.base.atomic import atomic_path
from mpnode.engine.numpy_path import NUMPY_ONLY

from . import standalone
from .arrays import model_arrays

#: what the exported file imports: all that the functions it holds use
_HEADER = '"""{doc}"""\nimport base64\n\nimport numpy as np\n'

#: the functions the exported file holds, by their source
FUNCTIONS = NUMPY_ONLY + (standalone.decode, standalone.controls, standalone.weighted, standalone.run)

_ROLLOUT = '''MODEL = decode({model})


def rollout(x0, steps=None, u=None, node_attrs=None, edge_weights=None):
    """x (B, T+1, N, dx) from x0 (B, N, dx) under controls u (B, T, N, du) (None without
    controls; steps defaults to u's length), a model's node attributes node_attrs (N, dp) or
    (B, N, dp) and edge weights edge_weights (E,) (None: MODEL's): see the module docstring."""
    return run(MODEL, x0, steps, u, node_attrs, edge_weights)
'''


def _encoded(value):
    """``value`` as a literal: an array as its base64 bytes, a dict entry by entry."""
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        a = a.astype(a.dtype.newbyteorder("<"))
        return {"base64": base64.b64encode(a.tobytes()).decode("ascii"), "dtype": a.dtype.str, "shape": list(a.shape)}
    if isinstance(value, dict):
        return {k: _encoded(v) for k, v in value.items()}
    return value


def numpy_module_source(model, graph):
    """The text of the module for ``model`` on ``graph`` (an mpnode Graph)."""
    functions = "\n\n".join(inspect.getsource(f) for f in FUNCTIONS)
    model_literal = repr(_encoded(model_arrays(model, graph)))
    return "\n\n".join([_HEADER.format(doc=standalone.__doc__), functions, _ROLLOUT.format(model=model_literal)])


def write_numpy_module(model, graph, path):
    """Write the module atomically to ``path``."""
    text = numpy_module_source(model, graph)
    with atomic_path(os.fspath(path)) as tmp:
        with open(tmp, "w") as f:
            f.write(text)
