"""A model on one graph as plain settings and arrays: what both export formats are written from."""
import numpy as np

from mpnode.engine.numpy_path import field_arrays


def model_arrays(model, graph):
    """{name: value}: the field as the NumPy path reads it (`mpnode.engine.numpy_path.field_arrays`:
    settings, named parameters, the kinematics' products, the graph's rows and weights) and what a
    rollout from the data's units adds: control_dim, dt, substeps, the dtype's name, the
    normalisation and the inputs a network model takes besides states and controls
    (`network_defaults`)."""
    model.check_nodes(graph.n_nodes)
    spec = model.spec
    p = field_arrays(spec, model.theta, graph)
    p.update(control_dim=spec.control_dim, dt=float(spec.dt), substeps=spec.substeps, dtype=np.dtype(model.dtype).name,
             x_mean=model.x_mean, x_std=model.x_std, u_mean=model.u_mean, u_std=model.u_std)
    p.update(network_defaults(model, graph, p["n_nodes"]))
    return p


def network_defaults(model, graph, n_nodes):
    """The node attributes and edge weights an exported rollout takes as inputs, with the values
    it uses when none are given: ``attr_dim``, ``attr_names`` and ``node_attrs`` (N, dp), every node at the
    training mean of each attribute (the mean its normalisation took, `Model.u_mean`), for a model
    with attributes; ``weight_scale`` and ``edge_weights`` (E,), the graph's own weights in the
    data's units (1 on every edge of an unweighted graph, as `Model.rollout` takes it), for a
    model of weighted graphs that hears neighbours.  A user's own are divided by weight_scale as
    the graph's are (``edge_weight``)."""
    spec, out = model.spec, {}
    if spec.attr_dim:
        mean = np.asarray(model.u_mean, dtype=np.float64)[-spec.attr_dim:]
        out.update(attr_dim=spec.attr_dim, attr_names=model.attr_names, node_attrs=np.tile(mean, (n_nodes, 1)))
    if spec.aggregation.weight_scale is not None and spec.kind != "node":
        w = graph.weights if graph.weighted else np.ones(graph.n_edges)
        out.update(weight_scale=float(spec.aggregation.weight_scale), edge_weights=np.asarray(w, dtype=np.float64))
    return out


def dense_aggregation(p, weight):
    """The (N, N) matrix A with A @ src = the aggregation of src (row i: weight_i times each edge's
    weight, 1 on an unweighted graph, on each node i hears, and 1 on itself with self-messages), in
    the model's dtype."""
    n = p["n_nodes"]
    rows = np.repeat(np.arange(n), np.diff(p["indptr"]))
    a = np.zeros((n, n))
    np.add.at(a, (rows, p["indices"]), p["edge_weight"].astype(np.float64) if "edge_weight" in p else 1.0)
    if p["self_messages"]:
        a[np.diag_indices(n)] += 1.0
    return (a * weight[:, None]).astype(p["dtype"])
