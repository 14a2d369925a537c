"""The losses' pass over a rollout's residuals, compiled (numba is imported with this module:
training needs it anyway, and `import mpnode` stays free of it)."""
import numpy as np
from numba import njit

from mpnode.engine.codegen import build_numba_codegen

build_numba_codegen()  # before the declaration below: the vector width it compiles for


@njit(cache=True, error_model="numpy")
def residual_pass(pred, x, is_huber, g, scale):
    """One pass over pred - x, in float64, at steps 1..T (e = 0 where it is NaN: x not observed):
    returns (the sum of huber(e) or e^2; whether pred is finite everywhere) and, when ``g`` has
    rows, writes the cotangent scale * dloss/de into g (0 at step 0: the initial state is
    given).  Loss and cotangent in one pass, where NumPy took eight and a float64 copy
    (what that cost: docs/evidence/speed.md#kept-stage-caches)."""
    total = 0.0
    finite = True
    grad = g.shape[0] > 0
    for t in range(pred.shape[0]):
        for i in range(pred.shape[1]):
            for d in range(pred.shape[2]):
                p = np.float64(pred[t, i, d])
                finite = finite and np.isfinite(p)
                e = 0.0 if t == 0 else p - np.float64(x[t, i, d])
                if np.isnan(e):
                    e = 0.0
                if is_huber:
                    c = min(max(e, -1.0), 1.0)
                    total += c * (e - 0.5 * c)
                    de = c
                else:
                    total += e * e
                    de = 2.0 * e
                if grad:
                    g[t, i, d] = scale * de
    return total, finite
