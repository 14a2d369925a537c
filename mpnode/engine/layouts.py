"""Each model kind's parameters: names, shapes, the flat layout and Glorot initialisation.

All parameters of a model live in one flat vector ``theta`` (the arrays below in this
order, each row-major) so that the optimiser, the per-thread gradient buffers and the
kernels share one layout; `split` gives named views for saving and inspection.  Names
and shapes are those of the model file (docs/model-format.md).
"""
import numpy as np


def param_shapes(spec):
    """{name: shape} of ``spec``'s kind, in the flat layout's order (spec: engine.FieldSpec)."""
    shapes = field_shapes(spec)
    if spec.encoder_window:  # after the field's: the kernels read theta from its start
        dx, H = spec.state_dim, spec.hidden
        shapes.update(E1=(spec.encoder_window * (2 * dx + 1), H), e1=(H,), E2=(H, dx), e2=(dx,))
    return shapes


def field_shapes(spec):
    """{name: shape} of the arrays the field (the kernels) reads, in layout order."""
    dx, du, dm, H = spec.state_dim, spec.control_dim, spec.message_dim, spec.hidden
    if spec.kind == "l2s":
        return {"W_lift": (dx + du, H), "b_lift": (H,), "W_msg": (H, H), "b_msg": (H,), "psi": (H,),
                "W_upd": (H, H), "b_upd": (H,), "W_out": (H, dx), "b_out": (dx,)}
    n = spec.n_nodes if spec.kind == "node" else 1  # a plain NODE sees all N nodes at once
    din, dout = n * (dx + du) + dm, n * dx + dm
    shapes = {"W1": (din, H), "b1": (H,), "W2": (H, H), "b2": (H,), "W3": (H, dout), "b3": (dout,)}
    if spec.linear_path:  # last, so the MLP's layout is the same either way
        shapes["W_agg"] = (dm, dx if spec.aggregation.target == "state" else dout)
    return shapes


#: weight matrices that start at zero, not Glorot: W_agg, so that a model with the linear
#: aggregate path starts as the same MLP without it; E2, so that a new initial-state encoder
#: starts by taking the first observation as it is
ZERO_INIT = ("W_agg", "E2")


def n_params(spec):
    return sum(int(np.prod(s)) for s in param_shapes(spec).values())


def split(theta, shapes):
    """Named views into ``theta`` for ``shapes`` ({name: shape}, in layout order)."""
    out, o = {}, 0
    for name, shape in shapes.items():
        size = int(np.prod(shape))
        out[name] = theta[o:o + size].reshape(shape)
        o += size
    if o != theta.size:
        raise ValueError(f"theta has {theta.size} entries, the shapes need {o}")
    return out


def join(params, shapes, dtype=None):
    """The flat vector of a dict of arrays, in the order of ``shapes``."""
    return np.concatenate([np.asarray(params[n], dtype=dtype).ravel() for n in shapes])


def glorot_init(spec, seed=0, dtype=np.float32):
    """Glorot-uniform weight matrices; zero biases and zero psi (Flux's defaults); zero ZERO_INIT.

    The draws do not depend on ZERO_INIT, so a model with W_agg starts with the same MLP."""
    rng = np.random.default_rng(seed)
    parts = {}
    for name, shape in param_shapes(spec).items():
        if name in ZERO_INIT:
            parts[name] = np.zeros(shape)
        elif len(shape) == 2:
            limit = np.sqrt(6.0 / (shape[0] + shape[1]))
            parts[name] = rng.uniform(-limit, limit, size=shape)
        else:
            parts[name] = np.zeros(shape)
    return join(parts, param_shapes(spec), dtype=dtype)
