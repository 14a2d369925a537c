"""A model's z-score constants changed without changing what the model computes.

The network works on z = (x - mean) / std and returns dz/dt.  With other constants
(mean', std'), z = a z' + c with a = std' / std and c = (mean' - mean) / std, so scaling
the input rows of x (and u) by a, shifting the first bias by c times them, and dividing the
output columns of dx/dt by a gives exactly the same rollouts in data units.  Fine-tuning
on new data with their own constants then weighs each state dimension in the loss as the
new data's spread (and `mpnode eval`'s nMSE) does, from the model it starts from.

An initial-state encoder (mpnode.model.encoder) reads normalised observations and writes a
normalised state: its value inputs and its output change the same way, which is exact where
its window's values were observed (a value not observed reads as 0 whatever the constants).
"""
import numpy as np

from mpnode.engine import layouts


def _affine(old_mean, old_std, new_mean, new_std):
    """(a, c) of z_old = a z_new + c, float64."""
    old_std = np.asarray(old_std, dtype=np.float64)
    return np.asarray(new_std) / old_std, (np.asarray(new_mean) - np.asarray(old_mean)) / old_std


def _input_blocks(spec):
    """(name of the first-layer weights, its bias, [(rows of x), ...], [(rows of u), ...]) per kind."""
    dx, du = spec.state_dim, spec.control_dim
    if spec.kind == "l2s":
        return "W_lift", "b_lift", [slice(0, dx)], [slice(dx, dx + du)]
    n = spec.n_nodes if spec.kind == "node" else 1  # node: [x_1..x_N, u_1..u_N]
    return ("W1", "b1", [slice(i * dx, (i + 1) * dx) for i in range(n)],
            [slice(n * dx + i * du, n * dx + (i + 1) * du) for i in range(n)])


def _output_blocks(spec):
    """[(weights, bias or None, [columns of dx/dt, ...]), ...]: every array that writes dx/dt."""
    dx = spec.state_dim
    if spec.kind == "l2s":
        return [("W_out", "b_out", [slice(0, dx)])]
    n = spec.n_nodes if spec.kind == "node" else 1
    cols = [slice(i * dx, (i + 1) * dx) for i in range(n)]
    out = [("W3", "b3", cols)]
    if spec.linear_path:
        out.append(("W_agg", None, cols))
    if spec.encoder_window:
        out.append(("E2", "e2", [slice(0, dx)]))
    return out


def _encoder_rows(spec):
    """The encoder's first-layer rows that read observed values: dx of them per window slot."""
    width = 2 * spec.state_dim + 1
    return [slice(k * width, k * width + spec.state_dim) for k in range(spec.encoder_window)]


def renormalised(model, x_mean, x_std, u_mean=None, u_std=None):
    """A copy of ``model`` that works on (x - x_mean) / x_std (and the same for u when given)
    and rolls out exactly as ``model`` does (to rounding)."""
    out = model.copy()
    p = {k: v.astype(np.float64) for k, v in model.params.items()}
    win, bin_, x_rows, u_rows = _input_blocks(model.spec)
    ax, cx = _affine(model.x_mean, model.x_std, x_mean, x_std)
    blocks = [(x_rows, ax, cx)]
    if model.spec.control_dim and u_mean is not None:
        blocks.append((u_rows, *_affine(model.u_mean, model.u_std, u_mean, u_std)))
        out.u_mean, out.u_std = np.asarray(u_mean, np.float64).copy(), np.asarray(u_std, np.float64).copy()
    if model.spec.encoder_window:
        blocks.append((_encoder_rows(model.spec), ax, cx, "E1", "e1"))
    for rows_list, a, c, *arrays in blocks:
        w_in, b_in = arrays or (win, bin_)
        for rows in rows_list:
            p[b_in] = p[b_in] + c @ p[w_in][rows]
            p[w_in][rows] = p[w_in][rows] * a[:, None]
    for w, b, cols_list in _output_blocks(model.spec):
        for cols in cols_list:
            p[w][:, cols] = p[w][:, cols] / ax
            if b is not None:
                p[b][cols] = p[b][cols] / ax
    out.theta = layouts.join(p, layouts.param_shapes(model.spec), dtype=model.dtype)
    out.x_mean, out.x_std = np.asarray(x_mean, np.float64).copy(), np.asarray(x_std, np.float64).copy()
    return out
