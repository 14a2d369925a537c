"""Generating trajectory files: reproducibility, re-integration, re-draws and the CLI."""
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.integrate import solve_ivp

from cli.main import main
from data_gen import BUILTIN, SETS, generate, integrate, make_rhs, simulate
from data_gen.initial import uniform
from data_gen.systems import SYSTEMS, lorenz_coupling
from mpnode.base.errors import NumericalError
from mpnode.base.graph import Graph
from mpnode.data import read_trajectories, write_trajectories


def small(name, B=4, T=10, **kw):
    return replace(BUILTIN[name], trajectories=B, horizon=T, **kw)


@pytest.mark.parametrize("name", ["coupled_pendulum", "lorenz3", "gene16_ba_multi", "kuramoto10_ws"])
def test_reintegrating_a_file_reproduces_it(tmp_path, name):
    path = tmp_path / "t.h5"
    write_trajectories(path, generate(small(name), workers=1))
    t = read_trajectories(path)
    a = t.attrs
    assert t.x.dtype == np.float64 and t.system == BUILTIN[name].system
    assert {"seed", "integrator", "rtol", "atol", "scene", "redrawn"} <= set(a)
    assert set(SYSTEMS[t.system].defaults) <= set(a)
    for b in range(t.n_trajectories):
        # only what the file says: its parameters, its graph, its integrator and tolerances
        f = make_rhs(t.system, {**a, **t.params}, t.graph_of(b))
        times = np.arange(t.horizon + 1) * t.dt
        sol = solve_ivp(f, (0, times[-1]), t.x[b, 0].ravel(), method=a["integrator"], t_eval=times,
                        rtol=a["rtol"], atol=a["atol"])
        np.testing.assert_allclose(sol.y.T.reshape(t.x[b].shape), t.x[b], rtol=0, atol=1e-7)


def test_reintegration_at_tighter_tolerance_agrees():
    t = generate(small("lorenz3", B=2, T=50), workers=1)
    f = make_rhs("lorenz", {**t.attrs, **t.params}, t.graphs[0])
    x = integrate(f, t.x[1, 0], t.horizon, t.dt, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(x, t.x[1], rtol=0, atol=1e-5)


def test_drawn_parameters_come_from_the_system_seed():
    t = generate(small("lorenz3", B=1, system_seed=5), workers=1)
    np.testing.assert_array_equal(t.params["H"], lorenz_coupling(3, 0.01, np.random.default_rng(5)))
    k = generate(small("kuramoto10_er", B=1), workers=1)
    np.testing.assert_array_equal(k.params["omega"], np.random.default_rng(0).standard_normal(3))
    # the initial-state seed leaves the physics alone
    assert np.array_equal(generate(small("kuramoto10_er", B=1, seed=9), workers=1).params["omega"],
                          k.params["omega"])


def test_same_seed_same_data_other_seed_other_data():
    a = generate(small("kuramoto10_ba"), workers=1)
    b = generate(small("kuramoto10_ba"), workers=1)
    c = generate(small("kuramoto10_ba", seed=1), workers=1)
    np.testing.assert_array_equal(a.x, b.x)
    assert not np.allclose(a.x[:, 0], c.x[:, 0])


def test_independent_of_workers_and_of_B():
    one = generate(small("gene16_ba_multi", B=12), workers=1)
    two = generate(small("gene16_ba_multi", B=12), workers=2)
    np.testing.assert_array_equal(one.x, two.x)
    np.testing.assert_array_equal(one.graph_index, two.graph_index)
    fewer = generate(small("gene16_ba_multi", B=5), workers=2)
    np.testing.assert_array_equal(fewer.x, one.x[:5])


def test_multi_graph_scene():
    t = generate(small("gene16_ba_multi", B=12), workers=1)
    assert len(t.graphs) == 5
    assert t.graph_index.tolist() == [b % 5 for b in range(12)]
    assert all(not t.graphs[0].equals(g) for g in t.graphs[1:])
    assert t.attrs["graph_seeds"].tolist() == [1, 2, 3, 4, 5]


def test_progress_reports_every_trajectory():
    seen = []
    generate(small("gene16_er", B=9), workers=2, progress=seen.append)
    assert sum(seen) == 9


# ---- re-draws near the pendulum's singularity ---------------------------------------------
def near_singular(rng, system, n_nodes):
    """A pendulum state 1e-7 from theta = pi/2, where the RHS divides by cos(theta)."""
    return np.array([[np.pi / 2 - 1e-7, 0.0], [0.0, 0.0]])


def sometimes_singular(rng, system, n_nodes):
    return near_singular(rng, system, n_nodes) if rng.random() < 0.5 else uniform(rng, system, n_nodes)


def run_pendulum(sampler, B, **kw):
    graph = Graph.complete(2)
    return simulate("coupled_pendulum", SYSTEMS["coupled_pendulum"].defaults, [graph], np.zeros(B, int),
                    sampler, 10, 0.05, 0, **kw)


def test_pendulum_near_singularity_is_refused():
    with pytest.raises(NumericalError, match="trajectory 0 failed for 3 initial states"):
        run_pendulum(near_singular, 2, max_tries=3, workers=1)
    with pytest.raises(NumericalError):
        run_pendulum(near_singular, 4, max_tries=3, workers=2)


def test_pendulum_crossing_the_singularity_stops_the_solver():
    f = make_rhs("coupled_pendulum", SYSTEMS["coupled_pendulum"].defaults, Graph.complete(2))
    with pytest.raises(NumericalError, match="left the region"):
        integrate(f, [[1.4, 3.0], [0.0, 0.0]], 20, 0.05, guard=SYSTEMS["coupled_pendulum"].guard)


def test_redraws_are_counted_and_the_kept_states_are_valid():
    x, redraws = run_pendulum(sometimes_singular, 20, workers=1)
    assert redraws.sum() > 0
    assert np.all(np.abs(np.cos(x[..., 0])) > 1e-6)
    assert np.all(np.abs(x[:, 0, :, 0]) < np.pi / 4)


# ---- the CLI ------------------------------------------------------------------------------
def cli(*args):
    return CliRunner().invoke(main, list(map(str, args)))


def test_cli_generate_ok(tmp_path):
    out = tmp_path / "k.h5"
    r = cli("generate", "kuramoto10_er", "-o", out, "--trajectories", 3, "--horizon", 5, "--dt", 0.1,
            "--seed", 4, "--workers", 1)
    assert r.exit_code == 0, r.output
    t = read_trajectories(out)
    assert t.x.shape == (3, 6, 10, 3) and t.dt == 0.1 and t.attrs["seed"] == 4
    assert t.attrs["scene"] == "kuramoto10_er" and "wrote" in r.stdout


def test_cli_unknown_scene_lists_the_names(tmp_path):
    r = cli("generate", "lorenz4", "-o", tmp_path / "x.h5")
    assert r.exit_code == 2
    assert "lorenz3" in r.stderr and "kuramoto10_ws" in r.stderr
    assert not (tmp_path / "x.h5").exists()


def test_cli_bad_toml_exits_2_without_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('system = "gene"\n[graph]\nbuilder = "edges"\nnodes = 3\nedges = [[0, 1]]\ncolour = 1\n')
    r = cli("generate", bad, "-o", tmp_path / "x.h5")
    assert r.exit_code == 2
    assert "graph.colour" in r.stderr and "Traceback" not in r.output
    assert not (tmp_path / "x.h5").exists()


def test_cli_failing_trajectories_write_nothing(tmp_path):
    # pendulums with gravity reversed fall over towards theta = pi/2 within the horizon
    scene = tmp_path / "upside_down.toml"
    scene.write_text('system = "coupled_pendulum"\ntrajectories = 2\nhorizon = 40\n[params]\ng = -9.81\n'
                     '[graph]\nbuilder = "edges"\nnodes = 2\nedges = [[0, 1]]\n')
    out = tmp_path / "x.h5"
    r = cli("generate", scene, "-o", out, "--workers", 1)
    assert r.exit_code == 3, r.output
    assert "failed for 10 initial states" in r.stderr
    assert not out.exists() and list(tmp_path.iterdir()) == [scene]


def test_cli_bad_option_and_missing_folder(tmp_path):
    assert cli("generate", "lorenz3", "-o", tmp_path / "x.h5", "--dt", 0).exit_code == 2
    r = cli("generate", "lorenz3", "-o", tmp_path / "no" / "x.h5")
    assert r.exit_code == 2 and "does not exist" in r.stderr


def test_cli_excitation_is_for_quadrotor_scenes_only(tmp_path):
    assert "--excitation" in cli("generate", "--help").output
    r = cli("generate", "lorenz3", "-o", tmp_path / "x.h5", "--excitation", 0.5)
    assert r.exit_code == 2 and "excitation" in r.stderr and "no thrusts" in r.stderr
    assert "Traceback" not in r.output and not (tmp_path / "x.h5").exists()
    assert cli("generate", "quad3", "-o", tmp_path / "x.h5", "--excitation", -1).exit_code == 2
    scene = tmp_path / "q.toml"
    scene.write_text('system = "quadrotor_load"\ninitial = "equilibrium"\ntrajectories = 1\nhorizon = 2\n'
                     'dt = 0.1\nintegrator = "LSODA"\nexcitation = 0.3\n[graph]\nbuilder = "complete"\nnodes = 3\n')
    r = cli("generate", scene, "-o", tmp_path / "q.h5", "--workers", 1)
    assert r.exit_code == 0, r.output
    assert read_trajectories(tmp_path / "q.h5").attrs["ctrl_thrust_excitation"] == 0.3


def test_cli_scenes_lists_every_builtin():
    r = cli("scenes")
    assert r.exit_code == 0
    lines = r.stdout.splitlines()
    assert [line.split()[0] for line in lines] == list(BUILTIN) + list(SETS)
    assert all("B=" in line and "dt=" in line for line in lines[:len(BUILTIN)])
    assert all(line.split()[1:3] == ["scene", "set:"] for line in lines[len(BUILTIN):])
    assert any("scene set: quad3 x 500" in line for line in lines[len(BUILTIN):])
