"""The MP-NODE MLP's parameters: names, shapes, the flat layout and Glorot initialisation.

All parameters live in one flat vector ``theta`` (order W1 b1 W2 b2 W3 b3, each
row-major) so that the optimiser, the per-thread gradient buffers and the kernels
share one layout; `split` gives named views for saving and inspection.
"""
import numpy as np

PARAM_NAMES = ("W1", "b1", "W2", "b2", "W3", "b3")


def param_shapes(state_dim, control_dim, message_dim, hidden):
    """Shapes of W1 b1 W2 b2 W3 b3: input [x, u, m'], output [dx/dt, dm/dt]."""
    din = state_dim + control_dim + message_dim
    dout = state_dim + message_dim
    return {
        "W1": (din, hidden), "b1": (hidden,),
        "W2": (hidden, hidden), "b2": (hidden,),
        "W3": (hidden, dout), "b3": (dout,),
    }


def n_params(state_dim, control_dim, message_dim, hidden):
    return sum(int(np.prod(s)) for s in param_shapes(state_dim, control_dim, message_dim, hidden).values())


def split(theta, shapes):
    """Named views into ``theta`` for the given shapes (in PARAM_NAMES order)."""
    out, o = {}, 0
    for name in PARAM_NAMES:
        size = int(np.prod(shapes[name]))
        out[name] = theta[o:o + size].reshape(shapes[name])
        o += size
    if o != theta.size:
        raise ValueError(f"theta has {theta.size} entries, the shapes need {o}")
    return out


def join(params, dtype=None):
    """The flat vector of a dict of arrays (PARAM_NAMES order)."""
    return np.concatenate([np.asarray(params[n], dtype=dtype).ravel() for n in PARAM_NAMES])


def glorot_init(state_dim, control_dim, message_dim, hidden, seed=0, dtype=np.float32):
    """Glorot-uniform weights, zero biases (Flux's default, as in the seed code)."""
    rng = np.random.default_rng(seed)
    parts = {}
    for name, shape in param_shapes(state_dim, control_dim, message_dim, hidden).items():
        if name.startswith("W"):
            limit = np.sqrt(6.0 / (shape[0] + shape[1]))
            parts[name] = rng.uniform(-limit, limit, size=shape)
        else:
            parts[name] = np.zeros(shape)
    return join(parts, dtype=dtype)
