"""RK4 rollouts of an MP-NODE over a flat (block-diagonal) graph, and their exact gradient.

The gradient is the *discrete adjoint*: the exact derivative of the RK4 rollout as
computed, obtained by walking the steps backwards.  Cost: memory for one state per
RK4 step (T*substeps+1 arrays of (M, dz)); time about 4x a rollout (forward,
recomputed stages, and a VJP that costs about twice a forward).  Stage values are
recomputed rather than stored, so memory does not grow with the hidden width.

Arrays here are time-major and flat over nodes: x (T+1, M, dx), u (T, M, du).
`mpnode.model` turns (B, T+1, N, dx) batches into this layout.
"""
import contextlib
import os
from dataclasses import dataclass

import numpy as np

from .graph import Graph

LOSSES = {"huber": 0, "mse": 1}


@dataclass(frozen=True)
class FieldSpec:
    """What the kernels need to know about a model besides its weights."""

    state_dim: int
    control_dim: int
    message_dim: int
    hidden: int
    dt: float
    substeps: int = 1
    zero_messages: bool = False
    self_messages: bool = False


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


def plan_blocks(graph, n_threads, blocks_per_thread=2, tile=128):
    """Block boundaries for the block drivers, or None when one graph is too big to split.

    Whole closed pieces are grouped greedily into about n_threads*blocks_per_thread blocks.
    """
    m = graph.n_nodes
    pieces = closed_pieces(graph)
    largest = int(np.max(np.diff(pieces))) if m else 0
    n_blocks = max(1, n_threads * blocks_per_thread)
    if m >= 2 * tile * n_threads and largest > m / n_blocks:
        return None
    target = m / n_blocks
    bounds = [0]
    for end in pieces[1:]:
        if end - bounds[-1] >= target or end == m:
            bounds.append(int(end))
    return np.asarray(bounds, dtype=np.int64)


def inverse_degree(graph, self_messages, dtype):
    """1 / (row length [+1 when a node hears itself]); 0 for a node that hears nobody."""
    d = graph.degrees() + (1 if self_messages else 0)
    out = np.zeros(graph.n_nodes, dtype=dtype)
    np.divide(1.0, d, out=out, where=d > 0, casting="unsafe")
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
# Entry points
# ---------------------------------------------------------------------------
def _prepare(spec, theta, graph, u, n_steps, n_nodes):
    dtype = theta.dtype
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
    inv_deg = inverse_degree(graph, spec.self_messages, dtype)
    h = dtype.type(spec.dt / spec.substeps)
    return u, inv_deg, h


def rollout(spec, theta, x0, graph, u=None, n_steps=1):
    """Integrate from x0 (messages start at 0).

    x0 : ndarray, shape (M, dx); u : ndarray, shape (n_steps, M, du) or None;
    returns x : ndarray, shape (n_steps+1, M, dx), in theta's dtype.
    """
    from . import kernels

    theta = np.ascontiguousarray(theta)
    x0 = np.ascontiguousarray(x0, dtype=theta.dtype)
    m = x0.shape[0]
    u, inv_deg, h = _prepare(spec, theta, graph, u, n_steps, m)
    out = np.empty((n_steps + 1, m, spec.state_dim), dtype=theta.dtype)
    args = (theta, spec.message_dim, spec.hidden, x0, u, graph.indptr, graph.indices, inv_deg)
    flags = (spec.substeps, h, spec.self_messages, spec.zero_messages, out)
    blocks = plan_blocks(graph, _n_threads())
    with single_threaded_blas():
        if blocks is None:
            kernels.rollout_stagewise(*args, *flags)
        else:
            kernels.rollout_blocks(*args, blocks, *flags)
    return out


def loss_and_grad(spec, theta, x, graph, u=None, loss="huber", n_nodes_total=None):
    """Loss of the rollout from x[0] against x[1..T] and its exact gradient.

    x : ndarray, shape (T+1, M, dx) -- the true states (x[0] is the initial state).
    The loss is Huber (delta 1) or squared error, summed over state dimensions and
    steps 1..T and divided by the number of nodes (``n_nodes_total``, default M).
    Returns (loss, gtheta like theta, gx0 of shape (M, dx)).
    """
    from . import kernels

    theta = np.ascontiguousarray(theta)
    x = np.ascontiguousarray(x, dtype=theta.dtype)
    n_steps, m = x.shape[0] - 1, x.shape[1]
    u, inv_deg, h = _prepare(spec, theta, graph, u, n_steps, m)
    kind = LOSSES[loss]
    scale = 1.0 / (n_nodes_total or m)
    dz = spec.state_dim + spec.message_dim
    states = np.empty((n_steps * spec.substeps + 1, m, dz), dtype=theta.dtype)
    gx0 = np.empty((m, spec.state_dim), dtype=theta.dtype)
    tgraph = transpose(graph)
    args = (theta, spec.message_dim, spec.hidden, x, u, graph.indptr, graph.indices, inv_deg,
            tgraph.indptr, tgraph.indices)
    blocks = plan_blocks(graph, _n_threads())
    n_parts = len(blocks) - 1 if blocks is not None else -(-m // kernels.TILE)
    gthetas = np.empty((n_parts, theta.size), dtype=theta.dtype)
    losses = np.zeros(n_parts, dtype=np.float64)
    tail = (spec.substeps, h, spec.self_messages, spec.zero_messages, kind, scale, states, gthetas, losses, gx0)
    with single_threaded_blas():
        if blocks is None:
            kernels.loss_grad_stagewise(*args, *tail)
        else:
            kernels.loss_grad_blocks(*args, blocks, *tail)
    return float(losses.sum()), gthetas.sum(axis=0, dtype=theta.dtype), gx0
