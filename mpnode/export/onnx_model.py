"""`mpnode export MODEL -o OUT.onnx`: a rollout of T steps on one graph as an ONNX graph.

Inputs, in order: ``x0`` (B, N, dx) and, for a model with controls, ``u`` (B, T, N, du), in
the data's units; output ``x`` (B, T+1, N, dx), as ``Model.rollout``; B is free, N and T are
fixed at export.  Computed in the model's dtype (a float64 model exports float64; every
operator used runs in double on onnxruntime's CPU provider).  The time loop is one ONNX
``Loop`` over T whose body is one dt (its RK4 substeps unrolled), so the file's size does
not grow with T.  The neighbour aggregation is a dense MatMul with the graph's (N, N)
weights: one GEMM per stage, fast for the graphs of a few hundred nodes a controller
runs on; its N^2 weights make it the wrong form beyond a few thousand nodes.

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
        a = g.op("Add", g.op("MatMul", g.const(dense_aggregation(p, p["weight"])), s), g.const(empty))
        t = g.op("Tanh", g.linear(a, p["W_upd"], p["b_upd"]))
        return g.linear(g.op("Add", g.op("Add", h0, h0), t), p["W_out"], p["b_out"])
    m = g.columns(z, dx, dx + p["message_dim"])
    heard = g.op("MatMul", g.const(dense_aggregation(p, p["weight"])), m)
    if p["zero_messages"]:
        heard = g.op("Mul", heard, g.const(0.0))
    k = _mlp(g, p, g.op("Concat", *xu, heard, axis=2))
    if "W_agg" in p:
        w = np.zeros((p["message_dim"], dx + p["message_dim"]))
        w[:, :p["W_agg"].shape[1]] = p["W_agg"]
        linear = heard if "linear_weight" not in p else g.op(
            "MatMul", g.const(dense_aggregation(p, p["linear_weight"])), m)
        k = g.op("Add", k, g.op("MatMul", linear, g.const(w)))
    if p["zero_messages"]:
        k = g.op("Mul", k, g.const(np.r_[np.ones(dx), np.zeros(p["message_dim"])]))
    return k


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
    u = None
    if p["control_dim"]:  # u_n[:, i]: this step's normalised controls, from the outer graph
        u = g.op("Gather", "u_n", "i", axis=1)
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
    n, dx, du, dm = p["n_nodes"], p["state_dim"], p["control_dim"], p["message_dim"]
    tensor_type = helper.np_dtype_to_tensor_dtype(np.dtype(p["dtype"]))
    g = _Graph("c", p["dtype"])
    xn = g.op("Div", g.op("Sub", "x0", g.const(p["x_mean"])), g.const(p["x_std"]))
    if dm:  # messages start at 0: [x, 0 * x[..., :1] broadcast to dm columns]
        zeros = g.op("Mul", g.columns(xn, 0, 1), g.const(np.zeros(dm)))
        z0 = g.op("Concat", xn, zeros, axis=2)
    else:
        z0 = xn
    inputs = [helper.make_tensor_value_info("x0", tensor_type, ["B", n, dx])]
    if du:
        inputs.append(helper.make_tensor_value_info("u", tensor_type, ["B", steps, n, du]))
        g.nodes.append(helper.make_node("Div", [g.op("Sub", "u", g.const(p["u_mean"])), g.const(p["u_std"])],
                                        ["u_n"]))
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


def write_onnx(model, graph, path, steps=1):
    """Write the rollout of ``steps`` steps on ``graph`` to ``path`` atomically."""
    proto = onnx_rollout(model, graph, steps)
    with atomic_path(os.fspath(path)) as tmp:
        with open(tmp, "wb") as f:
            f.write(proto.SerializeToString())
