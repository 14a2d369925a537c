"""Test helpers for the engine: a pure-NumPy MP-NODE reference and test graphs.

The reference is written from the semantics in ../shared/spec/model-format.md and
../shared/design.md only (no mpnode.kernels, no mpnode.mlp): a dense aggregation
matrix built with plain loops from the CSR rows, np.tanh, and classic RK4 written out.
"""
import numpy as np

from mpnode.graph import Graph


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


def aggregation_matrix(graph, self_messages):
    """A (M, M) with (A m)_k = mean of m_j over row k [plus k itself]; zero row if empty."""
    M = graph.n_nodes
    A = np.zeros((M, M))
    for k in range(M):
        row = [int(j) for j in graph.indices[graph.indptr[k]:graph.indptr[k + 1]]]
        if self_messages:
            row.append(k)
        for j in row:
            A[k, j] += 1.0 / len(row)
    return A


def field_ref(spec, theta, z, u, A):
    """[dx/dt, dm/dt] for all nodes; z (M, dx+dm), u (M, du)."""
    dx = spec.state_dim
    x, m = z[:, :dx], z[:, dx:]
    mp = np.zeros_like(m) if spec.zero_messages else A @ m
    out = mlp_ref(theta, np.concatenate([x, u, mp], axis=1), z.shape[1])
    if spec.zero_messages:
        out[:, dx:] = 0.0
    return out


def rollout_ref(spec, theta, x0, graph, u, n_steps, with_messages=False):
    """Classic RK4 at h = dt/substeps, u held over each dt; returns x (n_steps+1, M, dx).

    with_messages: return (x, m) with the messages m (n_steps+1, M, dm) too (the engine keeps
    only x; benchmarks/paper plots m from here).
    """
    theta = np.asarray(theta, dtype=np.float64)
    M, dx = x0.shape
    if u is None:
        u = np.zeros((n_steps, M, 0))
    A = aggregation_matrix(graph, spec.self_messages)
    z = np.concatenate([x0, np.zeros((M, spec.message_dim))], axis=1).astype(np.float64)
    h = spec.dt / spec.substeps
    out = np.empty((n_steps + 1, M, dx))
    msgs = np.zeros((n_steps + 1, M, spec.message_dim))
    out[0] = x0
    for t in range(n_steps):
        F = lambda zz: field_ref(spec, theta, zz, u[t], A)  # noqa: E731
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
    """Glorot-like weights and non-zero biases (zero biases would hide bias bugs)."""
    din = spec.state_dim + spec.control_dim + spec.message_dim
    dout = spec.state_dim + spec.message_dim
    H = spec.hidden
    parts = []
    for shape in [(din, H), (H,), (H, H), (H,), (H, dout), (dout,)]:
        fan = shape[0] + (shape[1] if len(shape) > 1 else 0)
        parts.append(rng.uniform(-1, 1, size=shape).ravel() * scale * np.sqrt(6.0 / fan))
    return np.concatenate(parts).astype(dtype)
