"""A model exported by `mpnode export MODEL -o OUT.py`: its rollout in NumPy alone, weights inside.

    import OUT
    x = OUT.rollout(x0, steps, u=None)   # x0 (B, N, dx) or (N, dx); u (B, T, N, du)

returns the states (B, T+1, N, dx) (or (T+1, N, dx)) in the data's units and the model's
dtype, as mpnode's ``Model.rollout`` on the graph it was exported for (to rounding: 1e-6
relative in mpnode's tests).  The model is classic RK4 at ``dt / substeps``, the controls
held over each dt, a node model's messages starting at 0; ``MODEL`` holds its settings
and arrays (docs/model-format.md names them).  This file needs numpy and nothing else.
"""
import base64

import numpy as np

from mpnode.engine.numpy_path import path  # the exported file holds its source instead (numpy_module)


def decode(value):
    """An exported model's value: an array from its base64 bytes, a dict entry by entry, a scalar as it is."""
    if isinstance(value, dict) and "base64" in value:
        raw = base64.b64decode(value["base64"])
        return np.frombuffer(raw, dtype=np.dtype(value["dtype"])).reshape(value["shape"]).copy()
    if isinstance(value, dict):
        return {key: decode(v) for key, v in value.items()}
    return value


def run(p, x0, steps=None, u=None):
    """The rollout of model ``p`` (see the module docstring for the arguments)."""
    dtype = np.dtype(p["dtype"])
    x0 = np.asarray(x0)
    single = x0.ndim == 2
    if single:
        x0 = x0[None]
        u = None if u is None else np.asarray(u)[None]
    n, dx, du = p["n_nodes"], p["state_dim"], p["control_dim"]
    if x0.ndim != 3 or x0.shape[1:] != (n, dx):
        raise ValueError(f"x0 has shape {x0.shape}, expected (B, {n}, {dx}) on the exported graph")
    if steps is None:
        if u is None:
            raise ValueError("give steps (or controls u, whose length sets it)")
        steps = u.shape[1]
    b = x0.shape[0]
    if du and (u is None or np.shape(u) != (b, steps, n, du)):
        raise ValueError(f"u has shape {None if u is None else np.shape(u)}, expected {(b, steps, n, du)}")
    un = np.zeros((steps, b, n, 0), dtype) if not du else ((np.moveaxis(u, 1, 0) - p["u_mean"]) / p["u_std"])
    z = np.concatenate([((x0 - p["x_mean"]) / p["x_std"]).astype(dtype), np.zeros((b, n, p["message_dim"]), dtype)],
                       axis=2)
    zs = path(p, z, un.astype(dtype), np.full(steps, p["dt"] / p["substeps"], dtype), np.full(steps, p["substeps"]))
    x = (np.moveaxis(zs[..., :dx], 0, 1) * p["x_std"] + p["x_mean"]).astype(dtype)
    return x[0] if single else x
