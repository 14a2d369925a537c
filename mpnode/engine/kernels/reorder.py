"""Node rows between the user's order and the kernels' (one large graph renumbered for locality).

A rollout of a million nodes returns T+1 slices of a million rows, each put back in the
user's order.  NumPy's fancy indexing does that on one core at ~23 ns a row, as much as a
fifth of the rollout itself; these loops share it among the threads (~2.5 ns a row on two).
"""
from numba import njit, prange

from .layers import JIT


@njit(parallel=True, **JIT)
def rows_to_kernel_order(a, order, out):
    """out[t, k] = a[t, order[k]] for every slice t (a, out: (T, M, c))."""
    for t in range(a.shape[0]):
        for k in prange(a.shape[1]):
            for d in range(a.shape[2]):
                out[t, k, d] = a[t, order[k], d]


@njit(parallel=True, **JIT)
def rows_to_user_order(a, order, scratch):
    """a[t, order[k]] = a[t, k] for every slice t, in place (scratch: (M, c), one slice's room)."""
    for t in range(a.shape[0]):
        for k in prange(a.shape[1]):
            for d in range(a.shape[2]):
                scratch[k, d] = a[t, k, d]
        for k in prange(a.shape[1]):
            for d in range(a.shape[2]):
                a[t, order[k], d] = scratch[k, d]
