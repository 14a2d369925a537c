"""mpnode: message-passing neural ODEs (MP-NODE) for networked dynamical systems.

Importing this package is cheap: it loads numpy only.  h5py, scipy, click and the
numba kernels are imported (and compiled, or loaded from cache) on first use.  The
packages, one layer each (docs/architecture.md): base, engine, data, model, evaluation,
training, runs, plot, control and export.
"""
__version__ = "0.1.0"

from mpnode.base.errors import InputError, NumericalError  # noqa: F401
from mpnode.base.graph import Graph, block_diagonal  # noqa: F401

#: public names, loaded on first use from the module that defines them
_LAZY = {
    "Model": "mpnode.model.model",
    "Ensemble": "mpnode.model.ensemble",
    "Simulator": "mpnode.model.simulator",
    "fit_network": "mpnode.evaluation.network_fit",
    "loss_and_grad": "mpnode.training.losses",
    "Trajectories": "mpnode.data.trajectories",
    "read_trajectories": "mpnode.data.files",
    "write_trajectories": "mpnode.data.files",
    "validate_trajectories": "mpnode.data.rules",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mpnode' has no attribute {name!r}")
