"""Trajectory files (../shared/spec/trajectory-format.md, version 1).

`Trajectories` is the in-memory form every part of mpnode passes around; the
reader validates every rule of the format and raises `InputError` naming the
file and the field; the writer validates too and writes atomically.
"""
from dataclasses import dataclass, field

import numpy as np

from .graph import Graph


@dataclass
class Trajectories:
    """A set of trajectories of one homogeneous networked system.

    x : ndarray, shape (B, T+1, N, dx) -- node states, x[b, 0] the initial state
    u : ndarray, shape (B, T, N, du), or None when du = 0 -- controls held over t -> t+1
    graphs : list of Graph, each on N nodes
    graph_index : ndarray, shape (B,), int -- graph of each trajectory
    dt : float -- time between saved states
    system : str -- the generating system, e.g. "lorenz"
    attrs : dict -- further root attributes (parameters, seed, solver, tolerances)
    params : dict name -> ndarray -- the `params/` group (system parameters)
    aux : dict name -> ndarray -- the `aux/` group (e.g. the quadrotor load)
    """

    x: np.ndarray
    graphs: list
    dt: float
    system: str
    u: np.ndarray = None
    graph_index: np.ndarray = None
    attrs: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    aux: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.graph_index is None:
            self.graph_index = np.zeros(self.x.shape[0], dtype=np.int64)

    @property
    def n_trajectories(self):
        return self.x.shape[0]

    @property
    def horizon(self):
        return self.x.shape[1] - 1

    @property
    def n_nodes(self):
        return self.x.shape[2]

    @property
    def state_dim(self):
        return self.x.shape[3]

    @property
    def control_dim(self):
        return 0 if self.u is None else self.u.shape[3]

    def graph_of(self, b):
        """The Graph trajectory ``b`` ran on."""
        return self.graphs[int(self.graph_index[b])]
