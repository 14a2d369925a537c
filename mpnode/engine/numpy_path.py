"""The slow path: every model kind's rollout in plain NumPy (no numba, nothing to compile).

What it is for: running a model where numba cannot be installed or compiled (the engine
falls back to it, see `engine.resolve_backend`, or ``backend="numpy"`` asks for it), and
being the reference the compiled kernels are tested against.  So it is written from the
semantics of the model format (docs/model-format.md) alone, as plainly as possible: the
field of each kind as array expressions, the neighbour aggregation as sums over the CSR
rows, classic RK4 written out.  It shares nothing with ``mpnode.engine.kernels``.

It is also the model of ``mpnode export -o OUT.py``: the functions in `NUMPY_ONLY` read a
model as plain settings and arrays (`field_arrays`) and use numpy alone, so the exported
module holds their source (mpnode.export.numpy_module) and a change to the field or the
step is made here once.  They take states with any leading axes before the node axis
(-2): (M, dz) here, (B, N, dz) in the exported module.

Arithmetic is in theta's dtype (float64 is the reference; float32 agrees with the
kernels to float32 rounding: np.tanh is not the kernels' tanh).  Rollouts only: there
is no gradient here, so training needs numba.  Cost: a few dozen NumPy calls per field
evaluation, so small graphs pay NumPy's per-call overhead (benchmarks/bench_simulator.py).
"""
import numpy as np

from . import layouts
from .kinematics import derivatives_of
from .plan import edge_array
from .schedule import time_grid
from .spec import checked_controls, rule_weights


def mlp(p, v):
    """tanh(tanh(v W1 + b1) W2 + b2) W3 + b3 over the last axis of v; p: the named arrays."""
    h1 = np.tanh(v @ p["W1"] + p["b1"])
    h2 = np.tanh(h1 @ p["W2"] + p["b2"])
    return h2 @ p["W3"] + p["b3"]


def aggregate(p, src, weight):
    """Node i of src (..., N, w): weight[i] * (the sum of w_ij src_j over the nodes j i hears
    [and i itself with self_messages]); a node that hears nobody has weight 0; w_ij the edge's
    ``edge_weight`` (1 when the graph has none)."""
    out = src.copy() if p["self_messages"] else np.zeros_like(src)
    rows = p["heard_rows"]
    heard = src[..., p["indices"], :]
    if "edge_weight" in p:
        heard = heard * p["edge_weight"][:, None]
    if len(rows):  # each row that hears someone is its own segment of the CSR indices
        out[..., rows, :] += np.add.reduceat(heard, p["indptr"][rows], axis=-2)
    return out * weight[:, None]


def field(p, z, u):
    """dz/dt (..., N, dz) of the model's kind at the full states z, controls u (..., N, du)."""
    k = network_field(p, z, u)
    if "kinematics" not in p:
        return k
    return derivatives_of(p["kinematics"], z[..., :p["state_dim"]], k)


def network_field(p, z, u):
    """The network's dz/dt, every dimension learned."""
    if p["kind"] == "node":
        return node_field(p, z, u)
    if p["kind"] == "l2s":
        return l2s_field(p, z, u)
    return mpnode_field(p, z, u)


def node_field(p, x, u):
    """Per system of n_nodes consecutive nodes: [dx_1..dx_N]/dt = MLP([x_1..x_N, u_1..u_N])."""
    systems = x.shape[:-2] + (x.shape[-2] // p["n_nodes"], -1)
    return mlp(p, np.concatenate([x.reshape(systems), u.reshape(systems)], axis=-1)).reshape(x.shape)


def l2s_field(p, x, u):
    """Encoder, one round of neighbour messages, decoder."""
    h0, a = l2s_heard(p, x, u)
    h1 = h0 + np.tanh(a @ p["W_upd"] + p["b_upd"])
    return (h1 + h0) @ p["W_out"] + p["b_out"]


def l2s_heard(p, x, u):
    """(h0, a): each node's encoded [x, u] and the aggregate of its neighbours' messages (psi for
    a node that hears nobody), the input the decoder's update layer takes."""
    h0 = np.tanh(np.concatenate([x, u], axis=-1) @ p["W_lift"] + p["b_lift"])
    a = aggregate(p, np.tanh(h0 @ p["W_msg"] + p["b_msg"]), p["weight"])
    a[..., p["empty_rows"], :] = p["psi"]
    return h0, a


def mpnode_field(p, z, u):
    """The MLP of [x, u, the aggregate of the messages heard], and the path linear in that aggregate."""
    dx = p["state_dim"]
    x, m = z[..., :dx], z[..., dx:]
    heard = np.zeros_like(m) if p["zero_messages"] else aggregate(p, m, p["weight"])
    k = mlp(p, np.concatenate([x, u, heard], axis=-1))
    if "W_agg" in p:  # onto dx + dm columns, or dx for linear_target "state"
        linear = heard if "linear_weight" not in p else aggregate(p, m, p["linear_weight"])
        k[..., :p["W_agg"].shape[1]] += linear @ p["W_agg"]
    if p["zero_messages"]:
        k[..., dx:] = 0
    return k


def rk4(p, z, u, h, substeps):
    """z after ``substeps`` classic RK4 steps of h (a scalar, or per node (..., N, 1)), u held."""
    h = np.asarray(h, z.dtype)
    two = z.dtype.type(2)
    half, sixth = h / two, h / z.dtype.type(6)
    for _ in range(substeps):
        k1 = field(p, z, u)
        k2 = field(p, z + half * k1, u)
        k3 = field(p, z + half * k2, u)
        k4 = field(p, z + h * k3, u)
        z = z + sixth * (k1 + two * k2 + two * k3 + k4)
    return z


def path(p, z, u, h, substeps):
    """The full states (T+1, ..., N, dz) from z under u (T, ..., N, du): interval t holds u[t]
    over substeps[t] RK4 steps of h[t]."""
    zs = [z]
    for t in range(len(u)):
        zs.append(rk4(p, zs[-1], u[t], h[t], substeps[t]))
    return np.stack(zs)


#: the model in numpy alone: the exported NumPy module holds these functions' source, so they
#: may use nothing but numpy and each other (tests/test_export.py checks)
NUMPY_ONLY = (mlp, aggregate, derivatives_of, field, network_field, node_field, l2s_field, l2s_heard,
              mpnode_field, rk4, path)


def field_arrays(spec, theta, graph):
    """The model on ``graph`` as the `NUMPY_ONLY` functions read it: the spec's settings, the
    field's named parameters (an initial-state encoder's left out: the field never reads them),
    the kinematics' products (``kinematics``: `Kinematics.matrices`) and, for the kinds that
    hear neighbours, the graph's rows (`_graph_arrays`) with each node's aggregation weight
    (``weight``; ``linear_weight`` when the linear path has its own rule)."""
    shapes = layouts.field_shapes(spec)
    p = {k: v for k, v in layouts.split(theta, layouts.param_shapes(spec)).items() if k in shapes}
    p.update(kind=spec.kind, state_dim=spec.state_dim, message_dim=spec.message_dim,
             n_nodes=int(spec.n_nodes if spec.kind == "node" else graph.n_nodes),
             zero_messages=bool(spec.zero_messages))
    if spec.kinematics is not None:
        p["kinematics"] = spec.kinematics.matrices(spec.state_dim, spec.state_width, theta.dtype)
    if spec.kind != "node":
        agg = spec.aggregation
        p.update(_graph_arrays(spec, graph, theta.dtype), weight=_weights(spec, graph, theta.dtype, agg.mlp))
        if agg.own_linear is not None:
            p["linear_weight"] = _weights(spec, graph, theta.dtype, agg.own_linear)
    return p


def _graph_arrays(spec, graph, dtype):
    """The CSR rows, the nodes that hear someone (``heard_rows``) and nobody (``empty_rows``),
    and the edges' weights (``edge_weight``) when the graph has them."""
    out = dict(self_messages=bool(spec.self_messages), indptr=graph.indptr, indices=graph.indices,
               heard_rows=np.flatnonzero(graph.degrees() > 0), empty_rows=empty_rows(spec, graph))
    w = edge_array(graph, dtype, spec.aggregation.weight_scale)
    if w.size:
        out["edge_weight"] = w
    return out


def _weights(spec, graph, dtype, rule):
    """Each node's factor on its sum under ``rule`` (mean, sum or scaled)."""
    return rule_weights(graph, spec.self_messages, rule, spec.aggregation.mean_degree, dtype)


def aggregator(spec, graph, dtype, rule=None):
    """The neighbour aggregation on ``graph`` as a function src (M, w) -> (M, w) (`aggregate`):
    weight 1/count (mean), 1 (sum) or 1/mean_degree (scaled).  rule: another than the spec's
    (the linear path's own)."""
    p = _graph_arrays(spec, graph, dtype)
    weight = _weights(spec, graph, dtype, rule or spec.aggregation.mlp)
    return lambda src: aggregate(p, src, weight)


def empty_rows(spec, graph):
    """Boolean (M,): the nodes that hear nobody (L2S gives them psi as their aggregate)."""
    return (graph.degrees() == 0) & (not spec.self_messages)


def make_field(spec, theta, graph):
    """The model's time derivative as a function (z (M, dz), u (M, du)) -> dz/dt (M, dz)."""
    p = field_arrays(spec, np.asarray(theta), graph)
    return lambda z, u: field(p, z, u)


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
    u = _controls(spec, graph, u, n_steps, z, dtype)
    nsub, hstep = time_grid(spec, n_steps, z.shape[0], dtype, intervals)
    zs = path(field_arrays(spec, theta, graph), z, u, hstep[:, :, None], nsub)
    x = np.ascontiguousarray(zs[..., :spec.state_dim])
    if with_messages:
        return x, np.ascontiguousarray(zs[..., spec.state_dim:]), zs[-1].copy()
    return x, zs[-1].copy()


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
