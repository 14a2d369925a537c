"""A model exported by `mpnode export MODEL -o OUT.py`: its rollout in NumPy alone, weights inside.

    import OUT
    x = OUT.rollout(x0, steps, u=None, node_attrs=None, edge_weights=None)

x0 (B, N, dx) or (N, dx); u (B, T, N, du), the controls; returns the states (B, T+1, N, dx)
(or (T+1, N, dx)) in the data's units and the model's dtype, as mpnode's ``Model.rollout`` on
the graph it was exported for (to rounding: 1e-6 relative in mpnode's tests).  The model is
classic RK4 at ``dt / substeps``, the controls held over each dt, a node model's messages
starting at 0; ``MODEL`` holds its settings and arrays (docs/model-format.md names them).

A model trained with node attributes takes ``node_attrs`` (N, dp) for every trajectory, or
(B, N, dp), in the data's units and the order of ``MODEL["attr_names"]``, held over every step;
None: ``MODEL["node_attrs"]``, every node at the training mean of each attribute.  A model of
weighted graphs takes ``edge_weights`` (E,), one per edge in the data's units, in the graph's
CSR order (edge k of row i, indptr[i] <= k < indptr[i+1], is node i hearing node indices[k]:
``MODEL["indptr"]``, ``MODEL["indices"]``); None: ``MODEL["edge_weights"]``, the exported
graph's.  This file needs numpy and nothing else.
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


def controls(p, u, node_attrs, b, steps):
    """What the field hears beside the states, normalised, (T, B, N, du + dp): the controls u, then
    the node attributes held over every step (see the module docstring)."""
    n, dp = p["n_nodes"], p.get("attr_dim", 0)
    du = p["control_dim"] - dp
    if du and (u is None or np.shape(u) != (b, steps, n, du)):
        raise ValueError(f"u has shape {None if u is None else np.shape(u)}, expected {(b, steps, n, du)}")
    if node_attrs is not None and not dp:
        raise ValueError("node_attrs are given, but this model was trained without node attributes")
    parts = [np.asarray(u, dtype=np.float64)] if du else []
    if dp:
        a = p["node_attrs"] if node_attrs is None else np.asarray(node_attrs, dtype=np.float64)
        if a.shape not in ((n, dp), (b, n, dp)):
            raise ValueError(f"node_attrs has shape {a.shape}, expected {(n, dp)} or {(b, n, dp)}")
        parts.append(np.broadcast_to(np.broadcast_to(a, (b, n, dp))[:, None], (b, steps, n, dp)))
    if not parts:
        return np.zeros((steps, b, n, 0), np.dtype(p["dtype"]))
    held = np.moveaxis(np.concatenate(parts, axis=3), 1, 0)
    return ((held - p["u_mean"]) / p["u_std"]).astype(p["dtype"])


def weighted(p, edge_weights):
    """``p`` with its edges weighted by ``edge_weights`` (E,) in the data's units, over the model's
    weight_scale as the exported graph's are; ``p`` itself for None."""
    if edge_weights is None:
        return p
    if "weight_scale" not in p:
        raise ValueError("edge_weights are given, but this model was trained on unweighted graphs")
    w = np.asarray(edge_weights, dtype=np.float64)
    if w.shape != p["edge_weights"].shape or not np.all(np.isfinite(w)):
        raise ValueError(f"edge_weights has shape {w.shape}, expected {p['edge_weights'].shape}, finite numbers")
    return {**p, "edge_weight": np.ascontiguousarray(w / p["weight_scale"], dtype=p["dtype"])}


def run(p, x0, steps=None, u=None, node_attrs=None, edge_weights=None):
    """The rollout of model ``p`` (see the module docstring for the arguments)."""
    dtype = np.dtype(p["dtype"])
    x0 = np.asarray(x0)
    single = x0.ndim == 2
    if single:
        x0 = x0[None]
        u = None if u is None else np.asarray(u)[None]
    n, dx = p["n_nodes"], p["state_dim"]
    if x0.ndim != 3 or x0.shape[1:] != (n, dx):
        raise ValueError(f"x0 has shape {x0.shape}, expected (B, {n}, {dx}) on the exported graph")
    if steps is None:
        if u is None:
            raise ValueError("give steps (or controls u, whose length sets it)")
        steps = u.shape[1]
    b = x0.shape[0]
    un = controls(p, u, node_attrs, b, steps)
    z = np.concatenate([((x0 - p["x_mean"]) / p["x_std"]).astype(dtype), np.zeros((b, n, p["message_dim"]), dtype)],
                       axis=2)
    zs = path(weighted(p, edge_weights), z, un, np.full(steps, p["dt"] / p["substeps"], dtype),
              np.full(steps, p["substeps"]))
    x = (np.moveaxis(zs[..., :dx], 0, 1) * p["x_std"] + p["x_mean"]).astype(dtype)
    return x[0] if single else x
