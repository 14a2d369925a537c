"""Dense layers, tanh, and neighbour sums on tiles of rows (nodes): forward/backward pairs.

Dense products go to BLAS (``np.dot`` on contiguous tiles; the caller pins BLAS to one
thread so numba's threads do not fight BLAS's own); elementwise work and the neighbour
sums are loops that LLVM vectorises.  (The MP-NODE field and the dense neighbour sums use
the feature-major products of ``feature_major`` instead.)  Every ``*_backward`` *adds* the parameter
cotangents into the buffers it is given, so one buffer can collect a whole rollout.
"""
import math

import numpy as np
from numba import njit
from numba.extending import overload

# No nnan/ninf: a NaN must survive the arithmetic so that callers can detect it.
FASTMATH = {"contract", "reassoc", "nsz", "arcp", "afn"}
# error_model="numpy": no ZeroDivisionError checks, which would stop the loops vectorising.
JIT = dict(cache=True, fastmath=FASTMATH, error_model="numpy")
# The neighbour sums without "reassoc": with it LLVM turns each CSR row's sum into masked
# gathers and a horizontal add, several times slower than scalar sums on Intel cores for the
# few neighbours a row has (docs/evidence/speed.md, "Neighbour sums without gathers").
ORDERED_JIT = dict(JIT, fastmath=FASTMATH - {"reassoc"})


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
    # float64: Cephes' tanh with its exp written out so that LLVM vectorises it (libm's is a
    # scalar call: docs/evidence/speed.md); 1.7 ulp at most (libm: 2.1), NaN -> NaN, +-inf -> +-1.
    def tanh64(x):
        ax = abs(x)
        ac = 20.0 if ax > 20.0 else ax  # tanh(20) == 1.0 in float64; NaN passes unchanged
        # |x| < 0.625: the Cephes rational, tanh = ac + ac z p / q
        z = ac * ac
        p = -9.64399179425052238628e-1
        p = p * z - 9.92877231001918586564e1
        p = p * z - 1.61468768441708447952e3
        q = z + 1.12811678491632931402e2
        q = q * z + 2.23548839060100448583e3
        q = q * z + 4.84406305325125486048e3
        # |x| >= 0.625: exp(2 ac) = 2^n (qe + pe) / (qe - pe), 2 ac = n ln2 + r, |r| <= ln2 / 2
        t = ac + ac
        n = np.rint(t * 1.4426950408889634)
        r = t - n * 6.93147180559945309417e-1
        rr = r * r
        pe = 1.26177193074810590878e-4
        pe = pe * rr + 3.02994407707441961300e-2
        pe = pe * rr + 9.99999999999999999910e-1
        pe = r * pe
        qe = 3.00198505138664455042e-6
        qe = qe * rr + 2.52448340349684104192e-3
        qe = qe * rr + 2.27265548208155028766e-1
        qe = qe * rr + 2.0
        # 2^n from the exponent bits (AVX2 has no vector float <-> int64 conversion)
        s = np.int64(np.float64(n + 4503599627371519.0).view(np.int64) << 52).view(np.float64)
        nn = qe - pe
        d = s * (qe + pe)  # exp(2 ac) = d / nn
        # one division serves both branches: 2 / (exp(2 ac) + 1) = 2 nn / (d + nn), or p / q
        big = ac >= 0.625
        c = (nn if big else p) / ((d + nn) if big else q)
        y = (1.0 - (c + c)) if big else (ac + ac * z * c)
        return math.copysign(y, x)

    return tanh64


@njit(inline="always", **JIT)
def copy_into(dst, src):
    """dst[:] = src for 2-D arrays, written as a loop: numba's assignment of an array to a slice
    compiles a shape-mismatch message formatted at run time, whose string code lengthened every
    driver's first compile (docs/evidence/cold-start.md).  This one's message is a constant."""
    if dst.shape != src.shape:
        raise ValueError("copy_into: the arrays' shapes differ")
    for i in range(dst.shape[0]):
        for d in range(dst.shape[1]):
            dst[i, d] = src[i, d]


@njit(inline="always", **JIT)
def add_into(dst, src):
    """dst[:] += src for 2-D arrays, as `copy_into` (a slice's ``+=`` assigns the slice too)."""
    if dst.shape != src.shape:
        raise ValueError("add_into: the arrays' shapes differ")
    for i in range(dst.shape[0]):
        for d in range(dst.shape[1]):
            dst[i, d] += src[i, d]


@njit(**JIT)
def dense_tanh_forward(X, W, b, Y):
    """Y = tanh(X W + b).  X (n, a), W (a, c), b (c,), Y (n, c) written in place."""
    np.dot(X, W, Y)
    n, c = Y.shape
    for r in range(n):
        for j in range(c):
            Y[r, j] = tanh(Y[r, j] + b[j])


@njit(**JIT)
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


@njit(**JIT)
def dense_forward(X, W, b):
    """Y = X W + b (a linear output layer)."""
    Y = np.dot(X, W)
    n, c = Y.shape
    for r in range(n):
        for j in range(c):
            Y[r, j] += b[j]
    return Y


@njit(**JIT)
def dense_backward(X, W, GY, gW, gb):
    """Cotangents of Y = X W + b: returns GX; adds into gW and gb."""
    gW += np.dot(X.T, GY)
    n, c = GY.shape
    for r in range(n):
        for j in range(c):
            gb[j] += GY[r, j]
    return np.dot(GY, W.T)


# ---------------------------------------------------------------------------
# Neighbour sums.  Rows of the arrays are nodes ``i - zoff`` (a block of the batch, or
# the whole graph with zoff = 0); node i hears indices[indptr[i]:indptr[i+1]].
# ---------------------------------------------------------------------------
@njit(inline="always", **JIT)
def row_sum4(src, col, nd, indptr, indices, row, zoff, self_row):
    """Columns col..col+nd (nd <= 4) of src summed over the CSR row ``row`` (entries ``- zoff``)
    and over src[self_row] if self_row >= 0.  Four scalar sums stay in registers: a sum kept
    in the output array chains every neighbour's add through a store and a load."""
    a0 = a1 = a2 = a3 = src.dtype.type(0)
    if self_row >= 0:
        a0 = src[self_row, col]
        if nd > 1:
            a1 = src[self_row, col + 1]
        if nd > 2:
            a2 = src[self_row, col + 2]
        if nd > 3:
            a3 = src[self_row, col + 3]
    for p in range(indptr[row], indptr[row + 1]):
        j = indices[p] - zoff
        a0 += src[j, col]
        if nd > 1:
            a1 += src[j, col + 1]
        if nd > 2:
            a2 += src[j, col + 2]
        if nd > 3:
            a3 += src[j, col + 3]
    return a0, a1, a2, a3


@njit(inline="always", **JIT)
def weighted_row_sum4(src, col, nd, indptr, indices, ew, row, zoff, self_row):
    """row_sum4 with each neighbour's columns times its edge's weight ew[p] (a self message
    counts once: it has no edge).  A copy of the walk rather than a flag in it, so that an
    unweighted graph runs the plain sums' code."""
    a0 = a1 = a2 = a3 = src.dtype.type(0)
    if self_row >= 0:
        a0 = src[self_row, col]
        if nd > 1:
            a1 = src[self_row, col + 1]
        if nd > 2:
            a2 = src[self_row, col + 2]
        if nd > 3:
            a3 = src[self_row, col + 3]
    for p in range(indptr[row], indptr[row + 1]):
        j = indices[p] - zoff
        w = ew[p]
        a0 += w * src[j, col]
        if nd > 1:
            a1 += w * src[j, col + 1]
        if nd > 2:
            a2 += w * src[j, col + 2]
        if nd > 3:
            a3 += w * src[j, col + 3]
    return a0, a1, a2, a3


@njit(inline="always", **JIT)
def store4(out, r, col, nd, sums, w):
    """out[r, col + k] = sums[k] * w for k < nd (constant indices keep the sums in registers)."""
    out[r, col] = sums[0] * w
    if nd > 1:
        out[r, col + 1] = sums[1] * w
    if nd > 2:
        out[r, col + 2] = sums[2] * w
    if nd > 3:
        out[r, col + 3] = sums[3] * w


@njit(inline="always", **JIT)
def row_sum(src, col0, width, indptr, indices, row, zoff, self_row, out, r, ocol0, w):
    """out[r, ocol0:ocol0+width] = w * (row_sum4 of columns col0:col0+width), four at a time."""
    for d0 in range(0, width, 4):
        nd = min(4, width - d0)
        store4(out, r, ocol0 + d0, nd, row_sum4(src, col0 + d0, nd, indptr, indices, row, zoff, self_row), w)


@njit(inline="always", **JIT)
def weighted_row_sum(src, col0, width, indptr, indices, ew, row, zoff, self_row, out, r, ocol0, w):
    """row_sum with the edges' weights ``ew``."""
    for d0 in range(0, width, 4):
        nd = min(4, width - d0)
        store4(out, r, ocol0 + d0, nd, weighted_row_sum4(src, col0 + d0, nd, indptr, indices, ew, row, zoff,
                                                          self_row), w)


@njit(inline="always", **JIT)
def gather_rows(src, col0, width, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0):
    """aggregate_tile's CSR walk for rows i0..i1 (inlined where ``width`` is a constant); an
    empty ``weight`` weighs every row 1, an empty ``ew`` every edge."""
    weighted = weight.shape[0] > 0
    if ew.shape[0] > 0:
        for r in range(i1 - i0):
            i = i0 + r
            w = weight[i] if weighted else src.dtype.type(1)
            weighted_row_sum(src, col0, width, indptr, indices, ew, i, zoff, i - zoff if self_msg else -1, out, r,
                             ocol0, w)
        return
    for r in range(i1 - i0):
        i = i0 + r
        w = weight[i] if weighted else src.dtype.type(1)
        row_sum(src, col0, width, indptr, indices, i, zoff, i - zoff if self_msg else -1, out, r, ocol0, w)


@njit(**ORDERED_JIT)
def aggregate_tile(src, col0, width, sums, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0):
    """out[r, ocol0:ocol0+width] = weight[i] * (sum over row i [and i itself] of ew[p] src[j, col0:]), i = i0 + r.

    ``ew``: the edges' weights (row i's at ew[indptr[i]:indptr[i+1]]), or empty: every edge 1.

    ``sums`` holds the row sums already (rows ``i - zoff``: the dense path) or is empty
    (then the sum walks the CSR row).  The weight decides the aggregation (mean: 1/degree).
    Narrow rows (messages) are summed in registers, widths 1-4 each by a copy of the walk
    compiled for that width (with the width a run-time value the sums lose their registers);
    wide rows (L2S's hidden width) add each neighbour's whole row, which vectorises.
    """
    if sums.shape[0] > 0:
        for r in range(i1 - i0):
            for d in range(width):
                out[r, ocol0 + d] = sums[i0 + r - zoff, d] * weight[i0 + r]
    elif width == 3:
        gather_rows(src, col0, 3, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0)
    elif width == 2:
        gather_rows(src, col0, 2, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0)
    elif width == 4:
        gather_rows(src, col0, 4, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0)
    elif width == 1:
        gather_rows(src, col0, 1, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0)
    elif width <= 8:
        gather_rows(src, col0, width, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0)
    else:
        add_rows(src, col0, width, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0)


@njit(inline="always", **JIT)
def add_rows(src, col0, width, indptr, indices, ew, weight, self_msg, i0, i1, zoff, out, ocol0):
    """aggregate_tile's CSR walk for wide rows: each neighbour's row added into the output row
    (times its edge's weight when ``ew`` is not empty)."""
    weighted = weight.shape[0] > 0
    edge_weighted = ew.shape[0] > 0
    for r in range(i1 - i0):
        i = i0 + r
        for d in range(width):
            out[r, ocol0 + d] = src[i - zoff, col0 + d] if self_msg else src.dtype.type(0)
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p] - zoff
            if edge_weighted:
                w = ew[p]  # read once: in the loop the compiler could not prove it unchanged by the stores
                for d in range(width):
                    out[r, ocol0 + d] += w * src[j, col0 + d]
            else:
                for d in range(width):
                    out[r, ocol0 + d] += src[j, col0 + d]
        if weighted:
            for d in range(width):
                out[r, ocol0 + d] *= weight[i]


@njit(**JIT)
def transpose_tile(g, tindptr, tindices, tew, self_msg, i0, i1, zoff, out, ocol0):
    """out[j, ocol0+d] = sum of w_ij g[i, d] over the nodes i that hear j [+ g[j, d]] (rows j - zoff).

    The transpose of the neighbour sum: ``g`` holds each receiver's (already weighted)
    cotangent; the CSR transpose (tindptr, tindices) lists, for sender j, who hears it, and
    ``tew`` the weights of those edges (empty: all 1).
    """
    aggregate_tile(g, np.int64(0), g.shape[1], np.empty((0, 0), g.dtype), tindptr, tindices, tew, np.empty(0, g.dtype),
                   self_msg, i0, i1, zoff, out[i0 - zoff:i1 - zoff], ocol0)


@njit(**JIT)
def edge_cotangent(g, src, indptr, indices, i0, i1, zoff, gw):
    """gw[p] += <g[i], src[j]> for every edge p = (i hears j) of rows i0..i1 (rows ``- zoff``):
    the cotangent of an edge's weight, from the receiver's aggregate cotangent ``g`` and what
    the sender sent, ``src`` (the rows of a node's gw are its own: no races between blocks)."""
    for i in range(i0, i1):
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p] - zoff
            acc = g.dtype.type(0)
            for d in range(g.shape[1]):
                acc += g[i - zoff, d] * src[j, d]
            gw[p] += acc
