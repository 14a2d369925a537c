"""The engine: RK4 rollouts of a field over a flat (block-diagonal) graph, and their exact VJP.

`forward` integrates; `forward_with_vjp` also returns the vector-Jacobian product of
the rollout, the *discrete adjoint*: for any cotangent gx of the output states it gives
the exact gradient, with respect to the parameters and the initial state, of
<gx, rollout> as computed (not of the ODE it approximates).  Losses, windows, multiple
shooting are the caller's business (`mpnode.losses`).  Cost: memory for one state per RK4
step (T*substeps+1 arrays of (M, dz)); time about 4x a rollout (forward, recomputed
stages, and a VJP that costs about twice a forward).  Stage values are recomputed rather
than stored, so memory does not grow with the hidden width.

Arrays here are time-major and flat over nodes: x (T+1, M, dx), u (T, M, du).
`mpnode.model` turns (B, T+1, N, dx) batches into this layout.
"""
import contextlib
import functools
import weakref
from dataclasses import dataclass, replace

import numpy as np

from .graph import Graph

#: the model kinds the engine integrates (docs/model-format.md)
KINDS = ("mpnode", "l2s", "node")
#: how a node combines what its neighbours send (model-format.md, "Aggregation")
AGGREGATIONS = ("mean", "sum", "scaled")
#: what the linear aggregate path adds to: every output, or dx/dt alone (model-format.md)
LINEAR_TARGETS = ("all", "state")


def default_aggregation(kind):
    """The aggregation a kind has when nothing says otherwise: the sum for l2s (as the Julia
    code's SegmentedSum), else the paper's mean."""
    return "sum" if kind == "l2s" else "mean"


@dataclass(frozen=True)
class FieldSpec:
    """What the kernels need to know about a model besides its weights.

    kind : "mpnode" (state [x, m], messages of size message_dim), "l2s" (state x,
        message_dim 0) or "node" (a plain neural ODE of a whole system of ``n_nodes``
        nodes; message_dim 0, the graph is ignored)
    aggregation : "mean", "sum" or "scaled" (the sum divided by ``mean_degree``)
    linear_aggregate : (mpnode only) the field also adds m' @ W_agg, a path linear in the
        aggregate m', so that a denser graph's larger aggregate is not squashed by the
        MLP's tanh units (the gene dynamics are linear in the neighbour sum)
    linear_target : what that path adds to: "all" ([dx/dt, dm/dt], W_agg (dm, dx+dm)) or
        "state" (dx/dt alone, W_agg (dm, dx): the messages' own dynamics then never hear
        the degree, only the MLP's degree-free input)
    linear_aggregation : the aggregate that path reads when it is not the MLP's own m'
        ("mean", "sum" or "scaled"; None: the MLP's).  E.g. aggregation "mean" with
        linear_aggregation "scaled": the MLP sees a degree-free input that stays in range on
        denser graphs, and the degree reaches the field only through the linear path
        (as PNA's degree scalers)
    """

    state_dim: int
    control_dim: int
    message_dim: int
    hidden: int
    dt: float
    substeps: int = 1
    zero_messages: bool = False
    self_messages: bool = False
    kind: str = "mpnode"
    aggregation: str = "mean"
    mean_degree: float = None
    n_nodes: int = None
    linear_aggregate: bool = False
    linear_aggregation: str = None
    linear_target: str = "all"

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, not {self.kind!r}")
        if self.aggregation not in AGGREGATIONS:
            raise ValueError(f"aggregation must be one of {AGGREGATIONS}, not {self.aggregation!r}")
        if self.linear_aggregation is not None and self.linear_aggregation not in AGGREGATIONS:
            raise ValueError(f"linear_aggregation must be one of {AGGREGATIONS} or None, "
                             f"not {self.linear_aggregation!r}")
        if self.linear_target not in LINEAR_TARGETS:
            raise ValueError(f"linear_target must be one of {LINEAR_TARGETS}, not {self.linear_target!r}")
        if self.linear_target != "all" and not self.linear_aggregate:
            raise ValueError("linear_target goes with linear_aggregate (the path it says where to add)")
        if self.linear_aggregation is not None and not self.linear_aggregate:
            raise ValueError("linear_aggregation goes with linear_aggregate (the path it feeds)")
        if ("scaled" in (self.aggregation, self.linear_aggregation)) != (self.mean_degree is not None):
            raise ValueError("mean_degree goes with aggregation or linear_aggregation 'scaled' (and only with it)")
        if self.mean_degree is not None and not self.mean_degree > 0:
            raise ValueError(f"mean_degree must be > 0, not {self.mean_degree}")
        if self.kind != "mpnode" and (self.message_dim or self.zero_messages):
            raise ValueError(f"a {self.kind} model has no message state (message_dim 0, no zero_messages)")
        if (self.kind == "node") != (self.n_nodes is not None):
            raise ValueError("n_nodes goes with kind 'node' (and only with it)")
        if self.linear_aggregate and (self.kind != "mpnode" or not self.message_dim or self.zero_messages):
            raise ValueError("linear_aggregate needs an mpnode model with messages (message_dim > 0, no zero_messages)")

    @property
    def dims(self):
        """The kernels' (kind, dx, du, dm, H, self_msg, zero_msg, linear_agg) tuple (kinds mpnode and l2s);
        linear_agg: flags, 1 the linear path is there, 2 it reads its own aggregate (see Plan.weight),
        4 it adds to dx/dt alone (mpnode.kernels.mpnode_field)."""
        flags = 0
        if self.linear_aggregate:
            flags = 1 | (2 if self.own_linear_aggregation else 0) | (4 if self.linear_target == "state" else 0)
        return (KINDS.index(self.kind), self.state_dim, self.control_dim, self.message_dim, self.hidden,
                int(self.self_messages), int(self.zero_messages), flags)

    @property
    def own_linear_aggregation(self):
        """The linear path's aggregation when it differs from the MLP's, else None."""
        la = self.linear_aggregation
        return la if self.linear_aggregate and la is not None and la != self.aggregation else None

    @property
    def state_width(self):
        """Columns of the integrated state z: dx + dm."""
        return self.state_dim + self.message_dim


# ---------------------------------------------------------------------------
# Graph preparation: closed blocks, degrees, the transpose.
# ---------------------------------------------------------------------------
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


class Plan:
    """How the kernels cover a graph: blocks of whole graphs, each dense or CSR.

    blocks : ndarray (n_blocks+1,) of node boundaries, or None for the stagewise drivers
    dense_n, dense_off : ndarray (n_blocks,) -- block b is copies of one dense_n[b]-node
        graph whose 0/1 adjacency (self-loop included for self_messages) starts at
        dense_A[dense_off[b]] (row-major); dense_n[b] = 0 means CSR
    dense_A, dense_AT : flat arrays of those matrices and their transposes
    weight : ndarray (M,) -- each node's factor on the sum of what its row sends (aggregation);
        (2M,) when the linear path has its own aggregation: then weight[M + i] is node i's
        factor from the MLP's aggregate to the linear path's (`linear_scale`), so that every
        kernel that reads weight[i] stays as it is
    order : ndarray (M,) or None -- the kernels' node k is the user's node order[k] (a
        locality order for one large graph, see `locality_order`); None: the user's order
    csr : Graph -- the graph as the kernels read it (renumbered by ``order``)
    transposed : Graph -- the CSR transpose of ``csr`` (computed on first use, for the adjoint)
    """

    def __init__(self, graph, n_threads, self_messages, dtype, aggregation, mean_degree, driver="auto",
                 blocks_per_thread=2, tile=128, ordering="auto", linear_aggregation=None):
        self.blocks = None
        self.order = None
        self.csr = Graph(graph.indptr, graph.indices)  # not the graph: the cache holds it weakly
        self._transposed = None
        self.weight = aggregation_weights(graph, self_messages, aggregation, mean_degree, dtype)
        if linear_aggregation is not None:
            self.weight = np.concatenate([self.weight, linear_scale(graph, self_messages, aggregation,
                                                                    linear_aggregation, mean_degree, dtype)])
        m = graph.n_nodes
        parts = graph.parts or (graph,)
        sizes = np.array([p.n_nodes for p in parts], dtype=np.int64)
        if graph.parts is None or len(parts) == 1:
            pieces = closed_pieces(graph)
            parts, sizes = (None,) * (len(pieces) - 1), np.diff(pieces)
        n_blocks = max(1, n_threads * blocks_per_thread)
        too_big = m >= 2 * tile * n_threads and sizes.max(initial=0) > m / n_blocks
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
                a[np.repeat(np.arange(g.n_nodes), g.degrees()), g.indices] = 1
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

    def to_kernel_order(self, a, axis=0):
        """``a`` with its node axis in the kernels' order (``a`` itself when there is no reordering)."""
        return a if self.order is None else np.take(a, self.order, axis=axis)

    def to_user_order(self, a):
        """Put the node axis (axis 1) of ``a`` (T, M, .) back in the user's order, in place,
        one time slice at a time (no second copy of a large rollout)."""
        if self.order is not None:
            for t in range(a.shape[0]):
                a[t, self.order] = a[t].copy()
        return a


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
    indices = position[graph.indices[starts + np.arange(graph.n_edges, dtype=np.int64)]]
    return Graph(indptr, indices, self_loops=graph.self_loops)


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
    key = (_n_threads(), bool(spec.self_messages), np.dtype(dtype).str, driver, spec.aggregation, spec.mean_degree,
           ordering, spec.own_linear_aggregation)
    per_graph = _plans.setdefault(graph, {})
    if key not in per_graph:
        per_graph[key] = Plan(graph, key[0], spec.self_messages, dtype, spec.aggregation, spec.mean_degree, driver,
                              ordering=ordering, linear_aggregation=spec.own_linear_aggregation)
    return per_graph[key]


def aggregation_weights(graph, self_messages, aggregation, mean_degree, dtype):
    """Each node's factor on the sum over its row [and itself]: mean 1 / that count, sum 1,
    scaled 1 / mean_degree; 0 for a node that hears nobody (its aggregate is 0)."""
    d = graph.degrees() + (1 if self_messages else 0)
    out = np.zeros(graph.n_nodes, dtype=dtype)
    if aggregation == "mean":
        np.divide(1.0, d, out=out, where=d > 0, casting="unsafe")
    else:
        out[d > 0] = 1.0 if aggregation == "sum" else 1.0 / mean_degree
    return out


def linear_scale(graph, self_messages, aggregation, linear_aggregation, mean_degree, dtype):
    """Each node's factor from the MLP's aggregate to the linear path's: the ratio of their
    weights (e.g. mean -> scaled: degree / mean_degree); 0 for a node that hears nobody."""
    w = aggregation_weights(graph, self_messages, aggregation, mean_degree, np.float64)
    wl = aggregation_weights(graph, self_messages, linear_aggregation, mean_degree, np.float64)
    out = np.zeros(graph.n_nodes, dtype=dtype)
    np.divide(wl, w, out=out, where=w > 0, casting="unsafe")
    return out


def transpose(graph):
    """The CSR transpose: row j lists the nodes that hear j (for the adjoint's scatter)."""
    rows = np.repeat(np.arange(graph.n_nodes, dtype=np.int64), graph.degrees())
    order = np.argsort(graph.indices, kind="stable")
    indptr = np.zeros(graph.n_nodes + 1, dtype=np.int64)
    np.cumsum(np.bincount(graph.indices, minlength=graph.n_nodes), out=indptr[1:])
    return Graph(indptr, rows[order], self_loops=graph.self_loops)


# ---------------------------------------------------------------------------
# Threads: numba's pool does the parallel work; BLAS runs single-threaded inside it.
# ---------------------------------------------------------------------------
_blas_libs = None


@contextlib.contextmanager
def single_threaded_blas():
    """Pin BLAS to one thread while numba's threads call it (two pools fight: 5-100x slower).

    The libraries are found once (threadpoolctl's scan costs ~2 ms); each call then only
    sets and restores their thread counts.
    """
    global _blas_libs
    if _blas_libs is None:
        import scipy.linalg.cython_blas  # noqa: F401  (the BLAS numba calls must be loaded to be seen)
        from threadpoolctl import ThreadpoolController

        _blas_libs = ThreadpoolController().select(user_api="blas").lib_controllers
    before = [lib.num_threads for lib in _blas_libs]
    for lib in _blas_libs:
        lib.set_num_threads(1)
    try:
        yield
    finally:
        for lib, n in zip(_blas_libs, before):
            lib.set_num_threads(n)


def _n_threads():
    import numba

    return numba.get_num_threads()


# ---------------------------------------------------------------------------
# Backends: the compiled kernels, or the NumPy path where numba cannot be imported.
# ---------------------------------------------------------------------------
#: "auto" (numba when it imports, else numpy), "numba" (the compiled kernels), "numpy"
#: (mpnode.numpy_engine: the same rollout in plain NumPy; slow, no training)
BACKENDS = ("auto", "numba", "numpy")
_numba_problem = []  # [] untried; [None] numba imports; [reason] it does not
_warned = []  # [True] once the fallback to NumPy has been announced


def numba_problem():
    """None when the compiled kernels import, else why not (tried once, then remembered)."""
    if not _numba_problem:
        try:
            from . import kernels  # noqa: F401  (imports numba and declares the kernels; compiles nothing)
            _numba_problem.append(None)
        except Exception as e:  # a missing numba, or a broken one (llvmlite raises OSError, ...)
            _numba_problem.append(f"{type(e).__name__}: {e}")
    return _numba_problem[0]


def resolve_backend(backend="auto", purpose="the compiled backend"):
    """"numba" or "numpy" for a requested backend (BACKENDS).

    "auto" falls back to "numpy" when numba cannot be imported, with one warning per
    process; "numba" then raises ImportError saying why.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, not {backend!r}")
    if backend == "numpy":
        return backend
    problem = numba_problem()
    if problem is None:
        return "numba"
    if backend == "numba":
        raise ImportError(f"{purpose} needs numba, which cannot be imported here ({problem}); "
                          "install numba, or roll out with backend='numpy' (no training)")
    if not _warned:
        import warnings

        _warned.append(True)
        warnings.warn(f"numba cannot be imported ({problem}): using the NumPy path, which rolls out "
                      "the same models several times slower and cannot train", RuntimeWarning, stacklevel=3)
    return "numpy"


# ---------------------------------------------------------------------------
# Entry points
# ---------------------------------------------------------------------------
def checked_controls(spec, graph, u, n_steps, n_nodes, dtype):
    """u as a contiguous (n_steps, M, du) array in ``dtype`` (width 0 for None), after checking
    that the parameters' dtype, u and the graph fit the states (ValueError, TypeError)."""
    if dtype not in (np.float32, np.float64):
        raise TypeError(f"parameters must be float32 or float64, not {dtype}")
    if u is None:
        if spec.control_dim:
            raise ValueError(f"the model takes controls (du={spec.control_dim}) but u is None")
        u = np.zeros((n_steps, n_nodes, 0), dtype=dtype)
    u = np.ascontiguousarray(u, dtype=dtype)
    if u.shape != (n_steps, n_nodes, spec.control_dim):
        raise ValueError(f"u has shape {u.shape}, expected {(n_steps, n_nodes, spec.control_dim)}")
    if graph.n_nodes != n_nodes:
        raise ValueError(f"graph has {graph.n_nodes} nodes but the states have {n_nodes}")
    return u


def _prepare(spec, theta, graph, u, n_steps, n_nodes, driver, ordering):
    dtype = theta.dtype
    u = checked_controls(spec, graph, u, n_steps, n_nodes, dtype)
    h = dtype.type(spec.dt / spec.substeps)
    return u, plan_for(graph, spec, dtype, driver, ordering), h


def _whole_systems(spec, x0, u, graph):
    """A plain NODE as the kernels run it: an MP-NODE field without messages on one "node"
    per system, whose state is [x_1, ..., x_N] and control [u_1, ..., u_N] (node-major, so
    the flat rows of a system reshape to it for free), on a graph with no edges."""
    n = spec.n_nodes
    m, dx = x0.shape
    if graph.n_nodes != m:
        raise ValueError(f"graph has {graph.n_nodes} nodes but the states have {m}")
    if m % n:
        raise ValueError(f"{m} nodes are not whole systems of {n} nodes (a node model's n_nodes)")
    inner = replace(spec, kind="mpnode", state_dim=n * dx, control_dim=n * spec.control_dim, n_nodes=None)
    u = None if u is None else np.asarray(u).reshape(u.shape[0], m // n, n * spec.control_dim)
    return inner, np.asarray(x0).reshape(m // n, n * dx), u, _edgeless(m // n)


@functools.lru_cache(maxsize=16)
def _edgeless(n):
    return Graph(np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int64))


def _run(spec, theta, z0, graph, u, n_steps, driver, keep_states, ordering):
    """The forward rollout from the full state z0: (x (n_steps+1, M, dx) and z at the end in
    the user's node order, states or None and u in the kernels' order, plan, h)."""
    from . import kernels

    theta = np.ascontiguousarray(theta)
    z0 = np.ascontiguousarray(z0, dtype=theta.dtype)
    m = z0.shape[0]
    if z0.shape != (m, spec.state_width):
        raise ValueError(f"the full state has shape {z0.shape}, expected (M, {spec.state_width}) (x, then messages)")
    u, plan, h = _prepare(spec, theta, graph, u, n_steps, m, driver, ordering)
    z0, u = plan.to_kernel_order(z0), np.ascontiguousarray(plan.to_kernel_order(u, axis=1))
    out = np.empty((n_steps + 1, m, spec.state_dim), dtype=theta.dtype)
    n_states = n_steps * spec.substeps + 1 if keep_states else 0
    states = np.empty((n_states, m if keep_states else 0, spec.state_width), dtype=theta.dtype)
    zend = np.empty_like(z0)
    g = (plan.csr.indptr, plan.csr.indices, plan.weight)
    with single_threaded_blas():
        if plan.blocks is None:
            kernels.rollout_stagewise(theta, spec.dims, z0, u, g, spec.substeps, h, out, states, zend)
        else:
            kernels.rollout_blocks(theta, spec.dims, z0, u, g, plan.blocks, plan.dense_n, plan.dense_off,
                                   plan.dense_A, spec.substeps, h, out, states, zend)
    return plan.to_user_order(out), states, plan.to_user_order(zend[None])[0], u, plan, h


def initial_state(spec, x0, dtype=None):
    """The full state [x0, 0] (M, dx + dm) a rollout starts from: messages start at 0."""
    x0 = np.asarray(x0)
    z0 = np.zeros((x0.shape[0], spec.state_width), dtype=dtype or x0.dtype)
    z0[:, :spec.state_dim] = x0
    return z0


def forward(spec, theta, x0, graph, u=None, n_steps=1, driver="auto", backend="auto", ordering="auto"):
    """Integrate from x0 (messages start at 0).

    x0 : ndarray, shape (M, dx); u : ndarray, shape (n_steps, M, du) or None;
    returns x : ndarray, shape (n_steps+1, M, dx), in theta's dtype.
    driver, ordering : see plan_for.  For kind "node" the graph only gives M (whole systems).
    backend : see `resolve_backend` ("auto": the compiled kernels, NumPy without numba).
    """
    z0 = initial_state(spec, x0, np.asarray(theta).dtype)
    return integrate(spec, theta, z0, graph, u, n_steps, driver, backend, ordering)[0]


def integrate(spec, theta, z0, graph, u=None, n_steps=1, driver="auto", backend="auto", ordering="auto"):
    """Integrate from a full state z0 = [x, m] (M, dx + dm), e.g. where an earlier call stopped.

    Returns (x, z): x (n_steps+1, M, dx) as `forward`, z (M, dx + dm) the full state at the
    end.  Calling this T times with n_steps=1, each from the last z, gives bit for bit the
    rollout of T steps (same kernels, same plan): the stepping API (mpnode.Simulator) is
    built on it.  Other arguments as `forward`.
    """
    if resolve_backend(backend) == "numpy":
        from . import numpy_engine

        return numpy_engine.integrate(spec, theta, z0, graph, u, n_steps)
    z_shape = np.shape(z0)
    shape = (n_steps + 1, z_shape[0], spec.state_dim)
    if spec.kind == "node":
        spec, z0, u, graph = _whole_systems(spec, z0, u, graph)
    x, _, zend, _, _, _ = _run(spec, theta, z0, graph, u, n_steps, driver, False, ordering)
    return x.reshape(shape), zend.reshape(z_shape)


def forward_with_vjp(spec, theta, x0, graph, u=None, n_steps=1, driver="auto", keep_states=True, ordering="auto"):
    """`forward`, and the vector-Jacobian product of the rollout (the discrete adjoint).

    Returns (x, vjp): x as `forward`; ``vjp(gx)`` takes the cotangent of every output
    state, gx : ndarray, shape (n_steps+1, M, dx), and returns (gtheta like theta,
    gx0 of shape (M, dx)): the gradient of sum(gx * x) with respect to theta and x0.
    vjp may be called several times; it keeps one state per RK4 step alive
    (``keep_states=False``: no vjp, the rollout alone).  Compiled kernels only (numba):
    the NumPy path rolls out but does not train.
    """
    resolve_backend("numba", purpose="computing gradients (training)")
    from . import kernels

    shape = (n_steps + 1,) + np.shape(x0)
    if spec.kind == "node":
        spec, x0, u, graph = _whole_systems(spec, x0, u, graph)
    z0 = initial_state(spec, x0, np.asarray(theta).dtype)
    x, states, _, u, plan, h = _run(spec, theta, z0, graph, u, n_steps, driver, keep_states, ordering)
    x = x.reshape(shape)
    if not keep_states:
        return x, None
    theta = np.ascontiguousarray(theta)
    m = states.shape[1]

    def vjp(gx):
        if np.shape(gx) != shape:
            raise ValueError(f"the cotangent has shape {np.shape(gx)}, the rollout {shape}")
        gx = np.asarray(gx, dtype=theta.dtype).reshape(n_steps + 1, m, spec.state_dim)
        gx = np.ascontiguousarray(plan.to_kernel_order(gx, axis=1))
        tgraph = plan.transposed
        n_parts = len(plan.blocks) - 1 if plan.blocks is not None else -(-m // kernels.STAGE_TILE)
        gthetas = np.empty((n_parts, theta.size), dtype=theta.dtype)
        gx0 = np.empty((m, spec.state_dim), dtype=theta.dtype)
        g, gt = (plan.csr.indptr, plan.csr.indices, plan.weight), (tgraph.indptr, tgraph.indices)
        with single_threaded_blas():
            if plan.blocks is None:
                kernels.vjp_stagewise(theta, spec.dims, u, g, gt, spec.substeps, h, states, gx, gthetas, gx0)
            else:
                kernels.vjp_blocks(theta, spec.dims, u, g, gt, plan.blocks, plan.dense_n, plan.dense_off,
                                   plan.dense_A, plan.dense_AT, spec.substeps, h, states, gx, gthetas, gx0)
        if plan.order is not None:
            gx0[plan.order] = gx0.copy()
        return gthetas.sum(axis=0, dtype=theta.dtype), gx0.reshape(shape[1:])

    return x, vjp
