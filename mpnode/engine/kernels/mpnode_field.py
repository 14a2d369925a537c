"""The MP-NODE field on a tile of nodes: k = MLP([x, u, m']) [+ m' W_agg], and its VJP.

A node's state is z = [x, m] (dz = dx + dm).  What a node sends its neighbours is its
message m itself (the columns dx: of z), so nothing is computed before the neighbour
sum; m' = weight * (sum over the row).  Parameters, flat in this order (row-major):
W1 (din, H), b1 (H), W2 (H, H), b2 (H), W3 (H, dout), b3 (dout) with din = dx + du + dm
and dout = dx + dm, then W_agg (dm, dout), or (dm, dx) when it feeds dx/dt alone, when
dims[LINEAR] is not 0 (the linear aggregate path; ``dims``: mpnode.engine.dims).  Its bits:
LINEAR_ON the path is there (reading the MLP's aggregate m'); LINEAR_OWN it reads s_i m'_i
instead, s_i = weight[M + i] (the weight array then has 2M entries; e.g. mean for the MLP,
scaled sum for the path: s_i = deg_i / D); LINEAR_STATE it adds to dx/dt only (W_agg (dm, dx)),
so the messages' own dynamics do not hear the degree.
"""
import numpy as np
from numba import njit

from ..dims import DM, DU, DX, HIDDEN, LINEAR, LINEAR_OWN, LINEAR_STATE, SELF_MSG, ZERO_MSG
from .feature_major import aligned_empty, dense_tanh_forward, param_cotangent, product, tanh_cotangent
from .layers import JIT, add_into, aggregate_tile, copy_into


@njit(inline="always", **JIT)
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


@njit(inline="always", **JIT)
def unpack_agg(theta, din, H, dout, dm, ncol):
    """The view W_agg (dm, ncol) that follows the MLP's parameters in ``theta`` (ncol: dout,
    or dx when the path feeds dx/dt alone)."""
    o = din * H + H + H * H + H + H * dout + dout
    return theta[o:o + dm * ncol].reshape(dm, ncol)


@njit(inline="always", **JIT)
def feature_major(A):
    """The (w, n) feature-major view of a tile's (n, w) cache rows (the same memory)."""
    return A.reshape(A.shape[1], A.shape[0])


@njit(inline="always", **JIT)
def transpose_into(A, B):
    """B (w, n) = A (n, w)^T."""
    for d in range(B.shape[0]):
        for r in range(B.shape[1]):
            B[d, r] = A[r, d]


@njit(inline="always", **JIT)
def linear_input(VT, c, weight, own, i0):
    """The linear path's input for rows i0..: VT[c:] (the MLP's aggregate, feature-major), each
    node r times weight[M + i0 + r] when the path has its ``own`` aggregation (M = weight.size / 2)."""
    AT = aligned_empty((VT.shape[0] - c, VT.shape[1]), VT)
    copy_into(AT, VT[c:])
    if own:
        off = weight.shape[0] // 2 + i0
        for d in range(AT.shape[0]):
            for r in range(AT.shape[1]):
                AT[d, r] *= weight[off + r]
    return AT


@njit(inline="always", **JIT)
def linear_aggregate_forward(Wa, VT, c, weight, own, i0, KT):
    """KT[:ncol] += Wa^T A (ncol = Wa's columns), A = linear_input(...): the aggregate's path
    around the MLP (whose tanh units cannot follow the larger aggregates of denser graphs;
    the gene dynamics are linear in them)."""
    ncol = Wa.shape[1]
    PT = aligned_empty((ncol, VT.shape[1]), VT)
    product(Wa, Wa[0, :0], linear_input(VT, c, weight, own, i0), PT)
    add_into(KT[:ncol], PT)


@njit(inline="always", **JIT)
def linear_aggregate_backward(Wa, VT, c, weight, own, i0, GKT, gWa, GVT):
    """VJP of linear_aggregate_forward: gWa += A G^T, GVT[c:] += s * (Wa G), G = GKT[:ncol]."""
    GT = GKT[:Wa.shape[1]]
    param_cotangent(linear_input(VT, c, weight, own, i0), GT, gWa, Wa[0, :0])
    GAT = aligned_empty((Wa.shape[0], GT.shape[1]), GT)
    product(Wa.T, Wa[0, :0], GT, GAT)
    if own:
        off = weight.shape[0] // 2 + i0
        for d in range(GAT.shape[0]):
            for r in range(GAT.shape[1]):
                GAT[d, r] *= weight[off + r]
    add_into(GVT[c:], GAT)


@njit(inline="always", **JIT)
def mlp_forward(theta, VT, H1T, H2T, dout):
    """KT (dout, n) = W3^T tanh(W2^T tanh(W1^T v + b1) + b2) + b3 per column v of VT; keeps H1T, H2T."""
    W1, b1, W2, b2, W3, b3 = unpack(theta, VT.shape[0], H1T.shape[0], dout)
    dense_tanh_forward(VT, W1, b1, H1T)
    dense_tanh_forward(H1T, W2, b2, H2T)
    KT = aligned_empty((dout, VT.shape[1]), VT)
    product(W3, b3, H2T, KT)
    return KT


@njit(**JIT)
def mlp_backward(theta, VT, H1T, H2T, GKT, gtheta):
    """VJP of mlp_forward: returns GVT (din, n); adds the parameter cotangents into gtheta."""
    din, Hd, dout = VT.shape[0], H1T.shape[0], GKT.shape[0]
    W1, b1, W2, b2, W3, b3 = unpack(theta, din, Hd, dout)
    gW1, gb1, gW2, gb2, gW3, gb3 = unpack(gtheta, din, Hd, dout)
    none = b1[:0]
    n = VT.shape[1]
    param_cotangent(H2T, GKT, gW3, gb3)
    GH2T = aligned_empty((Hd, n), VT)
    product(W3.T, none, GKT, GH2T)
    tanh_cotangent(H2T, GH2T)
    param_cotangent(H1T, GH2T, gW2, gb2)
    GH1T = aligned_empty((Hd, n), VT)
    product(W2.T, none, GH2T, GH1T)
    tanh_cotangent(H1T, GH1T)
    param_cotangent(VT, GH1T, gW1, gb1)
    GVT = aligned_empty((din, n), VT)
    product(W1.T, none, GH1T, GVT)
    return GVT


@njit(**JIT)
def update_tile(theta, dims, zin, u, sums, graph, i0, i1, zoff, V, H1, H2, msrc, mcol0):
    """k = F(zin) for nodes i0..i1: returns KT (dz, n), feature-major; V, H1, H2 (this tile's
    cache rows, used feature-major) keep the MLP's inputs and activations for the VJP.
    ``sums``: dense-path row sums or empty.  The neighbours' messages are read from
    msrc[:, mcol0:mcol0+dm]: zin itself (mcol0 = dx), or a compact copy of its message columns
    (mcol0 = 0; half the memory a gather touches)."""
    dx, du, dm, H = dims[DX], dims[DU], dims[DM], dims[HIDDEN]
    self_msg, zero_msg, linear_agg = dims[SELF_MSG], dims[ZERO_MSG], dims[LINEAR]
    indptr, indices, weight, ew = graph
    n = i1 - i0
    c = dx + du
    VT = feature_major(V)
    for d in range(dx):
        for r in range(n):
            VT[d, r] = zin[i0 + r - zoff, d]
    for d in range(du):
        for r in range(n):
            VT[dx + d, r] = u[i0 + r, d]
    if zero_msg:
        VT[c:] = 0
    elif sums.shape[0] > 0:  # the dense path's row sums, weighted straight into the tile
        for d in range(dm):
            for r in range(n):
                VT[c + d, r] = sums[i0 + r - zoff, d] * weight[i0 + r]
    else:
        # node-major rows, as the reverse pass's transpose writes them: one compiled aggregate_tile serves both
        AG = aligned_empty((n, dm), VT)
        aggregate_tile(msrc, mcol0, dm, sums, indptr, indices, ew, weight, self_msg, i0, i1, zoff, AG, np.int64(0))
        transpose_into(AG, VT[c:])
    KT = mlp_forward(theta, VT, feature_major(H1), feature_major(H2), dx + dm)
    if linear_agg:
        ncol = dx if linear_agg & LINEAR_STATE else dx + dm
        linear_aggregate_forward(unpack_agg(theta, c + dm, H, dx + dm, dm, ncol), VT, c, weight,
                                 (linear_agg & LINEAR_OWN) != 0, i0, KT)
    if zero_msg:
        KT[dx:] = 0
    return KT


@njit(**JIT)
def update_vjp_tile(theta, dims, GK, weight, i0, i1, zoff, V, H1, H2, gtheta, gin, gagg, gu):
    """VJP of update_tile for the cotangent GK (n, dz) of k.

    Writes the x part of the input's cotangent into gin[:, :dx] and each node's weighted
    aggregate cotangent into gagg (rows ``i - zoff``), which the transpose of the neighbour
    sum turns into the senders' message cotangents; adds into gtheta, and the controls'
    cotangent into gu (rows ``i``, as u) unless gu is empty (training does not ask for it).
    """
    dx, du, dm, H = dims[DX], dims[DU], dims[DM], dims[HIDDEN]
    zero_msg, linear_agg = dims[ZERO_MSG], dims[LINEAR]
    n = i1 - i0
    GKT = aligned_empty((GK.shape[1], n), GK)
    transpose_into(GK, GKT)
    if zero_msg:
        GKT[dx:] = 0
    VT = feature_major(V)
    GVT = mlp_backward(theta, VT, feature_major(H1), feature_major(H2), GKT, gtheta)
    c = dx + du
    if linear_agg:  # before the aggregate's cotangent is read out of GVT below
        din, dout = c + dm, dx + dm
        ncol = dx if linear_agg & LINEAR_STATE else dout
        linear_aggregate_backward(unpack_agg(theta, din, H, dout, dm, ncol), VT, c, weight,
                                  (linear_agg & LINEAR_OWN) != 0, i0,
                                  GKT, unpack_agg(gtheta, din, H, dout, dm, ncol), GVT)
    for r in range(n):
        i = i0 + r
        zi = i - zoff
        for d in range(dx):
            gin[zi, d] = GVT[d, r]
        if gu.shape[0] > 0:
            for d in range(du):
                gu[i, d] += GVT[dx + d, r]
        w = weight.dtype.type(0) if zero_msg else weight[i]
        for d in range(dm):
            gagg[zi, d] = GVT[c + d, r] * w
