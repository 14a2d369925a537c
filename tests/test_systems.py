"""The reference physics (data_gen/systems.py, graphs.py, initial.py) against hand arithmetic."""
import math

import numpy as np
import pytest
import scipy.sparse

from data_gen.graphs import GraphSpec, gene_graph, kuramoto_graph
from data_gen.initial import get_sampler, hotspots, uniform
from data_gen.systems import (
    SYSTEMS,
    adjacency,
    gene_rhs,
    kuramoto_rhs,
    lorenz_coupling,
    lorenz_rhs,
    make_rhs,
    pendulum_guard,
    pendulum_rhs,
)
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph


# ---- coupled pendulum ------------------------------------------------------------------
def test_pendulum_rhs_by_hand():
    # m = 1, l = 1, k = 2, g = 10; node 0: theta = pi/6, omega = 1; node 1: theta = 0, omega = 0
    # node 0: (sin(pi/6) (1 (1*1 - 10) - 2*1) + 2*1*sin 0) / (1*1*cos(pi/6)) = 0.5*(-11) / (sqrt(3)/2) = -11/sqrt(3)
    # node 1: (sin 0 * (...) + 2*1*sin(pi/6)) / (1*1*cos 0) = 2*0.5 / 1 = 1
    y = np.array([np.pi / 6, 1.0, 0.0, 0.0])
    dy = pendulum_rhs(0.0, y, m=1.0, l=1.0, k=2.0, g=10.0)
    np.testing.assert_allclose(dy, [1.0, -11 / math.sqrt(3), 0.0, 1.0], rtol=1e-14, atol=1e-15)


def test_pendulum_linearisation_is_second_order_accurate():
    # small angles: theta_i'' = -(g/l) theta_i - (k/m)(theta_i - theta_j); the error is O(eps^3)
    p = SYSTEMS["coupled_pendulum"].defaults
    m, l, k, g = p["m"], p["l"], p["k"], p["g"]
    direction = np.array([0.7, -0.4, -0.3, 0.9])  # theta_0, omega_0, theta_1, omega_1

    def error(eps):
        y = eps * direction
        th = y[0::2]
        linear = -(g / l) * th - (k / m) * (th - th[::-1])
        return np.max(np.abs(pendulum_rhs(0.0, y, m, l, k, g)[1::2] - linear))

    assert error(1e-2) < 10 * 1e-2**3
    assert error(1e-3) / error(1e-2) < 2e-3  # cubic: a factor 1e-3 per decade


def test_pendulum_guard_marks_the_singularity():
    ok = np.array([0.3, 0.0, -0.2, 0.0])
    bad = np.array([np.pi / 2 - 1e-8, 0.0, 0.0, 0.0])
    assert pendulum_guard(0.0, ok) > 0
    assert pendulum_guard(0.0, bad) < 0
    # one value per saved state for a (4, T) array
    assert pendulum_guard(None, np.stack([ok, bad], axis=1)).shape == (2,)


# ---- lorenz ----------------------------------------------------------------------------
def test_lorenz_rhs_by_hand():
    # node 0 = (1, 2, 3): (10 (2 - 1), 1 (28 - 3) - 2, 1*2 - 8/3*3) = (10, 23, -6)
    # node 1 = (2, 1, 0): (10 (1 - 2), 2 (28 - 0) - 1, 2*1 - 0) = (-10, 55, 2)
    # H has one entry: H[0, 3] = 0.5 -> x_0' gets + 0.5 * x_1 = + 1
    H = np.zeros((6, 6))
    H[0, 3] = 0.5
    y = np.array([1.0, 2.0, 3.0, 2.0, 1.0, 0.0])
    dy = lorenz_rhs(0.0, y, sigma=10.0, rho=28.0, beta=8.0 / 3.0, H=H)
    np.testing.assert_allclose(dy, [11.0, 23.0, -6.0, -10.0, 55.0, 2.0], rtol=1e-14)


@pytest.mark.parametrize("k, c", [(3, 0.01), (10, 1.0), (10, 5.0)])
def test_lorenz_coupling_has_zero_diagonal_blocks_and_norm_c(k, c):
    H = lorenz_coupling(k, c, np.random.default_rng(0))
    assert H.shape == (3 * k, 3 * k)
    for i in range(k):
        assert not H[3 * i:3 * i + 3, 3 * i:3 * i + 3].any()
    off = ~np.kron(np.eye(k, dtype=bool), np.ones((3, 3), dtype=bool))
    assert np.all(H[off] > 0)
    assert np.linalg.norm(H) == pytest.approx(c, rel=1e-12)


def test_lorenz_coupling_single_node_is_zero():
    assert not lorenz_coupling(1, 5.0, np.random.default_rng(0)).any()


# ---- gene ------------------------------------------------------------------------------
def test_gene_rhs_by_hand():
    # path 0 - 1 - 2 and an isolated node 3; x = (1, 2, 3, 4), b = f = 1, h = 2
    # x^2 / (1 + x^2) = 1/2, 4/5, 9/10 for nodes 0, 1, 2
    # node 0 hears 1: -1 + 4/5 = -0.2;  node 1 hears 0, 2: -2 + 1/2 + 9/10 = -0.6
    # node 2 hears 1: -3 + 4/5 = -2.2;  node 3 hears nobody: -4
    graph = Graph.from_edges(4, [(0, 1), (1, 2)])
    y = np.array([1.0, 2.0, 3.0, 4.0])
    dy = gene_rhs(0.0, y, b=1.0, f=1.0, h=2.0, A=adjacency(graph))
    np.testing.assert_allclose(dy, [-0.2, -0.6, -2.2, -4.0], rtol=1e-14)


def test_gene_rhs_follows_the_direction_of_the_csr_rows():
    # directed: node 0 hears node 1 (receiver 0, sender 1), node 1 hears nobody
    # node 0: -1*1^1 + 2^2/(1+2^2) = -1 + 0.8;  node 1: -2
    graph = Graph.from_edges(2, [(0, 1)], directed=True)
    dy = make_rhs("gene", SYSTEMS["gene"].defaults, graph)(0.0, np.array([1.0, 2.0]))
    np.testing.assert_allclose(dy, [-0.2, -2.0], rtol=1e-14)


def test_adjacency_stays_sparse():
    graph = Graph.from_edges(1000, [(i, i + 1) for i in range(999)])
    A = adjacency(graph)
    assert scipy.sparse.issparse(A) and A.nnz == 2 * 999


# ---- kuramoto --------------------------------------------------------------------------
def test_kuramoto_rhs_by_hand():
    # nodes 0 <-> 1, node 2 isolated; omega = (1, 2, 3), K = 1/3
    # theta_0 = (0, 0, 0), theta_1 = (pi/2, pi, pi/6), theta_2 = (5, 6, 7)
    # node 0: omega + K (sin(pi/2), sin(pi), sin(pi/6)) = (1 + 1/3, 2 + 0, 3 + 1/6)
    # node 1: omega + K (sin(-pi/2), sin(-pi), sin(-pi/6)) = (1 - 1/3, 2 - 0, 3 - 1/6)
    # node 2: omega
    graph = Graph.from_edges(3, [(0, 1)])
    y = np.array([0, 0, 0, np.pi / 2, np.pi, np.pi / 6, 5, 6, 7], dtype=float)
    dy = kuramoto_rhs(0.0, y, omega=np.array([1.0, 2.0, 3.0]), K=1 / 3, A=adjacency(graph))
    np.testing.assert_allclose(dy, [4 / 3, 2, 3 + 1 / 6, 2 / 3, 2, 3 - 1 / 6, 1, 2, 3], rtol=1e-14, atol=1e-15)


def test_kuramoto_rhs_matches_the_edge_sum():
    graph = kuramoto_graph("ba", 10, (3,)).build()[0]
    rng = np.random.default_rng(1)
    theta, omega = rng.uniform(-3, 3, (10, 3)), rng.standard_normal(3)
    direct = np.array([omega + 0.5 * sum(np.sin(theta[j] - theta[i])
                                         for j in graph.indices[graph.indptr[i]:graph.indptr[i + 1]])
                       for i in range(10)])
    dy = kuramoto_rhs(0.0, theta.ravel(), omega, 0.5, adjacency(graph))
    np.testing.assert_allclose(dy.reshape(10, 3), direct, rtol=1e-12, atol=1e-12)


# ---- graphs ----------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["coupled_pendulum", "spring_pendulums", "lorenz", "gene", "kuramoto"])
def test_every_right_hand_side_takes_states_as_columns(name):
    """The batched reference (data_gen.reference) evaluates K states at once as the columns of y
    (N*dx, K); each column must be exactly the right-hand side of that state alone."""
    system = SYSTEMS[name]
    n = 2 if name == "coupled_pendulum" else 5
    graph = Graph.complete(n) if system.complete else Graph.from_edges(n, [(0, 1), (1, 2), (3, 1), (4, 0)])
    rng = np.random.default_rng(1)
    params = {**system.defaults, **system.draw(system.defaults, n, rng)}
    f = make_rhs(name, params, graph)
    y = rng.uniform(0.1, 0.7, size=(n * system.state_dim, 4))
    columns = f(0.0, y)
    assert columns.shape == y.shape
    for k in range(4):
        np.testing.assert_array_equal(columns[:, k], f(0.0, y[:, k].copy()))


def test_spring_pendulums_on_two_nodes_are_the_coupled_pendulum_and_springs_pull_along_edges():
    p = SYSTEMS["spring_pendulums"].defaults
    rng = np.random.default_rng(2)
    y = rng.uniform(-0.6, 0.6, size=4)
    pair = make_rhs("spring_pendulums", p, Graph.complete(2))(0.0, y)
    np.testing.assert_allclose(pair, make_rhs("coupled_pendulum", p, Graph.complete(2))(0.0, y), rtol=1e-14)
    chain = Graph.from_edges(3, [(0, 1), (1, 0), (1, 2), (2, 1)])
    f = make_rhs("spring_pendulums", p, chain)
    y = np.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0])  # the middle one displaced, all at rest
    acc = f(0.0, y)[1::2]
    assert acc[0] > 0 and acc[2] > 0 and acc[1] < 0 and np.isclose(acc[0], acc[2])
    lin = -(p["g"] / p["l"]) * 0.05 - (p["k"] / p["m"]) * 2 * 0.05  # its two springs and gravity, small angle
    assert abs(acc[1] - lin) < 0.005 * abs(lin)


def test_dt_beyond_ten_time_scales_is_refused():
    pendulum = SYSTEMS["coupled_pendulum"]
    scale = 2 * np.pi * math.sqrt(1.5 / 9.81)  # the small-oscillation period
    pendulum.check_dt({}, 9.9 * scale, "scene")
    with pytest.raises(InputError, match=r"dt: is 1000, 407 times the time scale of coupled_pendulum \(2.46"):
        pendulum.check_dt({}, 1e3, "scene")
    SYSTEMS["gene"].check_dt({"b": 1e4}, 0.05, "scene")  # stiff (fast decay), yet slow where it matters
    SYSTEMS["gene"].check_dt({"b": 0.01}, 999.0, "scene")  # slow decay: a time scale of 100


def test_spec_graphs():
    er, ba, ws = (gene_graph(kind, 16, (1,)).build()[0] for kind in ("er", "ba", "ws"))
    assert ba.n_edges == 2 * 8 * (16 - 8)  # barabasi_albert(16, 8): m (n - m) undirected edges
    assert ws.n_edges == 16 * 8  # ring of degree N/2 = 8 (rewiring keeps the count)
    assert 0 < er.n_edges < 16 * 15
    k_er, k_ws = (kuramoto_graph(kind, 10, (1,)).build()[0] for kind in ("er", "ws"))
    assert k_er.n_edges == 2 * 5  # gnm: exactly 5 undirected edges
    assert k_ws.n_edges == 10 * 4  # networkx uses k - 1 = 4 neighbours for k = 5
    assert kuramoto_graph("ws", 10, (1,)).describe()["graph_ring_degree"] == 4


def test_graphs_are_seeded_and_sparse():
    spec = gene_graph("ba", 64, (1, 2))
    a1, a2 = spec.build()
    b1, _ = spec.build()
    assert a1.equals(b1) and not a1.equals(a2)
    assert len(spec.calls()) == 2 and "seed=2" in spec.calls()[1]
    assert isinstance(a1, Graph)


def test_edge_list_graph_is_sender_receiver():
    g = GraphSpec("edges", 3, edges=((0, 1),), directed=True).build()[0]
    assert g.indices[g.indptr[1]:g.indptr[2]].tolist() == [0]  # node 1 hears node 0
    assert g.indptr[1] == 0  # node 0 hears nobody


# ---- initial states --------------------------------------------------------------------
def test_uniform_sampler_ranges():
    x = uniform(np.random.default_rng(0), SYSTEMS["coupled_pendulum"], 2000)
    assert x.shape == (2000, 2)
    assert np.all(np.abs(x[:, 0]) < np.pi / 4) and np.all(np.abs(x[:, 1]) < 0.5)
    assert np.abs(x[:, 0]).max() > 0.7  # covers the range
    g = uniform(np.random.default_rng(0), SYSTEMS["gene"], 500)
    assert g.min() >= 0 and g.max() < 50 and g.max() > 45


def test_hotspots_sampler():
    x = hotspots(np.random.default_rng(4), SYSTEMS["gene"], 64)
    assert x.shape == (64, 1)
    hot = x[x > 0]
    assert hot.size > 0 and hot.min() >= 30 and hot.max() < 50
    assert np.any(x == 0) or hot.size == 64
    with pytest.raises(InputError, match="square"):
        get_sampler("hotspots", SYSTEMS["gene"], 10, "scene", "initial")
    with pytest.raises(InputError, match="not defined for lorenz"):
        get_sampler("hotspots", SYSTEMS["lorenz"], 16, "scene", "initial")
