"""Where on the network the error lies: each node's error, and the nodes that carry most of it.

A network's operator asks which nodes a model gets wrong (a grid's buses whose frequency it
misses), not only how wrong it is on average.  Node i is the same node only on one graph, so the
view is of one graph: the one most trajectories run on (the first of those, on a tie; with a graph
per trajectory, the first trajectory's).  Per node and state dimension, over those trajectories
and the scored steps (after the warm-up, to each trajectory's end, what was observed): the
normalised MSE, normalised as the overall error is (so that, with every entry observed and one
graph, the nodes' mean is the evaluation's normalised MSE, and their mean per dimension its
per-dimension error), and the RMS error in the data's units.  A prediction that leaves the data's
range but stays finite counts as its squared error (the overall error counts its step infinite
from there on); a non-finite one counts infinite.

A node's error is its mean over the *watched* dimensions, which the caller names (the swing
equation's frequency deviation; mpnode knows no system), all of them by default; the nodes are
ranked by it.
"""
from dataclasses import dataclass

import numpy as np

from .metrics import _mean, normalised_sq_error, variance

#: how many of the worst nodes the summary names
WORST = 5


@dataclass
class NodeErrors:
    """graph : the graph's index;  trajectories : (k,) the trajectories on it
    nmse, rmse : (N, dx) per node and state dimension (NaN: nothing scored)
    dims : the watched dimensions;  names : one per node (e.g. "bus 30"), or None
    """

    graph: int
    trajectories: np.ndarray
    nmse: np.ndarray
    rmse: np.ndarray
    dims: list
    names: list = None

    @property
    def error(self):
        """(N,) each node's normalised MSE over the watched dimensions (NaN: none scored)."""
        return _mean(self.nmse[:, self.dims], axis=1)

    @property
    def rms(self):
        """(N,) each node's RMS error over the watched dimensions, in the data's units."""
        return np.sqrt(_mean(self.rmse[:, self.dims] ** 2, axis=1))

    def ranked(self):
        """The nodes with a scored error, the largest error first (a tie: the lower index first)."""
        e = self.error
        scored = np.flatnonzero(~np.isnan(e))
        return scored[np.argsort(-e[scored], kind="stable")]

    def worst(self, k=WORST):
        """The k nodes of largest error, largest first."""
        return [int(i) for i in self.ranked()[:k]]

    def median(self):
        """The node of the (lower) median error, or None when no node was scored."""
        ranked = self.ranked()
        return int(ranked[::-1][(len(ranked) - 1) // 2]) if len(ranked) else None

    def name(self, i):
        return f"node {i}" if self.names is None else str(self.names[i])

    def entry(self, i):
        """A JSON-ready dict of node i: its index, name, normalised MSE and RMS error (watched dimensions)."""
        return {"node": int(i), "name": self.name(i), "nmse": _num(self.error[i]), "rmse": _num(self.rms[i])}

    def summary(self, n_trajectories):
        """The evaluation summary's ``per_node`` entry (inf/NaN as strings): graph, trajectories (on
        it), all_trajectories (bool), dims (watched), names (or None), nmse and rmse (per node, over
        the watched dimensions), nmse_per_dim and rmse_per_dim (N x dx), worst (the WORST nodes of
        largest nmse, largest first) and median (the node of the lower median nmse), each
        {node, name, nmse, rmse}."""
        median = self.median()
        return {"graph": self.graph, "trajectories": int(len(self.trajectories)),
                "all_trajectories": len(self.trajectories) == n_trajectories, "dims": list(self.dims),
                "names": None if self.names is None else [str(n) for n in self.names],
                "nmse": [_num(v) for v in self.error], "rmse": [_num(v) for v in self.rms],
                "nmse_per_dim": [[_num(v) for v in row] for row in self.nmse],
                "rmse_per_dim": [[_num(v) for v in row] for row in self.rmse],
                "worst": [self.entry(i) for i in self.worst()],
                "median": None if median is None else self.entry(median)}


def busiest_graph(graph_index):
    """(graph, trajectories on it): the graph most trajectories run on, the first of those on a tie."""
    graph_index = np.asarray(graph_index)
    counts = np.bincount(graph_index)
    g = int(np.argmax(counts))
    return g, np.flatnonzero(graph_index == g)


def node_errors(pred, scored, clean, graph_index, dims=None, names=None):
    """The NodeErrors of predictions ``pred`` against ``scored`` (B, T+1, N, dx; NaN: not scored), on
    the busiest graph, normalised by the variances of ``clean`` (the whole file, as the overall
    error).  dims : the watched dimensions (None or empty: all);  names : one per node, or None."""
    g, rows = busiest_graph(graph_index)
    p, s = np.asarray(pred)[rows, 1:], scored[rows, 1:]
    mse = _mean(normalised_sq_error(p, s, var=np.ones(s.shape[-1])), axis=(0, 1))  # (N, dx), data units
    dims = [int(d) for d in dims] if dims else list(range(s.shape[-1]))
    if names is not None and len(names) != s.shape[2]:
        names = None  # names of another network's nodes: by index instead
    return NodeErrors(g, rows, mse / variance(clean), np.sqrt(mse), dims, None if names is None else list(names))


def _num(v):
    """A float for JSON: NaN and inf as strings."""
    v = float(v)
    return v if np.isfinite(v) else str(v)
