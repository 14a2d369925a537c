"""A model on one graph as plain settings and arrays: what both export formats are written from."""
import numpy as np

from mpnode.engine.layouts import field_shapes
from mpnode.engine.spec import rule_weights


def model_arrays(model, graph):
    """{name: value}: the spec's settings, the normalisation, the field's named parameters
    (model dtype; an initial-state encoder's are left out: an export steps from a given state),
    the kinematics' products (``kin_*``: mpnode.engine.kinematics.Kinematics.matrices) and, for
    the kinds that hear neighbours, the graph's CSR rows with each node's aggregation weight
    (``weight``; ``linear_weight`` when the linear path has its own rule), the rows that hear
    someone and the empty rows (L2S gives them psi)."""
    spec, dtype = model.spec, model.dtype
    n = spec.n_nodes if spec.kind == "node" else graph.n_nodes
    model.check_nodes(graph.n_nodes)
    p = {"kind": spec.kind, "state_dim": spec.state_dim, "control_dim": spec.control_dim,
         "message_dim": spec.message_dim, "n_nodes": int(n), "dt": float(spec.dt), "substeps": spec.substeps,
         "self_messages": bool(spec.self_messages), "zero_messages": bool(spec.zero_messages),
         "dtype": np.dtype(dtype).name, "x_mean": model.x_mean, "x_std": model.x_std, "u_mean": model.u_mean,
         "u_std": model.u_std}
    p.update({k: np.array(v) for k, v in model.params.items() if k in field_shapes(spec)})
    if spec.kinematics is not None:  # the fixed derivatives, as products (Kinematics.matrices)
        fixed = spec.kinematics.matrices(spec.state_dim, spec.state_width, dtype)
        p.update({"kin_" + k: v for k, v in fixed.items()})
    if spec.kind != "node":
        agg = spec.aggregation
        deg = graph.degrees()
        p["weight"] = rule_weights(graph, spec.self_messages, agg.mlp, agg.mean_degree, dtype)
        if agg.own_linear is not None:
            p["linear_weight"] = rule_weights(graph, spec.self_messages, agg.own_linear, agg.mean_degree, dtype)
        p.update(indptr=graph.indptr.copy(), indices=graph.indices.copy(), heard_rows=np.flatnonzero(deg > 0),
                 empty_rows=(deg == 0) & (not spec.self_messages))
    return p


def dense_aggregation(p, weight):
    """The (N, N) matrix A with A @ src = the aggregation of src (row i: weight_i on each node i
    hears, and on itself with self-messages), in the model's dtype."""
    n = p["n_nodes"]
    rows = np.repeat(np.arange(n), np.diff(p["indptr"]))
    a = np.zeros((n, n))
    np.add.at(a, (rows, p["indices"]), 1.0)
    if p["self_messages"]:
        a[np.diag_indices(n)] += 1.0
    return (a * weight[:, None]).astype(p["dtype"])
