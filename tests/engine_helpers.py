"""Test helpers for the engine: a pure-NumPy reference of every model kind, and test graphs.

The reference is written from the semantics of the model format (docs/model-format.md)
only (no mpnode.kernels, no mpnode.layouts): a dense aggregation matrix built with plain
loops from the CSR rows, np.tanh, and classic RK4 written out.
"""
import numpy as np

from mpnode.engine import FieldSpec
from mpnode.graph import Graph, block_diagonal


# ---------------------------------------------------------------------------
# Graphs
# ---------------------------------------------------------------------------
def make_graph(rng, n, n_chords=None):
    """A random graph on n >= 5 nodes with every awkward case in it.

    Nodes 0..n-3 form an undirected path plus random undirected chords (so tile
    boundaries get crossed when n > 128); node n-2 hears node 0 but node 0 does not
    hear it, and node 1 hears n-2 but n-2 does not hear 1 (directed edges); node n-1
    is isolated (empty row, hears and is heard by nobody).
    """
    core = n - 2
    pairs = []
    for i in range(core - 1):
        pairs += [(i, i + 1), (i + 1, i)]
    n_chords = core // 2 if n_chords is None else n_chords
    for _ in range(n_chords):
        a, b = rng.integers(0, core, size=2)
        if a != b:
            pairs += [(a, b), (b, a)]
    pairs += [(n - 2, 0), (1, n - 2)]  # (receiver, sender): directed
    return Graph.from_edges(n, pairs, directed=True)


def permute_graph(graph, perm):
    """Relabel node i as perm[i]: edge (r, s) becomes (perm[r], perm[s])."""
    e = graph.edges()
    return Graph.from_edges(graph.n_nodes, perm[e], directed=True)


# ---------------------------------------------------------------------------
# The MP-NODE reference
# ---------------------------------------------------------------------------
def unpack(theta, din, H, dout):
    """W1 (din,H) b1 (H) W2 (H,H) b2 (H) W3 (H,dout) b3 (dout), row-major, in that order."""
    sizes = [("W1", (din, H)), ("b1", (H,)), ("W2", (H, H)), ("b2", (H,)), ("W3", (H, dout)), ("b3", (dout,))]
    out, o = {}, 0
    for name, shape in sizes:
        k = int(np.prod(shape))
        out[name] = theta[o:o + k].reshape(shape)
        o += k
    assert o == theta.size, (o, theta.size)
    return out


def mlp_ref(theta, V, dout):
    """W3^T tanh(W2^T tanh(W1^T v + b1) + b2) + b3 for every row v of V (n, din)."""
    n, din = V.shape
    H = _hidden(theta.size, din, dout)
    p = unpack(theta, din, H, dout)
    h1 = np.tanh(V @ p["W1"] + p["b1"])
    h2 = np.tanh(h1 @ p["W2"] + p["b2"])
    return h2 @ p["W3"] + p["b3"]


def _hidden(P, din, dout):
    # P = din H + H + H^2 + H + H dout + dout  ->  H^2 + (din + dout + 2) H + dout - P = 0
    b = din + dout + 2
    H = int(round((-b + np.sqrt(b * b - 4 * (dout - P))) / 2))
    assert H * H + b * H + dout == P
    return H


def aggregation_matrix(graph, self_messages, aggregation="mean", mean_degree=None):
    """A (M, M) with (A m)_k = the aggregation of m_j over row k [plus k itself]; zero row if empty.

    mean: 1/|row| each; sum: 1 each; scaled: 1/mean_degree each.
    """
    M = graph.n_nodes
    A = np.zeros((M, M))
    for k in range(M):
        row = [int(j) for j in graph.indices[graph.indptr[k]:graph.indptr[k + 1]]]
        if self_messages:
            row.append(k)
        for j in row:
            A[k, j] += {"mean": 1.0 / len(row), "sum": 1.0, "scaled": 1.0 / (mean_degree or 1.0)}[aggregation]
    return A


def empty_rows(graph, self_messages):
    """Boolean (M,): nodes that hear nobody."""
    return (np.diff(graph.indptr) == 0) & (not self_messages)


def field_ref(spec, theta, z, u, graph):
    """The model's time derivative for all nodes: [dx/dt, dm/dt] (MP-NODE) or dx/dt; z (M, dz), u (M, du)."""
    kind = spec.kind
    if kind == "l2s":
        return l2s_field_ref(spec, theta, z, u, graph)
    if kind == "node":
        return node_field_ref(spec, theta, z, u)
    A = aggregation_matrix(graph, spec.self_messages, spec.aggregation, spec.mean_degree)
    dx = spec.state_dim
    x, m = z[:, :dx], z[:, dx:]
    mp = np.zeros_like(m) if spec.zero_messages else A @ m
    out = mlp_ref(theta, np.concatenate([x, u, mp], axis=1), z.shape[1])
    if spec.zero_messages:
        out[:, dx:] = 0.0
    return out


L2S_SHAPES = ("W_lift", "b_lift", "W_msg", "b_msg", "psi", "W_upd", "b_upd", "W_out", "b_out")


def l2s_params(theta, dxu, H, dx):
    sizes = [(dxu, H), (H,), (H, H), (H,), (H,), (H, H), (H,), (H, dx), (dx,)]
    out, o = {}, 0
    for name, shape in zip(L2S_SHAPES, sizes):
        k = int(np.prod(shape))
        out[name] = theta[o:o + k].reshape(shape)
        o += k
    assert o == theta.size, (o, theta.size)
    return out


def l2s_field_ref(spec, theta, x, u, graph):
    """L2S: h0 = tanh([x,u] W_lift + b), s = tanh(h0 W_msg + b), a = agg(s) (psi if the row is empty),
    h1 = h0 + tanh(a W_upd + b), dx/dt = (h1 + h0) W_out + b_out."""
    dx, H = spec.state_dim, spec.hidden
    p = l2s_params(np.asarray(theta, dtype=np.float64), dx + spec.control_dim, H, dx)
    h0 = np.tanh(np.concatenate([x, u], axis=1) @ p["W_lift"] + p["b_lift"])
    s = np.tanh(h0 @ p["W_msg"] + p["b_msg"])
    a = aggregation_matrix(graph, spec.self_messages, spec.aggregation, spec.mean_degree) @ s
    a[empty_rows(graph, spec.self_messages)] = p["psi"]
    h1 = h0 + np.tanh(a @ p["W_upd"] + p["b_upd"])
    return (h1 + h0) @ p["W_out"] + p["b_out"]


def node_field_ref(spec, theta, x, u):
    """A plain NODE: per system of N nodes, [dx_1..dx_N]/dt = MLP([x_1..x_N, u_1..u_N])."""
    N, dx, du = spec.n_nodes, spec.state_dim, spec.control_dim
    B = x.shape[0] // N
    V = np.concatenate([x.reshape(B, N * dx), u.reshape(B, N * du)], axis=1)
    return mlp_ref(theta, V, N * dx).reshape(B * N, dx)


def rollout_ref(spec, theta, x0, graph, u, n_steps, with_messages=False):
    """Classic RK4 at h = dt/substeps, u held over each dt; returns x (n_steps+1, M, dx).

    with_messages: return (x, m) with the messages m (n_steps+1, M, dm) too (the engine keeps
    only x; benchmarks/paper plots m from here).
    """
    theta = np.asarray(theta, dtype=np.float64)
    M, dx = x0.shape
    if u is None:
        u = np.zeros((n_steps, M, 0))
    z = np.concatenate([x0, np.zeros((M, spec.message_dim))], axis=1).astype(np.float64)
    h = spec.dt / spec.substeps
    out = np.empty((n_steps + 1, M, dx))
    msgs = np.zeros((n_steps + 1, M, spec.message_dim))
    out[0] = x0
    for t in range(n_steps):
        F = lambda zz: field_ref(spec, theta, zz, u[t], graph)  # noqa: E731
        for _ in range(spec.substeps):
            k1 = F(z)
            k2 = F(z + h / 2 * k1)
            k3 = F(z + h / 2 * k2)
            k4 = F(z + h * k3)
            z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out[t + 1] = z[:, :dx]
        msgs[t + 1] = z[:, dx:]
    return (out, msgs) if with_messages else out


def loss_ref(pred, target, kind, n_nodes):
    """Huber(delta=1) or squared error of pred - target at steps 1..T, summed, / n_nodes."""
    e = pred[1:] - target[1:]
    if kind == "huber":
        a = np.abs(e)
        v = np.where(a <= 1, 0.5 * e * e, a - 0.5)
    else:
        v = e * e
    return v.sum() / n_nodes


def random_theta(rng, spec, scale=1.0, dtype=np.float64):
    """Glorot-like weights and non-zero biases and psi (zeros would hide bugs)."""
    kind = spec.kind
    dx, du, H = spec.state_dim, spec.control_dim, spec.hidden
    if kind == "l2s":
        shapes = [(dx + du, H), (H,), (H, H), (H,), (H,), (H, H), (H,), (H, dx), (dx,)]
    else:
        n = spec.n_nodes if kind == "node" else 1
        din, dout = n * (dx + du) + spec.message_dim, n * dx + spec.message_dim
        shapes = [(din, H), (H,), (H, H), (H,), (H, dout), (dout,)]
    parts = []
    for shape in shapes:
        fan = shape[0] + (shape[1] if len(shape) > 1 else 0)
        parts.append(rng.uniform(-1, 1, size=shape).ravel() * scale * np.sqrt(6.0 / fan))
    return np.concatenate(parts).astype(dtype)


# ---------------------------------------------------------------------------
# Test problems
# ---------------------------------------------------------------------------
def spec_(**kw):
    base = dict(state_dim=2, control_dim=2, message_dim=3, hidden=8, dt=0.1, substeps=3)
    base.update(kw)
    return FieldSpec(**base)


def mixed_graph(seed=0, big=150):
    """A batch: three copies of one 9-node graph, then one ``big``-node graph (nodes 27..).

    Each graph has an isolated node and directed edges (engine_helpers.make_graph).  The
    copies make a dense block, the big graph a CSR block that crosses TILE = 128 inside
    the block; as one graph it spans two tiles, so the stagewise driver meets edges
    across tiles.
    """
    rng = np.random.default_rng(seed)
    g9 = make_graph(rng, 9)
    return block_diagonal([g9, g9, g9, make_graph(rng, big)])


def problem(spec, graph, T, seed=1, dtype=np.float64):
    rng = np.random.default_rng(seed)
    M = graph.n_nodes
    theta = random_theta(rng, spec, dtype=dtype)
    x0 = rng.standard_normal((M, spec.state_dim))
    u = rng.standard_normal((T, M, spec.control_dim)) if spec.control_dim else None
    return theta, x0, u


def rel(a, b):
    return np.linalg.norm(np.ravel(a) - np.ravel(b)) / max(np.linalg.norm(np.ravel(b)), 1e-300)
