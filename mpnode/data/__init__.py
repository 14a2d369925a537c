"""Trajectory data: the `Trajectories` object, its HDF5 file format (docs/trajectory-format.md)
with one validator behind reader and writer, and `.npz` import (`mpnode convert`).

Owns: `trajectories`, `npz`.  May import: mpnode.base.
"""
from .npz import read_npz  # noqa: F401
from .trajectories import (  # noqa: F401
                           FORMAT_VERSION,
                           Trajectories,
                           read_trajectories,
                           summarize,
                           validate_trajectories,
                           write_trajectories,
)
