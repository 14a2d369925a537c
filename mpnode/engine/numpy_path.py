"""The slow path: every model kind's rollout in plain NumPy (no numba, nothing to compile).

What it is for: running a model where numba cannot be installed or compiled (the engine
falls back to it, see `engine.resolve_backend`, or ``backend="numpy"`` asks for it), and
being the reference the compiled kernels are tested against.  So it is written from the
semantics of the model format (docs/model-format.md) alone, as plainly as possible: the
field of each kind as array expressions, the neighbour aggregation as sums over the CSR
rows, classic RK4 written out.  It shares nothing with ``mpnode.engine.kernels``.

Arithmetic is in theta's dtype (float64 is the reference; float32 agrees with the
kernels to float32 rounding: np.tanh is not the kernels' tanh).  Rollouts only: there
is no gradient here, so training needs numba.  Cost: a few dozen NumPy calls per field
evaluation, so small graphs pay NumPy's per-call overhead (benchmarks/bench_simulator.py).
"""
import numpy as np

from . import layouts
from .kinematics import derivatives_of
from .schedule import time_grid
from .spec import checked_controls, rule_weights


def mlp(p, V):
    """tanh(tanh(V W1 + b1) W2 + b2) W3 + b3 for every row of V; p: the named arrays (layouts.split)."""
    h1 = np.tanh(V @ p["W1"] + p["b1"])
    h2 = np.tanh(h1 @ p["W2"] + p["b2"])
    return h2 @ p["W3"] + p["b3"]


def aggregator(spec, graph, dtype, rule=None):
    """The neighbour aggregation on ``graph`` as a function src (M, w) -> (M, w).

    Row i gets weight_i * (the sum of src over the nodes i hears [plus i itself with
    self_messages]): weight 1/count (mean), 1 (sum) or 1/mean_degree (scaled), and 0
    for a node that hears nobody.  rule: another than the spec's (the linear path's own).
    """
    agg = spec.aggregation
    weight = rule_weights(graph, spec.self_messages, rule or agg.mlp, agg.mean_degree, dtype)[:, None]
    rows = np.flatnonzero(graph.degrees() > 0)
    starts = graph.indptr[:-1][rows]  # the rows that hear someone, each its own segment of indices
    indices = graph.indices

    def aggregate(src):
        out = src.copy() if spec.self_messages else np.zeros_like(src)
        if len(indices):
            out[rows] += np.add.reduceat(src[indices], starts, axis=0)
        return out * weight

    return aggregate


def empty_rows(spec, graph):
    """Boolean (M,): the nodes that hear nobody (L2S gives them psi as their aggregate)."""
    return (graph.degrees() == 0) & (not spec.self_messages)


def make_field(spec, theta, graph):
    """The model's time derivative as a function (z (M, dz), u (M, du)) -> dz/dt (M, dz)."""
    field = _network_field(spec, theta, graph)
    if spec.kinematics is None:
        return field
    dx = spec.state_dim
    fixed = spec.kinematics.matrices(dx, spec.state_width, theta.dtype)
    return lambda z, u: derivatives_of(fixed, z[:, :dx], field(z, u))


def _network_field(spec, theta, graph):
    """The network's time derivative, every dimension learned."""
    p = layouts.split(theta, layouts.param_shapes(spec))
    dx = spec.state_dim
    if spec.kind == "node":
        def node_field(x, u):  # per system of N nodes: [dx_1..dx_N]/dt = MLP([x_1..x_N, u_1..u_N])
            n_sys = x.shape[0] // spec.n_nodes
            return mlp(p, np.concatenate([x.reshape(n_sys, -1), u.reshape(n_sys, -1)], axis=1)).reshape(x.shape)

        return node_field
    aggregate = aggregator(spec, graph, theta.dtype)
    if spec.kind == "l2s":
        empty = empty_rows(spec, graph)

        def l2s_field(x, u):
            h0 = np.tanh(np.concatenate([x, u], axis=1) @ p["W_lift"] + p["b_lift"])
            a = aggregate(np.tanh(h0 @ p["W_msg"] + p["b_msg"]))
            a[empty] = p["psi"]
            h1 = h0 + np.tanh(a @ p["W_upd"] + p["b_upd"])
            return (h1 + h0) @ p["W_out"] + p["b_out"]

        return l2s_field
    own = spec.aggregation.own_linear  # the linear path's own rule, when not the MLP's
    linear = None if own is None else aggregator(spec, graph, theta.dtype, own)

    def mpnode_field(z, u):
        x, m = z[:, :dx], z[:, dx:]
        heard = np.zeros_like(m) if spec.zero_messages else aggregate(m)
        k = mlp(p, np.concatenate([x, u, heard], axis=1))
        if spec.linear_path:  # the path linear in the aggregate, around the MLP
            ncol = p["W_agg"].shape[1]  # dx + dm, or dx for linear_target "state"
            k[:, :ncol] += (heard if linear is None else linear(m)) @ p["W_agg"]
        if spec.zero_messages:
            k[:, dx:] = 0
        return k

    return mpnode_field


def integrate(spec, theta, z0, graph, u=None, n_steps=1, with_messages=False, intervals=None):
    """Classic RK4 from the full state z0 = [x, m] (M, dx+dm), u held over each output interval:
    ``substeps`` steps of dt/substeps per dt, or the steps of `mpnode.engine.schedule.time_grid`
    for the per-node ``intervals`` (n_steps, M).

    Returns (x (n_steps+1, M, dx), z (M, dx+dm) at the end), as `engine.integrate`;
    with_messages: (x, m (n_steps+1, M, dm), z), the messages after every step too.
    """
    theta = np.asarray(theta)
    dtype = theta.dtype
    z = np.array(z0, dtype=dtype)
    m, dx = z.shape[0], spec.state_dim
    u = _controls(spec, graph, u, n_steps, z, dtype)
    field = make_field(spec, theta, graph)
    nsub, hstep = time_grid(spec, n_steps, m, dtype, intervals)
    two = dtype.type(2)
    x = np.empty((n_steps + 1, m, dx), dtype=dtype)
    msgs = np.empty((n_steps + 1, m, z.shape[1] - dx), dtype=dtype)
    x[0], msgs[0] = z[:, :dx], z[:, dx:]
    for t in range(n_steps):
        h = hstep[t][:, None]
        half, sixth = h / dtype.type(2), h / dtype.type(6)
        for _ in range(nsub[t]):
            k1 = field(z, u[t])
            k2 = field(z + half * k1, u[t])
            k3 = field(z + half * k2, u[t])
            k4 = field(z + h * k3, u[t])
            z = z + sixth * (k1 + two * k2 + two * k3 + k4)
        x[t + 1], msgs[t + 1] = z[:, :dx], z[:, dx:]
    return (x, msgs, z) if with_messages else (x, z)


def rollout(spec, theta, x0, graph, u=None, n_steps=1, with_messages=False, intervals=None):
    """From x0 (M, dx), messages starting at 0: x (n_steps+1, M, dx), or (x, m) with the
    messages m (n_steps+1, M, dm) after every step (the compiled engine keeps only x)."""
    x0 = np.asarray(x0)
    z0 = np.zeros((x0.shape[0], spec.state_dim + spec.message_dim), dtype=np.asarray(theta).dtype)
    z0[:, :spec.state_dim] = x0
    out = integrate(spec, theta, z0, graph, u, n_steps, with_messages, intervals)
    return out[:2] if with_messages else out[0]


def _controls(spec, graph, u, n_steps, z, dtype):
    """u as (n_steps, M, du) after the compiled engine's checks, and whole systems for kind node."""
    m = z.shape[0]
    if z.shape != (m, spec.state_dim + spec.message_dim):
        raise ValueError(f"the full state has shape {z.shape}, expected (M, {spec.state_dim + spec.message_dim})")
    if spec.kind == "node" and m % spec.n_nodes:
        raise ValueError(f"{m} nodes are not whole systems of {spec.n_nodes} nodes (a node model's n_nodes)")
    return checked_controls(spec, graph, u, n_steps, m, dtype)
