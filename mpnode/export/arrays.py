"""A model on one graph as plain settings and arrays: what both export formats are written from."""
import numpy as np

from mpnode.engine.numpy_path import field_arrays


def model_arrays(model, graph):
    """{name: value}: the field as the NumPy path reads it (`mpnode.engine.numpy_path.field_arrays`:
    settings, named parameters, the kinematics' products, the graph's rows and weights) and what a
    rollout from the data's units adds: control_dim, dt, substeps, the dtype's name and the
    normalisation."""
    model.check_nodes(graph.n_nodes)
    spec = model.spec
    p = field_arrays(spec, model.theta, graph)
    p.update(control_dim=spec.control_dim, dt=float(spec.dt), substeps=spec.substeps, dtype=np.dtype(model.dtype).name,
             x_mean=model.x_mean, x_std=model.x_std, u_mean=model.u_mean, u_std=model.u_std)
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
