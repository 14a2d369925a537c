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
from .layers import (
    JIT,
    aggregate_tile,
    dense_backward,
    dense_forward,
    dense_tanh_backward,
    dense_tanh_forward,
)


@njit(**JIT)
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


@njit(**JIT)
def unpack_agg(theta, din, H, dout, dm, ncol):
    """The view W_agg (dm, ncol) that follows the MLP's parameters in ``theta`` (ncol: dout,
    or dx when the path feeds dx/dt alone)."""
    o = din * H + H + H * H + H + H * dout + dout
    return theta[o:o + dm * ncol].reshape(dm, ncol)


@njit(**JIT)
def linear_input(V, c, weight, own, i0):
    """The linear path's input for rows i0..: V[:, c:] (the MLP's aggregate), each row r
    times weight[M + i0 + r] when the path has its ``own`` aggregation (M = weight.size / 2)."""
    Va = np.ascontiguousarray(V[:, c:])
    if own:
        off = weight.shape[0] // 2 + i0
        for r in range(Va.shape[0]):
            Va[r] *= weight[off + r]
    return Va


@njit(**JIT)
def linear_aggregate_forward(Wa, V, c, weight, own, i0, K):
    """K[:, :ncol] += A Wa (ncol = Wa's columns), A = linear_input(...): the aggregate's path
    around the MLP (whose tanh units cannot follow the larger aggregates of denser graphs;
    the gene dynamics are linear in them)."""
    K[:, :Wa.shape[1]] += np.dot(linear_input(V, c, weight, own, i0), Wa)


@njit(**JIT)
def linear_aggregate_backward(Wa, V, c, weight, own, i0, GK, gWa, GV):
    """VJP of linear_aggregate_forward: gWa += A^T G, GV[:, c:] += s * (G Wa^T), G = GK[:, :ncol]."""
    G = np.ascontiguousarray(GK[:, :Wa.shape[1]])
    gWa += np.dot(linear_input(V, c, weight, own, i0).T, G)
    GA = np.dot(G, Wa.T)
    if own:
        off = weight.shape[0] // 2 + i0
        for r in range(GA.shape[0]):
            GA[r] *= weight[off + r]
    GV[:, c:] += GA


@njit(**JIT)
def mlp_forward(theta, V, H1, H2, dout):
    """K = W3^T tanh(W2^T tanh(W1^T v + b1) + b2) + b3 per row v of V; keeps H1, H2."""
    W1, b1, W2, b2, W3, b3 = unpack(theta, V.shape[1], H1.shape[1], dout)
    dense_tanh_forward(V, W1, b1, H1)
    dense_tanh_forward(H1, W2, b2, H2)
    return dense_forward(H2, W3, b3)


@njit(**JIT)
def mlp_backward(theta, V, H1, H2, GK, gtheta):
    """VJP of mlp_forward: returns GV (n, din); adds the parameter cotangents into gtheta."""
    din, Hd, dout = V.shape[1], H1.shape[1], GK.shape[1]
    W1, b1, W2, b2, W3, b3 = unpack(theta, din, Hd, dout)
    gW1, gb1, gW2, gb2, gW3, gb3 = unpack(gtheta, din, Hd, dout)
    GH2 = dense_backward(H2, W3, GK, gW3, gb3)
    GH1 = dense_tanh_backward(H1, W2, H2, GH2, gW2, gb2)
    return dense_tanh_backward(V, W1, H1, GH1, gW1, gb1)


@njit(**JIT)
def update_tile(theta, dims, zin, u, sums, graph, i0, i1, zoff, V, H1, H2, msrc, mcol0):
    """k = F(zin) for nodes i0..i1: returns K (n, dz); V, H1, H2 (this tile's rows) keep the
    MLP's inputs and activations for the VJP.  ``sums``: dense-path row sums or empty.
    The neighbours' messages are read from msrc[:, mcol0:mcol0+dm]: zin itself (mcol0 = dx),
    or a compact copy of its message columns (mcol0 = 0; half the memory a gather touches)."""
    dx, du, dm, H = dims[DX], dims[DU], dims[DM], dims[HIDDEN]
    self_msg, zero_msg, linear_agg = dims[SELF_MSG], dims[ZERO_MSG], dims[LINEAR]
    indptr, indices, weight = graph
    c = dx + du
    for r in range(i1 - i0):
        zi = i0 + r - zoff
        for d in range(dx):
            V[r, d] = zin[zi, d]
        for d in range(du):
            V[r, dx + d] = u[i0 + r, d]
    if zero_msg:
        V[:, c:] = 0
    else:
        aggregate_tile(msrc, mcol0, dm, sums, indptr, indices, weight, self_msg, i0, i1, zoff, V, c)
    K = mlp_forward(theta, V, H1, H2, dx + dm)
    if linear_agg:
        ncol = dx if linear_agg & LINEAR_STATE else dx + dm
        linear_aggregate_forward(unpack_agg(theta, c + dm, H, dx + dm, dm, ncol), V, c, weight,
                                 (linear_agg & LINEAR_OWN) != 0,
                                 i0, K)
    if zero_msg:
        K[:, dx:] = 0
    return K


@njit(**JIT)
def update_vjp_tile(theta, dims, GK, weight, i0, i1, zoff, V, H1, H2, gtheta, gin, gagg, gu):
    """VJP of update_tile for the cotangent GK of k (overwritten).

    Writes the x part of the input's cotangent into gin[:, :dx] and each node's weighted
    aggregate cotangent into gagg (rows ``i - zoff``), which the transpose of the neighbour
    sum turns into the senders' message cotangents; adds into gtheta, and the controls'
    cotangent into gu (rows ``i``, as u) unless gu is empty (training does not ask for it).
    """
    dx, du, dm, H = dims[DX], dims[DU], dims[DM], dims[HIDDEN]
    zero_msg, linear_agg = dims[ZERO_MSG], dims[LINEAR]
    if zero_msg:
        GK[:, dx:] = 0
    GV = mlp_backward(theta, V, H1, H2, GK, gtheta)  # GK is left as it was given
    c = dx + du
    if linear_agg:  # before the aggregate's cotangent is read out of GV below
        din, dout = c + dm, dx + dm
        ncol = dx if linear_agg & LINEAR_STATE else dout
        linear_aggregate_backward(unpack_agg(theta, din, H, dout, dm, ncol), V, c, weight,
                                  (linear_agg & LINEAR_OWN) != 0, i0,
                                  GK, unpack_agg(gtheta, din, H, dout, dm, ncol), GV)
    for r in range(i1 - i0):
        i = i0 + r
        zi = i - zoff
        for d in range(dx):
            gin[zi, d] = GV[r, d]
        if gu.shape[0] > 0:
            for d in range(du):
                gu[i, d] += GV[r, dx + d]
        w = weight.dtype.type(0) if zero_msg else weight[i]
        for d in range(dm):
            gagg[zi, d] = GV[r, c + d] * w
