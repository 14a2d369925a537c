"""Numba kernels: the MP-NODE field on tiles of nodes, RK4 rollouts and their discrete adjoint.

Layout.  The B graphs of a batch are one block-diagonal graph of M nodes.  A node's
integrated state is ``z = [x, m]`` (dz = dx + dm), kept in arrays of shape (rows, dz).
Arrays hold either all M nodes (``zoff = 0``) or one *block* of nodes ``lo..hi`` with
``zoff = lo``: global node ``i`` lives in row ``i - zoff``.

Two drivers per job, sharing every tile function:
- *block* drivers: the nodes split into blocks closed under the graph (whole graphs of
  the batch); each thread runs the whole time loop of its blocks, no barrier per stage.
- *stagewise* drivers: one large connected graph; every RK stage is a parallel loop
  over tiles of nodes (a barrier per stage is cheap next to the work of a big graph).

Dense products go to BLAS (``np.dot`` on contiguous tiles of ``TILE`` rows; the caller
pins BLAS to one thread so numba's threads do not fight BLAS's own); elementwise work,
aggregation and the RK combinations are loops.  Gradients of the parameters go to one
buffer per block (or per tile) and are reduced by the caller: deterministic, no races.

Parameter layout of the flat vector (see mpnode.mlp): W1 (din, H), b1 (H), W2 (H, H),
b2 (H), W3 (H, dout), b3 (dout) with din = dx + du + dm, dout = dx + dm.
"""
import numpy as np
from numba import njit, prange
from numba.extending import overload

TILE = 128  # rows per BLAS call inside a block (blocks hold a few hundred nodes)
STAGE_TILE = 256  # rows per parallel task of the stagewise drivers (one big graph: fewer, larger tasks)
# No nnan/ninf: a NaN must survive the arithmetic so that callers can detect it.
FASTMATH = {"contract", "reassoc", "nsz", "arcp", "afn"}

# error_model="numpy": no ZeroDivisionError checks, which would stop the loops vectorising.
_JIT = dict(cache=True, fastmath=FASTMATH, error_model="numpy")

HUBER = 0
MSE = 1

# RK4 (classic): stage s reads z + C[s] h k_{s-1}; z+ = z + h sum_s B[s] k_s.
_RK_C = (0.0, 0.5, 0.5, 1.0)
_RK_B = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)


def tanh(x):
    """tanh in the kernel's precision (numba resolves this to the overload below)."""
    return np.tanh(x)


@overload(tanh, jit_options={"fastmath": FASTMATH, "error_model": "numpy"})
def _tanh_overload(x):
    from numba import types

    if x == types.float32:
        # The clamped 13/6 odd rational of Eigen/XLA: a few ulp in float32, vectorises.
        def tanh32(x):
            lim = np.float32(7.90531110763549805)
            x = min(max(x, -lim), lim)
            x2 = x * x
            p = np.float32(-2.76076847742355e-16)
            p = x2 * p + np.float32(2.00018790482477e-13)
            p = x2 * p + np.float32(-8.60467152213735e-11)
            p = x2 * p + np.float32(5.12229709037114e-08)
            p = x2 * p + np.float32(1.48572235717979e-05)
            p = x2 * p + np.float32(6.37261928875436e-04)
            p = x2 * p + np.float32(4.89352455891786e-03)
            q = np.float32(1.19825839466702e-06)
            q = x2 * q + np.float32(1.18534705686654e-04)
            q = x2 * q + np.float32(2.26843463243900e-03)
            q = x2 * q + np.float32(4.89352518554385e-03)
            return x * p / q

        return tanh32
    # float64 is the correctness path: exact libm tanh so 1 - y^2 is its true derivative.
    return lambda x: np.tanh(x)


# ---------------------------------------------------------------------------
# Layers of the MLP on a tile (rows = nodes).  Forward/backward pairs.
# ---------------------------------------------------------------------------
@njit(**_JIT)
def dense_tanh_forward(X, W, b, Y):
    """Y = tanh(X W + b).  X (n, a), W (a, c), b (c,), Y (n, c) written in place."""
    np.dot(X, W, Y)
    n, c = Y.shape
    for r in range(n):
        for j in range(c):
            Y[r, j] = tanh(Y[r, j] + b[j])


@njit(**_JIT)
def dense_tanh_backward(X, W, Y, GY, gW, gb):
    """Cotangents of Y = tanh(X W + b): returns GX; adds into gW (a, c) and gb (c,).

    GY (n, c) is overwritten with the cotangent of the pre-activation.
    """
    n, c = Y.shape
    for r in range(n):
        for j in range(c):
            GY[r, j] *= 1 - Y[r, j] * Y[r, j]
    gW += np.dot(X.T, GY)
    for r in range(n):
        for j in range(c):
            gb[j] += GY[r, j]
    return np.dot(GY, W.T)


@njit(**_JIT)
def dense_forward(X, W, b):
    """Y = X W + b (the linear output layer)."""
    Y = np.dot(X, W)
    n, c = Y.shape
    for r in range(n):
        for j in range(c):
            Y[r, j] += b[j]
    return Y


@njit(**_JIT)
def dense_backward(X, W, GY, gW, gb):
    """Cotangents of Y = X W + b: returns GX; adds into gW and gb."""
    gW += np.dot(X.T, GY)
    n, c = GY.shape
    for r in range(n):
        for j in range(c):
            gb[j] += GY[r, j]
    return np.dot(GY, W.T)


@njit(**_JIT)
def unpack(theta, din, H, dout):
    """Views (W1, b1, W2, b2, W3, b3) into the flat parameter vector ``theta``."""
    o = 0
    W1 = theta[o:o + din * H].reshape(din, H)
    o += din * H
    b1 = theta[o:o + H]
    o += H
    W2 = theta[o:o + H * H].reshape(H, H)
    o += H * H
    b2 = theta[o:o + H]
    o += H
    W3 = theta[o:o + H * dout].reshape(H, dout)
    o += H * dout
    b3 = theta[o:o + dout]
    return W1, b1, W2, b2, W3, b3


@njit(**_JIT)
def mlp_forward(theta, V, H1, H2, dout):
    """K = W3^T tanh(W2^T tanh(W1^T v + b1) + b2) + b3 per row v of V; keeps H1, H2."""
    din = V.shape[1]
    Hd = H1.shape[1]
    W1, b1, W2, b2, W3, b3 = unpack(theta, din, Hd, dout)
    dense_tanh_forward(V, W1, b1, H1)
    dense_tanh_forward(H1, W2, b2, H2)
    return dense_forward(H2, W3, b3)


@njit(**_JIT)
def mlp_backward(theta, V, H1, H2, GK, gtheta):
    """VJP of mlp_forward: returns GV (n, din); adds the parameter cotangents into gtheta."""
    din = V.shape[1]
    Hd = H1.shape[1]
    dout = GK.shape[1]
    W1, b1, W2, b2, W3, b3 = unpack(theta, din, Hd, dout)
    gW1, gb1, gW2, gb2, gW3, gb3 = unpack(gtheta, din, Hd, dout)
    GH2 = dense_backward(H2, W3, GK, gW3, gb3)
    GH1 = dense_tanh_backward(H1, W2, H2, GH2, gW2, gb2)
    return dense_tanh_backward(V, W1, H1, GH1, gW1, gb1)


# ---------------------------------------------------------------------------
# The graph field on a tile: inputs [x, u, m'], MLP, RK combination.
# ---------------------------------------------------------------------------
@njit(**_JIT)
def gather_inputs(zin, zoff, u, indptr, indices, inv_deg, t0, t1, dx, self_msg, zero_msg, msum, V):
    """V[r] = [x_i, u_i, m'_i] for nodes i = t0 + r; m'_i = inv_deg[i] * sum of row i's messages.

    When ``msum`` has rows it already holds each node's message sum (dense path,
    rows ``i - zoff``); otherwise the sum runs over the CSR row.
    """
    du = u.shape[1]
    dm = zin.shape[1] - dx
    c = dx + du
    dense = msum.shape[0] > 0
    for r in range(t1 - t0):
        i = t0 + r
        zi = i - zoff
        for d in range(dx):
            V[r, d] = zin[zi, d]
        for d in range(du):
            V[r, dx + d] = u[i, d]
        w = inv_deg[i]
        if zero_msg:
            for d in range(dm):
                V[r, c + d] = 0
        elif dense:
            for d in range(dm):
                V[r, c + d] = msum[zi, d] * w
        else:
            p0 = indptr[i]
            p1 = indptr[i + 1]
            for d in range(dm):
                acc = zin[zi, dx + d] if self_msg else zin.dtype.type(0)
                for p in range(p0, p1):
                    acc += zin[indices[p] - zoff, dx + d]
                V[r, c + d] = acc * w


@njit(**_JIT)
def dense_sum(A, src, col0, out, ocol0):
    """out[b*N + i, ocol0+d] = sum_j A[i, j] src[b*N + j, col0+d] for every graph b of the rows.

    The rows of ``src`` are k copies of one N-node graph with 0/1 adjacency A (N, N);
    the k graphs go through one GEMM (N, N) @ (N, k*dm).
    """
    N = A.shape[0]
    k = src.shape[0] // N
    dm = out.shape[1] - ocol0
    Mt = np.empty((N, k * dm), src.dtype)
    for b in range(k):
        for j in range(N):
            for d in range(dm):
                Mt[j, b * dm + d] = src[b * N + j, col0 + d]
    R = np.dot(A, Mt)
    for b in range(k):
        for i in range(N):
            for d in range(dm):
                out[b * N + i, ocol0 + d] = R[i, b * dm + d]


@njit(**_JIT)
def stage_tile(stage, h, theta, z, zin, zout, acc, u, indptr, indices, inv_deg,
               t0, t1, zoff, dx, self_msg, zero_msg, msum, V, H1, H2):
    """One RK4 stage for nodes t0..t1: k = F(zin), then fold k into the step.

    stage 0..2 write the next stage's input ``zout = z + C[s+1] h k`` and the running
    sum ``acc``; stage 3 finishes the step in place: ``z += h/6 (acc + k)``.
    V, H1, H2 (rows of this tile) receive the MLP's inputs and hidden activations.
    """
    gather_inputs(zin, zoff, u, indptr, indices, inv_deg, t0, t1, dx, self_msg, zero_msg, msum, V)
    K = mlp_forward(theta, V, H1, H2, z.shape[1])
    dz = z.shape[1]
    if zero_msg:
        for r in range(t1 - t0):
            for d in range(dx, dz):
                K[r, d] = 0
    if stage == 3:
        c = h * z.dtype.type(_RK_B[3])
        for r in range(t1 - t0):
            zi = t0 + r - zoff
            for d in range(dz):
                z[zi, d] += c * (acc[zi, d] + K[r, d])
        return
    c = h * z.dtype.type(_RK_C[stage + 1])
    if stage == 0:  # acc = k1 (acc's old contents are not read: they may be anything)
        for r in range(t1 - t0):
            zi = t0 + r - zoff
            for d in range(dz):
                acc[zi, d] = K[r, d]
                zout[zi, d] = z[zi, d] + c * K[r, d]
    else:  # acc += 2 k2, 2 k3: with k1 and k4 that is 6 x the RK4 weights
        two = z.dtype.type(2)
        for r in range(t1 - t0):
            zi = t0 + r - zoff
            for d in range(dz):
                acc[zi, d] += two * K[r, d]
                zout[zi, d] = z[zi, d] + c * K[r, d]


@njit(**_JIT)
def _stage_arrays(stage, z, za, zb):
    """(input, output) arrays of a stage: z -> za -> zb -> za -> z (ping-pong buffers)."""
    if stage == 0:
        return z, za
    if stage == 1:
        return za, zb
    if stage == 2:
        return zb, za
    return za, z


@njit(**_JIT)
def rk4_substep_range(h, theta, z, za, zb, acc, u, indptr, indices, inv_deg, lo, hi, zoff,
                      dx, self_msg, zero_msg, A, msum, Vc, H1c, H2c):
    """One RK4 step for the closed node range lo..hi (sequential over its tiles).

    A non-empty ``A`` (N, N) says the range is copies of one N-node graph with that 0/1
    adjacency (self-loop included when nodes hear themselves): message sums then come
    from one GEMM per stage into ``msum`` instead of the CSR rows.  The MLP inputs and
    activations of stage s land in Vc/H1c/H2c[s] (rows ``i - zoff``), where the adjoint
    finds them.
    """
    dense = A.shape[0] > 0 and not zero_msg
    sums = msum[:msum.shape[0] if dense else 0]  # empty: gather_inputs walks the CSR rows
    for stage in range(4):
        zin, zout = _stage_arrays(stage, z, za, zb)
        if dense:
            dense_sum(A, zin[lo - zoff:hi - zoff], dx, msum[lo - zoff:hi - zoff], 0)
        for t0 in range(lo, hi, TILE):
            t1 = min(hi, t0 + TILE)
            r0 = t0 - zoff
            r1 = t1 - zoff
            stage_tile(stage, h, theta, z, zin, zout, acc, u, indptr, indices, inv_deg, t0, t1, zoff, dx,
                       self_msg, zero_msg, sums, Vc[stage, r0:r1], H1c[stage, r0:r1], H2c[stage, r0:r1])


# ---------------------------------------------------------------------------
# Reverse pass of one stage: MLP VJP, then the transpose of the mean aggregation.
# ---------------------------------------------------------------------------
@njit(**_JIT)
def stage_vjp_tile(stage, h, theta, a, gnext, gin, gmp, t0, t1, zoff, dx, du, inv_deg, zero_msg,
                   V, H1, H2, gtheta):
    """Cotangent of stage ``stage``'s field for nodes t0..t1.

    The cotangent of k_s is ``B[s] h a + C[s+1] h gnext`` (a: cotangent of the step's
    result, gnext: of the next stage's input).  Writes the x part of the stage input's
    cotangent into ``gin`` and the message-mean cotangent, already divided by the
    degree, into ``gmp`` (scattered to the senders by transpose_tile).
    """
    dz = a.shape[1]
    n = t1 - t0
    GK = np.empty((n, dz), a.dtype)
    wb = h * a.dtype.type(_RK_B[stage])
    wc = h * a.dtype.type(_RK_C[stage + 1]) if stage < 3 else a.dtype.type(0)
    for r in range(n):
        zi = t0 + r - zoff
        for d in range(dz):
            GK[r, d] = wb * a[zi, d]
        if stage < 3:
            for d in range(dz):
                GK[r, d] += wc * gnext[zi, d]
        if zero_msg:
            for d in range(dx, dz):
                GK[r, d] = 0
    GV = mlp_backward(theta, V, H1, H2, GK, gtheta)
    c = dx + du
    for r in range(n):
        i = t0 + r
        zi = i - zoff
        for d in range(dx):
            gin[zi, d] = GV[r, d]
        w = inv_deg[i]
        for d in range(dz - dx):
            gmp[zi, d] = GV[r, c + d] * w


@njit(**_JIT)
def transpose_tile(gin, gmp, tindptr, tindices, t0, t1, zoff, dx, self_msg, zero_msg):
    """gin[j, dx:] = sum of gmp[i] over the nodes i that hear j (the CSR transpose)."""
    dz = gin.shape[1]
    for j in range(t0, t1):
        zj = j - zoff
        for d in range(dx, dz):
            gin[zj, d] = 0
        if zero_msg:
            continue
        for p in range(tindptr[j], tindptr[j + 1]):
            i = tindices[p] - zoff
            for d in range(dx, dz):
                gin[zj, d] += gmp[i, d - dx]
        if self_msg:
            for d in range(dx, dz):
                gin[zj, d] += gmp[zj, d - dx]


@njit(**_JIT)
def loss_tile(kind, pred, target, scale, grad):
    """Sum over the rows of Huber(delta=1) or squared error of pred - target, times scale.

    When ``grad`` has rows, adds scale * d(loss)/d(pred) into grad[:, :dx].
    """
    total = 0.0
    n, dx = target.shape
    for r in range(n):
        for d in range(dx):
            e = pred[r, d] - target[r, d]
            if kind == HUBER:
                ae = abs(e)
                if ae <= 1:
                    total += 0.5 * e * e
                    g = e
                else:
                    total += ae - 0.5
                    g = 1.0 if e > 0 else -1.0
            else:
                total += e * e
                g = 2 * e
            if grad.shape[0]:
                grad[r, d] += scale * g
    return total * scale


# ---------------------------------------------------------------------------
# Drivers.  dm, hidden: message size and hidden width; h = dt / substeps.
# X (T+1, M, dx) and U (T, M, du) are time-major; Zs (T*substeps+1, M, dz) keeps the
# state after every RK4 step for the reverse pass (stage values are recomputed).
# ---------------------------------------------------------------------------
@njit(**_JIT)
def _scratch(n, dz, din, hidden, dtype_like):
    """Per-block work arrays: z, two stage buffers, the RK sum, and stage caches (4, n, .)."""
    z = np.zeros((n, dz), dtype_like.dtype)
    Vc = np.empty((4, n, din), dtype_like.dtype)
    H1c = np.empty((4, n, hidden), dtype_like.dtype)
    H2c = np.empty((4, n, hidden), dtype_like.dtype)
    return z, np.empty_like(z), np.empty_like(z), np.empty_like(z), Vc, H1c, H2c


@njit(**_JIT)
def _dense_block(dense_A, n, off):
    """The (n, n) adjacency of a dense block; (0, 0) when the block uses CSR."""
    return dense_A[off:off + n * n].reshape(n, n)


@njit(parallel=True, **_JIT)
def rollout_blocks(theta, dm, hidden, x0, U, indptr, indices, inv_deg, block_ptr, dense_n, dense_off,
                   dense_A, substeps, h, self_msg, zero_msg, out):
    """Forward rollout, each thread running whole blocks of graphs through all steps.

    x0 (M, dx); out (T+1, M, dx) receives x at every output step.  Block b is made of
    copies of one dense_n[b]-node graph whose 0/1 adjacency is the row-major (N, N)
    matrix at dense_A[dense_off[b]:] (dense_n[b] = 0: use the CSR rows).
    """
    dx = x0.shape[1]
    dz = dx + dm
    din = dz + U.shape[2]
    T = out.shape[0] - 1
    for b in prange(len(block_ptr) - 1):
        lo = block_ptr[b]
        hi = block_ptr[b + 1]
        z, za, zb, acc, Vc, H1c, H2c = _scratch(hi - lo, dz, din, hidden, x0)
        A = _dense_block(dense_A, dense_n[b], dense_off[b])
        msum = np.empty((hi - lo, dm), x0.dtype)
        z[:, :dx] = x0[lo:hi]
        out[0, lo:hi] = x0[lo:hi]
        for t in range(T):
            for s in range(substeps):
                rk4_substep_range(h, theta, z, za, zb, acc, U[t], indptr, indices, inv_deg, lo, hi, lo,
                                  dx, self_msg, zero_msg, A, msum, Vc, H1c, H2c)
            out[t + 1, lo:hi] = z[:, :dx]


@njit(parallel=True, **_JIT)
def rollout_stagewise(theta, dm, hidden, x0, U, indptr, indices, inv_deg, substeps, h,
                      self_msg, zero_msg, out):
    """Forward rollout of one large graph: each RK stage is a parallel loop over tiles."""
    M, dx = x0.shape
    dz = dx + dm
    din = dz + U.shape[2]
    T = out.shape[0] - 1
    ntiles = (M + STAGE_TILE - 1) // STAGE_TILE
    z = np.zeros((M, dz), x0.dtype)
    z[:, :dx] = x0
    za = np.empty_like(z)
    zb = np.empty_like(z)
    acc = np.empty_like(z)
    out[0] = x0
    for t in range(T):
        for s in range(substeps):
            for stage in range(4):
                zin, zout = _stage_arrays(stage, z, za, zb)
                for k in prange(ntiles):
                    t0 = k * STAGE_TILE
                    t1 = min(M, t0 + STAGE_TILE)
                    V = np.empty((t1 - t0, din), x0.dtype)
                    H1 = np.empty((t1 - t0, hidden), x0.dtype)
                    H2 = np.empty((t1 - t0, hidden), x0.dtype)
                    stage_tile(stage, h, theta, z, zin, zout, acc, U[t], indptr, indices, inv_deg,
                               t0, t1, 0, dx, self_msg, zero_msg, za[:0, :dm], V, H1, H2)
        out[t + 1] = z[:, :dx]


@njit(**_JIT)
def substep_adjoint_range(h, theta, zstart, a, U_t, indptr, indices, inv_deg, tindptr, tindices,
                          lo, hi, zoff, dx, self_msg, zero_msg, A, AT, msum, work, gtheta):
    """Reverse one RK4 step for the closed range lo..hi: returns the cotangent of its start state.

    zstart: state at the step's start; a: cotangent of the state at its end.  The four
    stages are recomputed (caches in ``work``), then walked backwards (design.md).
    """
    z, za, zb, acc, Vc, H1c, H2c = work
    z[:] = zstart
    rk4_substep_range(h, theta, z, za, zb, acc, U_t, indptr, indices, inv_deg, lo, hi, zoff,
                      dx, self_msg, zero_msg, A, msum, Vc, H1c, H2c)
    du = U_t.shape[1]
    gz = a.copy()
    gnext = za  # cotangent of the next stage's input (stage buffers are free now)
    gin = zb
    gmp = np.empty((a.shape[0], a.shape[1] - dx), a.dtype)
    for stage in range(3, -1, -1):
        for t0 in range(lo, hi, TILE):
            t1 = min(hi, t0 + TILE)
            r0 = t0 - zoff
            r1 = t1 - zoff
            stage_vjp_tile(stage, h, theta, a, gnext, gin, gmp, t0, t1, zoff, dx, du, inv_deg, zero_msg,
                           Vc[stage, r0:r1], H1c[stage, r0:r1], H2c[stage, r0:r1], gtheta)
        if AT.shape[0] > 0 and not zero_msg:
            dense_sum(AT, gmp[lo - zoff:hi - zoff], 0, gin[lo - zoff:hi - zoff], dx)
        else:
            for t0 in range(lo, hi, TILE):
                transpose_tile(gin, gmp, tindptr, tindices, t0, min(hi, t0 + TILE), zoff, dx, self_msg, zero_msg)
        gz += gin
        gnext, gin = gin, gnext
    return gz


@njit(parallel=True, **_JIT)
def loss_grad_blocks(theta, dm, hidden, X, U, indptr, indices, inv_deg, tindptr, tindices, block_ptr,
                     dense_n, dense_off, dense_A, dense_AT, substeps, h, self_msg, zero_msg, loss_kind, scale,
                     Zs, gthetas, losses, gx0):
    """Loss of the rollout from X[0] against X[1..T] and its exact discrete gradient.

    One thread per block: forward (states kept in Zs), then the reverse pass.  Writes the
    block's loss into losses[b], its parameter gradient into gthetas[b] and the gradient
    with respect to the initial states into gx0 (M, dx).  Dense blocks as in rollout_blocks;
    dense_AT holds the transposed adjacencies at the same offsets.
    """
    dx = X.shape[2]
    dz = dx + dm
    din = dz + U.shape[2]
    T = X.shape[0] - 1
    none = np.empty((0, dx), X.dtype)
    for b in prange(len(block_ptr) - 1):
        lo = block_ptr[b]
        hi = block_ptr[b + 1]
        work = _scratch(hi - lo, dz, din, hidden, X)
        z, za, zb, acc, Vc, H1c, H2c = work
        A = _dense_block(dense_A, dense_n[b], dense_off[b])
        AT = _dense_block(dense_AT, dense_n[b], dense_off[b])
        msum = np.empty((hi - lo, dm), X.dtype)
        z[:, :dx] = X[0, lo:hi]
        Zs[0, lo:hi] = z
        loss = 0.0
        for t in range(T):
            for s in range(substeps):
                rk4_substep_range(h, theta, z, za, zb, acc, U[t], indptr, indices, inv_deg, lo, hi, lo,
                                  dx, self_msg, zero_msg, A, msum, Vc, H1c, H2c)
                Zs[t * substeps + s + 1, lo:hi] = z
            loss += loss_tile(loss_kind, z, X[t + 1, lo:hi], scale, none)
        losses[b] = loss
        gz = np.zeros((hi - lo, dz), X.dtype)
        gtheta = gthetas[b]
        gtheta[:] = 0
        for t in range(T - 1, -1, -1):
            loss_tile(loss_kind, Zs[(t + 1) * substeps, lo:hi], X[t + 1, lo:hi], scale, gz)
            for s in range(substeps - 1, -1, -1):
                gz = substep_adjoint_range(h, theta, Zs[t * substeps + s, lo:hi], gz, U[t], indptr, indices,
                                           inv_deg, tindptr, tindices, lo, hi, lo, dx, self_msg, zero_msg,
                                           A, AT, msum, work, gtheta)
        gx0[lo:hi] = gz[:, :dx]


@njit(parallel=True, **_JIT)
def rk4_substep_tiles(h, theta, z, za, zb, acc, u, indptr, indices, inv_deg, dx, self_msg, zero_msg, Vc, H1c, H2c):
    """One RK4 step of a whole graph, each stage a parallel loop over tiles; stage s's MLP
    inputs and activations go to Vc/H1c/H2c[s] (all M rows) for the adjoint."""
    M, dz = z.shape
    for stage in range(4):
        zin, zout = _stage_arrays(stage, z, za, zb)
        for k in prange((M + STAGE_TILE - 1) // STAGE_TILE):
            t0 = k * STAGE_TILE
            t1 = min(M, t0 + STAGE_TILE)
            stage_tile(stage, h, theta, z, zin, zout, acc, u, indptr, indices, inv_deg, t0, t1, 0, dx,
                       self_msg, zero_msg, za[:0, :dz - dx], Vc[stage, t0:t1], H1c[stage, t0:t1], H2c[stage, t0:t1])


@njit(parallel=True, **_JIT)
def loss_grad_stagewise(theta, dm, hidden, X, U, indptr, indices, inv_deg, tindptr, tindices,
                        substeps, h, self_msg, zero_msg, loss_kind, scale, Zs, gthetas, losses, gx0):
    """As loss_grad_blocks for one large graph: every phase is a parallel loop over tiles.

    gthetas (ntiles, P) and losses (ntiles,) hold one partial sum per tile.
    """
    T1, M, dx = X.shape
    T = T1 - 1
    dz = dx + dm
    din = dz + U.shape[2]
    du = U.shape[2]
    ntiles = (M + STAGE_TILE - 1) // STAGE_TILE
    z, za, zb, acc, Vc, H1c, H2c = _scratch(M, dz, din, hidden, X)
    z[:, :dx] = X[0]
    Zs[0] = z
    none = np.empty((0, dx), X.dtype)
    losses[:] = 0
    gthetas[:] = 0
    for t in range(T):
        for s in range(substeps):
            rk4_substep_tiles(h, theta, z, za, zb, acc, U[t], indptr, indices, inv_deg, dx, self_msg, zero_msg,
                              Vc, H1c, H2c)
            Zs[t * substeps + s + 1] = z
        for k in prange(ntiles):
            t0 = k * STAGE_TILE
            t1 = min(M, t0 + STAGE_TILE)
            losses[k] += loss_tile(loss_kind, z[t0:t1], X[t + 1, t0:t1], scale, none)
    gz = np.zeros((M, dz), X.dtype)
    gnew = np.empty_like(gz)
    gbuf0 = np.empty_like(gz)
    gbuf1 = np.empty_like(gz)
    gmp = np.empty((M, dm), X.dtype)
    for t in range(T - 1, -1, -1):
        for k in prange(ntiles):
            t0 = k * STAGE_TILE
            t1 = min(M, t0 + STAGE_TILE)
            loss_tile(loss_kind, Zs[(t + 1) * substeps, t0:t1], X[t + 1, t0:t1], scale, gz[t0:t1])
        for s in range(substeps - 1, -1, -1):
            z[:] = Zs[t * substeps + s]
            rk4_substep_tiles(h, theta, z, za, zb, acc, U[t], indptr, indices, inv_deg, dx, self_msg, zero_msg,
                              Vc, H1c, H2c)
            gnew[:] = gz
            gnext = gbuf0
            gin = gbuf1
            for stage in range(3, -1, -1):
                for k in prange(ntiles):
                    t0 = k * STAGE_TILE
                    t1 = min(M, t0 + STAGE_TILE)
                    stage_vjp_tile(stage, h, theta, gz, gnext, gin, gmp, t0, t1, 0, dx, du, inv_deg, zero_msg,
                                   Vc[stage, t0:t1], H1c[stage, t0:t1], H2c[stage, t0:t1], gthetas[k])
                for k in prange(ntiles):
                    t0 = k * STAGE_TILE
                    t1 = min(M, t0 + STAGE_TILE)
                    transpose_tile(gin, gmp, tindptr, tindices, t0, t1, 0, dx, self_msg, zero_msg)
                    gnew[t0:t1] += gin[t0:t1]
                gnext, gin = gin, gnext
            gz[:] = gnew
    gx0[:] = gz[:, :dx]
