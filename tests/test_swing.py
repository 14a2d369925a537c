"""Power grids (docs/systems.md#swing): the swing equation against an independent computation, its
operating point, the refusals of grids without one, the real IEEE cases (when PYPOWER, the extra
grids, is installed), the synthetic family's coverage of them, their scenes' files, and the recipe
that learns them."""
import json
import sys
from dataclasses import replace

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from data_gen import BUILTIN, SETS, generate, initial_states, integrate, make_rhs, read_scene
from data_gen import grids
from data_gen.graphs import power_grid_graph
from data_gen.per_trajectory import scene_graphs
from data_gen.swing import DEFAULTS, disturbed, draw_grid, operating_point, strength
from data_gen.systems import SYSTEMS, trajectory_rhs
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph
from mpnode.data import read_trajectories

SWING = SYSTEMS["swing"]
#: a triangle with a tail: buses 0, 1, 2 meshed, 3 and 4 hanging on
EDGES = [(0, 1), (1, 2), (2, 0), (2, 3), (3, 4)]


def pypower_or_skip():
    pytest.importorskip("pypower", reason="PYPOWER (the extra grids: pip install 'mpnode[grids]') is not installed")


def lines(n, edges, b):
    """A weighted graph: line k of ``edges`` with susceptance b[k], both ways."""
    return Graph.from_edges(n, edges, weights=np.asarray(b, dtype=np.float64))


def small(name, B=2, T=10, **kw):
    return replace(BUILTIN[name], trajectories=B, horizon=T, **kw)


def state(theta, omega):
    return np.stack([np.cos(theta), np.sin(theta), omega], axis=1).ravel()


def synthetic(n=20, seed=0):
    """A grid of the family: its weighted graph and node attributes [M, D, P]."""
    graph = Graph.from_networkx(power_grid_graph(n, seed))
    weights, attrs = draw_grid(DEFAULTS, graph, np.random.default_rng(seed))
    return graph.reweighted(weights), attrs


def case(buses, branches, gens, slack=1):
    """A MATPOWER-format case dict: buses [(number, load MW)], branches [(from, to, x)], gens [(bus, MW)]."""
    bus = np.zeros((len(buses), 13))
    bus[:, 0], bus[:, 2] = np.array(buses, dtype=float).T
    bus[:, 1] = [3 if b == slack else 1 for b, _ in buses]
    branch = np.zeros((len(branches), 13))
    branch[:, [0, 1, 3]] = branches
    branch[:, 10] = 1
    gen = np.zeros((len(gens), 21))
    gen[:, [0, 1]] = gens
    gen[:, 7] = 1
    return {"baseMVA": 100.0, "bus": bus, "branch": branch, "gen": gen}


#: four buses on a ring with a parallel line; generation 150 MW against a load of 140 MW
RING = case([(1, 0), (2, 60), (3, 80), (4, 0)], [(1, 2, 0.1), (2, 3, 0.2), (3, 4, 0.1), (4, 1, 0.2), (1, 2, 0.1)],
            [(1, 100), (4, 50)])


# ---- the equation -----------------------------------------------------------------------------
def test_rhs_against_the_line_sum():
    graph = lines(5, EDGES, [10.0, 5.0, 20.0, 2.0, 7.0])
    rng = np.random.default_rng(1)
    theta, omega = rng.uniform(-np.pi, np.pi, 5), rng.uniform(-2, 2, 5)
    M, D, P = rng.uniform(0.1, 2, 5), rng.uniform(0.1, 2, 5), rng.uniform(-1, 1, 5)
    f = make_rhs("swing", DEFAULTS, graph, np.stack([M, D, P], axis=1))
    dy = f(0.0, state(theta, omega))
    w = {(int(r), int(s)): wt for (r, s), wt in zip(graph.edges(), graph.weights)}
    flow = [sum(w[i, j] * np.sin(theta[i] - theta[j]) for j in range(5) if (i, j) in w) for i in range(5)]
    np.testing.assert_allclose(dy[2::3], (P - D * omega - np.array(flow)) / M, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(dy[0::3], -np.sin(theta) * omega, rtol=1e-13)
    np.testing.assert_allclose(dy[1::3], np.cos(theta) * omega, rtol=1e-13)


def test_rhs_takes_states_as_columns():
    graph, attrs = synthetic(8, seed=2)
    f = make_rhs("swing", DEFAULTS, graph, attrs)
    y = np.random.default_rng(3).uniform(-1, 1, size=(24, 4))
    for k in range(4):
        np.testing.assert_array_equal(f(0.0, y)[:, k], f(0.0, y[:, k].copy()))


def test_the_inertia_rule_sets_each_bus_frequency_and_bounds_the_fastest_mode():
    graph, attrs = synthetic(30, seed=4)
    M, D, P = attrs.T
    own = np.sqrt(strength(graph) / M) / (2 * np.pi)  # each bus swinging against its lines
    assert set(np.round(own, 12)) <= {DEFAULTS["f_gen"], DEFAULTS["f_load"]}
    assert np.all((own == DEFAULTS["f_gen"]) == (P > 0)) and np.allclose(D, DEFAULTS["gamma"] * M)
    L = np.diag(strength(graph)) - _dense(graph)
    fastest = np.sqrt(np.linalg.eigvals(L / M[:, None]).real.max()) / (2 * np.pi)
    assert fastest <= np.sqrt(2) * DEFAULTS["f_load"] + 1e-9


def _dense(graph):
    B = np.zeros((graph.n_nodes, graph.n_nodes))
    B[tuple(graph.edges().T)] = graph.weights
    return B


# ---- the operating point ----------------------------------------------------------------------
def assert_fixed_point(graph, attrs):
    theta = operating_point(graph, attrs[:, 2], inertia=attrs[:, 0])
    dy = make_rhs("swing", DEFAULTS, graph, attrs)(0.0, state(theta, np.zeros(graph.n_nodes)))
    assert np.abs(dy).max() < 1e-9 * np.abs(attrs[:, 2] / attrs[:, 0]).max()
    assert abs(np.dot(attrs[:, 0], theta)) < 1e-9 * attrs[:, 0].sum()  # the centre of inertia at 0
    return theta


def test_a_synthetic_grid_rests_at_its_operating_point_and_its_powers_balance():
    for seed in range(5):
        graph, attrs = synthetic(20, seed)
        P = attrs[:, 2]
        assert abs(P.sum()) < 1e-12 * np.abs(P).sum() and P.max() > 0 > P.min()
        theta = assert_fixed_point(graph, attrs)
        r, s = graph.edges().T
        assert np.abs(theta[r] - theta[s]).max() < np.pi / 2


def test_ieee14_rests_at_its_operating_point_with_the_imbalance_on_the_slack():
    pypower_or_skip()
    graph, power, generator, record = grids.case_network(grids.load_case(14, "ieee14"), "ieee14")
    assert graph.n_nodes == 14 and generator.sum() == 5 and abs(power.sum()) < 1e-12
    assert record["grid_slack_bus"] == 1 and record["grid_imbalance_on_slack"] == pytest.approx(2.724 - 2.59)
    assert power[0] == pytest.approx(2.324 - record["grid_imbalance_on_slack"])  # bus 1: 232.4 MW, no load
    assert_fixed_point(graph, grids.grid_attrs(graph, power, generator, DEFAULTS))


def test_powers_beyond_the_lines_have_no_synchronous_state():
    graph = lines(3, [(0, 1), (1, 2)], [1.0, 1.0])
    with pytest.raises(InputError, match="no synchronous state") as e:
        operating_point(graph, [1.5, 0.0, -1.5], "grid")
    assert e.value.field == "power" and "\n" not in str(e.value)
    assert operating_point(graph, [0.5, 0.0, -0.5]) is not None


def test_unbalanced_powers_isolated_buses_and_pieces_are_refused():
    graph = lines(3, [(0, 1), (1, 2)], [1.0, 1.0])
    with pytest.raises(InputError, match="do not balance"):
        operating_point(graph, [0.5, 0.0, -0.4], "grid")
    with pytest.raises(InputError, match="bus 3 has no line"):
        operating_point(lines(4, [(0, 1), (1, 2)], [1.0, 1.0]), [0.5, 0.0, -0.5, 0.0], "grid")
    with pytest.raises(InputError, match="in 2 pieces") as e:
        operating_point(lines(4, [(0, 1), (2, 3)], [1.0, 1.0]), [0.5, -0.5, 0.5, -0.5], "grid")
    assert e.value.field == "graph"


# ---- the cases --------------------------------------------------------------------------------
def test_a_case_converts_parallel_lines_add_and_the_slack_balances():
    graph, power, generator, record = grids.case_network(RING, "ring")
    B = _dense(graph)
    assert B[0, 1] == B[1, 0] == pytest.approx(20.0) and B[1, 2] == pytest.approx(5.0)  # two lines of x = 0.1
    np.testing.assert_allclose(power, [1.0 - 0.1, -0.6, -0.8, 0.5])  # 10 MW surplus taken off the slack, bus 1
    assert generator.tolist() == [True, False, False, True] and record["grid_imbalance_on_slack"] == pytest.approx(0.1)


@pytest.mark.parametrize("doctor, field, words", [
    (lambda c: c["branch"].__setitem__((1, 3), 0.0), "branch 1 (bus 2 - bus 3)/x", "zero reactance"),
    (lambda c: c["branch"].__setitem__((slice(1, 3), 10), 0), "bus", "bus 3 is isolated"),
    (lambda c: c["bus"].__setitem__((0, 1), 2), "bus", "no slack bus"),
    (lambda c: c["gen"].__setitem__((1, 1), 3000.0), "power", "no synchronous state"),
])
def test_bad_cases_are_refused_in_one_sentence(doctor, field, words):
    bad = {k: np.array(v) for k, v in RING.items()}
    doctor(bad)
    with pytest.raises(InputError, match=words) as e:
        graph, power, generator, _ = grids.case_network(bad, "bad")
        operating_point(graph, power, "bad", inertia=grids.grid_attrs(graph, power, generator, DEFAULTS)[:, 0])
    assert e.value.source == "bad" and e.value.field == field and "\n" not in str(e.value)


def test_a_series_capacitor_bus_is_reduced_to_one_line():
    # 1 - 2 (x 0.6) - 3 (x -0.35): bus 2 carries nothing and its lines add to less than 0
    capacitor = case([(1, 0), (2, 0), (3, 50)], [(1, 2, 0.6), (2, 3, -0.35), (1, 3, 0.5)], [(1, 50)])
    graph, power, _, record = grids.case_network(capacitor, "capacitor")
    assert graph.n_nodes == 2 and record["grid_removed_buses"].tolist() == [2]
    assert _dense(graph)[0, 1] == pytest.approx(1 / 0.25 + 1 / 0.5)  # in series: 1 / (0.6 - 0.35)
    np.testing.assert_allclose(power, [0.5, -0.5])


def test_every_ieee_case_converts_with_its_bus_count():
    pypower_or_skip()
    for number, n in grids.CASES.items():
        graph, power, generator, record = grids.case_network(grids.load_case(number, "case"), "case")
        assert graph.n_nodes == n and graph.weights.min() > 0 and abs(power.sum()) < 1e-9
    assert record["grid_removed_buses"].tolist() == [1201]  # case300's series capacitor


def test_a_case_changed_halves_one_bus_inertia_or_takes_one_line_out():
    """What a fitted network is tested against: the machines as the rule makes them on the whole grid,
    one bus's inertia scaled, or one line gone (both directions) and every machine unchanged."""
    pypower_or_skip()
    scene = small("ieee14")
    p = {**DEFAULTS, **scene.params}
    graph, attrs, _ = scene.graph.network(p, "ieee14")
    halved, changed, record = replace(scene.graph, inertia_factors=((5, 0.5),)).network(p, "ieee14")
    assert changed[5, 0] == attrs[5, 0] / 2 and np.array_equal(np.delete(changed, 5, 0), np.delete(attrs, 5, 0))
    assert halved.equals(graph) and record["grid_inertia_factors"].tolist() == [[5, 0.5]]
    cut, same, record = replace(scene.graph, lines_out=((1, 2),)).network(p, "ieee14")
    assert cut.n_edges == graph.n_edges - 2 and np.array_equal(same, attrs)
    assert record["grid_lines_out"].tolist() == [[1, 2]]
    assert not {(1, 2), (2, 1)} & set(map(tuple, cut.edges().tolist()))
    for change, words in [({"lines_out": ((0, 13),)}, "no line"), ({"lines_out": ((6, 7),)}, "pieces"),
                          ({"inertia_factors": ((14, 0.5),)}, "nodes 0..13"),
                          ({"inertia_factors": ((3, 0.0),)}, "> 0")]:
        with pytest.raises(InputError, match=words):
            replace(scene.graph, **change).network(p, "ieee14")
    traj = generate(replace(scene, graph=replace(scene.graph, lines_out=((1, 2),))), workers=1)
    assert traj.graphs[0].n_edges == graph.n_edges - 2 and traj.attrs["grid_lines_out"].tolist() == [[1, 2]]


def test_without_pypower_an_ieee_scene_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pypower", None)  # as if not installed
    r = CliRunner().invoke(main, ["generate", "ieee14", "-o", str(tmp_path / "t.h5"), "-B", "2", "--workers", "1"])
    assert r.exit_code == 2 and "pip install 'mpnode[grids]'" in r.stderr and not (tmp_path / "t.h5").exists()
    generate(small("grid10"), workers=1)  # the other scenes need nothing of it


def test_a_bad_case_exits_2_and_writes_nothing(tmp_path, monkeypatch):
    bad = {k: np.array(v) for k, v in RING.items()}
    bad["branch"][1, 3] = 0.0
    monkeypatch.setattr(grids, "load_case", lambda number, source: bad)
    r = CliRunner().invoke(main, ["generate", "ieee14", "-o", str(tmp_path / "t.h5"), "-B", "2", "--workers", "1"])
    assert r.exit_code == 2 and "zero reactance" in r.stderr and not (tmp_path / "t.h5").exists()
    assert len([line for line in r.stderr.splitlines() if line.startswith("Error")]) == 1


# ---- the family against the real cases --------------------------------------------------------
def test_the_synthetic_family_covers_the_real_cases():
    pypower_or_skip()
    real = [scene_graphs(small(f"ieee{n}", B=1)) for n in grids.CASES]
    real = grids.joint_ranges([grids.grid_ranges(m.graphs[0], m.node_attrs[0]) for m in real])
    family = []
    for name, _ in SETS["grids10-30"].members:
        made = scene_graphs(small(name, B=100))
        family += [grids.grid_ranges(g, a) for g, a in zip(made.graphs, made.node_attrs)]
    family = grids.joint_ranges(family)
    for quantity, (low, high) in real.items():
        assert family[quantity][0] <= low and high <= family[quantity][1], quantity


# ---- the scenes' trajectories -----------------------------------------------------------------
def grid_energy(x, graph, attrs):
    """sum_i M_i omega_i^2 / 2 - sum_i P_i theta_i - sum_lines B_ij cos(theta_i - theta_j), x (T+1, N, 3): its
    rate along the swing equation is -sum_i D_i omega_i^2 (theta unwrapped in time; sum P = 0 leaves it
    blind to a common turn)."""
    theta = np.unwrap(np.arctan2(x[..., 1], x[..., 0]), axis=0)
    r, s = graph.edges().T
    lines = 0.5 * (graph.weights * np.cos(theta[:, r] - theta[:, s])).sum(axis=-1)  # each line listed twice
    return 0.5 * (attrs[:, 0] * x[..., 2] ** 2).sum(axis=-1) - (attrs[:, 2] * theta).sum(axis=-1) - lines


def test_a_trajectory_starts_disturbed_and_its_energy_only_falls():
    t = generate(small("grid20", B=6, T=100), workers=1)
    for b in range(6):
        x0, graph, attrs = t.x[b, 0], t.graphs[b], t.node_attrs[b]
        np.testing.assert_allclose(x0[:, 0] ** 2 + x0[:, 1] ** 2, 1.0, atol=1e-15)
        assert 1 <= np.count_nonzero(x0[:, 2]) <= DEFAULTS["kick_buses"]
        assert np.abs(x0[:, 2]).max() <= DEFAULTS["kick_speed"]
        rest = operating_point(graph, attrs[:, 2], inertia=attrs[:, 0])
        e = grid_energy(t.x[b], graph, attrs) - grid_energy(state(rest, 0 * rest).reshape(1, -1, 3), graph, attrs)
        assert np.all(np.diff(e) < 1e-9 * e[0]) and e[-1] < 0.05 * e[0]  # damped over its 5 s
        np.testing.assert_allclose(np.sum(t.x[b, :, :, :2] ** 2, axis=-1), 1.0, atol=1e-6)  # on the circle


def test_the_disturbance_is_drawn_from_the_trajectory_generator_alone():
    graph, attrs = synthetic(12, seed=5)
    draw = lambda seed: disturbed(np.random.default_rng(seed), SWING, 12, graph=graph,  # noqa: E731
                                  node_attrs=attrs, params=DEFAULTS)
    np.testing.assert_array_equal(draw(1), draw(1))
    assert not np.allclose(draw(1), draw(2))


@pytest.mark.parametrize("name", ["grid10", "ieee14"])
def test_simulate_starts_from_the_states_and_grids_generate_draws(name):
    if name.startswith("ieee"):
        pypower_or_skip()
    scene = small(name, B=3, T=2)
    t = generate(scene, workers=2)
    x0, graphs, gi = initial_states(scene)  # what `mpnode simulate` starts from
    np.testing.assert_array_equal(x0, t.x[:, 0])
    assert all(graphs[gi[b]].equals(t.graph_of(b)) for b in range(3))


@pytest.mark.parametrize("name", ["grid10", "ieee14"])
def test_reference_trajectories_agree_with_a_tighter_solve(name):
    if name.startswith("ieee"):
        pypower_or_skip()
    t = generate(small(name, B=2, T=100), workers=1)
    for b in range(2):
        x = integrate(trajectory_rhs(t, b), t.x[b, 0], t.horizon, t.dt, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(x, t.x[b], rtol=0, atol=1e-6)


def test_a_scene_file_puts_the_family_on_its_own_graph(tmp_path):
    path = tmp_path / "grid.toml"
    path.write_text('system = "swing"\ninitial = "disturbed"\ntrajectories = 3\nhorizon = 5\n[params]\nb_max = 10\n'
                    '[graph]\nbuilder = "power_grid"\nnodes = 15\nseed = 4\n')
    t = generate(read_scene(path), workers=1)
    assert len({tuple(g.indices) for g in t.graphs}) == 1 and len({tuple(g.weights) for g in t.graphs}) == 3
    assert t.attrs["graph_calls"] == ["data_gen.graphs.power_grid_graph(n=15, seed=4)"]


# ---- the command line -------------------------------------------------------------------------
def cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_cli_generates_the_scene_set(tmp_path):
    r = cli("generate", "grids10-30", "-o", f"{tmp_path}/", "-B", 2, "-T", 5, "--workers", 1)
    assert r.exit_code == 0, r.output
    for name, n in (("grid10", 10), ("grid20", 20), ("grid30", 30)):
        t = read_trajectories(tmp_path / f"{name}.h5")
        assert t.x.shape == (2, 6, n, 3) and t.node_attrs.shape == (2, n, 3) and len(t.graphs) == 2
        assert t.attr_names == list(SWING.attr_names) and all(g.weighted for g in t.graphs)


def test_cli_generates_ieee14(tmp_path):
    pypower_or_skip()
    out = tmp_path / "ieee14.h5"
    r = cli("generate", "ieee14", "-o", out, "-B", 3, "-T", 5, "--workers", 1)
    assert r.exit_code == 0, r.output
    t = read_trajectories(out)
    assert t.x.shape == (3, 6, 14, 3) and len(t.graphs) == 1 and t.graphs[0].n_edges == 40
    assert t.attrs["grid_case"] == "case14" and t.attrs["grid_bus_numbers"].tolist() == list(range(1, 15))
    with h5py.File(out, "r") as f:
        assert int(f.attrs["format_version"]) == 3 and f["node_attrs"].shape == (14, 3)  # one grid for all


def test_recipe_auto_learns_a_grid_on_windows_first_and_the_flag_wins(tmp_path):
    assert cli("generate", "grid10", "-o", tmp_path / "g.h5", "-B", 4, "-T", 25, "--workers", 1).exit_code == 0
    for name, flags, window in (("auto", (), 10), ("full", ("--curriculum", "full"), 25)):
        out = tmp_path / f"{name}.h5"
        r = cli("train", tmp_path / "g.h5", "-o", out, "--epochs", 1, "--hidden", 8, *flags)
        assert r.exit_code == 0, r.output
        assert ("curriculum (10, 20)" in r.output) == (name == "auto")
        log = [json.loads(line) for line in (tmp_path / f"{name}.h5.log.jsonl").read_text().splitlines()]
        assert [e["window"] for e in log if e["epoch"] == 1] == [window]
