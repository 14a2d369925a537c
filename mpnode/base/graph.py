"""Graphs as CSR arrays: who each node hears.

Node ``i`` receives messages from ``indices[indptr[i]:indptr[i+1]]``.  CSR is what
the kernels read, what the trajectory files store, and it keeps sparse graphs
sparse: nothing here builds a dense N x N matrix.  A weighted graph carries one number per
edge beside ``indices`` (how strongly the receiver hears that sender); its sign is the user's
to give meaning to, the graph only stores it.
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
    weights : ndarray, shape (E,), float64, or None -- edge p, (row i, sender indices[p]), has
        weight weights[p]; None: unweighted (every edge counts alike)
    """

    indptr: np.ndarray
    indices: np.ndarray
    self_loops: bool = False
    parts: tuple = None
    weights: np.ndarray = None

    def __post_init__(self):
        object.__setattr__(self, "indptr", np.ascontiguousarray(self.indptr, dtype=np.int64))
        object.__setattr__(self, "indices", np.ascontiguousarray(self.indices, dtype=np.int64))
        if self.weights is not None:
            w = np.asarray(self.weights)
            if w.dtype.kind in "iuf":  # anything else stays as given, for validate to name
                w = np.ascontiguousarray(w, dtype=np.float64)
            object.__setattr__(self, "weights", w)

    @property
    def n_nodes(self):
        return len(self.indptr) - 1

    @property
    def n_edges(self):
        return len(self.indices)

    @property
    def weighted(self):
        return self.weights is not None

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
            and (self.weights is None) == (other.weights is None)
            and (self.weights is None or np.array_equal(self.weights, other.weights))
        )

    def validate(self, source="graph", field="graph"):
        """Check the CSR invariants and the weights; raise InputError naming ``source``/``field``."""
        check_csr(self.indptr, self.indices, self.n_nodes, self.self_loops, source, field, self.weights)
        return self

    def reweighted(self, weights):
        """The same edges with other ``weights`` (E,) (None: unweighted), checked; for fitting code
        that changes the strengths and keeps the wiring.  ``parts`` is dropped: its weights would disagree."""
        graph = Graph(self.indptr, self.indices, self_loops=self.self_loops, weights=weights)
        if graph.weighted:
            check_weights(graph.weights, self.n_edges, "graph", "graph/weights")
        return graph

    # ---- constructors -------------------------------------------------
    @classmethod
    def from_edges(cls, n_nodes, edges, directed=False, self_loops=False, weights=None):
        """Build from (receiver, sender) pairs; undirected adds both directions (a self-loop once).

        weights : (E,) one per pair, or None (unweighted); undirected, both directions get the
        pair's weight.  Duplicate pairs are merged, and their weights add: parallel lines between
        two nodes act as one line of their summed strength.  Rows are sorted, the weights with them.
        """
        e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        w = None if weights is None else check_weights(weights, len(e), "edge list", "weights")
        if not directed:
            back = e[:, 0] != e[:, 1]  # a self-loop is one edge either way
            e = np.concatenate([e, e[back, ::-1]])
            w = None if w is None else np.concatenate([w, w[back]])
        if len(e) and (e.min() < 0 or e.max() >= n_nodes):
            raise InputError("edge list", "edges", f"node id out of range for N={n_nodes}",
                             f"ids in 0..{n_nodes - 1}")
        if not self_loops:
            keep = e[:, 0] != e[:, 1]
            e, w = e[keep], None if w is None else w[keep]
        keys, first, inverse = np.unique(e[:, 0] * max(n_nodes, 1) + e[:, 1], return_index=True, return_inverse=True)
        e = e[first]  # sorted by receiver, then sender
        w = None if w is None else np.bincount(inverse.reshape(-1), weights=w, minlength=len(keys))
        indptr = np.zeros(n_nodes + 1, dtype=np.int64)
        np.cumsum(np.bincount(e[:, 0], minlength=n_nodes), out=indptr[1:])
        return cls(indptr, e[:, 1].copy(), self_loops=self_loops, weights=w)

    @classmethod
    def from_networkx(cls, g, source="networkx graph", field="graph"):
        """Build from a networkx graph whose nodes are 0..N-1 (directed or not).

        For a DiGraph an edge u -> v means v hears u.  Edges with a ``weight`` attribute give
        a weighted graph; then every edge needs one (a missing weight is not guessed as 1).
        """
        n = g.number_of_nodes()
        if set(g.nodes) != set(range(n)):
            raise InputError("networkx graph", "nodes", "node labels are not 0..N-1",
                             "nx.convert_node_labels_to_integers(g)")
        triples = list(g.edges(data="weight"))
        pairs = [(v, u) for u, v, _ in triples]  # (receiver, sender)
        has_loops = any(u == v for u, v in pairs)
        weights = _networkx_weights(triples, source, field)
        return cls.from_edges(n, pairs, directed=g.is_directed(), self_loops=has_loops, weights=weights)

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
    hears u; a ``weight`` on every edge makes it weighted); or an edge list of (sender,
    receiver) pairs, shape (E, 2), integers 0..N-1, or of (sender, receiver, weight) triples,
    shape (E, 3) -- undirected unless ``directed`` (then each pair is one way only: the
    receiver hears the sender).  Node i is the data's node i.  An edge list or networkx graph
    that lists a node with itself gets a graph that allows self-loops; duplicate pairs count
    once, their weights added.
    """
    if isinstance(g, Graph):
        if g.n_nodes != n_nodes:
            raise InputError(source, field, f"has {g.n_nodes} nodes but the data have N = {n_nodes}",
                             "a graph with one node per node of x (x[:, :, i] is node i)")
        return g.validate(source, field)
    if is_networkx(g):
        return _from_networkx(g, n_nodes, source, field)
    e, w = _edge_array(g, source, field)
    if len(e) and (e.min() < 0 or e.max() >= n_nodes):
        bad = e[(e < 0) | (e >= n_nodes)][0]
        raise InputError(source, field, f"names node {bad}, but the data have N = {n_nodes} nodes",
                         f"node ids in 0..{n_nodes - 1} (x[:, :, i] is node i)")
    if w is not None:
        w = check_weights(w, len(e), source, f"{field}/weights")
    loops = bool(np.any(e[:, 0] == e[:, 1]))
    return Graph.from_edges(n_nodes, e[:, ::-1], directed=bool(directed), self_loops=loops,  # (receiver, sender)
                            weights=w)


def _edge_array(g, source, field):
    """(node ids as int64 (E, 2), the weight column (E,) or None) of an edge list of pairs (E, 2)
    or (sender, receiver, weight) triples (E, 3); integral floats are accepted as ids (e.g. from MATLAB)."""
    try:
        e = np.asarray(g)
    except ValueError:  # ragged
        e = None
    if e is None or e.dtype == object or not (e.ndim == 2 and e.shape[1] in (2, 3) or e.size == 0):
        what = f"has shape {e.shape}" if e is not None and e.dtype != object and e.ndim else f"is a {type(g).__name__}"
        raise InputError(source, field, what, "an edge list of (sender, receiver) pairs, shape (E, 2), or of "
                         "(sender, receiver, weight) triples, shape (E, 3); or an mpnode.Graph or a networkx graph")
    w = e[:, 2] if e.ndim == 2 and e.shape[1] == 3 else None
    e = e[:, :2] if w is not None else e
    if e.size and e.dtype.kind == "f" and np.all(np.isfinite(e)) and np.all(e == np.round(e)):
        e = e.astype(np.int64)
    if e.size and e.dtype.kind not in "iu":
        raise InputError(source, field, f"has dtype {e.dtype}",
                         "integer node ids" + (" in the first two columns (sender, receiver)" if w is not None else ""))
    return e.reshape(-1, 2).astype(np.int64), w


def _networkx_weights(triples, source, field):
    """The ``weight`` of every (u, v, weight) edge, or None when no edge has one."""
    if all(w is None for _, _, w in triples):
        return None
    for u, v, w in triples:
        if w is None:
            raise InputError(source, field, f"edge ({u!r}, {v!r}) has no weight attribute, but other edges have one",
                             "a weight on every edge, or on none (an unweighted graph)")
        if isinstance(w, (bool, np.bool_)) or not isinstance(w, (int, float, np.integer, np.floating)):
            raise InputError(source, f"{field}/weights", f"edge ({u!r}, {v!r}) has weight {w!r}",
                             "a real number on every edge")
    return np.array([w for _, _, w in triples], dtype=np.float64)


def check_weights(weights, n_edges, source, field):
    """``weights`` as float64 (E,) when they are one finite number per edge (negative allowed: the
    data layer only stores them); else InputError naming ``source``/``field`` and the fix."""
    w = np.asarray(weights)
    if w.dtype.kind not in "iuf":
        raise InputError(source, field, f"has dtype {w.dtype}", "real numbers, one weight per edge")
    if w.shape != (n_edges,):
        raise InputError(source, field, f"has shape {w.shape}, but the graph has {n_edges} edges",
                         f"one weight per edge, shape ({n_edges},), in the order of the edges")
    if not np.all(np.isfinite(w)):
        p = int(np.argmax(~np.isfinite(w)))
        raise InputError(source, field, f"is {w[p]} at edge {p}", "finite weights (negative ones are allowed)")
    return np.ascontiguousarray(w, dtype=np.float64)


def _from_networkx(g, n_nodes, source, field):
    n = g.number_of_nodes()
    if n != n_nodes:
        raise InputError(source, field, f"is a networkx graph with {n} nodes but the data have N = {n_nodes}",
                         "one graph node per node of x")
    if set(g.nodes) != set(range(n)):
        raise InputError(source, field, "is a networkx graph whose nodes are not labelled 0..N-1",
                         "node i of the graph is x[:, :, i]: relabel, e.g. nx.relabel_nodes(g, {label: i, ...})")
    return Graph.from_networkx(g, source, field)


def block_diagonal(graphs):
    """One graph made of ``graphs`` side by side (node ids offset); the batch layout.

    Weighted if any part is (an unweighted part's edges then weigh 1, as they count unweighted)."""
    graphs = list(graphs)
    sizes = np.array([g.n_nodes for g in graphs], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    eoff = np.concatenate([[0], np.cumsum([g.n_edges for g in graphs])])
    indptr = np.concatenate([[0]] + [g.indptr[1:] + eoff[i] for i, g in enumerate(graphs)])
    indices = np.concatenate([g.indices + offsets[i] for i, g in enumerate(graphs)]) if graphs else np.zeros(0)
    weights = None
    if any(g.weighted for g in graphs):
        weights = np.concatenate([g.weights if g.weighted else np.ones(g.n_edges) for g in graphs])
    parts = tuple(p for g in graphs for p in (g.parts or (g,)))
    return Graph(indptr, indices, self_loops=any(g.self_loops for g in graphs), parts=parts, weights=weights)


def check_csr(indptr, indices, n_nodes, allow_self_loops, source, field, weights=None):
    """Raise InputError unless (indptr, indices) is a valid CSR graph on n_nodes nodes, and
    ``weights``, when given, one finite number per edge (named ``field``/weights)."""
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
    if weights is not None:
        check_weights(weights, len(indices), source, f"{field}/weights")
