"""How the kernels cover a graph (`Plan`): blocks of whole graphs (dense or CSR), or one large
graph renumbered for locality; and the graph arrays they read (aggregation weights, the transpose)."""
import functools
import weakref

import numpy as np

from mpnode.base.graph import Graph

from .backend import n_threads


def closed_pieces(graph):
    """Cut points splitting nodes 0..M into consecutive ranges no edge crosses.

    Returns ndarray of starts plus M, e.g. [0, 3, 6, ..., M] for a batch of 3-node graphs.
    """
    m = graph.n_nodes
    deg = graph.degrees()
    ids = np.arange(m)
    lo, hi = ids.copy(), ids.copy()
    rows = deg > 0
    if graph.n_edges:
        starts = graph.indptr[:-1][rows]
        lo[rows] = np.minimum(lo[rows], np.minimum.reduceat(graph.indices, starts))
        hi[rows] = np.maximum(hi[rows], np.maximum.reduceat(graph.indices, starts))
    prefix_max = np.maximum.accumulate(hi)  # prefix_max[c-1]: furthest node reached from 0..c-1
    suffix_min = np.minimum.accumulate(lo[::-1])[::-1]  # suffix_min[c]: nearest node reached from c..M-1
    c = ids[1:]
    cuts = c[(prefix_max[:-1] < c) & (suffix_min[1:] >= c)]
    return np.concatenate([[0], cuts, [m]]).astype(np.int64)


DENSE_MAX_NODES = 128
#: a graph that cannot be split into blocks runs stagewise once it gives every thread this many
#: nodes (two stagewise tasks' worth); smaller ones run as one block
STAGEWISE_MIN_NODES_PER_THREAD = 256


class Plan:
    """How the kernels cover a graph: blocks of whole graphs, each dense or CSR.

    blocks : ndarray (n_blocks+1,) of node boundaries, or None for the stagewise drivers
    dense_n, dense_off : ndarray (n_blocks,) -- block b is copies of one dense_n[b]-node
        graph whose 0/1 adjacency (self-loop included for self_messages) starts at
        dense_A[dense_off[b]] (row-major); dense_n[b] = 0 means CSR
    dense_A, dense_AT : flat arrays of those matrices and their transposes
    weight : ndarray -- `Aggregation.weights`: (M,) each node's factor on the sum of its row,
        then M more when the linear path has its own rule
    edge_weight : ndarray (E,) -- each CSR entry's weight in the kernels' dtype, or empty for an
        unweighted graph (the kernels then run their plain sums)
    order : ndarray (M,) or None -- the kernels' node k is the user's node order[k] (a
        locality order for one large graph, see `locality_order`); None: the user's order
    csr : Graph -- the graph as the kernels read it (renumbered by ``order``)
    transposed : Graph -- the CSR transpose of ``csr`` (computed on first use, for the adjoint)
    """

    def __init__(self, graph, n_threads, self_messages, dtype, aggregation, driver="auto", ordering="auto"):
        self.blocks = None
        self.order = None
        self.csr = Graph(graph.indptr, graph.indices, weights=graph.weights)  # the cache holds the graph weakly
        self._transposed = None
        self.dtype = np.dtype(dtype)
        self.weight_scale = aggregation.weight_scale
        self.weight = aggregation.weights(graph, self_messages, dtype)
        m = graph.n_nodes
        parts = graph.parts or (graph,)
        sizes = np.array([p.n_nodes for p in parts], dtype=np.int64)
        if graph.parts is None or len(parts) == 1:
            pieces = closed_pieces(graph)
            parts, sizes = (None,) * (len(pieces) - 1), np.diff(pieces)
        n_blocks = max(1, n_threads)
        too_big = m >= STAGEWISE_MIN_NODES_PER_THREAD * n_threads and sizes.max(initial=0) > m / n_blocks
        if driver == "stagewise" or (driver == "auto" and too_big):
            if ordering != "none":  # one graph too big to split: stagewise, in a cache-friendly order
                self.order = locality_order(self.csr, force=ordering == "rcm")
            if self.order is not None:
                self.csr = renumbered(self.csr, self.order)
                self.weight = self.weight.reshape(-1, m)[:, self.order].ravel()  # both halves, if two
            return
        target = m / n_blocks
        # Greedy: whole parts into blocks of about `target` nodes, closing a block early
        # where the graph changes so that blocks of copies can go dense.
        bounds, owners, start, size = [0], [], 0, 0
        for k, n in enumerate(sizes):
            size += n
            last = k + 1 == len(sizes)
            if last or size >= target or (parts[k + 1] is not parts[start] and size >= target / 4):
                bounds.append(bounds[-1] + size)
                owners.append(parts[start] if all(p is parts[start] for p in parts[start:k + 1]) else None)
                start, size = k + 1, 0
        self.blocks = np.asarray(bounds, dtype=np.int64)
        self.dense_n = np.zeros(len(owners), dtype=np.int64)
        self.dense_off = np.zeros(len(owners), dtype=np.int64)
        mats, mats_t, offset, seen = [], [], 0, {}
        for b, g in enumerate(owners):
            if g is None or not _worth_dense(g):
                continue
            if id(g) not in seen:
                a = np.zeros((g.n_nodes, g.n_nodes), dtype=dtype)
                w = edge_array(g, dtype, self.weight_scale)
                a[np.repeat(np.arange(g.n_nodes), g.degrees()), g.indices] = w if w.size else 1
                if self_messages:  # += : a self-loop in the row and hearing oneself both count
                    a[np.diag_indices(g.n_nodes)] += 1
                seen[id(g)] = offset
                mats.append(a.ravel())
                mats_t.append(np.ascontiguousarray(a.T).ravel())
                offset += a.size
            self.dense_n[b] = g.n_nodes
            self.dense_off[b] = seen[id(g)]
        self.dense_A = np.concatenate(mats) if mats else np.zeros(0, dtype=dtype)
        self.dense_AT = np.concatenate(mats_t) if mats_t else np.zeros(0, dtype=dtype)

    @property
    def transposed(self):
        if self._transposed is None:
            self._transposed = transpose(self.csr)
        return self._transposed

    @functools.cached_property
    def edge_weight(self):
        return edge_array(self.csr, self.dtype, self.weight_scale)

    @functools.cached_property
    def _transposed_edge_weight(self):
        return edge_array(self.transposed, self.dtype, self.weight_scale)

    def kernel_graph(self):
        """The graph tuple the kernels read: (indptr, indices, weight, edge weights)."""
        return self.csr.indptr, self.csr.indices, self.weight, self.edge_weight

    def kernel_transposed(self):
        """The transpose as the kernels read it: (indptr, indices, edge weights)."""
        t = self.transposed
        return t.indptr, t.indices, self._transposed_edge_weight

    def to_kernel_order(self, a, axis=0):
        """``a`` with its node axis (0, or 1 of a (T, M, ...) array) in the kernels' order (``a``
        itself when there is no reordering)."""
        if self.order is None:
            return a
        if axis == 0:
            return np.take(a, self.order, axis=0)
        from .kernels import rows_to_kernel_order

        a = np.ascontiguousarray(a)
        out = np.empty_like(a)
        if a.size:
            rows_to_kernel_order(_slices(a), self.order, _slices(out))
        return out

    def to_user_order(self, a):
        """Put the node axis (axis 1) of ``a`` (T, M, ...), C-contiguous, back in the user's order,
        in place, one time slice at a time (no second copy of a large rollout)."""
        if self.order is not None and a.size:
            from .kernels import rows_to_user_order

            if not a.flags.c_contiguous:  # a reshaped copy would be reordered instead of ``a``
                raise ValueError("to_user_order reorders in place: the array must be C-contiguous")
            rows = _slices(a)
            rows_to_user_order(rows, self.order, np.empty_like(rows[0]))
        return a


def edge_array(graph, dtype, scale=None):
    """The weights the kernels multiply a graph's messages by, w / scale (`Aggregation.weight_scale`)
    in ``dtype``; an empty array (every edge 1) for an unweighted graph under a model of such."""
    if graph.weights is None and scale is None:
        return np.zeros(0, dtype)
    w = np.ones(graph.n_edges) if graph.weights is None else graph.weights
    return np.ascontiguousarray(w / (scale or 1.0), dtype=dtype)


def _slices(a):
    """A (T, M, ...) array as (T, M, c) rows (a view)."""
    return a.reshape(a.shape[0], a.shape[1], -1)


#: one graph of fewer nodes keeps its order: its states fit in the caches anyway
LOCALITY_MIN_NODES = 65536
#: an edge is local when its two ends are at most this many rows apart (their state rows
#: are then near each other in memory, likely in cache while the tile is computed)
LOCALITY_WINDOW = 4096


def local_fraction(graph, position=None):
    """The fraction of edges whose ends are within LOCALITY_WINDOW rows, with node i at
    row ``position[i]`` (default: at row i)."""
    rows = np.repeat(np.arange(graph.n_nodes, dtype=np.int64), graph.degrees())
    cols = graph.indices
    if position is not None:
        rows, cols = position[rows], position[cols]
    return float(np.mean(np.abs(rows - cols) <= LOCALITY_WINDOW))


def locality_order(graph, force=False):
    """A node order that keeps neighbours close in memory, or None if the graph's own is as good.

    The CSR gather of one large graph reads each neighbour's state row; when the node
    numbering is arbitrary (a grid or a road network numbered in any order), nearly every
    read misses the caches.  Reverse Cuthill-McKee numbers nodes breadth-first, so graphs
    with locality get neighbours within a few thousand rows.  Taken only when it makes at
    least a quarter more of the edges local; random (expander) graphs have no such order.
    ``force``: return the RCM order whatever the graph (tests use it on small graphs).
    """
    m = graph.n_nodes
    if not force and (m < LOCALITY_MIN_NODES or not graph.n_edges):
        return None
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    adjacency = csr_matrix((np.ones(graph.n_edges, dtype=np.int8), graph.indices, graph.indptr), shape=(m, m))
    order = reverse_cuthill_mckee(adjacency, symmetric_mode=False).astype(np.int64)
    position = np.empty(m, dtype=np.int64)
    position[order] = np.arange(m, dtype=np.int64)
    if not force and local_fraction(graph, position) < local_fraction(graph) + 0.25:
        return None
    return order


def renumbered(graph, order):
    """The graph with node ``order[k]`` renamed k (rows moved, neighbour ids mapped; each row
    keeps its neighbours' order, so sums add in the same order as on the user's graph)."""
    m = graph.n_nodes
    position = np.empty(m, dtype=np.int64)
    position[order] = np.arange(m, dtype=np.int64)
    deg = graph.degrees()[order]
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(deg, out=indptr[1:])
    starts = np.repeat(graph.indptr[order] - indptr[:-1], deg)
    entries = starts + np.arange(graph.n_edges, dtype=np.int64)
    weights = None if graph.weights is None else graph.weights[entries]
    return Graph(indptr, position[graph.indices[entries]], self_loops=graph.self_loops, weights=weights)


def _worth_dense(g):
    """Small graphs, or dense ones up to DENSE_MAX_NODES: one GEMM beats walking CSR rows."""
    n = g.n_nodes
    return n <= 16 or (n <= DENSE_MAX_NODES and g.n_edges * 8 >= n * n)


_plans = weakref.WeakKeyDictionary()


DRIVERS = ("auto", "blocks", "stagewise")
ORDERINGS = ("auto", "none", "rcm")


def plan_for(graph, spec, dtype, driver="auto", ordering="auto"):
    """The Plan for ``graph`` under ``spec``'s aggregation (cached per graph object: batches
    reuse their graphs).

    driver : "auto" (block drivers unless one graph is too big to split), or force
    "blocks" / "stagewise" (the results agree to rounding; tests and benchmarks use this).
    ordering : how the stagewise driver numbers the nodes inside: "auto" (`locality_order`),
    "none" (the user's order) or "rcm" (reverse Cuthill-McKee always).  Outputs are in the
    user's order whatever this says; results agree to rounding.
    """
    if driver not in DRIVERS:
        raise ValueError(f"driver must be one of {DRIVERS}, not {driver!r}")
    if ordering not in ORDERINGS:
        raise ValueError(f"ordering must be one of {ORDERINGS}, not {ordering!r}")
    key = (n_threads(), bool(spec.self_messages), np.dtype(dtype).str, driver, spec.aggregation, ordering)
    per_graph = _plans.setdefault(graph, {})
    if key not in per_graph:
        per_graph[key] = Plan(graph, key[0], spec.self_messages, dtype, spec.aggregation, driver, ordering=ordering)
    return per_graph[key]


def transpose(graph):
    """The CSR transpose: row j lists the nodes that hear j (for the adjoint's scatter)."""
    rows = np.repeat(np.arange(graph.n_nodes, dtype=np.int64), graph.degrees())
    order = np.argsort(graph.indices, kind="stable")
    indptr = np.zeros(graph.n_nodes + 1, dtype=np.int64)
    np.cumsum(np.bincount(graph.indices, minlength=graph.n_nodes), out=indptr[1:])
    weights = None if graph.weights is None else graph.weights[order]
    return Graph(indptr, rows[order], self_loops=graph.self_loops, weights=weights)

