"""Test helpers for networks whose nodes and edges differ: a tiny weighted, attributed system."""
import numpy as np

from mpnode.base.graph import Graph
from mpnode.data import Trajectories


def ring(n, weights=None):
    g = Graph.from_edges(n, [(i, (i + 1) % n) for i in range(n)])
    return g if weights is None else g.reweighted(weights)


def relaxing_nodes(B=24, N=4, T=20, dt=0.1, seed=0):
    """dx_i/dt = -a_i x_i + sum_j w_ij (x_j - x_i) / deg_i (exact enough at 20 Euler substeps):
    each node relaxes at its own rate a_i and hears each neighbour by its own weight, drawn per
    trajectory; x (B, T+1, N, 1), attributes ``rate``, one weighted ring per trajectory."""
    rng = np.random.default_rng(seed)
    g = ring(N)
    rows = np.repeat(np.arange(N), g.degrees())
    x = np.empty((B, T + 1, N, 1))
    rates, graphs = rng.uniform(0.2, 2.0, (B, N, 1)), []
    for b in range(B):
        gb = g.reweighted(rng.uniform(0.2, 3.0, g.n_edges))
        graphs.append(gb)
        z = rng.uniform(-1, 1, N)
        x[b, 0, :, 0] = z
        for t in range(T):
            for _ in range(20):
                pull = np.bincount(rows, gb.weights * (z[g.indices] - z[rows]), minlength=N) / g.degrees()
                z = z + dt / 20 * (-rates[b, :, 0] * z + pull)
            x[b, t + 1, :, 0] = z
    return Trajectories.from_arrays(x, graphs, dt=dt, system="relaxing", graph_index=np.arange(B),
                                    node_attrs=rates, attr_names=["rate"])
