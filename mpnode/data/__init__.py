"""Trajectory data: the `Trajectories` object, its rules and HDF5 file format
(docs/trajectory-format.md: version 1, regular and complete; version 2, data as they come;
version 3, weighted edges and node attributes),
`.npz` import (`mpnode convert`) and the summary `mpnode inspect` shows.

Owns: `trajectories`, `rules`, `files`, `npz`, `summary`.  May import: mpnode.base.
"""
from .files import FORMAT_VERSION, read_trajectories, write_trajectories  # noqa: F401
from .npz import read_npz  # noqa: F401
from .rules import validate_trajectories  # noqa: F401
from .summary import summarize  # noqa: F401
from .trajectories import Trajectories  # noqa: F401
