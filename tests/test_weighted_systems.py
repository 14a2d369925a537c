"""Networks whose nodes and edges differ (docs/systems.md#networks-whose-nodes-and-edges-differ):
kuramoto_het and spring_pendulums_het against independent computations, and their scenes' files."""
from dataclasses import replace

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from data_gen import BUILTIN, generate, initial_states, integrate, make_rhs, read_scene
from data_gen.graphs import GraphDraws, GraphSpec, symmetric_weights
from data_gen.per_trajectory import scene_graphs
from data_gen.reference import reference_timing
from data_gen.scenes import check_scene
from data_gen.systems import SYSTEMS, adjacency, kuramoto_rhs, spring_pendulums_rhs, trajectory_rhs
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph
from mpnode.data import read_trajectories, write_trajectories

SCENES = ["kuramoto_het10", "kuramoto_het50_ba", "spring_pendulums_het4", "spring_pendulums_het10"]
#: a graph with a triangle, a tail and a node (5) that hears nobody
EDGES = [(0, 1), (1, 2), (2, 0), (2, 3), (3, 4)]


def weighted(n, edges, low, high, seed=0):
    graph = Graph.from_edges(n, edges)
    return graph.reweighted(symmetric_weights(graph, low, high, np.random.default_rng(seed)))


def small(name, B=3, T=10, **kw):
    return replace(BUILTIN[name], trajectories=B, horizon=T, **kw)


def rows(graph):
    """{(receiver, sender): weight}."""
    return {(int(r), int(s)): float(w) for (r, s), w in zip(graph.edges(), graph.weights)}


def phases(y):
    """kuramoto_het's flat state (2N,) as the N phases."""
    return np.arctan2(y[1::2], y[0::2])


def phase_rates(f, y):
    """theta' of kuramoto_het from its (cos, sin)': theta' = c s' - s c' on the circle."""
    dy = f(0.0, y)
    return y[0::2] * dy[1::2] - y[1::2] * dy[0::2]


# ---- the weights ------------------------------------------------------------------------------
def test_symmetric_weights_are_one_draw_per_pair_within_the_range():
    graph = weighted(6, EDGES, 0.5, 1.5)
    w = rows(graph)
    assert len(w) == 2 * len(EDGES) and all(w[r, s] == w[s, r] for r, s in w)
    assert all(0.5 <= v <= 1.5 for v in w.values()) and len(set(w.values())) == len(EDGES)
    one_way = Graph.from_edges(3, [(0, 1), (1, 0), (2, 1)], directed=True)  # both ways listed: still one pair
    w = rows(one_way.reweighted(symmetric_weights(one_way, 1.0, 4.0, np.random.default_rng(1))))
    assert w[0, 1] == w[1, 0] and w[2, 1] != w[0, 1]


# ---- kuramoto_het -----------------------------------------------------------------------------
def test_kuramoto_het_against_the_edge_sum():
    graph = weighted(6, EDGES, 0.5, 1.5)
    rng = np.random.default_rng(2)
    theta, omega, K = rng.uniform(-np.pi, np.pi, 6), rng.uniform(0, 2, 6), 1.3
    y = np.stack([np.cos(theta), np.sin(theta)], axis=1).ravel()
    f = make_rhs("kuramoto_het", {"K": K}, graph, omega[:, None])
    w, deg = rows(graph), graph.degrees()
    direct = [omega[i] + (K / deg[i] * sum(w[i, j] * np.sin(theta[j] - theta[i]) for j in range(6) if (i, j) in w)
                          if deg[i] else 0.0) for i in range(6)]
    np.testing.assert_allclose(phase_rates(f, y), direct, rtol=1e-13, atol=1e-14)
    assert phase_rates(f, y)[5] == omega[5]  # hears nobody: its own frequency
    dy = f(0.0, y)
    np.testing.assert_allclose(y[0::2] * dy[0::2] + y[1::2] * dy[1::2], 0.0, atol=1e-15)  # stays on the circle


def test_kuramoto_het_with_one_frequency_and_unit_weights_is_kuramoto():
    # on a ring every node hears 2: K / deg_i = K / 2 is the old (summed) coupling; the old system's three
    # phases per node run alike, so its first phase is the new system's only one
    n, K, omega = 8, 1.2, 0.7
    ring = Graph.from_edges(n, [(i, (i + 1) % n) for i in range(n)])
    theta = np.random.default_rng(3).uniform(-np.pi, np.pi, n)
    new = make_rhs("kuramoto_het", {"K": K}, ring.reweighted(np.ones(ring.n_edges)), np.full((n, 1), omega))
    y = np.stack([np.cos(theta), np.sin(theta)], axis=1).ravel()
    old = kuramoto_rhs(0.0, np.repeat(theta, 3), np.full(3, omega), K / 2, adjacency(ring))
    np.testing.assert_allclose(phase_rates(new, y), old[0::3], rtol=1e-13)


def test_kuramoto_het_symmetric_coupling_cancels_in_the_degree_weighted_sum():
    # w_ij = w_ji: sum_i deg_i (theta_i' - omega_i) = K sum_ij w_ij sin(theta_j - theta_i) = 0 (the mean coupling's
    # form of sum_i theta_i' = sum_i omega_i); unweighted by degree it does not cancel on this irregular graph
    graph = weighted(6, EDGES, 0.5, 1.5, seed=4)
    rng = np.random.default_rng(5)
    omega = rng.uniform(0, 2, 6)
    f = make_rhs("kuramoto_het", {"K": 2.0}, graph, omega[:, None])
    for _ in range(5):
        theta = rng.uniform(-np.pi, np.pi, 6)
        rate = phase_rates(f, np.stack([np.cos(theta), np.sin(theta)], axis=1).ravel())
        assert abs(np.dot(graph.degrees(), rate - omega)) < 1e-13
    assert abs(np.sum(rate - omega)) > 1e-3


# ---- spring_pendulums_het ---------------------------------------------------------------------
def test_spring_pendulums_het_with_equal_values_is_spring_pendulums():
    p = SYSTEMS["spring_pendulums"].defaults
    graph = Graph.from_edges(6, EDGES)
    y = np.random.default_rng(6).uniform(-0.6, 0.6, size=(12, 3))
    old = spring_pendulums_rhs(0.0, y, p["m"], p["l"], p["k"], p["g"], adjacency(graph), graph.degrees())
    same = np.tile([p["l"], p["m"]], (6, 1))
    new = make_rhs("spring_pendulums_het", {"g": p["g"]}, graph.reweighted(np.full(graph.n_edges, p["k"])), same)
    np.testing.assert_allclose(new(0.0, y), old, rtol=1e-13, atol=1e-14)


def pendulum_energy(y, graph, attrs, g):
    """sum_i m_i X_i'^2 / 2 + m_i g X_i^2 / (2 l_i) + sum_edges k_ij (X_i - X_j)^2 / 2, X_i = l_i sin(theta_i):
    conserved by m_i X_i'' = -m_i g X_i / l_i + sum_j k_ij (X_j - X_i) with k_ij = k_ji.  y (..., 2N)."""
    l, m = attrs[:, 0], attrs[:, 1]
    theta, omega = y[..., 0::2], y[..., 1::2]
    X, V = l * np.sin(theta), l * np.cos(theta) * omega
    springs = sum(k * (X[..., i] - X[..., j]) ** 2 for (i, j), k in rows(graph).items() if i < j)
    return np.sum(m * V**2 / 2 + m * g * X**2 / (2 * l), axis=-1) + springs / 2


def test_spring_pendulums_het_conserves_the_energy_of_the_bobs_and_springs():
    graph = weighted(6, EDGES, 1.0, 4.0, seed=7)
    rng = np.random.default_rng(8)
    attrs = np.stack([rng.uniform(1, 2, 6), rng.uniform(0.5, 2, 6)], axis=1)
    f = make_rhs("spring_pendulums_het", {"g": 9.81}, graph, attrs)
    y = rng.uniform(-0.5, 0.5, 12)
    energy = lambda z: pendulum_energy(z, graph, attrs, 9.81)  # noqa: E731
    h = 1e-6  # dE/dt along the field by central differences: zero up to the differences' own error
    slope = (energy(y + h * f(0, y)) - energy(y - h * f(0, y))) / (2 * h)
    assert abs(slope) < 1e-6 * energy(y)


@pytest.mark.parametrize("name", ["kuramoto_het", "spring_pendulums_het"])
def test_het_right_hand_sides_take_states_as_columns(name):
    system = SYSTEMS[name]
    graph = weighted(6, EDGES, 1.0, 2.0)
    rng = np.random.default_rng(9)
    attrs = rng.uniform(1.0, 2.0, size=(6, len(system.attr_names)))
    f = make_rhs(name, system.defaults, graph, attrs)
    y = rng.uniform(0.1, 0.7, size=(12, 4))
    for k in range(4):
        np.testing.assert_array_equal(f(0.0, y)[:, k], f(0.0, y[:, k].copy()))


# ---- the scenes' files ------------------------------------------------------------------------
@pytest.mark.parametrize("name", SCENES)
def test_files_carry_node_attributes_and_weighted_graphs_in_their_ranges(tmp_path, name):
    path = tmp_path / "het.h5"
    write_trajectories(path, generate(small(name, B=6), workers=1))
    t = read_trajectories(path)
    system = SYSTEMS[t.system]
    p = {**system.defaults}
    with h5py.File(path, "r") as f:
        assert int(f.attrs["format_version"]) == 3
    assert t.attr_names == list(system.attr_names) and t.node_attrs.shape == (6, t.n_nodes, len(system.attr_names))
    assert len(t.graphs) == 6 and t.graph_index.tolist() == list(range(6))
    *nodes, edges = system.ranges  # the attributes' ranges in attr_names' order, then the edges' (w or k)
    for d, (lo, hi, _) in enumerate(nodes):
        a = t.node_attrs[..., d]
        assert p[lo] <= a.min() and a.max() <= p[hi] and a.std() > 0.1 * (p[hi] - p[lo])
    w_lo, w_hi = p[edges[0]], p[edges[1]]
    for g in t.graphs:
        w = rows(g)
        assert all(w_lo <= v <= w_hi for v in w.values()) and all(w[r, s] == w[s, r] for r, s in w)
    assert len({tuple(g.weights[:3]) for g in t.graphs}) == 6  # drawn afresh for each trajectory
    if t.system == "kuramoto_het":
        np.testing.assert_allclose(np.sum(t.x**2, axis=-1), 1.0, atol=1e-6)  # the state stays on the circle
        assert {"graph_family", "graph_seed"} <= set(t.aux)


def test_the_training_graphs_mix_two_families_and_the_test_graphs_have_hubs():
    train = scene_graphs(small("kuramoto_het10", B=40))
    assert set(train.aux["graph_family"]) == {0, 1}
    test = scene_graphs(small("kuramoto_het50_ba", B=5))
    assert len({g.n_edges for g in test.graphs}) == 1  # barabasi_albert(50, 2): 2 (50 - 2) edges, other wiring
    assert len({tuple(g.indices) for g in test.graphs}) == 5
    assert max(g.degrees().max() for g in test.graphs) > 3 * max(g.degrees().max() for g in train.graphs) / 2


def test_draws_depend_on_the_seed_and_b_alone():
    scene = small("spring_pendulums_het4", B=6)
    a, b = generate(scene, workers=1), generate(replace(scene, trajectories=3), workers=2)
    np.testing.assert_array_equal(a.x[:3], b.x)
    np.testing.assert_array_equal(a.node_attrs[:3], b.node_attrs)
    assert all(g.equals(h) for g, h in zip(a.graphs, b.graphs))
    c = scene_graphs(replace(scene, seed=1))
    assert not np.allclose(c.node_attrs, a.node_attrs) and not np.allclose(c.graphs[0].weights, a.graphs[0].weights)
    x0, graphs, gi = initial_states(scene)  # what `mpnode simulate` starts from: the same states and graphs
    np.testing.assert_array_equal(x0, a.x[:, 0])
    assert all(g.equals(h) for g, h in zip(graphs, a.graphs)) and gi.tolist() == list(range(6))


@pytest.mark.parametrize("name", SCENES)
def test_reference_trajectories_agree_with_a_tighter_solve(name):
    t = generate(small(name, B=2, T=50), workers=1)
    for b in range(2):
        x = integrate(trajectory_rhs(t, b), t.x[b, 0], t.horizon, t.dt, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(x, t.x[b], rtol=0, atol=1e-6)


def test_generated_pendulums_keep_their_energy():
    t = generate(small("spring_pendulums_het10", B=3, T=50), workers=1)
    for b in range(3):
        e = pendulum_energy(t.x[b].reshape(t.horizon + 1, -1), t.graphs[b], t.node_attrs[b], t.attrs["g"])
        assert np.ptp(e) < 1e-7 * e[0]


def test_kuramoto_het10_partly_synchronises_over_its_horizon():
    # neighbours' phases drift together from random starts, yet the horizon ends well short of lock-step
    t = generate(small("kuramoto_het10", B=16, T=50), workers=2)
    coherence = []
    for b in range(16):
        pairs = t.graphs[b].edges()
        theta = np.arctan2(t.x[b, :, :, 1], t.x[b, :, :, 0])
        coherence.append(np.cos(theta[:, pairs[:, 0]] - theta[:, pairs[:, 1]]).mean(axis=1))
    start, end = np.mean(coherence, axis=0)[[0, -1]]
    assert abs(start) < 0.2 and 0.25 < end < 0.8


def test_the_reference_timing_runs_one_trajectory_at_a_time():
    t = generate(small("kuramoto_het10", B=2, T=10), workers=1)
    timing = reference_timing(t, 2, target=1e-3)
    assert timing is not None and timing["reached"] and timing["sample"] == 2


# ---- scene files and the command line ---------------------------------------------------------
def test_a_scene_file_weighs_fixed_graphs_per_trajectory(tmp_path):
    path = tmp_path / "ring.toml"
    path.write_text('system = "kuramoto_het"\ntrajectories = 4\nhorizon = 5\n[params]\nK = 0.5\nw_min = 1\nw_max = 3\n'
                    '[graph]\nbuilder = "watts_strogatz"\nnodes = 8\nk = 2\np = 0.0\nseed = 1\n')
    t = generate(read_scene(path), workers=1)
    assert len(t.graphs) == 4 and len({tuple(g.indices) for g in t.graphs}) == 1  # one wiring, four weightings
    assert all(1 <= g.weights.min() and g.weights.max() <= 3 for g in t.graphs) and t.attrs["K"] == 0.5


@pytest.mark.parametrize("system, params, field", [
    ("spring_pendulums_het", "l_min = 3.0", "params.l_min"), ("spring_pendulums_het", "k_min = -1.0", "params.k_min"),
    ("spring_pendulums_het", "m_min = 0.0\nm_max = 1.0", "params.m_min"),
    # wider than numpy draws from: the frequencies' time scale (1e-308 s) refuses it first
    ("kuramoto_het", "omega_min = -1e308\nomega_max = 1e308", "dt"),
])
def test_ranges_a_scene_file_cannot_draw_from(tmp_path, system, params, field):
    path = tmp_path / "bad.toml"
    path.write_text(f'system = "{system}"\n[params]\n{params}\n'
                    '[graph]\nbuilder = "edges"\nnodes = 3\nedges = [[0, 1], [1, 2]]\n')
    with pytest.raises(InputError) as e:
        read_scene(path)
    assert e.value.field == field


@pytest.mark.parametrize("name, dims", [("kuramoto_het10", (10, 1)), ("spring_pendulums_het4", (4, 2))])
def test_cli_generate_writes_format_3(tmp_path, name, dims):
    out = tmp_path / "het.h5"
    r = CliRunner().invoke(main, ["generate", name, "-o", str(out), "--trajectories", "3", "--horizon", "5",
                                  "--workers", "1", "--noise", "0.01"])
    assert r.exit_code == 0, r.output
    t = read_trajectories(out)
    assert t.x.shape[:3] == (3, 6, dims[0]) and t.node_attrs.shape == (3, *dims) and t.truth is not None
    assert all(g.weighted for g in t.graphs) and t.attrs["scene"] == name
    with h5py.File(out, "r") as f:
        assert int(f.attrs["format_version"]) == 3
    r = CliRunner().invoke(main, ["scenes"])
    assert all(s in r.stdout for s in SCENES)


def test_graphs_drawn_per_trajectory_come_from_random_builders_on_one_n():
    scene = BUILTIN["kuramoto_het10"]
    for family in (GraphSpec("edges", 10, edges=((0, 1),)), GraphSpec("gnp", 12, {"p": 0.4})):
        with pytest.raises(InputError, match="random builders on 10 nodes"):
            check_scene(replace(scene, graph=GraphDraws((scene.graph.families[0], family))), "scene")
