"""`mpnode export MODEL -o OUT.onnx`: a rollout of T steps on one graph as an ONNX graph.

Inputs, in order: ``x0`` (B, N, dx); for a model with controls, ``u`` (B, T, N, du); for a
model with node attributes, ``node_attrs`` (1, N, dp) or (B, N, dp), held over every step; for
a model of weighted graphs, ``edge_weights`` (E,), in the graph's CSR order; all in the data's
units; output ``x`` (B, T+1, N, dx), as ``Model.rollout``; B is free, N and T are fixed at
export.  ``node_attrs`` and ``edge_weights`` have defaults, initializers of the same name that
a run may override (onnxruntime: feed them by name; ``get_overridable_initializers()`` lists
them, and loading the file logs a warning that they are graph inputs, which is what lets a run
override them): every node at the training mean of each attribute, the exported graph's
weights (`arrays.network_defaults`).  Computed in the model's
dtype (a float64 model exports float64; every operator used runs in double on onnxruntime's
CPU provider).  The time loop is one ONNX ``Loop`` over T whose body is one dt (its RK4
substeps unrolled), so the file's size does not grow with T.  The neighbour aggregation is a
dense MatMul with the graph's (N, N) weights (built once per run from ``edge_weights`` for a
model of weighted graphs): one GEMM per stage, fast for the graphs of a few hundred nodes a
controller runs on; its N^2 weights make it the wrong form beyond a few thousand nodes.

Needs the ``onnx`` extra (pip install 'mpnode[onnx]'): onnx writes and checks the graph,
onnxruntime runs it.  The graph is built op by op, so it is a second implementation of the
field and RK4; the tests hold it to the NumPy path's (mpnode.engine.numpy_path, which the
NumPy module export holds).
"""
import os

import numpy as np

from mpnode.base.atomic import atomic_path
from mpnode.base.errors import InputError

from .arrays import dense_aggregation, model_arrays

INSTALL_HINT = "the onnx extra installed: pip install 'mpnode[onnx]' (from a checkout: pip install '.[onnx]')"
OPSET = 17


def require_onnx(flag, path):
    """InputError unless onnx can be imported (cheap: call it before any work)."""
    try:
        import onnx  # noqa: F401
    except ImportError:
        raise InputError(flag, path, "needs onnx (the onnx extra), which is not installed", INSTALL_HINT) from None


class _Graph:
    """Nodes and constants of one ONNX graph under construction; each op returns its output name."""

    def __init__(self, prefix, dtype):
        self.prefix, self.dtype, self.nodes, self.constants = prefix, np.dtype(dtype), [], []

    def name(self):
        return f"{self.prefix}{len(self.nodes) + len(self.constants)}"

    def const(self, value, dtype=None):
        from onnx import numpy_helper

        out = self.name()
        self.constants.append(numpy_helper.from_array(np.asarray(value, dtype=dtype or self.dtype), out))
        return out

    def op(self, kind, *inputs, **attrs):
        from onnx import helper

        out = self.name()
        self.nodes.append(helper.make_node(kind, list(inputs), [out], **attrs))
        return out

    def linear(self, v, w, b):
        return self.op("Add", self.op("MatMul", v, self.const(w)), self.const(b))

    def columns(self, v, lo, hi):
        """v[..., lo:hi]."""
        return self.op("Slice", v, self.const([lo], np.int64), self.const([hi], np.int64),
                       self.const([-1], np.int64))


def _mlp(g, p, v):
    h1 = g.op("Tanh", g.linear(v, p["W1"], p["b1"]))
    h2 = g.op("Tanh", g.linear(h1, p["W2"], p["b2"]))
    return g.linear(h2, p["W3"], p["b3"])


def _field(g, p, z, u):
    """dz/dt of the model's kind: z (B, N, dz), u (B, N, du) or None -> (B, N, dz)."""
    k = _network_field(g, p, z, u)
    if "kinematics" not in p:
        return k
    kin = p["kinematics"]  # the fixed derivatives as products, as mpnode.engine.kinematics.derivatives_of
    x = g.columns(z, 0, p["state_dim"])
    q = g.op("Unsqueeze", g.linear(x, kin["Sq"], kin["mq"]), g.const([-1], np.int64))
    w = g.op("Unsqueeze", g.linear(x, kin["Sw"], kin["mw"]), g.const([-2], np.int64))
    outer = g.op("Reshape", g.op("Mul", q, w), g.const([0, 0, kin["T"].shape[0]], np.int64))
    fixed = g.op("Add", g.linear(x, kin["A"], kin["offset"]), g.op("MatMul", outer, g.const(kin["T"])))
    return g.op("Add", g.op("Mul", k, g.const(kin["keep"])), fixed)


def _network_field(g, p, z, u):
    """The network's dz/dt, every dimension learned."""
    dx, kind = p["state_dim"], p["kind"]
    if kind == "node":
        n, du = p["n_nodes"], p["control_dim"]
        flat = [g.op("Reshape", z, g.const([0, n * dx], np.int64))]
        if u is not None:
            flat.append(g.op("Reshape", u, g.const([0, n * du], np.int64)))
        v = g.op("Concat", *flat, axis=1)
        return g.op("Reshape", _mlp(g, p, v), g.const([0, n, dx], np.int64))
    xu = [z] if kind == "l2s" else [g.columns(z, 0, dx)]
    if u is not None:
        xu.append(u)
    if kind == "l2s":
        h0 = g.op("Tanh", g.linear(g.op("Concat", *xu, axis=2), p["W_lift"], p["b_lift"]))
        s = g.op("Tanh", g.linear(h0, p["W_msg"], p["b_msg"]))
        empty = p["empty_rows"][:, None] * p["psi"][None, :]  # psi on the rows that hear nobody
        a = g.op("Add", g.op("MatMul", _aggregation(g, p, "weight"), s), g.const(empty))
        t = g.op("Tanh", g.linear(a, p["W_upd"], p["b_upd"]))
        return g.linear(g.op("Add", g.op("Add", h0, h0), t), p["W_out"], p["b_out"])
    m = g.columns(z, dx, dx + p["message_dim"])
    heard = g.op("MatMul", _aggregation(g, p, "weight"), m)
    if p["zero_messages"]:
        heard = g.op("Mul", heard, g.const(0.0))
    k = _mlp(g, p, g.op("Concat", *xu, heard, axis=2))
    if "W_agg" in p:
        w = np.zeros((p["message_dim"], dx + p["message_dim"]))
        w[:, :p["W_agg"].shape[1]] = p["W_agg"]
        linear = heard if "linear_weight" not in p else g.op("MatMul", _aggregation(g, p, "linear_weight"), m)
        k = g.op("Add", k, g.op("MatMul", linear, g.const(w)))
    if p["zero_messages"]:
        k = g.op("Mul", k, g.const(np.r_[np.ones(dx), np.zeros(p["message_dim"])]))
    return k


def _aggregation(g, p, key):
    """The (N, N) aggregation matrix of the rule whose node factors are ``p[key]``: for a model of
    weighted graphs the outer graph's, built from the run's edge weights (`_weighted_aggregations`),
    else a constant."""
    return f"agg_{key}" if "weight_scale" in p else g.const(dense_aggregation(p, p[key]))


def _weighted_aggregations(g, p):
    """The aggregation matrices ``agg_weight`` (and ``agg_linear_weight``) of the input
    ``edge_weights`` (E,), once per run: each edge's weight over weight_scale added at (receiver,
    sender) (ScatterND: parallel edges add), 1 on the diagonal with self-messages, each row times
    the rule's node factor."""
    from onnx import helper, numpy_helper

    n = p["n_nodes"]
    zero = numpy_helper.from_array(np.zeros(1, dtype=g.dtype))
    a = g.op("ConstantOfShape", g.const([n * n], np.int64), value=zero)
    if len(p["indices"]):
        rows = np.repeat(np.arange(n), np.diff(p["indptr"]))
        w = g.op("Div", "edge_weights", g.const(p["weight_scale"]))
        a = g.op("ScatterND", a, g.const((rows * n + p["indices"])[:, None], np.int64), w, reduction="add")
    a = g.op("Reshape", a, g.const([n, n], np.int64))
    if p["self_messages"]:
        a = g.op("Add", a, g.const(np.eye(n)))
    for key in ("weight", "linear_weight"):
        if key in p:
            g.nodes.append(helper.make_node("Mul", [a, g.const(p[key][:, None])], [f"agg_{key}"]))


def _one_dt(g, p, z, u):
    """z after one dt: ``substeps`` classic RK4 steps, u held."""
    h = p["dt"] / p["substeps"]
    for _ in range(p["substeps"]):
        k1 = _field(g, p, z, u)
        k2 = _field(g, p, g.op("Add", z, g.op("Mul", k1, g.const(h / 2))), u)
        k3 = _field(g, p, g.op("Add", z, g.op("Mul", k2, g.const(h / 2))), u)
        k4 = _field(g, p, g.op("Add", z, g.op("Mul", k3, g.const(h))), u)
        two = g.const(2.0)
        total = g.op("Add", g.op("Add", k1, g.op("Mul", k2, two)), g.op("Add", g.op("Mul", k3, two), k4))
        z = g.op("Add", z, g.op("Mul", total, g.const(h / 6)))
    return z


def _loop_body(p, tensor_type):
    """The Loop's body: (i, cond, z) -> (cond, z after one dt, its x as the scan output)."""
    from onnx import TensorProto, helper

    g = _Graph("body_", p["dtype"])
    heard = []  # what the field hears beside the states, normalised, from the outer graph
    if p["control_dim"] - p.get("attr_dim", 0):  # u_n[:, i]: this step's controls
        heard.append(g.op("Gather", "u_n", "i", axis=1))
    if p.get("attr_dim"):  # the node attributes, held
        heard.append("a_n")
    u = None if not heard else heard[0] if len(heard) == 1 else g.op("Concat", *heard, axis=2)
    z = _one_dt(g, p, "z", u)
    g.nodes.append(helper.make_node("Identity", ["cond"], ["cond_out"]))
    g.nodes.append(helper.make_node("Identity", [z], ["z_out"]))
    x = g.columns(z, 0, p["state_dim"])
    g.nodes.append(helper.make_node("Identity", [x], ["x_out"]))
    dz = p["state_dim"] + p["message_dim"]
    n = p["n_nodes"]
    return helper.make_graph(
        g.nodes, "one_dt",
        [helper.make_tensor_value_info("i", TensorProto.INT64, []),
         helper.make_tensor_value_info("cond", TensorProto.BOOL, []),
         helper.make_tensor_value_info("z", tensor_type, ["B", n, dz])],
        [helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
         helper.make_tensor_value_info("z_out", tensor_type, ["B", n, dz]),
         helper.make_tensor_value_info("x_out", tensor_type, ["B", n, p["state_dim"]])],
        g.constants)


def onnx_rollout(model, graph, steps):
    """The ONNX ModelProto of ``model``'s rollout of ``steps`` steps on ``graph`` (checked)."""
    import onnx
    from onnx import helper

    p = model_arrays(model, graph)
    n, dx, dm = p["n_nodes"], p["state_dim"], p["message_dim"]
    tensor_type = helper.np_dtype_to_tensor_dtype(np.dtype(p["dtype"]))
    g = _Graph("c", p["dtype"])
    xn = g.op("Div", g.op("Sub", "x0", g.const(p["x_mean"])), g.const(p["x_std"]))
    if dm:  # messages start at 0: [x, 0 * x[..., :1] broadcast to dm columns]
        zeros = g.op("Mul", g.columns(xn, 0, 1), g.const(np.zeros(dm)))
        z0 = g.op("Concat", xn, zeros, axis=2)
    else:
        z0 = xn
    inputs = [helper.make_tensor_value_info("x0", tensor_type, ["B", n, dx])] + _heard_inputs(g, p, steps, tensor_type)
    trips, cond = g.const(steps, np.int64), g.const(True, np.bool_)
    g.nodes.append(helper.make_node("Loop", [trips, cond, z0], ["z_end", "x_path"], body=_loop_body(p, tensor_type)))
    path = g.op("Transpose", "x_path", perm=[1, 0, 2, 3])  # (T, B, N, dx) -> (B, T, N, dx)
    xn_all = g.op("Concat", g.op("Unsqueeze", xn, g.const([1], np.int64)), path, axis=1)
    g.nodes.append(helper.make_node("Add", [g.op("Mul", xn_all, g.const(p["x_std"])), g.const(p["x_mean"])], ["x"]))
    out = helper.make_tensor_value_info("x", tensor_type, ["B", steps + 1, n, dx])
    proto = helper.make_model(helper.make_graph(g.nodes, f"mpnode_{p['kind']}_rollout", inputs, [out], g.constants),
                              opset_imports=[helper.make_opsetid("", OPSET)], producer_name="mpnode")
    onnx.checker.check_model(proto, full_check=True)
    return proto


def _heard_inputs(g, p, steps, tensor_type):
    """The inputs beside x0, as the Loop's body reads them: the controls ``u`` (normalised: u_n),
    the node attributes ``node_attrs`` (normalised and broadcast to (B, N, dp): a_n) and the
    ``edge_weights`` (the aggregation matrices), the last two with their defaults."""
    from onnx import helper, numpy_helper

    n, dp = p["n_nodes"], p.get("attr_dim", 0)
    du = p["control_dim"] - dp
    inputs = []
    if du:
        inputs.append(helper.make_tensor_value_info("u", tensor_type, ["B", steps, n, du]))
        g.nodes.append(helper.make_node("Div", [g.op("Sub", "u", g.const(p["u_mean"][:du])),
                                                g.const(p["u_std"][:du])], ["u_n"]))
    if dp:
        inputs.append(helper.make_tensor_value_info("node_attrs", tensor_type, ["A", n, dp]))
        g.constants.append(numpy_helper.from_array(p["node_attrs"][None].astype(g.dtype), "node_attrs"))
        a = g.op("Div", g.op("Sub", "node_attrs", g.const(p["u_mean"][du:])), g.const(p["u_std"][du:]))
        shape = g.op("Concat", g.op("Shape", "x0", start=0, end=1), g.const([n, dp], np.int64), axis=0)
        g.nodes.append(helper.make_node("Expand", [a, shape], ["a_n"]))
    if "weight_scale" in p:
        inputs.append(helper.make_tensor_value_info("edge_weights", tensor_type, [len(p["indices"])]))
        g.constants.append(numpy_helper.from_array(p["edge_weights"].astype(g.dtype), "edge_weights"))
        _weighted_aggregations(g, p)
    return inputs


def write_onnx(model, graph, path, steps=1):
    """Write the rollout of ``steps`` steps on ``graph`` to ``path`` atomically."""
    proto = onnx_rollout(model, graph, steps)
    with atomic_path(os.fspath(path)) as tmp:
        with open(tmp, "wb") as f:
            f.write(proto.SerializeToString())
