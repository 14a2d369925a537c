"""Dense layers on feature-major tiles: a tile's activations are (width, n) arrays.

With the nodes along the contiguous axis every product vectorises over nodes, and the sum
over the layer's inputs is unrolled at compile time: one loop per chunk width (8, 4, 2, 1),
all four inlined into `product`: a width splits into 8s, then the binary digits of the rest
(13 = 8 + 4 + 1).
For each output row the running sums of a chunk stay in registers (one FMA per input, the
weight broadcast from memory) and the row is stored once per chunk.  A chunk's sums are one
chain of dependent FMAs, so a short chunk leaves the core more chains in flight: on an Intel
Cascade Lake core chunks of 8 ran the products (32 inputs, 32 outputs) 1.5-1.6x faster than
one 32-wide pass (docs/evidence/speed.md#shorter-chains-for-intel-cores).
BLAS's small-GEMM calls, which these replace, reached half the machine's rate on the
model's widths (docs/evidence/speed.md#the-engine-against-the-flop-floor-and-the-peers).
"""
import numpy as np
from numba import njit

from .layers import JIT, tanh

CHUNKS = (8, 4, 2, 1)
ALIGN = 64  # bytes: a 512-bit vector; loads that straddle two cache lines ran the products 1.3-1.5x slower


@njit(**JIT)
def aligned_empty(shape, like):
    """np.empty(shape) of ``like``'s dtype, starting on an ALIGN-byte boundary (numba aligns
    small arrays to 32 bytes only)."""
    size = 1
    for s in shape:
        size *= s
    item = like.itemsize
    buf = np.empty(size + ALIGN // item, like.dtype)
    start = ((-buf.ctypes.data) % ALIGN) // item
    return buf[start:start + size].reshape(shape)


def _partial_product(width):
    """YT[j, :] = (b[j] or YT[j, :]) + sum over k0 <= k < k0 + width of W[k, j] XT[k, :],
    for every output j; ``width`` is a compile-time constant (the loop over k unrolls).
    Inlined, and indices rather than views of W and XT: a call, like a view, counts a reference
    to each array it is given (an atomic add and its release), which on a small block's short
    rows cost more than a thin layer's sums (docs/evidence/speed.md#references-counted-on-small-blocks)."""

    @njit(inline="always", **JIT)
    def partial_product(W, b, XT, k0, YT, first):
        c, n = YT.shape
        zero = YT.dtype.type(0)
        for j in range(c):
            bj = b[j] if b.shape[0] > 0 else zero
            for r in range(n):  # the conditions are the same for every r: LLVM hoists them
                s = bj if first else YT[j, r]
                for k in range(width):
                    s += W[k0 + k, j] * XT[k0 + k, r]
                YT[j, r] = s

    return partial_product


_P8, _P4, _P2, _P1 = (_partial_product(w) for w in CHUNKS)


@njit(inline="always", **JIT)
def _chunk(width, W, b, XT, k0, YT, first):
    if width == 8:
        _P8(W, b, XT, k0, YT, first)
    elif width == 4:
        _P4(W, b, XT, k0, YT, first)
    elif width == 2:
        _P2(W, b, XT, k0, YT, first)
    else:
        _P1(W, b, XT, k0, YT, first)


@njit(**JIT)
def product(W, b, XT, YT, act=False):
    """YT (c, n) = W^T XT + b, then tanh if ``act``, for W (a, c), XT (a, n); b may be
    empty (no bias).  ``W`` may be a transposed view (the backward pass multiplies by W itself)."""
    a = W.shape[0]
    k0 = a - a  # an int64 from the start, as the loop makes it (a literal 0 would be typed apart)
    while k0 < a:
        width = CHUNKS[0]
        while width > a - k0:
            width //= 2
        _chunk(width, W, b, XT, k0, YT, k0 == 0)
        k0 += width
    if act:  # a pass of its own: inside the unrolled sums it slowed both precisions
        c, n = YT.shape
        for j in range(c):
            for r in range(n):
                YT[j, r] = tanh(YT[j, r])


@njit(inline="always", **JIT)
def dense_tanh_forward(XT, W, b, YT):
    """YT = tanh(W^T XT + b): the hidden layer, feature-major."""
    product(W, b, XT, YT, True)


@njit(**JIT)
def dense_sum(AT, src, col0, out, ocol0):
    """out[b*N + i, ocol0+d] = sum_j AT[j, i] src[b*N + j, col0+d] for every graph b of the rows.

    The rows of ``src`` are k copies of one N-node graph whose adjacency's transpose is AT (N, N)
    (C order: `product` reads it as it lies, and no product of another memory order is compiled
    for the forward pass); the k graphs go through one product (N, N) @ (N, k*w), which beats
    walking CSR rows for small graphs (and, unlike a BLAS call, takes no lock that two threads wait on).
    """
    N = AT.shape[0]
    k = src.shape[0] // N
    w = out.shape[1] - ocol0
    Mt = aligned_empty((N, k * w), src)
    for b in range(k):
        for j in range(N):
            for d in range(w):
                Mt[j, b * w + d] = src[b * N + j, col0 + d]
    R = aligned_empty((N, k * w), src)
    product(AT, AT[0, :0], Mt, R)
    for b in range(k):
        for i in range(N):
            for d in range(w):
                out[b * N + i, ocol0 + d] = R[i, b * w + d]


@njit(**JIT)
def tanh_cotangent(YT, GYT):
    """GYT *= 1 - YT^2: the cotangent through tanh, from its output."""
    c, n = YT.shape
    for j in range(c):
        for r in range(n):
            GYT[j, r] *= 1 - YT[j, r] * YT[j, r]


@njit(**JIT)
def param_cotangent(XT, GYT, gW, gb):
    """gW (a, c) += XT GYT^T and gb (c,) += the rows' sums (gb empty: no bias): a layer's
    parameter cotangents, two inputs at a time (`_two_inputs`)."""
    a, n = XT.shape
    c = GYT.shape[0]
    zero = GYT.dtype.type(0)
    for j in range(c if gb.shape[0] > 0 else 0):
        s = zero
        for r in range(n):
            s += GYT[j, r]
        gb[j] += s
    for k in range(0, a - 1, 2):
        _two_inputs(XT, k, k + 1, GYT, gW)
    if a % 2:  # the last input of an odd width, paired with itself (the copy's sums not written)
        _two_inputs(XT, a - 1, a - 1, GYT, gW)


@njit(**JIT)
def _two_inputs(XT, k, m, GYT, gW):
    """gW[k, j] += XT[k] . GYT[j] and, unless m is k, gW[m, j] += XT[m] . GYT[j]: a 2 x 4 block of
    sums per pass over the nodes, every load shared by two or four of them, eight independent FMA
    chains in flight (four left an Intel core waiting on their latency:
    docs/evidence/speed.md#shorter-chains-for-intel-cores).  Indices, not row views, as in
    `_partial_product`."""
    c, n = GYT.shape
    zero = GYT.dtype.type(0)
    c4 = c - c % 4
    for j in range(0, c4, 4):
        s0 = s1 = s2 = s3 = t0 = t1 = t2 = t3 = zero
        for r in range(n):
            xr, yr = XT[k, r], XT[m, r]
            s0 += xr * GYT[j, r]
            s1 += xr * GYT[j + 1, r]
            s2 += xr * GYT[j + 2, r]
            s3 += xr * GYT[j + 3, r]
            t0 += yr * GYT[j, r]
            t1 += yr * GYT[j + 1, r]
            t2 += yr * GYT[j + 2, r]
            t3 += yr * GYT[j + 3, r]
        gW[k, j] += s0
        gW[k, j + 1] += s1
        gW[k, j + 2] += s2
        gW[k, j + 3] += s3
        if m != k:
            gW[m, j] += t0
            gW[m, j + 1] += t1
            gW[m, j + 2] += t2
            gW[m, j + 3] += t3
    for j in range(c4, c):
        s = t = zero
        for r in range(n):
            s += XT[k, r] * GYT[j, r]
            t += XT[m, r] * GYT[j, r]
        gW[k, j] += s
        if m != k:
            gW[m, j] += t
