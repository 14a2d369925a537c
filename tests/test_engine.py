"""The engine (mpnode.engine.kernels via mpnode.engine): layers, rollouts and exact gradients.

Everything correctness-related runs in float64 against the pure-NumPy reference in
engine_helpers.py or against central finite differences.  Both drivers are covered:
``blocks`` (closed pieces of the graph, one thread per block) and ``stagewise`` (one
big graph, a parallel loop over tiles per RK stage).  The ``driver`` fixture forces the
stagewise driver on small graphs by making engine.plan_for say "one big graph",
and spies on the kernel entry points so a test fails if the intended driver did not run.
The block driver itself has two ways to aggregate messages: CSR rows, and one dense GEMM
for a block made of copies of one small graph; the test graphs contain both kinds of
block (checked by test_test_graphs_cover_dense_and_csr_blocks).
"""
import dataclasses

import numba
import numpy as np
import pytest
from engine_helpers import (
    DRIVERS_AND_DTYPES,
    DRIVERS_IN_FLOAT32,
    loss_ref,
    make_graph,
    mixed_graph,
    params,
    permute_graph,
    problem,
    random_theta,
    rel,
    rollout_ref,
    spec_,
)

from mpnode import engine
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import FieldSpec, kernels
from mpnode.engine import numpy_path as numpy_engine
from mpnode.engine import plan as engine_plan
from mpnode.engine.kernels import feature_major, mpnode_field
from mpnode.training import losses

# ---------------------------------------------------------------------------
# 1. Layer VJPs against central finite differences
# ---------------------------------------------------------------------------
EPS_LAYER = 1e-6


def fd_grad(f, arrays, eps=EPS_LAYER):
    """Central-difference gradient of scalar f() with respect to every entry of each array."""
    out = []
    for a in arrays:
        g = np.zeros_like(a)
        flat, gflat = a.reshape(-1), g.reshape(-1)
        for i in range(flat.size):
            old = flat[i]
            flat[i] = old + eps
            fp = f()
            flat[i] = old - eps
            fm = f()
            flat[i] = old
            gflat[i] = (fp - fm) / (2 * eps)
        out.append(g)
    return out


def test_dense_tanh_vjp_matches_finite_differences():
    rng = np.random.default_rng(0)
    n, a, c = 5, 4, 3
    X, W, b = rng.standard_normal((n, a)), rng.standard_normal((a, c)) * 0.5, rng.standard_normal(c) * 0.5
    GY = rng.standard_normal((n, c))

    def f():
        Y = np.empty((n, c))
        kernels.dense_tanh_forward(X, W, b, Y)
        return np.sum(GY * Y)

    Y = np.empty((n, c))
    kernels.dense_tanh_forward(X, W, b, Y)
    np.testing.assert_allclose(Y, np.tanh(X @ W + b), rtol=1e-13, atol=1e-14)
    # backward *adds* into gW, gb: start them non-zero
    gW0, gb0 = rng.standard_normal((a, c)), rng.standard_normal(c)
    gW, gb = gW0.copy(), gb0.copy()
    GX = kernels.dense_tanh_backward(X, W, Y, GY.copy(), gW, gb)
    fX, fW, fb = fd_grad(f, [X, W, b])
    assert rel(GX, fX) < 1e-6
    assert rel(gW - gW0, fW) < 1e-6
    assert rel(gb - gb0, fb) < 1e-6


def test_dense_vjp_matches_finite_differences():
    rng = np.random.default_rng(1)
    n, a, c = 5, 4, 3
    X, W, b = rng.standard_normal((n, a)), rng.standard_normal((a, c)), rng.standard_normal(c)
    GY = rng.standard_normal((n, c))

    def f():
        return np.sum(GY * kernels.dense_forward(X, W, b))

    np.testing.assert_allclose(kernels.dense_forward(X, W, b), X @ W + b, rtol=1e-13, atol=1e-14)
    gW0, gb0 = rng.standard_normal((a, c)), rng.standard_normal(c)
    gW, gb = gW0.copy(), gb0.copy()
    GX = kernels.dense_backward(X, W, GY.copy(), gW, gb)
    fX, fW, fb = fd_grad(f, [X, W, b])
    assert rel(GX, fX) < 1e-6
    assert rel(gW - gW0, fW) < 1e-6
    assert rel(gb - gb0, fb) < 1e-6


def test_mlp_vjp_matches_finite_differences():
    """The MLP on a feature-major tile (columns are nodes): values and every cotangent."""
    rng = np.random.default_rng(2)
    n, din, H, dout = 6, 5, 7, 4
    spec = FieldSpec(state_dim=2, control_dim=1, message_dim=2, hidden=H, dt=0.1)  # din = 2+1+2 = 5, dout = 2+2 = 4
    theta = random_theta(rng, spec, scale=1.5)
    VT = rng.standard_normal((din, n))
    GKT = rng.standard_normal((dout, n))

    def f():
        H1T, H2T = np.empty((H, n)), np.empty((H, n))
        return np.sum(GKT * mpnode_field.mlp_forward(theta, VT, H1T, H2T, dout))

    H1T, H2T = np.empty((H, n)), np.empty((H, n))
    KT = mpnode_field.mlp_forward(theta, VT, H1T, H2T, dout)
    p = params(spec, theta)
    np.testing.assert_allclose(KT.T, numpy_engine.mlp(p, VT.T), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(H1T.T, np.tanh(VT.T @ p["W1"] + p["b1"]), rtol=1e-13, atol=1e-14)
    gtheta0 = rng.standard_normal(theta.size)
    gtheta = gtheta0.copy()
    GVT = mpnode_field.mlp_backward(theta, VT, H1T, H2T, GKT.copy(), gtheta)
    fV, ftheta = fd_grad(f, [VT, theta])
    assert rel(GVT, fV) < 1e-6
    g = gtheta - gtheta0
    # every parameter block on its own (W1 b1 W2 b2 W3 b3), not only the whole vector
    for name, blk in params(spec, g).items():
        assert rel(blk, params(spec, ftheta)[name]) < 1e-6, name


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_feature_major_tiles_start_on_a_vector_boundary(dtype):
    """Tile arrays start on 64 bytes (a 512-bit vector), whatever numba's allocator gives."""
    like = np.zeros(1, dtype)
    for shape in [(3, 5), (32, 128), (2, 7, 6)]:
        a = feature_major.aligned_empty(shape, like)
        assert a.shape == shape and a.dtype == dtype and a.flags.c_contiguous
        assert a.ctypes.data % feature_major.ALIGN == 0


@pytest.mark.parametrize("a", [1, 5, 6, 13, 32, 37, 64, 70])
def test_feature_major_product_every_width(a):
    """The product's chunks (8, 4, 2, 1) cover any input width, with or without a bias,
    with the weights given transposed (as the backward pass does)."""
    rng = np.random.default_rng(a)
    n, c = 19, 11
    W, b, XT = rng.standard_normal((a, c)), rng.standard_normal(c), rng.standard_normal((a, n))
    YT = np.empty((c, n))
    feature_major.product(W, b, XT, YT)
    np.testing.assert_allclose(YT, W.T @ XT + b[:, None], rtol=1e-12, atol=1e-12)
    WT = rng.standard_normal((c, a))
    feature_major.product(WT.T, b[:0], XT, YT)
    np.testing.assert_allclose(YT, WT @ XT, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-12), (np.float32, 1e-5)])
@pytest.mark.parametrize("n", [0, 1, 19])
@pytest.mark.parametrize("a, c", [(1, 1), (2, 4), (5, 3), (13, 32), (32, 26), (33, 7)])
def test_feature_major_param_cotangent_every_width(a, c, n, dtype, tol):
    """The parameter cotangents (inputs in pairs, outputs in fours, then the odd ones left)
    add XT GYT^T and the rows' sums into what the buffers hold, for every remainder."""
    rng = np.random.default_rng(a * 100 + c)
    XT, GYT = rng.standard_normal((a, n)).astype(dtype), rng.standard_normal((c, n)).astype(dtype)
    gW, gb = rng.standard_normal((a, c)).astype(dtype), rng.standard_normal(c).astype(dtype)
    product = XT.astype(np.float64) @ GYT.T.astype(np.float64)
    want_W, want_b = gW + product, gb + GYT.sum(axis=1, dtype=np.float64)
    feature_major.param_cotangent(XT, GYT, gW, gb)
    np.testing.assert_allclose(gW, want_W, rtol=tol, atol=tol)
    np.testing.assert_allclose(gb, want_b, rtol=tol, atol=tol)
    feature_major.param_cotangent(XT, GYT, gW, gb[:0])  # no bias: only gW changes
    np.testing.assert_allclose(gW, want_W + product, rtol=tol, atol=tol)


@pytest.mark.parametrize("width", [1, 2, 3, 4, 5, 7, 8, 13])
@pytest.mark.parametrize("self_msg", [False, True])
@pytest.mark.parametrize("edge_weighted", [False, True])
def test_neighbour_sums_every_width(width, self_msg, edge_weighted):
    """The CSR walk (a compiled copy per narrow width, chunks of four beyond; plain or with edge
    weights) and its transpose against dense sums, on rows ``zoff`` into the arrays, with empty
    rows and an output offset."""
    rng = np.random.default_rng(width)
    m, zoff, i0, i1, col0, ocol0 = 23, 4, 6, 20, 2, 1
    A = (rng.random((m, m)) < 0.25) * 1.0
    A[i0 + 1] = 0  # a row with no neighbours
    np.fill_diagonal(A, 0)
    g = Graph.from_edges(m, np.argwhere(A), directed=True)  # node i hears j where A[i, j]
    ew = np.empty(0)
    if edge_weighted:
        A[A > 0] = rng.uniform(-2, 2, int(A.sum()))
        ew = A[A != 0]  # row-major: the CSR order
    indptr, indices = g.indptr, g.indices + zoff
    heard = A + np.eye(m) * self_msg
    src = rng.standard_normal((m, col0 + width + 1))
    weight = rng.random(m + zoff)
    out = np.full((i1 - i0, ocol0 + width), np.nan)
    kernels.layers.aggregate_tile(src, col0, width, np.empty((0, 0)), np.concatenate([np.zeros(zoff, np.int64), indptr]),
                                  indices, ew, weight, self_msg, i0 + zoff, i1 + zoff, zoff, out, ocol0)
    want = weight[i0 + zoff:i1 + zoff, None] * (heard @ src[:, col0:col0 + width])[i0:i1]
    np.testing.assert_allclose(out[:, ocol0:], want, rtol=1e-13, atol=1e-13)
    gcot = rng.standard_normal((m, width))
    t = Graph.from_edges(m, np.argwhere(A)[:, ::-1], directed=True)  # for sender j, who hears it
    tew = A.T[A.T != 0] if edge_weighted else ew
    tout = np.full((m, ocol0 + width), np.nan)
    kernels.layers.transpose_tile(gcot, np.concatenate([np.zeros(zoff, np.int64), t.indptr]), t.indices + zoff,
                                  tew, self_msg, i0 + zoff, i1 + zoff, zoff, tout, ocol0)
    np.testing.assert_allclose(tout[i0:i1, ocol0:], (heard.T @ gcot)[i0:i1], rtol=1e-13, atol=1e-13)


# ---------------------------------------------------------------------------
# 2. Rollouts against the NumPy reference
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("self_messages", [False, True])
@pytest.mark.parametrize("zero_messages", [False, True])
def test_rollout_matches_reference(driver, self_messages, zero_messages):
    spec = spec_(self_messages=self_messages, zero_messages=zero_messages)
    graph = mixed_graph()
    T = 3
    theta, x0, u = problem(spec, graph, T)
    got = engine.forward(spec, theta, x0, graph, u, T)
    want = rollout_ref(spec, theta, x0, graph, u, T)
    assert got.shape == (T + 1, graph.n_nodes, spec.state_dim) and got.dtype == np.float64
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    # the trajectory must actually move, or the comparison would prove little
    assert np.abs(got[-1] - got[0]).max() > 1e-2


@pytest.mark.parametrize("spec", [spec_(control_dim=0, message_dim=0, substeps=2),
                                  spec_(state_dim=1, control_dim=0, message_dim=1, substeps=1, self_messages=True)],
                         ids=["no-controls-no-messages", "dx1-dm1"])
def test_rollout_matches_reference_small_dims(driver, spec):
    for graph in (mixed_graph(3), Graph.from_edges(6, [])):  # the second has no edges at all
        theta, x0, u = problem(spec, graph, 3)
        np.testing.assert_allclose(engine.forward(spec, theta, x0, graph, u, 3),
                                   rollout_ref(spec, theta, x0, graph, u, 3), rtol=1e-12, atol=1e-12)
        x = targets_off_the_kink(rollout_ref(spec, theta, x0, graph, u, 3), np.random.default_rng(2))
        loss, gtheta, gx0 = losses.value_and_grad(spec, theta, x, graph, u)
        assert abs(loss - loss_ref(rollout_ref(spec, theta, x0, graph, u, 3), x, "huber", graph.n_nodes)) < 1e-12 * loss
        assert np.all(np.isfinite(gtheta)) and np.all(np.isfinite(gx0))


def test_reference_aggregation_semantics():
    """The reference itself: mean over the row, 0 for an empty row, +self with self_messages;
    sum and scaled (applied to the identity, the aggregation shows its matrix)."""
    g = Graph.from_edges(4, [(0, 1), (0, 2), (2, 1)], directed=True)  # 0 hears 1,2; 2 hears 1; 1, 3 hear nobody

    def matrix(**kw):
        return numpy_engine.aggregator(spec_(**kw), g, np.float64)(np.eye(4))

    np.testing.assert_array_equal(matrix(), [[0, .5, .5, 0], [0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_allclose(matrix(self_messages=True),
                               [[1 / 3, 1 / 3, 1 / 3, 0], [0, 1, 0, 0], [0, .5, .5, 0], [0, 0, 0, 1]])
    np.testing.assert_array_equal(matrix(aggregation="sum"), [[0, 1, 1, 0], [0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_array_equal(matrix(aggregation="scaled", mean_degree=4.0),
                                  [[0, .25, .25, 0], [0, 0, 0, 0], [0, .25, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_array_equal(numpy_engine.empty_rows(spec_(), g), [False, True, False, True])


def test_one_big_graph_runs_stagewise_and_matches_reference(driver_calls):
    """No forcing: a connected graph of STAGEWISE_MIN_NODES_PER_THREAD nodes per thread or more
    goes to the stagewise driver."""
    n = engine_plan.STAGEWISE_MIN_NODES_PER_THREAD * numba.get_num_threads() + 40
    graph = make_graph(np.random.default_rng(5), n)
    spec = spec_(self_messages=True, substeps=2)
    theta, x0, u = problem(spec, graph, 2)
    got = engine.forward(spec, theta, x0, graph, u, 2)
    assert driver_calls == ["rollout_stagewise"]
    np.testing.assert_allclose(got, rollout_ref(spec, theta, x0, graph, u, 2), rtol=1e-12, atol=1e-12)


def test_test_graphs_cover_dense_and_csr_blocks():
    """Coverage guard: the block driver sees both a dense block and a CSR block in mixed_graph.

    If the planner changes, this fails rather than letting the other tests silently stop
    covering one of the two aggregation paths.
    """
    for big in (230, 220):
        plan = engine_plan.plan_for(mixed_graph(big=big), spec_(), np.float64)
        assert plan.blocks is not None
        assert np.any(plan.dense_n > 0) and np.any(plan.dense_n == 0), (plan.blocks, plan.dense_n)


@pytest.mark.parametrize("self_messages", [False, True])
def test_graph_with_self_loops_matches_reference(driver, self_messages):
    """A graph that lists a node in its own row (self_loops=True, allowed in trajectory files).

    Spec: m'_k is the mean over row k, plus k itself when self_messages -- so with both, k's
    own message counts twice.  The dense block path (a batch of copies of the graph) and the
    CSR path (the graph alone) must both agree with that, forward and backward.
    """
    pairs = [(0, 1), (1, 0), (1, 2), (2, 1), (1, 1), (3, 0)]  # node 1 hears itself; 3 hears 0; 4 isolated
    g = Graph.from_edges(5, pairs, directed=True, self_loops=True)
    copies = 4
    batch = block_diagonal([g] * copies)
    spec = spec_(self_messages=self_messages)
    T = 3
    theta, x0, u = problem(spec, batch, T, seed=31)
    want = rollout_ref(spec, theta, x0, batch, u, T)
    np.testing.assert_allclose(engine.forward(spec, theta, x0, batch, u, T), want, rtol=1e-12, atol=1e-12)
    x = targets_off_the_kink(want, np.random.default_rng(32))
    loss, gtheta, gx0 = losses.value_and_grad(spec, theta, x, batch, u)
    assert abs(loss - loss_ref(want, x, "huber", batch.n_nodes)) < 1e-12 * loss
    gsum = np.zeros_like(gtheta)
    for c in range(copies):
        s = slice(5 * c, 5 * c + 5)
        np.testing.assert_allclose(engine.forward(spec, theta, x0[s], g, u[:, s], T), want[:, s],
                                   rtol=1e-12, atol=1e-12)
        _, gi, gx0i = losses.value_and_grad(spec, theta, x[:, s], g, u[:, s], n_nodes=batch.n_nodes)
        np.testing.assert_allclose(gx0i, gx0[s], rtol=1e-10, atol=1e-12 * np.abs(gx0).max())
        gsum += gi
    np.testing.assert_allclose(gsum, gtheta, rtol=1e-10, atol=1e-12 * np.abs(gtheta).max())


# ---------------------------------------------------------------------------
# 3. The whole-rollout gradient against central finite differences
# ---------------------------------------------------------------------------
def targets_off_the_kink(pred, rng):
    """Targets pred[t] + e with |e| in [0.05, 0.7] or [1.3, 2.5]: both Huber branches are used
    and every residual stays >= 0.3 away from the kink at |e| = 1, far beyond what an FD step
    (<= 1e-4 in norm) can move it, so the loss is smooth along every FD segment."""
    shape = pred[1:].shape
    mag = np.where(rng.random(shape) < 0.5, rng.uniform(0.05, 0.7, shape), rng.uniform(1.3, 2.5, shape))
    x = pred.copy()
    x[1:] += mag * rng.choice([-1.0, 1.0], shape)
    return x


@pytest.mark.parametrize("kind,self_messages,zero_messages", [("huber", False, False), ("mse", False, False),
                                                              ("huber", True, False), ("mse", False, True)],
                         ids=["huber", "mse", "huber-self", "mse-zero"])
def test_gradient_matches_finite_differences(driver, kind, self_messages, zero_messages):
    spec = spec_(self_messages=self_messages, zero_messages=zero_messages)
    rng = np.random.default_rng(7)
    graph = mixed_graph(7, big=220)
    T = 3
    theta, x0, u = problem(spec, graph, T, seed=8)
    x = targets_off_the_kink(rollout_ref(spec, theta, x0, graph, u, T), rng)
    loss, gtheta, gx0 = losses.value_and_grad(spec, theta, x, graph, u, kind)
    assert gtheta.shape == theta.shape and gx0.shape == x0.shape
    # the loss value itself against the reference
    assert abs(loss - loss_ref(rollout_ref(spec, theta, x0, graph, u, T), x, kind, graph.n_nodes)) < 1e-12 * loss

    def L(th, x0_):
        xx = x.copy()
        xx[0] = x0_
        return losses.value_and_grad(spec, th, xx, graph, u, kind)[0]

    # Random directions of unit norm, step 1e-4 (about 1e-5 per coordinate): the truncation
    # error (~step^2) and the rounding noise (~1e-16 * loss / step) are both <= ~1e-8 relative.
    eps = 1e-4
    for _ in range(2):
        d = rng.standard_normal(theta.size)
        d /= np.linalg.norm(d)
        fd = (L(theta + eps * d, x0) - L(theta - eps * d, x0)) / (2 * eps)
        assert abs(fd - gtheta @ d) < 1e-6 * abs(fd), (fd, gtheta @ d)
        d = rng.standard_normal(x0.shape)
        d /= np.linalg.norm(d)
        fd = (L(theta, x0 + eps * d) - L(theta, x0 - eps * d)) / (2 * eps)
        assert abs(fd - np.sum(gx0 * d)) < 1e-6 * abs(fd), (fd, np.sum(gx0 * d))
    # A few single coordinates: the largest entries of theta's gradient (one per parameter
    # block where it is not identically zero), and initial states of the awkward nodes:
    # isolated nodes, nodes with a directed edge (in a dense and in the CSR block), nodes
    # next to the tile boundaries (global: 127|128, inside the big graph's block: 27+127|27+128).
    eps = 1e-5
    offsets = np.cumsum([0] + [b.size for b in params(spec, gtheta).values()])
    for lo, hi in zip(offsets[:-1], offsets[1:]):
        if not np.any(gtheta[lo:hi]):
            continue
        i = lo + int(np.argmax(np.abs(gtheta[lo:hi])))
        e = np.zeros_like(theta)
        e[i] = eps
        fd = (L(theta + e, x0) - L(theta - e, x0)) / (2 * eps)
        assert abs(fd - gtheta[i]) < 1e-6 * abs(fd), (i, fd, gtheta[i])
    big0 = 36  # the big graph's first node (mixed_graph); a tile boundary lies TILE nodes further
    for node, d in [(8, 0), (17, 1), (9 + 7, 1), (0, 0), (big0 - 1, 1), (big0, 0),
                    (big0 + kernels.TILE - 1, 0), (big0 + kernels.TILE, 1), (big0 + 210, 0), (big0 + 219, 1)]:
        e = np.zeros_like(x0)
        e[node, d] = eps
        fd = (L(theta, x0 + e) - L(theta, x0 - e)) / (2 * eps)
        assert abs(fd - gx0[node, d]) < 1e-6 * max(abs(fd), 1e-3 * np.abs(gx0).max()), (node, d, fd, gx0[node, d])


# ---------------------------------------------------------------------------
# 4. RK4 is fourth order
# ---------------------------------------------------------------------------
def test_rk4_global_error_is_fourth_order():
    """Halving h (via substeps) must shrink the global error ~16x.

    The exact solution is the kernel's own at 256 substeps (its error, ~(1/32)^4 of the
    coarsest, is negligible).  A 3/8-rule slip or a wrong stage weight gives order <= 3
    (ratio <= 8) or no convergence at all.
    """
    spec = spec_(control_dim=2, dt=0.5, substeps=1, self_messages=True)
    graph = make_graph(np.random.default_rng(11), 9)
    T = 4
    theta, x0, u = problem(spec, graph, T, seed=12)
    exact = engine.forward(dataclasses.replace(spec, substeps=256), theta, x0, graph, u, T)
    np.testing.assert_allclose(exact, rollout_ref(dataclasses.replace(spec, substeps=256), theta, x0, graph, u, T),
                               rtol=1e-11, atol=1e-11)
    errs = [np.abs(engine.forward(dataclasses.replace(spec, substeps=s), theta, x0, graph, u, T) - exact).max()
            for s in (2, 4, 8)]
    assert errs[-1] > 1e-11, errs  # well above rounding, so the ratios measure truncation
    for coarse, fine in zip(errs[:-1], errs[1:]):
        assert 12 <= coarse / fine <= 20, errs


# ---------------------------------------------------------------------------
# 5. Relabelling nodes permutes the output and nothing else
# ---------------------------------------------------------------------------
def test_relabelling_nodes_permutes_rollout_and_gradient(driver):
    spec = spec_(self_messages=True)
    graph = mixed_graph(4)
    M, T = graph.n_nodes, 3
    theta, x0, u = problem(spec, graph, T, seed=13)
    perm = np.random.default_rng(14).permutation(M)  # old node i becomes node perm[i]
    pgraph = permute_graph(graph, perm)
    px0 = np.empty_like(x0)
    px0[perm] = x0
    pu = np.empty_like(u)
    pu[:, perm] = u
    out = engine.forward(spec, theta, x0, graph, u, T)
    pout = engine.forward(spec, theta, px0, pgraph, pu, T)
    np.testing.assert_allclose(pout[:, perm], out, rtol=1e-12, atol=1e-12)

    x = out + 0.3
    px = np.empty_like(x)
    px[:, perm] = x
    loss, gtheta, gx0 = losses.value_and_grad(spec, theta, x, graph, u)
    ploss, pgtheta, pgx0 = losses.value_and_grad(spec, theta, px, pgraph, pu)
    assert abs(ploss - loss) <= 1e-12 * loss
    np.testing.assert_allclose(pgtheta, gtheta, rtol=1e-12, atol=1e-12 * np.abs(gtheta).max())
    np.testing.assert_allclose(pgx0[perm], gx0, rtol=1e-12, atol=1e-12 * np.abs(gx0).max())


def shuffled_grid(side, seed):
    """A side x side 4-neighbour grid whose nodes are numbered at random (as a user's file may),
    or row by row for seed None."""
    n = side * side
    ids = (np.arange(n) if seed is None else np.random.default_rng(seed).permutation(n)).reshape(side, side)
    pairs = np.concatenate([np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], 1),
                            np.stack([ids[:-1].ravel(), ids[1:].ravel()], 1)])
    return Graph.from_edges(side * side, pairs)


def test_locality_order_is_invisible_to_users():
    """The stagewise driver renumbering nodes inside (RCM) changes neither the rollout nor
    the gradients, which come back in the user's node order."""
    spec = spec_(self_messages=True)
    graph = shuffled_grid(23, seed=3)
    M, T = graph.n_nodes, 3
    theta, x0, u = problem(spec, graph, T, seed=21)
    plan = engine_plan.plan_for(graph, spec, np.float64, driver="stagewise", ordering="rcm")
    assert plan.order is not None and not np.array_equal(plan.order, np.arange(M))
    x, vjp = engine.forward_with_vjp(spec, theta, x0, graph, u, T, driver="stagewise", ordering="rcm")
    x_, vjp_ = engine.forward_with_vjp(spec, theta, x0, graph, u, T, driver="stagewise", ordering="none")
    np.testing.assert_allclose(x, rollout_ref(spec, theta, x0, graph, u, T), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(x, x_, rtol=1e-13, atol=1e-13)
    gx = np.random.default_rng(22).standard_normal(x.shape)
    (gtheta, gx0, gu), (gtheta_, gx0_, gu_) = vjp(gx, controls=True), vjp_(gx, controls=True)
    np.testing.assert_allclose(gtheta, gtheta_, rtol=1e-12, atol=1e-12 * np.abs(gtheta_).max())
    np.testing.assert_allclose(gx0, gx0_, rtol=1e-12, atol=1e-12 * np.abs(gx0_).max())
    np.testing.assert_allclose(gu, gu_, rtol=1e-12, atol=1e-12 * np.abs(gu_).max())
    gtheta2, gx02 = vjp(gx)  # training's call: no controls' cotangent to put back in order
    np.testing.assert_array_equal(gtheta2, gtheta)
    np.testing.assert_array_equal(gx02, gx0)


def test_locality_order_moves_each_nodes_step_sizes_with_it():
    """Nodes observed at their own times keep their own step sizes when the kernels renumber
    them (a regular grid's step sizes are not moved: they are the same everywhere)."""
    spec = spec_(substeps=2)
    graph = shuffled_grid(17, seed=5)
    T = 3
    theta, x0, u = problem(spec, graph, T, seed=26)
    iv = spec.dt * np.random.default_rng(27).uniform(0.3, 1.7, (T, graph.n_nodes))
    x = engine.forward(spec, theta, x0, graph, u, T, driver="stagewise", ordering="rcm", intervals=iv)
    x_ = engine.forward(spec, theta, x0, graph, u, T, driver="stagewise", ordering="none", intervals=iv)
    np.testing.assert_allclose(x, x_, rtol=1e-13, atol=1e-13)


def test_locality_order_only_where_it_brings_neighbours_together():
    """Auto ordering: a randomly numbered grid gets RCM (nearly every edge local after it);
    a grid numbered row by row and a random regular graph (no locality to find) keep theirs."""
    import networkx as nx

    side = 300  # 90,000 nodes >= LOCALITY_MIN_NODES
    grid = shuffled_grid(side, seed=4)
    order = engine_plan.locality_order(grid)
    assert order is not None and np.array_equal(np.sort(order), np.arange(side * side))
    position = np.empty_like(order)
    position[order] = np.arange(len(order))
    assert engine_plan.local_fraction(grid) < 0.1 < 0.99 < engine_plan.local_fraction(grid, position)
    assert engine_plan.locality_order(shuffled_grid(side, seed=None)) is None
    regular = Graph.from_networkx(nx.random_regular_graph(6, 70000, seed=0))
    assert engine_plan.locality_order(regular) is None


# ---------------------------------------------------------------------------
# 6. A block-diagonal batch equals its graphs run one by one
# ---------------------------------------------------------------------------
def test_batch_equals_graphs_one_by_one():
    rng = np.random.default_rng(15)
    g9 = make_graph(rng, 9)
    # different sizes, a repeated graph (B copies of one graph), and a block of > TILE nodes
    graphs = [g9, make_graph(rng, 5), g9, make_graph(rng, 20)] + [g9] * 5 + [make_graph(rng, 130)]
    batch = block_diagonal(graphs)
    plan = engine_plan.plan_for(batch, spec_(self_messages=True), np.float64)
    assert len(plan.blocks) > 2  # really several blocks
    spec = spec_(self_messages=True)
    T = 3
    theta, x0, u = problem(spec, batch, T, seed=16)
    out = engine.forward(spec, theta, x0, batch, u, T)
    x = targets_off_the_kink(out, rng)
    loss, gtheta, gx0 = losses.value_and_grad(spec, theta, x, batch, u)
    M = batch.n_nodes
    lo, loss_sum, gsum = 0, 0.0, np.zeros_like(gtheta)
    for g in graphs:
        hi = lo + g.n_nodes
        np.testing.assert_allclose(engine.forward(spec, theta, x0[lo:hi], g, u[:, lo:hi], T), out[:, lo:hi],
                                   rtol=1e-12, atol=1e-12)
        li, gi, gx0i = losses.value_and_grad(spec, theta, x[:, lo:hi], g, u[:, lo:hi], n_nodes=M)
        np.testing.assert_allclose(gx0i, gx0[lo:hi], rtol=1e-12, atol=1e-12 * np.abs(gx0).max())
        loss_sum += li
        gsum += gi
        lo = hi
    assert abs(loss_sum - loss) <= 1e-12 * loss
    np.testing.assert_allclose(gsum, gtheta, rtol=1e-11, atol=1e-12 * np.abs(gtheta).max())


# ---------------------------------------------------------------------------
# 7. float32 agrees with float64 to float32 precision
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("driver", DRIVERS_IN_FLOAT32, indirect=True)
def test_float32_agrees_with_float64_over_50_steps(driver):
    """Bound: float32 unit roundoff u = 6e-8.  A 50-step rollout makes ~50 * 4 stages of
    O(10) roundings per value (dot products of length H = 16, the few-ulp rational tanh,
    the RK combination); as a random walk that is ~sqrt(2000) * u ~ 3e-6 relative, and the
    field's mild Lipschitz growth over t = 2.5 adds at most a few times that.  1e-5 relative
    to the trajectory's scale leaves a margin; a float32 path that is wrong (a bad tanh
    coefficient, a dropped term, float16-level rounding) is off by 1e-3 or more.
    """
    spec = spec_(hidden=16, dt=0.05, substeps=1)
    graph = mixed_graph(17)
    T = 50
    theta, x0, u = problem(spec, graph, T, seed=18)
    x64 = engine.forward(spec, theta, x0, graph, u, T)
    x32 = engine.forward(spec, theta.astype(np.float32), x0.astype(np.float32), graph,
                            u.astype(np.float32), T)
    assert x32.dtype == np.float32
    scale = np.abs(x64).max()
    assert np.abs(x64[-1] - x64[0]).max() > 0.1 * scale  # it moves
    assert np.abs(x32 - x64).max() < 1e-5 * scale
    # the gradient too (reverse pass in float32): looser, the adjoint sums many terms
    x = targets_off_the_kink(x64, np.random.default_rng(19))
    l64, g64, gx64 = losses.value_and_grad(spec, theta, x, graph, u)
    l32, g32, gx32 = losses.value_and_grad(spec, theta.astype(np.float32), x, graph, u)
    assert g32.dtype == np.float32 and gx32.dtype == np.float32
    assert abs(l32 - l64) < 1e-5 * l64
    assert rel(g32, g64) < 1e-4 and rel(gx32, gx64) < 1e-4


# ---------------------------------------------------------------------------
# 8. zero_messages makes nodes independent
# ---------------------------------------------------------------------------
def test_zero_messages_decouples_nodes(driver):
    graph = mixed_graph(20)
    T = 5
    spec = spec_(zero_messages=True)
    theta, x0, u = problem(spec, graph, T, seed=21)
    node = 3  # has neighbours in the 9-node graph
    x0b = x0.copy()
    x0b[node] += 0.5
    others = np.arange(graph.n_nodes) != node
    a = engine.forward(spec, theta, x0, graph, u, T)
    b = engine.forward(spec, theta, x0b, graph, u, T)
    np.testing.assert_array_equal(a[:, others], b[:, others])
    assert np.abs(a[1:, node] - b[1:, node]).min() > 0
    # control: with messages on, the same change does reach the neighbours
    on = dataclasses.replace(spec, zero_messages=False)
    a = engine.forward(on, theta, x0, graph, u, T)
    b = engine.forward(on, theta, x0b, graph, u, T)
    nbrs = graph.indices[graph.indptr[node]:graph.indptr[node + 1]]
    assert np.all(np.abs(a[-1, nbrs] - b[-1, nbrs]).max(axis=1) > 1e-8)
    # ... but still never the isolated node, nor the other graph of the batch
    np.testing.assert_array_equal(a[:, 8], b[:, 8])
    np.testing.assert_array_equal(a[:, 9:], b[:, 9:])


def test_zero_messages_gives_exactly_zero_message_gradients(driver):
    graph = mixed_graph(22)
    T = 3
    spec = spec_(zero_messages=True)
    theta, x0, u = problem(spec, graph, T, seed=23)
    x = targets_off_the_kink(rollout_ref(spec, theta, x0, graph, u, T), np.random.default_rng(24))
    _, gtheta, _ = losses.value_and_grad(spec, theta, x, graph, u)
    dx, du = spec.state_dim, spec.control_dim
    g = params(spec, gtheta)
    assert np.all(g["W3"][:, dx:] == 0) and np.all(g["b3"][dx:] == 0)
    assert np.all(g["W1"][dx + du:] == 0)  # m' is clamped to 0: its input rows get nothing
    assert np.all(g["W3"][:, :dx] != 0) and np.all(g["b3"][:dx] != 0)


# ---------------------------------------------------------------------------
# 10. Determinism
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("driver,dtype", DRIVERS_AND_DTYPES, indirect=["driver"])
def test_gradient_is_bit_identical_across_calls(driver, dtype):
    rng = np.random.default_rng(25)
    graph = block_diagonal([make_graph(rng, 9), make_graph(rng, 150), make_graph(rng, 40), make_graph(rng, 9)])
    spec = spec_(self_messages=True)
    T = 4
    theta, x0, u = problem(spec, graph, T, seed=26, dtype=dtype)
    x = targets_off_the_kink(rollout_ref(spec, theta, x0, graph, u, T), rng)
    first = losses.value_and_grad(spec, theta, x, graph, u)
    for _ in range(3):
        again = losses.value_and_grad(spec, theta, x, graph, u)
        assert again[0] == first[0]
        np.testing.assert_array_equal(again[1], first[1])
        np.testing.assert_array_equal(again[2], first[2])
    r1 = engine.forward(spec, theta, x0, graph, u, T)
    np.testing.assert_array_equal(engine.forward(spec, theta, x0, graph, u, T), r1)


# ---------------------------------------------------------------------------
# 11. Blocks go to whichever thread is free
# ---------------------------------------------------------------------------
def _record_blocks(seconds_on_calling_thread, fail_at=None):
    """A stand-in for a block driver (time.sleep releases the GIL, as the drivers do): the blocks
    each thread ran, in ``ran``; the calling thread is slow."""
    import threading
    import time

    caller, ran = threading.current_thread(), []

    def run(b0, b1):
        ran.append((threading.current_thread() is caller, b0, b1))
        time.sleep(seconds_on_calling_thread if threading.current_thread() is caller else 0.005)
        if b0 == fail_at:
            raise ValueError("block failed")

    return run, ran


def test_a_slow_thread_takes_fewer_blocks(monkeypatch):
    from mpnode.engine import backend

    monkeypatch.setattr(backend, "n_threads", lambda: 2)
    run, ran = _record_blocks(0.25)
    backend.run_blocks(run, 8)
    assert sorted(b for _, b, _ in ran) == list(range(8)) and all(b1 == b0 + 1 for _, b0, b1 in ran)
    assert sum(on_caller for on_caller, _, _ in ran) == 1  # the other thread ran the other seven meanwhile


def test_a_failed_block_is_raised_once_every_thread_has_stopped(monkeypatch):
    import time

    from mpnode.engine import backend

    monkeypatch.setattr(backend, "n_threads", lambda: 2)
    run, ran = _record_blocks(0.05, fail_at=0)
    with pytest.raises(ValueError, match="block failed"):
        backend.run_blocks(run, 40)
    after = len(ran)
    time.sleep(0.05)
    assert len(ran) == after < 40  # nothing runs after the call returned, and no new block once one failed
