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


def decode(spec):
    """The model of an exported file: scalars as they are, arrays from their base64 bytes."""
    out = {}
    for key, value in spec.items():
        if isinstance(value, dict) and "base64" in value:
            raw = base64.b64decode(value["base64"])
            value = np.frombuffer(raw, dtype=np.dtype(value["dtype"])).reshape(value["shape"]).copy()
        out[key] = value
    return out


def mlp(p, v):
    """tanh(tanh(v W1 + b1) W2 + b2) W3 + b3 over the last axis of v."""
    h1 = np.tanh(v @ p["W1"] + p["b1"])
    h2 = np.tanh(h1 @ p["W2"] + p["b2"])
    return h2 @ p["W3"] + p["b3"]


def aggregate(p, src, weight):
    """Row i: weight[i] * (the sum of src over the nodes i hears [and i itself]); src (B, N, w)."""
    out = src.copy() if p["self_messages"] else np.zeros_like(src)
    rows = p["heard_rows"]
    if len(rows):
        out[:, rows] += np.add.reduceat(src[:, p["indices"]], p["indptr"][rows], axis=1)
    return out * weight[:, None]


def field(p, z, u):
    """dz/dt (B, N, dz) of the model's kind at the full state z, controls u (B, N, du)."""
    k = network_field(p, z, u)
    if "kin_keep" not in p:
        return k
    x = z[..., :p["state_dim"]]  # the derivatives the kinematics fix (a position's is its velocity)
    outer = (x @ p["kin_Sq"] + p["kin_mq"])[..., :, None] * (x @ p["kin_Sw"] + p["kin_mw"])[..., None, :]
    return k * p["kin_keep"] + x @ p["kin_A"] + p["kin_offset"] + outer.reshape(*x.shape[:-1], -1) @ p["kin_T"]


def network_field(p, z, u):
    """The network's dz/dt, every dimension learned."""
    dx, kind = p["state_dim"], p["kind"]
    if kind == "node":
        b = z.shape[0]
        return mlp(p, np.concatenate([z.reshape(b, -1), u.reshape(b, -1)], axis=1)).reshape(z.shape)
    if kind == "l2s":
        h0 = np.tanh(np.concatenate([z, u], axis=2) @ p["W_lift"] + p["b_lift"])
        a = aggregate(p, np.tanh(h0 @ p["W_msg"] + p["b_msg"]), p["weight"])
        a[:, p["empty_rows"]] = p["psi"]
        h1 = h0 + np.tanh(a @ p["W_upd"] + p["b_upd"])
        return (h1 + h0) @ p["W_out"] + p["b_out"]
    x, m = z[..., :dx], z[..., dx:]
    heard = np.zeros_like(m) if p["zero_messages"] else aggregate(p, m, p["weight"])
    k = mlp(p, np.concatenate([x, u, heard], axis=2))
    if "W_agg" in p:  # the path linear in the aggregate, around the MLP
        linear = heard if "linear_weight" not in p else aggregate(p, m, p["linear_weight"])
        k[..., :p["W_agg"].shape[1]] += linear @ p["W_agg"]
    if p["zero_messages"]:
        k[..., dx:] = 0
    return k


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
    un = np.zeros((b, steps, n, 0), dtype) if not du else ((u - p["u_mean"]) / p["u_std"]).astype(dtype)
    z = np.concatenate([((x0 - p["x_mean"]) / p["x_std"]).astype(dtype), np.zeros((b, n, p["message_dim"]), dtype)],
                       axis=2)
    h = dtype.type(p["dt"] / p["substeps"])
    half, sixth, two = h / dtype.type(2), h / dtype.type(6), dtype.type(2)
    xs = [z[..., :dx]]
    for t in range(steps):
        for _ in range(p["substeps"]):
            k1 = field(p, z, un[:, t])
            k2 = field(p, z + half * k1, un[:, t])
            k3 = field(p, z + half * k2, un[:, t])
            k4 = field(p, z + h * k3, un[:, t])
            z = z + sixth * (k1 + two * k2 + two * k3 + k4)
        xs.append(z[..., :dx])
    x = (np.stack(xs, axis=1) * p["x_std"] + p["x_mean"]).astype(dtype)
    return x[0] if single else x
