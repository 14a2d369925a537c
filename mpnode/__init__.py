"""mpnode: message-passing neural ODEs (MP-NODE) for networked dynamical systems.

Importing this package is cheap: it loads numpy only.  h5py, scipy, click and the
numba kernels are imported (and compiled, or loaded from cache) on first use.
"""
__version__ = "0.1.0"

from .errors import InputError, NumericalError  # noqa: F401
from .graph import Graph, block_diagonal  # noqa: F401

_LAZY = {
    "Model": "model",
    "Simulator": "simulator",
    "loss_and_grad": "model",
    "Trajectories": "data",
    "read_trajectories": "data",
    "write_trajectories": "data",
    "validate_trajectories": "data",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'mpnode' has no attribute {name!r}")
