"""Adam on mpnode's flat parameter vector, with gradient clipping per parameter array.

Clipping each of the parameter arrays on its own when *that array's* L2 norm exceeds the
threshold (500) is what the original training does (Flux's ``ClipNorm`` before ``ADAM``
applies to every array separately; docs/design.md); ``mode="global"`` clips by one norm
over all parameters instead.

The moments are kept in float64 whatever the model's dtype, so the update is the same
arithmetic on every run (resume is bit-for-bit) and float32 models lose nothing to the
bias correction.
"""
import numpy as np

CLIP_MODES = ("per-array", "global")


def array_slices(shapes):
    """Slices of the flat vector, one per parameter array, in ``shapes``' order.

    shapes : dict name -> shape (mpnode.mlp.param_shapes); returns list of slice.
    """
    out, o = [], 0
    for shape in shapes.values():
        size = int(np.prod(shape))
        out.append(slice(o, o + size))
        o += size
    return out


def clip_gradient(g, max_norm, slices, mode="per-array"):
    """Clip ``g`` (shape (P,), float64, modified in place) and return its norm before clipping.

    max_norm <= 0 or None disables clipping.  Per-array: every slice whose L2 norm exceeds
    ``max_norm`` is scaled down to exactly ``max_norm``; global: the whole vector is.
    """
    total = float(np.sqrt(np.dot(g, g)))
    if not max_norm or max_norm <= 0:
        return total
    if mode == "global":
        if total > max_norm:
            g *= max_norm / total
    elif mode == "per-array":
        for s in slices:
            n = float(np.sqrt(np.dot(g[s], g[s])))
            if n > max_norm:
                g[s] *= max_norm / n
    else:
        raise ValueError(f"clip mode {mode!r} is not one of {CLIP_MODES}")
    return total


class Adam:
    """Adam (Kingma & Ba), Flux's formulation.

    m = b1 m + (1-b1) g;  v = b2 v + (1-b2) g^2;
    theta -= lr * (m / (1-b1^t)) / (sqrt(v / (1-b2^t)) + eps)
    """

    def __init__(self, n_params, lr=1e-3, beta1=0.9, beta2=0.999, eps=1e-8):
        self.lr = float(lr)
        self.beta1, self.beta2, self.eps = float(beta1), float(beta2), float(eps)
        self.m = np.zeros(n_params)
        self.v = np.zeros(n_params)
        self.t = 0
        self._step = np.empty(n_params)
        self._tmp = np.empty(n_params)

    def update(self, g):
        """The step to subtract from the parameters for gradient ``g`` (shape (P,), float64).

        Advances the moments; returns a float64 array owned by the optimiser (reused).
        """
        b1, b2 = self.beta1, self.beta2
        self.t += 1
        self.m *= b1
        self.m += (1.0 - b1) * g
        self.v *= b2
        np.multiply(g, g, out=self._tmp)
        self._tmp *= 1.0 - b2
        self.v += self._tmp
        np.divide(self.v, 1.0 - b2 ** self.t, out=self._tmp)
        np.sqrt(self._tmp, out=self._tmp)
        self._tmp += self.eps
        np.divide(self.m, 1.0 - b1 ** self.t, out=self._step)
        self._step /= self._tmp
        self._step *= self.lr
        return self._step

    # ---- state for checkpoints -----------------------------------------------
    def state(self):
        return {"adam_m": self.m.copy(), "adam_v": self.v.copy(), "adam_t": np.int64(self.t),
                "lr": np.float64(self.lr)}

    def load_state(self, state):
        self.m[:] = state["adam_m"]
        self.v[:] = state["adam_v"]
        self.t = int(state["adam_t"])
        self.lr = float(state["lr"])
