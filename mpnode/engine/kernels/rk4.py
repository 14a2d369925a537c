"""Classic RK4 rollouts of a field on a flat graph, and their reverse pass (discrete adjoint).

Layout.  The B graphs of a batch are one block-diagonal graph of M nodes.  A node's
integrated state is z (dz columns: [x, m] for the MP-NODE, x for L2S), kept in arrays
of shape (rows, dz); rows hold either all M nodes (``zoff = 0``) or one *block* of
nodes ``lo..hi`` (``zoff = lo``): node ``i`` lives in row ``i - zoff``.

A stage evaluates the field in three phases: *send* (what each node sends; only L2S
computes anything), the neighbour *sum* (a dense GEMM for blocks of copies of one small
graph, else the CSR rows), and *update* (the per-node network), whose output k is
folded into the RK4 step at once.  The reverse pass walks the same phases backwards:
update VJP, the transpose of the sum, send VJP.

Two drivers per direction, sharing every tile function:
- *block* drivers: the nodes split into blocks closed under the graph (whole graphs of
  the batch); a call runs the whole time loop of blocks b0..b1, no barrier per stage, without
  the GIL: the caller runs the blocks on threads of its own (`mpnode.engine.backend.run_blocks`).
  They are plain functions, not numba parallel loops: a parallel loop over a driver's body
  took a quarter of its first compile (docs/evidence/cold-start.md).
- *stagewise* drivers: one large connected graph; every phase of a stage is a parallel
  loop over tiles of nodes.

Time.  Output step t (t = 0..T-1) is reached by ``nsub[t]`` RK4 steps, node i's of size
``hstep[t, i]``: every node of a trajectory has its trajectory's step size, so a batch whose
trajectories are observed at different times is integrated together (a regular batch has
nsub[t] = substeps and one step size everywhere; a trajectory that has ended has size 0).

The forward drivers start from a full state z0 (M, dz) and return the final one in
``zend`` (a rollout continues exactly where the last one stopped); they keep the state
after every RK4 step when given a ``states`` array (sum(nsub)+1, M, dz); the reverse
drivers take the cotangent of every output state, GX (T+1, M, dx), read each step's stage
caches where the forward kept them (block drivers, given ``kept``: a driver compiled apart, without
the forward stage) or recompute them from the kept state, and return the parameter cotangent (one buffer per block or
tile, reduced by the caller: deterministic, no races), the initial state's and, when the
caller gives GU (T, M, du) rows, the controls' (each node's rows are its own: no races
either).  ``dims``: the model's integers (slots in mpnode.engine.dims); ``graph`` =
(indptr, indices, weight, ew) -- ``weight`` each node's factor on its row's sum, ``ew`` the
edges' weights or empty (all 1) -- and ``tgraph`` = (tindptr, tindices, tew) its transpose.

Which field.  The functions that run a field take ``l2s``: None for the MP-NODE field, 1 for
L2S.  numba drops a branch on ``l2s is None`` when it compiles for ``l2s`` None, so an MP-NODE
driver holds no L2S code, and a first MP-NODE run compiles none (docs/evidence/cold-start.md).
An L2S driver (``l2s`` an int64) holds both fields' code: numba drops
such a branch only for None or a literal, and ``numba.literally`` would have made every call
from Python try a compile first.
"""
import numpy as np
from numba import njit, prange

from ..dims import DM, DU, DX, HIDDEN, KINEMATICS, KIND, L2S, SELF_MSG, ZERO_MSG
from . import kinematics, l2s_field, mpnode_field
from .feature_major import aligned_empty, dense_sum
from .layers import JIT, add_into, copy_into, edge_cotangent, transpose_tile

TILE = 192  # rows per tile inside a block (one block per thread: a few hundred nodes)
STAGE_TILE = 256  # rows per parallel task of the stagewise drivers (one big graph: fewer, larger tasks)

# RK4 (classic): stage s reads z + C[s] h k_{s-1}; z+ = z + h sum_s B[s] k_s.
RK_C = (0.0, 0.5, 0.5, 1.0)
RK_B = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)
#: C[s+1], the next stage's, indexed by s (0 after the last stage): every index in range, since
#: numba's parallel loops may hoist a lookup out of the branch that guards it
RK_C_NEXT = RK_C[1:] + (0.0,)


# ---------------------------------------------------------------------------
# Sizes and work arrays
# ---------------------------------------------------------------------------
@njit(inline="always", **JIT)
def sent_width(dims):
    """Columns a node sends its neighbours: dm (MP-NODE messages) or H (L2S)."""
    return dims[HIDDEN] if dims[KIND] == L2S else dims[DM]


@njit(inline="always", **JIT)
def state_width(dims):
    return dims[DX] + (0 if dims[KIND] == L2S else dims[DM])


@njit(**JIT)
def caches(dims, slots, n, like):
    """Per-stage caches of the field (slots, n, .): MP-NODE (V, H1, H2, -, -), L2S (V, H0, S, A, T)."""
    kind, dx, du, dm, H = dims[KIND], dims[DX], dims[DU], dims[DM], dims[HIDDEN]
    if kind == L2S:
        w = (dx + du, H, H, H, H)
    else:
        w = (dx + du + dm, H, H, 0, 0)
    return (aligned_empty((slots, n, w[0]), like), aligned_empty((slots, n, w[1]), like),
            aligned_empty((slots, n, w[2]), like), aligned_empty((slots, n, w[3]), like),
            aligned_empty((slots, n, w[4]), like))


@njit(inline="always", **JIT)
def stage_arrays(stage, z, za, zb):
    """(input, output) arrays of a stage: z -> za -> zb -> za -> z (ping-pong buffers)."""
    if stage == 0:
        return z, za
    if stage == 1:
        return za, zb
    if stage == 2:
        return zb, za
    return za, z


@njit(inline="always", **JIT)
def dense_block(mats, n, off):
    """A dense block's (n, n) matrix (its adjacency, or the adjacency's transpose) from the flat ``mats``;
    (0, 0) when the block uses CSR."""
    return mats[off:off + n * n].reshape(n, n)


# ---------------------------------------------------------------------------
# One stage: send, sum, update + fold
# ---------------------------------------------------------------------------
@njit(inline="always", **JIT)
def fold_tile(stage, h, K, z, zout, acc, i0, i1, zoff):
    """Fold k of nodes i0..i1 into the step: stages 0..2 write the next stage's input
    ``zout = z + C[s+1] h k`` and the running sum ``acc``; stage 3 finishes ``z += h/6 (acc + k)``.
    h (M,): node i's step size (every node of a trajectory has its trajectory's)."""
    dz = z.shape[1]
    if stage == 3:
        b3 = z.dtype.type(RK_B[3])
        for r in range(i1 - i0):
            zi = i0 + r - zoff
            c = h[i0 + r] * b3
            for d in range(dz):
                z[zi, d] += c * (acc[zi, d] + K[r, d])
        return
    cs = z.dtype.type(RK_C_NEXT[stage])
    if stage == 0:  # acc = k1 (acc's old contents are not read: they may be anything)
        for r in range(i1 - i0):
            zi = i0 + r - zoff
            c = h[i0 + r] * cs
            for d in range(dz):
                acc[zi, d] = K[r, d]
                zout[zi, d] = z[zi, d] + c * K[r, d]
    else:  # acc += 2 k2, 2 k3: with k1 and k4 that is 6 x the RK4 weights
        two = z.dtype.type(2)
        for r in range(i1 - i0):
            zi = i0 + r - zoff
            c = h[i0 + r] * cs
            for d in range(dz):
                acc[zi, d] += two * K[r, d]
                zout[zi, d] = z[zi, d] + c * K[r, d]


@njit(inline="always", **JIT)
def send_tile(theta, dims, l2s, zin, u, i0, i1, zoff, C, slot, r0, r1):
    """Phase 1 for nodes i0..i1 (cache rows r0..r1 of slot ``slot``); nothing for the MP-NODE."""
    if l2s is not None:
        l2s_field.send_tile(theta, dims, zin, u, i0, i1, zoff, C[0][slot, r0:r1], C[1][slot, r0:r1],
                            C[2][slot, r0:r1])


@njit(inline="always", **JIT)
def update_tile(theta, dims, l2s, zin, u, S, sums, graph, i0, i1, zoff, C, slot, r0, r1, msrc, mcol0):
    """Phase 3 for nodes i0..i1: k (n, dz) (for the MP-NODE a view of its feature-major
    result).  S: what everyone sent (L2S, rows ``i - zoff``); msrc[:, mcol0:]: the MP-NODE's
    messages (zin itself, or a compact copy: mpnode_field.update_tile)."""
    if l2s is not None:
        return l2s_field.update_tile(theta, dims, S, sums, graph, i0, i1, zoff, C[1][slot, r0:r1],
                                     C[3][slot, r0:r1], C[4][slot, r0:r1])
    KT = mpnode_field.update_tile(theta, dims, zin, u, sums, graph, i0, i1, zoff, C[0][slot, r0:r1],
                                  C[1][slot, r0:r1], C[2][slot, r0:r1], msrc, mcol0)
    if dims[KINEMATICS]:
        kinematics.apply(theta, dims, mpnode_field.feature_major(C[0][slot, r0:r1]), KT)
    return KT.T


@njit(**JIT)
def stage_range(stage, h, theta, dims, l2s, z, zin, zout, acc, u, graph, lo, hi, zoff, AT, sums, C):
    """One RK stage of the closed node range lo..hi, tile by tile; caches C[.][stage] (rows i - zoff).

    A non-empty ``AT`` (N, N) says the range is copies of one N-node graph whose adjacency
    (self-loop included when nodes hear themselves) has that transpose: the neighbour sums
    then come from one GEMM into ``sums`` instead of the CSR rows.
    """
    dx, zero_msg = dims[DX], dims[ZERO_MSG]
    for i0 in range(lo, hi, TILE):
        i1 = min(hi, i0 + TILE)
        send_tile(theta, dims, l2s, zin, u, i0, i1, zoff, C, stage, i0 - zoff, i1 - zoff)
    src, col0 = (C[2][stage], 0) if l2s is not None else (zin, dx)
    n_dense = 0
    if AT.shape[0] > 0 and not zero_msg:
        dense_sum(AT, src[lo - zoff:hi - zoff], col0, sums[lo - zoff:hi - zoff], np.int64(0))
        n_dense = sums.shape[0]
    for i0 in range(lo, hi, TILE):
        i1 = min(hi, i0 + TILE)
        K = update_tile(theta, dims, l2s, zin, u, C[2][stage], sums[:n_dense], graph, i0, i1, zoff, C, stage,
                        i0 - zoff, i1 - zoff, zin, dx)
        fold_tile(stage, h, K, z, zout, acc, i0, i1, zoff)


@njit(inline="always", **JIT)
def substep_range(h, theta, dims, l2s, z, za, zb, acc, u, graph, lo, hi, zoff, AT, sums, C, smsg):
    """One RK4 step of the closed node range lo..hi (z updated in place); each stage's input
    messages copied into smsg[stage] (rows i - zoff) unless it is empty (the edge weights'
    cotangent reads them)."""
    dx = dims[DX]
    for stage in range(4):
        zin, zout = stage_arrays(stage, z, za, zb)
        if smsg.shape[1] > 0:
            copy_into(smsg[stage], zin[:, dx:dx + smsg.shape[2]])
        stage_range(stage, h, theta, dims, l2s, z, zin, zout, acc, u, graph, lo, hi, zoff, AT, sums, C)


# ---------------------------------------------------------------------------
# Reverse of one stage: update VJP, transpose of the sum, send VJP
# ---------------------------------------------------------------------------
@njit(inline="always", **JIT)
def k_cotangent(stage, h, a, gnext, i0, i1, zoff):
    """Cotangent of k_s for nodes i0..i1: B[s] h a + C[s+1] h gnext (a: of the step's result,
    gnext: of the next stage's input; h (M,) the nodes' step sizes)."""
    n, dz = i1 - i0, a.shape[1]
    GK = np.empty((n, dz), a.dtype)
    cb = a.dtype.type(RK_B[stage])
    cc = a.dtype.type(RK_C_NEXT[stage])
    for r in range(n):
        zi = i0 + r - zoff
        wb = h[i0 + r] * cb
        wc = h[i0 + r] * cc
        for d in range(dz):
            GK[r, d] = wb * a[zi, d]
        if stage < 3:
            for d in range(dz):
                GK[r, d] += wc * gnext[zi, d]
    return GK


@njit(inline="always", **JIT)
def update_vjp_tile(stage, h, theta, dims, l2s, a, gnext, graph, i0, i1, zoff, C, slot, r0, r1, gtheta, gin, gagg, gh0,
                    gu):
    """Reverse phase 3 for nodes i0..i1: the field's VJP up to each node's aggregate (gagg);
    the controls' cotangent added into gu (rows ``i``) unless it is empty."""
    GK = k_cotangent(stage, h, a, gnext, i0, i1, zoff)
    if l2s is not None:
        l2s_field.update_vjp_tile(theta, dims, GK, graph, i0, i1, zoff, C[1][slot, r0:r1], C[3][slot, r0:r1],
                                  C[4][slot, r0:r1], gtheta, gagg, gh0)
    else:
        G = kinematics.take(theta, dims, GK) if dims[KINEMATICS] else GK[:0]
        mpnode_field.update_vjp_tile(theta, dims, GK, graph[2], i0, i1, zoff, C[0][slot, r0:r1],
                                     C[1][slot, r0:r1], C[2][slot, r0:r1], gtheta, gin, gagg, gu)
        if dims[KINEMATICS]:  # after the field's VJP, which writes gin's x columns
            kinematics.vjp(theta, dims, mpnode_field.feature_major(C[0][slot, r0:r1]), G, gin, i0, zoff)


@njit(inline="always", **JIT)
def send_vjp_tile(theta, dims, l2s, gS, gh0, i0, i1, zoff, C, slot, r0, r1, gtheta, gin, gu):
    """Reverse phase 1 (L2S): the senders' cotangent gS through the send layers into gin (and gu)."""
    if l2s is not None:
        l2s_field.send_vjp_tile(theta, dims, gS, gh0, i0, i1, zoff, C[0][slot, r0:r1], C[1][slot, r0:r1],
                                C[2][slot, r0:r1], gtheta, gin, gu)


@njit(inline="always", **JIT)
def substep_vjp_range(h, theta, dims, l2s, zstart, a, u, graph, tgraph, lo, hi, zoff, AT, A, sums, work, C, gtheta, gu,
                      gw):
    """Reverse one RK4 step of the closed range lo..hi: returns the cotangent of its start state.
    Inlined into vjp_blocks, so that LLVM optimises its callees once, not twice (docs/evidence/cold-start.md).

    zstart: the state at the step's start, or None; a: the cotangent of the state at its end.
    The four stages' caches C are the forward's when zstart is None, else recomputed from
    zstart into C; then the stages are walked backwards.  u is held over the step, so its cotangent
    (added into gu unless empty) sums over the four stages; the edge weights' (indexed as the
    CSR entries) is added into gw unless it is empty, and then an MP-NODE's stages must be
    recomputed (their input messages are in no cache).
    """
    z, za, zb, acc, gagg, gS, gh0, smsg = work
    dx, self_msg = dims[DX], dims[SELF_MSG]
    if zstart is not None:
        copy_into(z, zstart)
        substep_range(h, theta, dims, l2s, z, za, zb, acc, u, graph, lo, hi, zoff, AT, sums, C, smsg)
    gz = a.copy()
    gnext = za  # cotangent of the next stage's input (stage buffers are free now)
    gin = zb
    target, tcol = (gS, 0) if l2s is not None else (gin, dx)
    for stage in range(3, -1, -1):
        for i0 in range(lo, hi, TILE):
            i1 = min(hi, i0 + TILE)
            update_vjp_tile(stage, h, theta, dims, l2s, a, gnext, graph, i0, i1, zoff, C, stage, i0 - zoff, i1 - zoff,
                            gtheta, gin, gagg, gh0, gu)
        if l2s is None:
            target = gin
        if gw.shape[0] > 0:
            sent = C[2][stage] if l2s is not None else smsg[stage]
            edge_cotangent(gagg, sent, graph[0], graph[1], lo, hi, zoff, gw)
        if A.shape[0] > 0:  # the sum's transpose: a product by A^T, which dense_sum takes as A
            dense_sum(A, gagg[lo - zoff:hi - zoff], np.int64(0), target[lo - zoff:hi - zoff], tcol)
        else:
            for i0 in range(lo, hi, TILE):
                transpose_tile(gagg, tgraph[0], tgraph[1], tgraph[2], self_msg, i0, min(hi, i0 + TILE), zoff, target,
                               tcol)
        for i0 in range(lo, hi, TILE):
            i1 = min(hi, i0 + TILE)
            send_vjp_tile(theta, dims, l2s, gS, gh0, i0, i1, zoff, C, stage, i0 - zoff, i1 - zoff, gtheta, gin, gu)
        gz += gin
        gnext, gin = gin, gnext
    return gz


# ---------------------------------------------------------------------------
# Block drivers: a call runs blocks b0..b1 through all steps, the GIL released.
# Z0 (M, dz) the full initial state, U (T, M, du); out (T+1, M, dx); states
# (T*substeps+1, M, dz) or empty; zend (M, dz) receives the full final state, so that a
# later call can continue bit for bit where this one stopped (mpnode.Simulator).
# Block b is made of copies of one dense_n[b]-node graph whose adjacency is the row-major
# (N, N) matrix at dense_A[dense_off[b]:], its transpose at dense_AT[dense_off[b]:] (dense_n[b] = 0:
# use the CSR rows); the forward sums multiply by the transpose (`feature_major.dense_sum`).
# ---------------------------------------------------------------------------
@njit(inline="always", **JIT)
def _block_work(dims, n, like, slots):
    """A block's state buffers and ``slots`` stage caches (4 where the stages are computed
    here, 0 where they are the kept ones)."""
    dz = state_width(dims)
    z = np.zeros((n, dz), like.dtype)
    return z, np.empty_like(z), np.empty_like(z), np.empty_like(z), caches(dims, slots, n, like)


@njit(inline="always", **JIT)
def block_caches(kept, M, lo, hi):
    """Block lo..hi's part of the kept stage caches: per cache, (steps, 4, n, width).

    ``kept`` holds, per cache of `caches`, a (steps * 4 * M, width) array in which block lo..hi
    owns the rows steps * 4 * lo up to steps * 4 * hi (no rows: nothing kept, steps = 0)."""
    steps = kept[0].shape[0] // (4 * M)
    return (_block_part(kept[0], steps, lo, hi), _block_part(kept[1], steps, lo, hi),
            _block_part(kept[2], steps, lo, hi), _block_part(kept[3], steps, lo, hi),
            _block_part(kept[4], steps, lo, hi))


@njit(inline="always", **JIT)
def _block_part(c, steps, lo, hi):
    return c[steps * 4 * lo:steps * 4 * hi].reshape(steps, 4, hi - lo, c.shape[1])


@njit(inline="always", **JIT)
def step_caches(P, k):
    """The caches of RK4 step k (4 stages) from a block's kept caches P."""
    return P[0][k], P[1][k], P[2][k], P[3][k], P[4][k]


@njit(nogil=True, **JIT)
def rollout_blocks(theta, dims, l2s, b0, b1, z0, U, graph, block_ptr, dense_n, dense_off, dense_AT, nsub, hstep, out,
                   states, zend, kept):
    """Forward rollout of blocks b0..b1 from the full state z0: x at every output step into ``out``,
    the final z into zend; every RK4 step's stage caches into ``kept`` when it has rows (`block_caches`)."""
    dx = dims[DX]
    T = out.shape[0] - 1
    keep = states.shape[0] > 0
    keep_caches = kept[0].shape[0] > 0
    for b in range(b0, b1):
        lo = block_ptr[b]
        hi = block_ptr[b + 1]
        z, za, zb, acc, C = _block_work(dims, hi - lo, z0, 0 if keep_caches else 4)
        P = block_caches(kept, z0.shape[0], lo, hi)
        AT = dense_block(dense_AT, dense_n[b], dense_off[b])
        sums = np.empty((hi - lo, sent_width(dims)), z0.dtype)
        smsg = np.empty((4, 0, 0), z0.dtype)
        copy_into(z, z0[lo:hi])
        copy_into(out[0, lo:hi], z0[lo:hi, :dx])
        if keep:
            copy_into(states[0, lo:hi], z)
        k = 0
        for t in range(T):
            for s in range(nsub[t]):
                Ck = step_caches(P, k) if keep_caches else C
                substep_range(hstep[t], theta, dims, l2s, z, za, zb, acc, U[t], graph, lo, hi, lo, AT, sums, Ck, smsg)
                k += 1
                if keep:
                    copy_into(states[k, lo:hi], z)
            copy_into(out[t + 1, lo:hi], z[:, :dx])
        copy_into(zend[lo:hi], z)


@njit(nogil=True, **JIT)
def vjp_blocks(theta, dims, l2s, b0, b1, U, graph, tgraph, block_ptr, dense_n, dense_off, dense_A, dense_AT, nsub,
               hstep, states, kept, GX, gthetas, gx0, GU, GW):
    """Reverse pass of blocks b0..b1: cotangents GX (T+1, M, dx) of the output states -> gthetas[b] (block b's
    parameter cotangent) and gx0 (M, dx); the controls' cotangent added into GU (T, M, du)
    unless GU has no rows (T, 0, du), the edge weights' into GW (E,) unless it is empty.
    One of ``states`` and ``kept`` (from rollout_blocks) is None: with ``kept``, every step's stage
    caches, the reverse pass reads them; with ``states``, every step's start state, it recomputes
    each step's stages (as the edge weights' cotangent of an MP-NODE needs).  numba drops a branch
    on an argument that is None, so a driver compiled for kept caches holds no forward stage
    (docs/evidence/cold-start.md)."""
    dx = dims[DX]
    T = GX.shape[0] - 1
    sw = sent_width(dims)
    edge_messages = GW.shape[0] > 0 and l2s is None
    for b in range(b0, b1):
        lo = block_ptr[b]
        hi = block_ptr[b + 1]
        n = hi - lo
        z, za, zb, acc, C = _block_work(dims, n, GX, 0 if states is None else 4)
        gS = np.empty((n if l2s is not None else 0, sw), GX.dtype)
        gh0 = np.empty((n if l2s is not None else 0, dims[HIDDEN]), GX.dtype)
        smsg = np.empty((4, n if edge_messages else 0, dims[DM]), GX.dtype)
        work = (z, za, zb, acc, np.empty((n, sw), GX.dtype), gS, gh0, smsg)
        A = dense_block(dense_A, dense_n[b], dense_off[b])
        AT = dense_block(dense_AT, dense_n[b], dense_off[b])
        sums = np.empty((n, sw), GX.dtype)
        gtheta = gthetas[b]
        gtheta[:] = 0
        gz = np.zeros_like(z)
        if kept is not None:
            P = block_caches(kept, GX.shape[1], lo, hi)
        k = nsub.sum()
        for t in range(T - 1, -1, -1):
            add_into(gz[:, :dx], GX[t + 1, lo:hi])
            for s in range(nsub[t] - 1, -1, -1):
                k -= 1
                if states is not None:
                    gz = substep_vjp_range(hstep[t], theta, dims, l2s, states[k, lo:hi], gz, U[t], graph, tgraph, lo,
                                           hi, lo, AT, A, sums, work, C, gtheta, GU[t], GW)
                if kept is not None:
                    gz = substep_vjp_range(hstep[t], theta, dims, l2s, None, gz, U[t], graph, tgraph, lo, hi, lo, AT,
                                           A, sums, work, step_caches(P, k), gtheta, GU[t], GW)
        copy_into(gx0[lo:hi], gz[:, :dx])
        add_into(gx0[lo:hi], GX[0, lo:hi])


# ---------------------------------------------------------------------------
# Stagewise drivers: one large graph, every phase a parallel loop over tiles.
# ---------------------------------------------------------------------------
@njit(parallel=True, **JIT)
def rollout_stagewise(theta, dims, l2s, z0, U, graph, nsub, hstep, out, states, zend):
    """Forward rollout of one large graph (arguments as rollout_blocks).  Work arrays are per
    tile; only what nodes send is kept for the whole graph (L2S: h0, s; MP-NODE: a compact
    copy of the stage input's message columns, ping-pong, which the neighbour gather reads:
    on a graph too large for the caches that halves the memory its random reads touch), so
    memory stays ~ M * (4 dz + 2 dm or 2 H) beside ``states``."""
    M = z0.shape[0]
    dx, du, dm, H = dims[DX], dims[DU], dims[DM], dims[HIDDEN]
    T = out.shape[0] - 1
    keep = states.shape[0] > 0
    ntiles = (M + STAGE_TILE - 1) // STAGE_TILE
    z = z0.copy()
    za, zb, acc = np.empty_like(z), np.empty_like(z), np.empty_like(z)
    H0 = np.empty((M if l2s is not None else 0, H), z0.dtype)
    S = np.empty_like(H0)
    none = np.empty((0, 0), z0.dtype)
    msg = np.empty((M if l2s is None else 0, dm), z0.dtype)
    if l2s is None:
        _copy_rows(msg, z0[:, dx:dx + dm])  # the first stage's input is z0
    mnext = np.empty_like(msg)
    _copy_rows(out[0], z0[:, :dx])
    if keep:
        _copy_rows(states[0], z)
    j = 0
    for t in range(T):
        h = hstep[t]
        for s in range(nsub[t]):
            for stage in range(4):
                zin, zout = stage_arrays(stage, z, za, zb)
                if l2s is not None:
                    for k in prange(ntiles):
                        i0 = k * STAGE_TILE
                        i1 = min(M, i0 + STAGE_TILE)
                        V = np.empty((i1 - i0, dx + du), z0.dtype)
                        l2s_field.send_tile(theta, dims, zin, U[t], i0, i1, 0, V, H0[i0:i1], S[i0:i1])
                for k in prange(ntiles):
                    i0 = k * STAGE_TILE
                    i1 = min(M, i0 + STAGE_TILE)
                    C = caches(dims, 1, i1 - i0, z0)
                    if l2s is not None:
                        K = l2s_field.update_tile(theta, dims, S, none, graph, i0, i1, 0, H0[i0:i1], C[3][0], C[4][0])
                    else:
                        KT = mpnode_field.update_tile(theta, dims, zin, U[t], none, graph, i0, i1, 0, C[0][0],
                                                      C[1][0], C[2][0], msg, 0)
                        if dims[KINEMATICS]:
                            kinematics.apply(theta, dims, mpnode_field.feature_major(C[0][0]), KT)
                        K = KT.T
                    fold_tile(stage, h, K, z, zout, acc, i0, i1, 0)
                    if l2s is None:  # the next stage's messages: zout's (stage 3: the new z's)
                        copy_messages(z if stage == 3 else zout, dx, mnext, i0, i1)
                msg, mnext = mnext, msg
            j += 1
            if keep:
                _copy_rows(states[j], z)
        _copy_rows(out[t + 1], z[:, :dx])
    _copy_rows(zend, z)


@njit(**JIT)
def copy_messages(z, dx, msg, i0, i1):
    """msg[i] = the message columns of z[i] for nodes i0..i1: the compact copy the next stage's
    neighbour sums read (its random reads touch half the memory of z's rows)."""
    for i in range(i0, i1):
        for d in range(msg.shape[1]):
            msg[i, d] = z[i, dx + d]


@njit(parallel=True, **JIT)
def substep_tiles(h, theta, dims, l2s, z, za, zb, acc, u, graph, C, msg, mnext):
    """One RK4 step of a whole graph, keeping every stage's caches C (4, M, .) for the VJP;
    msg, mnext (M, dm): the MP-NODE's message copies (as rollout_stagewise's)."""
    M = z.shape[0]
    dx = dims[DX]
    ntiles = (M + STAGE_TILE - 1) // STAGE_TILE
    none = np.empty((0, 0), z.dtype)
    if l2s is None:
        for k in prange(ntiles):
            copy_messages(z, dx, msg, k * STAGE_TILE, min(M, (k + 1) * STAGE_TILE))
    for stage in range(4):
        zin, zout = stage_arrays(stage, z, za, zb)
        if l2s is not None:
            for k in prange(ntiles):
                i0 = k * STAGE_TILE
                i1 = min(M, i0 + STAGE_TILE)
                send_tile(theta, dims, l2s, zin, u, i0, i1, 0, C, stage, i0, i1)
        for k in prange(ntiles):
            i0 = k * STAGE_TILE
            i1 = min(M, i0 + STAGE_TILE)
            K = update_tile(theta, dims, l2s, zin, u, C[2][stage], none, graph, i0, i1, 0, C, stage, i0, i1, msg, 0)
            fold_tile(stage, h, K, z, zout, acc, i0, i1, 0)
            if l2s is None and stage < 3:
                copy_messages(zout, dx, mnext, i0, i1)
        msg, mnext = mnext, msg


@njit(parallel=True, **JIT)
def _add_rows(acc, G):
    for i in prange(acc.shape[0]):
        for d in range(G.shape[1]):
            acc[i, d] += G[i, d]


@njit(parallel=True, **JIT)
def _copy_rows(dst, src):
    """dst[:] = src, the rows in parallel, without numba's slice assignment (`layers.copy_into`)."""
    for i in prange(dst.shape[0]):
        for d in range(src.shape[1]):
            dst[i, d] = src[i, d]


@njit(parallel=True, **JIT)
def vjp_stagewise(theta, dims, l2s, U, graph, tgraph, nsub, hstep, states, GX, gthetas, gx0, GU):
    """As vjp_blocks for one large graph; gthetas (ntiles, P) holds one partial sum per tile."""
    T1, M, dx = GX.shape
    T = T1 - 1
    self_msg = dims[SELF_MSG]
    sw = sent_width(dims)
    ntiles = (M + STAGE_TILE - 1) // STAGE_TILE
    z = np.empty((M, state_width(dims)), GX.dtype)
    za, zb, acc = np.empty_like(z), np.empty_like(z), np.empty_like(z)
    C = caches(dims, 4, M, GX)
    gagg = np.empty((M, sw), GX.dtype)
    gS = np.empty((M if l2s is not None else 0, sw), GX.dtype)
    gh0 = np.empty((M if l2s is not None else 0, dims[HIDDEN]), GX.dtype)
    gthetas[:] = 0
    gz = np.zeros_like(z)
    msg = np.empty((M if l2s is None else 0, dims[DM]), GX.dtype)
    mnext = np.empty_like(msg)
    gnew, gbuf0, gbuf1 = np.empty_like(z), np.empty_like(z), np.empty_like(z)
    j = states.shape[0] - 1
    for t in range(T - 1, -1, -1):
        _add_rows(gz[:, :dx], GX[t + 1])
        h = hstep[t]
        for s in range(nsub[t] - 1, -1, -1):
            j -= 1
            _copy_rows(z, states[j])
            substep_tiles(h, theta, dims, l2s, z, za, zb, acc, U[t], graph, C, msg, mnext)
            _copy_rows(gnew, gz)
            gnext, gin = gbuf0, gbuf1
            for stage in range(3, -1, -1):
                for k in prange(ntiles):
                    i0 = k * STAGE_TILE
                    i1 = min(M, i0 + STAGE_TILE)
                    update_vjp_tile(stage, h, theta, dims, l2s, gz, gnext, graph, i0, i1, 0, C, stage, i0, i1,
                                    gthetas[k], gin, gagg, gh0, GU[t])
                for k in prange(ntiles):
                    i0 = k * STAGE_TILE
                    i1 = min(M, i0 + STAGE_TILE)
                    if l2s is not None:
                        transpose_tile(gagg, tgraph[0], tgraph[1], tgraph[2], self_msg, i0, i1, 0, gS, 0)
                        send_vjp_tile(theta, dims, l2s, gS, gh0, i0, i1, 0, C, stage, i0, i1, gthetas[k], gin, GU[t])
                    else:
                        transpose_tile(gagg, tgraph[0], tgraph[1], tgraph[2], self_msg, i0, i1, 0, gin, dx)
                    # not add_into: the raise of its shape check would make this loop run serially
                    for i in range(i0, i1):
                        for d in range(gin.shape[1]):
                            gnew[i, d] += gin[i, d]
                gnext, gin = gin, gnext
            _copy_rows(gz, gnew)
    _copy_rows(gx0, gz[:, :dx])
    _add_rows(gx0, GX[0])
