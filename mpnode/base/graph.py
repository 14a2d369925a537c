"""Graphs as CSR arrays: who each node hears.

Node ``i`` receives messages from ``indices[indptr[i]:indptr[i+1]]``.  CSR is what
the kernels read, what the trajectory files store, and it keeps sparse graphs
sparse: nothing here builds a dense N x N matrix.
"""
from dataclasses import dataclass

import numpy as np

from .errors import InputError


@dataclass(frozen=True, eq=False)
class Graph:
    """A directed graph in CSR form.

    indptr : ndarray, shape (N+1,), int64
    indices : ndarray, shape (E,), int64 -- row i lists the nodes i hears
    self_loops : bool -- True when self-loops are intended (files must say so)
    parts : tuple of Graph, or None -- for a block-diagonal batch, the graphs it is made
        of (in order); lets the kernels treat B copies of one small graph densely.
    """

    indptr: np.ndarray
    indices: np.ndarray
    self_loops: bool = False
    parts: tuple = None

    def __post_init__(self):
        object.__setattr__(self, "indptr", np.ascontiguousarray(self.indptr, dtype=np.int64))
        object.__setattr__(self, "indices", np.ascontiguousarray(self.indices, dtype=np.int64))

    @property
    def n_nodes(self):
        return len(self.indptr) - 1

    @property
    def n_edges(self):
        return len(self.indices)

    def degrees(self):
        """In-degree of every node (the length of its row), shape (N,)."""
        return np.diff(self.indptr)

    def edges(self):
        """The edges as (receiver, sender) pairs, shape (E, 2)."""
        rows = np.repeat(np.arange(self.n_nodes, dtype=np.int64), self.degrees())
        return np.stack([rows, self.indices], axis=1)

    def equals(self, other):
        return (
            np.array_equal(self.indptr, other.indptr)
            and np.array_equal(self.indices, other.indices)
            and self.self_loops == other.self_loops
        )

    def validate(self, source="graph", field="graph"):
        """Check the CSR invariants; raise InputError naming ``source``/``field``."""
        check_csr(self.indptr, self.indices, self.n_nodes, self.self_loops, source, field)
        return self

    # ---- constructors -------------------------------------------------
    @classmethod
    def from_edges(cls, n_nodes, edges, directed=False, self_loops=False):
        """Build from (receiver, sender) pairs; undirected adds both directions.

        Duplicate edges are merged; rows are sorted.
        """
        e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        if not directed:
            e = np.concatenate([e, e[:, ::-1]])
        if len(e) and (e.min() < 0 or e.max() >= n_nodes):
            raise InputError("edge list", "edges", f"node id out of range for N={n_nodes}",
                             f"ids in 0..{n_nodes - 1}")
        if not self_loops:
            e = e[e[:, 0] != e[:, 1]]
        e = np.unique(e, axis=0)  # sorted by receiver, then sender
        indptr = np.zeros(n_nodes + 1, dtype=np.int64)
        np.cumsum(np.bincount(e[:, 0], minlength=n_nodes), out=indptr[1:])
        return cls(indptr, e[:, 1].copy(), self_loops=self_loops)

    @classmethod
    def from_networkx(cls, g):
        """Build from a networkx graph whose nodes are 0..N-1 (directed or not).

        For a DiGraph an edge u -> v means v hears u.
        """
        n = g.number_of_nodes()
        if set(g.nodes) != set(range(n)):
            raise InputError("networkx graph", "nodes", "node labels are not 0..N-1",
                             "nx.convert_node_labels_to_integers(g)")
        pairs = [(v, u) for u, v in g.edges()]  # (receiver, sender)
        has_loops = any(u == v for u, v in pairs)
        return cls.from_edges(n, pairs, directed=g.is_directed(), self_loops=has_loops)

    @classmethod
    def complete(cls, n_nodes):
        """Every node hears every other node (no self-loops)."""
        cols = np.tile(np.arange(n_nodes, dtype=np.int64), n_nodes).reshape(n_nodes, n_nodes)
        mask = ~np.eye(n_nodes, dtype=bool)
        indices = cols[mask]
        indptr = np.arange(n_nodes + 1, dtype=np.int64) * (n_nodes - 1)
        return cls(indptr, indices)


def is_networkx(g):
    """True for a networkx graph or a subclass of one (checked by type, so networkx is never
    imported here)."""
    return any(c.__module__.split(".")[0] == "networkx" for c in type(g).__mro__)


def as_graph(g, n_nodes, directed=False, source="graph", field="graph"):
    """A Graph on ``n_nodes`` nodes from what a user holds; InputError naming ``source``/``field``.

    g : an mpnode Graph; a networkx graph with nodes 0..N-1 (a DiGraph edge u -> v means v
    hears u); or an edge list of (sender, receiver) pairs, shape (E, 2), integers 0..N-1 --
    undirected unless ``directed`` (then each pair is one way only: the receiver hears the
    sender).  Node i is the data's node i.  An edge list or networkx graph that lists a node
    with itself gets a graph that allows self-loops; duplicate pairs count once.
    """
    if isinstance(g, Graph):
        if g.n_nodes != n_nodes:
            raise InputError(source, field, f"has {g.n_nodes} nodes but the data have N = {n_nodes}",
                             "a graph with one node per node of x (x[:, :, i] is node i)")
        return g.validate(source, field)
    if is_networkx(g):
        return _from_networkx(g, n_nodes, source, field)
    e = _edge_array(g, source, field)
    if len(e) and (e.min() < 0 or e.max() >= n_nodes):
        bad = e[(e < 0) | (e >= n_nodes)][0]
        raise InputError(source, field, f"names node {bad}, but the data have N = {n_nodes} nodes",
                         f"node ids in 0..{n_nodes - 1} (x[:, :, i] is node i)")
    loops = bool(np.any(e[:, 0] == e[:, 1]))
    return Graph.from_edges(n_nodes, e[:, ::-1], directed=bool(directed), self_loops=loops)  # (receiver, sender)


def _edge_array(g, source, field):
    """An edge list as an int64 array (E, 2); integral floats are accepted (e.g. from MATLAB)."""
    try:
        e = np.asarray(g)
    except ValueError:  # ragged
        e = None
    if e is None or e.dtype == object or not (e.ndim == 2 and e.shape[1] == 2 or e.size == 0):
        what = f"has shape {e.shape}" if e is not None and e.dtype != object and e.ndim else f"is a {type(g).__name__}"
        raise InputError(source, field, what, "an edge list of (sender, receiver) pairs, shape (E, 2); "
                         "or an mpnode.Graph or a networkx graph")
    if e.size and e.dtype.kind == "f" and np.all(np.isfinite(e)) and np.all(e == np.round(e)):
        e = e.astype(np.int64)
    if e.size and e.dtype.kind not in "iu":
        raise InputError(source, field, f"has dtype {e.dtype}", "integer node ids")
    return e.reshape(-1, 2).astype(np.int64)


def _from_networkx(g, n_nodes, source, field):
    n = g.number_of_nodes()
    if n != n_nodes:
        raise InputError(source, field, f"is a networkx graph with {n} nodes but the data have N = {n_nodes}",
                         "one graph node per node of x")
    if set(g.nodes) != set(range(n)):
        raise InputError(source, field, "is a networkx graph whose nodes are not labelled 0..N-1",
                         "node i of the graph is x[:, :, i]: relabel, e.g. nx.relabel_nodes(g, {label: i, ...})")
    return Graph.from_networkx(g)


def block_diagonal(graphs):
    """One graph made of ``graphs`` side by side (node ids offset); the batch layout."""
    graphs = list(graphs)
    sizes = np.array([g.n_nodes for g in graphs], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    eoff = np.concatenate([[0], np.cumsum([g.n_edges for g in graphs])])
    indptr = np.concatenate([[0]] + [g.indptr[1:] + eoff[i] for i, g in enumerate(graphs)])
    indices = np.concatenate([g.indices + offsets[i] for i, g in enumerate(graphs)]) if graphs else np.zeros(0)
    parts = tuple(p for g in graphs for p in (g.parts or (g,)))
    return Graph(indptr, indices, self_loops=any(g.self_loops for g in graphs), parts=parts)


def check_csr(indptr, indices, n_nodes, allow_self_loops, source, field):
    """Raise InputError unless (indptr, indices) is a valid CSR graph on n_nodes nodes."""
    indptr = np.asarray(indptr)
    indices = np.asarray(indices)
    if indptr.ndim != 1 or len(indptr) != n_nodes + 1:
        raise InputError(source, f"{field}/indptr", f"has shape {indptr.shape}", f"shape ({n_nodes + 1},)")
    if indices.ndim != 1:
        raise InputError(source, f"{field}/indices", f"has shape {indices.shape}", "a 1-D array")
    for name, a in (("indptr", indptr), ("indices", indices)):
        if a.size and not np.issubdtype(a.dtype, np.integer):
            raise InputError(source, f"{field}/{name}", f"has dtype {a.dtype}", "an integer dtype")
    if indptr[0] != 0:
        raise InputError(source, f"{field}/indptr", f"starts at {indptr[0]}", "indptr[0] == 0")
    if np.any(np.diff(indptr) < 0):
        i = int(np.argmax(np.diff(indptr) < 0))
        raise InputError(source, f"{field}/indptr", f"decreases at position {i}", "a non-decreasing row pointer")
    if indptr[-1] != len(indices):
        raise InputError(source, f"{field}/indptr", f"ends at {indptr[-1]} but indices has {len(indices)} entries",
                         "indptr[N] == len(indices)")
    if len(indices) and (indices.min() < 0 or indices.max() >= n_nodes):
        bad = int(indices[(indices < 0) | (indices >= n_nodes)][0])
        raise InputError(source, f"{field}/indices", f"contains node id {bad}", f"ids in 0..{n_nodes - 1}")
    rows = np.repeat(np.arange(n_nodes), np.diff(indptr))
    if len(indices):
        order = np.lexsort((indices, rows))
        r, c = rows[order], indices[order]
        dup = (r[1:] == r[:-1]) & (c[1:] == c[:-1])
        if np.any(dup):
            k = int(np.argmax(dup))
            raise InputError(source, f"{field}/indices", f"row {r[k]} lists node {c[k]} twice",
                             "no duplicate column inside a row")
        if not allow_self_loops and np.any(rows == indices):
            k = int(np.argmax(rows == indices))
            raise InputError(source, f"{field}/indices", f"node {rows[k]} lists itself (a self-loop)",
                             "no self-loops unless the graph group has attribute self_loops = 1")
