"""The L2S field (the paper's graph-network ODE baseline) on a tile of nodes, and its VJP.

Per node k, with z-scored x_k and u_k (the state is x alone):
    h0_k = tanh([x_k, u_k] W_lift + b_lift)          (send: every node, before the sum)
    s_k  = tanh(h0_k W_msg + b_msg)                  (what k sends)
    a_k  = weight_k * sum of s_j over k's row        (psi when the row is empty)
    t_k  = tanh(a_k W_upd + b_upd)                   (update)
    dx_k/dt = (2 h0_k + t_k) W_out + b_out           (= ((h0 + t) + h0) W_out: h1 = h0 + t)
Parameters, flat in this order: W_lift (dx+du, H), b_lift (H), W_msg (H, H), b_msg (H),
psi (H), W_upd (H, H), b_upd (H), W_out (H, dx), b_out (dx).
``dims`` (mpnode.engine.dims) has dims[DM] = 0 and dims[LINEAR] = 0.
"""
import numpy as np
from numba import njit

from ..dims import DU, DX, HIDDEN, SELF_MSG
from .layers import (
    JIT,
    aggregate_tile,
    dense_backward,
    dense_forward,
    dense_tanh_backward,
    dense_tanh_forward,
)


@njit(**JIT)
def unpack(theta, dxu, H, dx):
    """Views (W_lift, b_lift, W_msg, b_msg, psi, W_upd, b_upd, W_out, b_out) into ``theta``."""
    o = 0
    W_lift = theta[o:o + dxu * H].reshape(dxu, H)
    o += dxu * H
    b_lift = theta[o:o + H]
    o += H
    W_msg = theta[o:o + H * H].reshape(H, H)
    o += H * H
    b_msg = theta[o:o + H]
    o += H
    psi = theta[o:o + H]
    o += H
    W_upd = theta[o:o + H * H].reshape(H, H)
    o += H * H
    b_upd = theta[o:o + H]
    o += H
    W_out = theta[o:o + H * dx].reshape(H, dx)
    o += H * dx
    b_out = theta[o:o + dx]
    return W_lift, b_lift, W_msg, b_msg, psi, W_upd, b_upd, W_out, b_out


@njit(**JIT)
def send_tile(theta, dims, zin, u, i0, i1, zoff, V, H0, S):
    """h0 and s for nodes i0..i1 into H0, S (this tile's rows); V keeps [x, u]."""
    dx, du, H = dims[DX], dims[DU], dims[HIDDEN]
    W_lift, b_lift, W_msg, b_msg, _, _, _, _, _ = unpack(theta, dx + du, H, dx)
    for r in range(i1 - i0):
        zi = i0 + r - zoff
        for d in range(dx):
            V[r, d] = zin[zi, d]
        for d in range(du):
            V[r, dx + d] = u[i0 + r, d]
    dense_tanh_forward(V, W_lift, b_lift, H0)
    dense_tanh_forward(H0, W_msg, b_msg, S)


@njit(**JIT)
def _empty_row(indptr, self_msg, i):
    return not self_msg and indptr[i + 1] == indptr[i]


@njit(**JIT)
def _residual(H0, T):
    """h1 + h0 = 2 h0 + t, the decoder's input."""
    O = np.empty_like(H0)
    two = H0.dtype.type(2)
    n, c = H0.shape
    for r in range(n):
        for d in range(c):
            O[r, d] = two * H0[r, d] + T[r, d]
    return O


@njit(**JIT)
def update_tile(theta, dims, S_all, sums, graph, i0, i1, zoff, H0, A, T):
    """dx/dt for nodes i0..i1 from everyone's s (S_all, rows ``i - zoff``): returns K (n, dx).

    H0: this tile's h0 rows; A, T (this tile's rows) keep a and t for the VJP.
    """
    dx, du, H, self_msg = dims[DX], dims[DU], dims[HIDDEN], dims[SELF_MSG]
    indptr, indices, weight, ew = graph
    _, _, _, _, psi, W_upd, b_upd, W_out, b_out = unpack(theta, dx + du, H, dx)
    aggregate_tile(S_all, 0, H, sums, indptr, indices, ew, weight, self_msg, i0, i1, zoff, A, 0)
    for r in range(i1 - i0):
        if _empty_row(indptr, self_msg, i0 + r):
            for d in range(psi.shape[0]):
                A[r, d] = psi[d]
    dense_tanh_forward(A, W_upd, b_upd, T)
    return dense_forward(_residual(H0, T), W_out, b_out)


@njit(**JIT)
def update_vjp_tile(theta, dims, GK, graph, i0, i1, zoff, H0, A, T, gtheta, gagg, gh0):
    """VJP of update_tile for the cotangent GK of dx/dt.

    Writes each node's weighted cotangent of a into gagg and the direct cotangent of h0
    (through the residual and the decoder) into gh0, both rows ``i - zoff``; an empty
    row's cotangent of a goes to psi.  Adds into gtheta.
    """
    dx, du, H, self_msg = dims[DX], dims[DU], dims[HIDDEN], dims[SELF_MSG]
    indptr, _, weight, _ = graph
    _, _, _, _, psi, W_upd, b_upd, W_out, b_out = unpack(theta, dx + du, H, dx)
    _, _, _, _, gpsi, gW_upd, gb_upd, gW_out, gb_out = unpack(gtheta, dx + du, H, dx)
    GO = dense_backward(_residual(H0, T), W_out, GK, gW_out, gb_out)
    two = GO.dtype.type(2)
    for r in range(i1 - i0):
        zi = i0 + r - zoff
        for d in range(H):
            gh0[zi, d] = two * GO[r, d]
    GA = dense_tanh_backward(A, W_upd, T, GO, gW_upd, gb_upd)
    for r in range(i1 - i0):
        i = i0 + r
        zi = i - zoff
        if _empty_row(indptr, self_msg, i):
            gpsi += GA[r]
            gagg[zi, :] = 0
        else:
            w = weight[i]
            for d in range(H):
                gagg[zi, d] = GA[r, d] * w


@njit(**JIT)
def send_vjp_tile(theta, dims, gS, gh0, i0, i1, zoff, V, H0, S, gtheta, gin, gu):
    """VJP of send_tile: gS (cotangent of s, rows ``i - zoff``) and gh0 -> gin[:, :dx], and
    added into gu (rows ``i``, as u) unless gu is empty."""
    dx, du, H = dims[DX], dims[DU], dims[HIDDEN]
    W_lift, _, W_msg, _, _, _, _, _, _ = unpack(theta, dx + du, H, dx)
    gW_lift, gb_lift, gW_msg, gb_msg, _, _, _, _, _ = unpack(gtheta, dx + du, H, dx)
    n = i1 - i0
    GS = np.empty((n, H), gS.dtype)
    for r in range(n):
        zi = i0 + r - zoff
        for d in range(H):
            GS[r, d] = gS[zi, d]
    GH0 = dense_tanh_backward(H0, W_msg, S, GS, gW_msg, gb_msg)
    for r in range(n):
        zi = i0 + r - zoff
        for d in range(H):
            GH0[r, d] += gh0[zi, d]
    GV = dense_tanh_backward(V, W_lift, H0, GH0, gW_lift, gb_lift)
    for r in range(n):
        zi = i0 + r - zoff
        for d in range(dx):
            gin[zi, d] = GV[r, d]
    if gu.shape[0] > 0:
        for r in range(n):
            for d in range(du):
                gu[i0 + r, d] += GV[r, dx + d]
