"""The Jacobians of one step, d(next x)/d(x) and d(next x)/d(u), exactly, by compressed reverse mode.

A row of a step's Jacobian is one VJP of the step (the engine's discrete adjoint) with a
one-hot cotangent.  Rows whose nonzeros never share a column can share a VJP: their
cotangents are added and each entry of the result belongs to exactly one of them.  Which
columns a row can touch follows the graph: within one RK4 step a node's next state hears
the nodes up to `reach_hops` away (messages held at their current values: an MP-NODE
node's own x and u enter its messages at the second stage, which reach a neighbour's
third and so on).  So the rows of the B copies are coloured once (greedy, on the graph's
reach pattern), and every (colour, state dimension) pair is one copy of the whole batch
in a single block-diagonal rollout of one step through the block driver: the cost is
colours x dx copies of one step and its VJP, whatever N (docs/evidence/control.md).
"""
import functools

import numpy as np

from mpnode.base.graph import block_diagonal

from .rollout import integrate_with_vjp

#: most nodes in one batched step (copies beyond it go in further batches): bounds the memory
MAX_BATCH_NODES = 1 << 20


def reach_hops(spec):
    """How many hops of the graph one step of ``spec`` reaches (None: the whole system, kind node).

    MP-NODE: its messages carry x and u one hop per stage from the second on, 4 substeps - 1
    (0 without messages); L2S: every stage hears the neighbours' x, 4 substeps.
    """
    if spec.kind == "node":
        return None
    if spec.kind == "l2s":
        return 4 * spec.substeps
    return 4 * spec.substeps - 1 if spec.message_dim and not spec.zero_messages else 0


def reach_pattern(spec, graph):
    """P (N, N) scipy CSR of booleans: P[i, j] when node i's next state can depend on node j's
    state or control (j within reach_hops of i along the edges i hears)."""
    import scipy.sparse as sp

    n = graph.n_nodes
    hops = reach_hops(spec)
    if hops is None:
        return sp.csr_array(np.ones((n, n), dtype=bool))
    step = sp.csr_array((np.ones(graph.n_edges, dtype=bool), graph.indices, graph.indptr), shape=(n, n))
    step = (step + sp.eye_array(n, dtype=bool, format="csr")).astype(bool)
    pattern = sp.eye_array(n, dtype=bool, format="csr")
    for _ in range(hops):
        pattern = (pattern @ step).astype(bool)
    pattern.sort_indices()
    return pattern.tocsr()


def row_colours(pattern):
    """Colours (N,) of the pattern's rows such that two rows of one colour share no column
    (greedy, most nonzeros first): one VJP then serves every row of a colour."""
    conflicts = (pattern @ pattern.T).tocsr()
    n = pattern.shape[0]
    colour = np.full(n, -1, dtype=np.int64)
    taken = np.full(n + 1, -1, dtype=np.int64)
    for i in np.argsort(-np.diff(conflicts.indptr), kind="stable"):
        near = colour[conflicts.indices[conflicts.indptr[i]:conflicts.indptr[i + 1]]]
        taken[near[near >= 0]] = i
        c = 0
        while taken[c] == i:
            c += 1
        colour[i] = c
    return colour


@functools.lru_cache(maxsize=8)
def _copies(graph, n):
    return block_diagonal([graph] * n)


@functools.lru_cache(maxsize=8)
def _colouring(spec, graph):
    """(pattern, colours) of ``spec`` on ``graph``, kept: a control loop asks every step."""
    pattern = reach_pattern(spec, graph)
    return pattern, row_colours(pattern)


def step_jacobians(spec, theta, z, graph, u=None, sparse=False):
    """d(x after one step)/d(x) and d(.)/d(u) of B copies of ``graph`` from the full state z.

    z : (B*N, dx + dm) the full state (messages held at their values); u : (B*N, du) or None;
    graph : one copy's Graph (N nodes).  In the units the engine integrates (normalised),
    node-major.  Returns dense (B, N*dx, N*dx) and (B, N*dx, N*du), or with ``sparse``
    two lists of B scipy CSR arrays of those shapes, their pattern `reach_pattern`'s.
    """
    n, dx, du = graph.n_nodes, spec.state_dim, spec.control_dim
    z = np.asarray(z)
    b = z.shape[0] // n
    pattern, colour = _colouring(spec, graph)
    n_copies = (int(colour.max()) + 1) * dx
    rows, cols = np.repeat(np.arange(n), np.diff(pattern.indptr)), pattern.indices
    gx_all = np.empty((n_copies, b, n, dx), dtype=np.asarray(theta).dtype)
    gu_all = np.empty((n_copies, b, n, du), dtype=gx_all.dtype)
    per_batch = max(1, MAX_BATCH_NODES // max(1, b * n))
    for lo in range(0, n_copies, per_batch):
        hi = min(n_copies, lo + per_batch)
        gx_all[lo:hi], gu_all[lo:hi] = _compressed_rows(spec, theta, z, graph, u, colour, lo, hi)
    # row (i, d) of copy b sits in VJP copy colour[i] * dx + d, at node j: the entry (i, d), (j, .)
    copy = (colour[rows][:, None] * dx + np.arange(dx)).ravel()  # (nnz * dx,) pairs (i, j), then d
    jx = gx_all[copy, :, np.repeat(cols, dx)]  # (nnz * dx, b, dx)
    ju = gu_all[copy, :, np.repeat(cols, dx)]
    return (_assemble(jx, rows, cols, n, dx, dx, sparse),
            _assemble(ju, rows, cols, n, dx, du, sparse))


def _compressed_rows(spec, theta, z, graph, u, colour, lo, hi):
    """VJPs of one step for copies lo..hi of the batch (copy c: the rows of colour c // dx,
    state dimension c % dx, as one summed cotangent): gx0 (hi-lo, B, N, dx) and gu (.., du)."""
    n, dx = graph.n_nodes, spec.state_dim
    b = z.shape[0] // n
    k = hi - lo
    big = _copies(graph, k * b)
    zz = np.tile(z, (k, 1))
    uu = None if u is None else np.tile(np.asarray(u), (k, 1))[None]
    _, vjp = integrate_with_vjp(spec, theta, zz, big, uu, 1)
    gx = np.zeros((2, k, b, n, dx), dtype=np.asarray(theta).dtype)
    for c in range(lo, hi):
        gx[1, c - lo, :, colour == c // dx, c % dx] = 1
    _, gx0, gu = vjp(gx.reshape(2, k * b * n, dx), controls=True)
    return gx0.reshape(k, b, n, dx), gu.reshape(k, b, n, spec.control_dim)


def _assemble(values, rows, cols, n, dx, dc, sparse):
    """values (nnz * dx, B, dc) of the pattern's entries (i, j) by output dimension d, as B
    matrices (n*dx, n*dc): dense (B, ., .) or a list of CSR arrays."""
    import scipy.sparse as sp

    b = values.shape[1]
    r = (rows[:, None] * dx + np.arange(dx)).ravel()  # (nnz * dx,)
    rr = np.repeat(r, dc)
    cc = (np.repeat(cols, dx)[:, None] * dc + np.arange(dc)).ravel()
    if not sparse:
        out = np.zeros((b, n * dx, n * dc), dtype=values.dtype)
        out[:, rr, cc] = values.transpose(1, 0, 2).reshape(b, -1)
        return out
    return [sp.csr_array((values[:, k].ravel(), (rr, cc)), shape=(n * dx, n * dc)) for k in range(b)]
