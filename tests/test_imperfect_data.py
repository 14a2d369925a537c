"""Data as they come: observation times of their own, values not observed, noise and states nobody
measured -- the format (version 2), the engine's per-trajectory time grid and its exact gradient,
the initial-state encoder, training and evaluation on such data, and `mpnode generate`'s
degradations."""
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from doc_snippets import fenced_blocks, run_python, run_shell
from engine_helpers import make_graph, problem, spec_

from cli.main import main
from mpnode import InputError, engine, read_trajectories, write_trajectories
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import layouts, numpy_path
from mpnode.engine.schedule import time_grid
from mpnode.model import Model, batch_graph
from mpnode.training import losses
from mpnode.training.batches import Batch

RING = [(0, 1), (1, 2), (2, 0)]


def jittered_intervals(rng, T, n_traj, n_nodes, dt):
    """(T, M) intervals per node: each trajectory its own, one gap of 3.5 dt (several RK4 steps)
    and the last trajectory ending early (intervals 0)."""
    iv = dt * rng.uniform(0.3, 1.6, size=(T, n_traj))
    iv[T // 2, 0] = 3.5 * dt
    iv[T - 2:, -1] = 0.0
    return np.repeat(iv, n_nodes, axis=1)


# ---- the engine -------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["mpnode", "l2s", "node"])
def test_a_rollout_at_each_trajectorys_own_times_matches_the_numpy_reference(driver, kind):
    rng = np.random.default_rng(3)
    g = make_graph(rng, 6)
    batch = block_diagonal([g] * 4)
    kw = dict(kind=kind, message_dim=3 if kind == "mpnode" else 0, substeps=2)
    spec = spec_(**kw, n_nodes=6) if kind == "node" else spec_(**kw)
    T = 6
    theta, x0, u = problem(spec, batch, T, seed=5)
    iv = jittered_intervals(rng, T, 4, 6, spec.dt)
    got = engine.forward(spec, theta, x0, batch, u, T, intervals=iv)
    want = numpy_path.rollout(spec, theta, x0, batch, u, T, intervals=iv)
    np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11)
    np.testing.assert_array_equal(got[-2:, -6:], np.broadcast_to(got[-3, -6:], (2, 6, spec.state_dim)))  # ended


@pytest.mark.parametrize("kind", ["mpnode", "l2s", "node"])
def test_the_controls_gradient_at_each_trajectorys_own_times_is_exact(driver, kind):
    """vjp(gx, controls=True) through irregular intervals (a gap of several RK4 steps, a
    trajectory that has ended: its controls after the end get no gradient) against central
    finite differences in float64."""
    rng = np.random.default_rng(4)
    batch = block_diagonal([Graph.from_edges(3, RING)] * 2)
    kw = dict(kind=kind, message_dim=2 if kind == "mpnode" else 0, control_dim=2, substeps=2)
    spec = spec_(**kw, n_nodes=3) if kind == "node" else spec_(**kw)
    T = 5
    theta, x0, u = problem(spec, batch, T, seed=6)
    iv = jittered_intervals(rng, T, 2, 3, spec.dt)
    x, vjp = engine.forward_with_vjp(spec, theta, x0, batch, u, T, intervals=iv)
    g = rng.standard_normal(x.shape)
    gu = vjp(g, controls=True)[2]
    assert not np.any(gu[T - 2:, 3:])  # the second trajectory ended: its last controls do nothing
    eps = 1e-5
    for _ in range(3):
        d = rng.standard_normal(u.shape)
        d /= np.linalg.norm(d)
        plus = np.sum(g * engine.forward(spec, theta, x0, batch, u + eps * d, T, intervals=iv))
        minus = np.sum(g * engine.forward(spec, theta, x0, batch, u - eps * d, T, intervals=iv))
        fd = (plus - minus) / (2 * eps)
        assert abs(fd - np.sum(gu * d)) < 1e-6 * abs(fd), (fd, np.sum(gu * d))


def test_intervals_of_one_dt_are_the_regular_rollout_bit_for_bit():
    rng = np.random.default_rng(1)
    g = make_graph(rng, 7)
    spec = spec_(substeps=3)
    theta, x0, u = problem(spec, g, 5, seed=2, dtype=np.float32)
    regular = engine.forward(spec, theta, x0, g, u, 5)
    same = engine.forward(spec, theta, x0, g, u, 5, intervals=np.full((5, 7), spec.dt))
    np.testing.assert_array_equal(regular, same)


def test_the_time_grid_keeps_every_step_within_the_models_and_refuses_huge_gaps():
    spec = spec_(substeps=2, dt=0.1)
    iv = np.array([[0.1, 0.05, 0.0], [0.35, 0.1, 0.2]])
    nsub, h = time_grid(spec, 2, 3, np.float64, iv)
    assert list(nsub) == [2, 7] and np.all(h <= 0.05 + 1e-15)
    np.testing.assert_allclose(h * nsub[:, None], iv)
    with pytest.raises(ValueError, match="more than 1000"):
        time_grid(spec, 1, 1, np.float64, np.array([[60.0]]))


def test_the_gradient_with_times_missing_values_and_an_encoder_is_exact():
    """The discrete adjoint through irregular intervals (one needing several substeps), a loss on
    the observed entries only, a hidden dimension and the initial-state encoder, against central
    finite differences in float64."""
    rng = np.random.default_rng(7)
    spec = spec_(control_dim=1, substeps=1, encoder_window=3)
    g = block_diagonal([Graph.from_edges(3, RING)] * 2)
    T, M = 5, 6
    theta = rng.uniform(-0.6, 0.6, layouts.n_params(spec))
    x = rng.standard_normal((T + 1, M, spec.state_dim))
    x[..., 1] = np.nan  # a dimension nobody measured
    x[rng.random(x.shape) < 0.2] = np.nan
    x[0, :, 0] = rng.standard_normal(M)
    u = rng.standard_normal((T, M, 1))
    iv = jittered_intervals(rng, T, 2, 3, spec.dt)
    batch = Batch(x, u, g, iv)
    visible = np.repeat([2, 3], 3)
    value, grad = losses.batch_value_and_grad(spec, theta, batch, "mse", visible)
    picks = np.concatenate([rng.choice(theta.size - 200, 12, replace=False), theta.size - 1 - np.arange(8)])
    eps = 1e-6
    for i in picks:
        plus, minus = theta.copy(), theta.copy()
        plus[i] += eps
        minus[i] -= eps
        fd = (losses.batch_value_and_grad(spec, plus, batch, "mse", visible)[0]
              - losses.batch_value_and_grad(spec, minus, batch, "mse", visible)[0]) / (2 * eps)
        assert abs(grad[i] - fd) <= 1e-6 * max(1.0, abs(fd)), (i, grad[i], fd)
    assert np.any(grad[-8:] != 0)  # the encoder's weights learn


# ---- the format ---------------------------------------------------------------------------------
def test_times_missing_values_and_different_lengths_round_trip_as_version_2(tmp_path):
    rng = np.random.default_rng(0)
    x = [rng.standard_normal((6, 3, 2)), rng.standard_normal((4, 3, 2))]
    x[0][2, 1, 0] = np.nan
    t = [np.cumsum(rng.uniform(0.05, 0.2, 6)), np.array([0.0, 0.1, 0.25, 0.3])]
    write_trajectories(tmp_path / "a.h5", x=x, t=t, graph=RING, system="s")
    back = read_trajectories(tmp_path / "a.h5")
    with h5py.File(tmp_path / "a.h5") as f:
        assert f.attrs["format_version"] == 2
    assert list(back.lengths) == [6, 4] and np.isnan(back.t[1, 4:]).all()
    np.testing.assert_array_equal(back.x[0], x[0])
    assert back.dt == pytest.approx(np.median(np.concatenate([np.diff(t[0]), np.diff(t[1])])))
    write_trajectories(tmp_path / "b.h5", x=np.zeros((2, 3, 3, 1)), graph=RING, dt=0.1, system="s")
    with h5py.File(tmp_path / "b.h5") as f:
        assert f.attrs["format_version"] == 1 and "t" not in f  # nothing new needed: every reader reads it


@pytest.mark.parametrize("t, x0, field, phrase", [
    ([0, 0.1, 0.1, 0.3], None, "t", "strictly increasing"),
    ([0, 0.2, 0.1, 0.3], None, "t", "strictly increasing"),
    ([0, np.inf, 0.2, 0.3], None, "t", "finite times"),
    ([0, np.nan, 0.2, 0.3], None, "t", "NaN time before a finite one"),
    ([0, 0.1, 0.2, 200.0], None, "t", "split the trajectory at the gap"),
    ([0, 0.1, 0.2, 0.3], np.nan, "x", "nothing observed at its first time"),
])
def test_a_file_that_breaks_a_rule_of_version_2_is_refused(tmp_path, t, x0, field, phrase):
    x = np.ones((1, 4, 3, 2))
    if x0 is not None:
        x[0, 0] = x0
    with pytest.raises(InputError) as e:
        write_trajectories(tmp_path / "a.h5", x=x, t=np.array(t, dtype=float), graph=RING, dt=0.1, system="s")
    assert e.value.field == field and phrase in str(e.value)
    assert not (tmp_path / "a.h5").exists()


def test_convert_takes_times_and_missing_values_and_inspect_describes_them(tmp_path):
    rng = np.random.default_rng(2)
    x = rng.standard_normal((3, 5, 3, 2))
    x[:, :, :, 1][rng.random((3, 5, 3)) < 0.5] = np.nan
    x[:, 0, :, 1] = 1.0
    t = np.cumsum(rng.uniform(0.05, 0.15, (3, 5)), axis=1)
    np.savez(tmp_path / "a.npz", x=x, t=t, edges=np.array(RING), system="s")
    run = CliRunner().invoke
    res = run(main, ["convert", str(tmp_path / "a.npz"), "-o", str(tmp_path / "a.h5")])
    assert res.exit_code == 0, res.output
    back = read_trajectories(tmp_path / "a.h5")
    np.testing.assert_array_equal(back.t, t)
    res = run(main, ["inspect", str(tmp_path / "a.h5")])
    assert res.exit_code == 0 and "irregular: gaps" in res.output and "per dimension 100%" in res.output


# ---- training and evaluation ---------------------------------------------------------------------
def test_a_model_rolls_out_at_given_times_as_at_regular_ones(fresh):
    m = Model.create(2, message_dim=3, hidden=8, dt=0.1, dtype=np.float64)
    x0 = np.random.default_rng(1).standard_normal((4, 3, 2))
    g = Graph.from_edges(3, RING)
    times = np.broadcast_to(np.arange(6) * 0.1, (4, 6))
    np.testing.assert_allclose(m.rollout(x0, g, times=times), m.rollout(x0, g, steps=5), rtol=1e-12, atol=1e-12)


@pytest.fixture(scope="module")
def degraded(tmp_path_factory):
    """A clean pendulum file, the same trajectories with 5 % noise, and jittered, 20 % missing,
    5 % noise and the velocity hidden."""
    folder = tmp_path_factory.mktemp("degraded")
    run = CliRunner().invoke
    files = {name: str(folder / f"{name}.h5") for name in ("clean", "noisy", "bad")}
    extras = {"clean": [], "noisy": ["--noise", "0.05"],
              "bad": ["--jitter", "0.5", "--drop", "0.2", "--noise", "0.05", "--hide", "1"]}
    for name, out in files.items():
        res = run(main, ["generate", "coupled_pendulum", "-o", out, "-B", "12", "-T", "20", "--seed", "3",
                         *extras[name]])
        assert res.exit_code == 0, res.output
    return files


def test_generate_degrades_and_keeps_the_truth(degraded):
    c, b = read_trajectories(degraded["clean"]), read_trajectories(degraded["bad"])
    np.testing.assert_array_equal(read_trajectories(degraded["noisy"]).truth, c.x)
    assert not b.regular and np.isnan(b.x[..., 1]).all() and b.truth.shape == b.x.shape
    seen = ~np.isnan(b.x[..., 0])
    assert 0.7 < seen.mean() < 0.9  # 20 % dropped
    noise = (b.x[..., 0] - b.truth[..., 0])[seen]
    assert 0.02 < noise.std() / c.x[..., 0].std() < 0.08  # 5 % of the dimension's spread
    on_grid = np.isclose(b.t / c.dt, np.round(b.t / c.dt))  # unjittered observations are the clean states
    np.testing.assert_allclose(b.truth[:, 0], c.x[:, 0])
    assert on_grid[:, 0].all() and not on_grid.all()


def test_training_takes_such_data_as_they_are_and_eval_scores_after_a_warm_up(degraded, tmp_path):
    clean, noisy, bad = degraded["clean"], degraded["noisy"], degraded["bad"]
    run = CliRunner().invoke
    model = str(tmp_path / "m.h5")
    res = run(main, ["train", bad, "-o", model, "--epochs", "3", "--hidden", "8"])
    assert res.exit_code == 0, res.output
    assert "encoder_window 5" in res.output  # the recipe's choice for imperfect data
    m = Model.load(model)
    assert m.spec.encoder_window == 5 and m.attrs["unmeasured_dims"] == [1]
    pred = str(tmp_path / "p.h5")
    res = run(main, ["eval", model, bad, "--warmup", "4", "--predictions", pred, "--reference-sample", "0"])
    assert res.exit_code == 0, res.output
    assert "scored after them" in res.output and "never measured in training: not scored" in res.output
    p, b = read_trajectories(pred), read_trajectories(bad)
    assert p.x.shape == b.x.shape and np.isfinite(p.x).all()
    np.testing.assert_array_equal(p.t, b.t)
    observations = str(tmp_path / "observations.h5")  # the noisy data as a user would have them: no truth
    n = read_trajectories(noisy)
    n.truth = None
    write_trajectories(observations, n)
    scores = {}
    for data, truth in ((noisy, None), (observations, clean), (observations, None)):
        res = run(main, ["eval", model, data, "--json", "--reference-sample", "0"] + (["--truth", truth] if truth else []))
        assert res.exit_code == 0, res.output
        scores[data, truth] = json.loads(res.stdout)["nmse"]  # warnings go to standard error
    assert scores[noisy, None] == scores[observations, clean] != scores[observations, None]


@pytest.mark.slow
def test_the_worked_example_runs_as_written(tmp_path, monkeypatch):
    """docs/data-as-they-come.md in one folder: its python, then its commands (a shorter training)."""
    pytest.importorskip("matplotlib", reason="the example draws a figure: the plot extra is not installed")
    doc = Path(__file__).resolve().parents[1] / "docs" / "data-as-they-come.md"
    blocks = fenced_blocks(doc.read_text())
    assert [lang for lang, _, _ in blocks] == ["python", ""]
    run_python(blocks[0][1], tmp_path, monkeypatch)
    commands = blocks[1][1]
    assert commands.count("--time-limit 5m") == 1
    run_shell(commands.replace("--time-limit 5m", "--epochs 2"), tmp_path)
    assert (tmp_path / "log_eval.png").exists() and read_trajectories(tmp_path / "log_onward.h5").horizon == 400
    log = read_trajectories(tmp_path / "log.h5")
    assert not log.regular and log.unmeasured_dims().tolist() == [1]


def test_the_simulator_warms_up_on_observations_and_stands_at_the_last_one():
    m = Model.create(2, message_dim=3, hidden=8, dt=0.1, dtype=np.float64, encoder_window=3)
    m.params["E2"][:] = 0.1  # an encoder that does something
    g = Graph.from_edges(3, RING)
    rng = np.random.default_rng(4)
    obs = rng.standard_normal((2, 3, 3, 2))
    obs[:, :, :, 1] = np.nan
    times = np.array([[0.0, 0.07, 0.2], [0.0, 0.1, 0.15]])
    from mpnode import Simulator

    sim = Simulator(m, g)
    now = sim.warm_up(obs, times)
    start = m.initial_state(obs, times)
    np.testing.assert_allclose(now, m.rollout(start, g, times=times)[:, -1], rtol=1e-12, atol=1e-12)
    assert np.isfinite(sim.step()).all()


def test_refitting_the_normalisation_keeps_what_a_model_with_an_encoder_computes():
    from mpnode.model.renormalise import renormalised

    rng = np.random.default_rng(9)
    m = Model.create(2, message_dim=3, hidden=8, dt=0.1, dtype=np.float64, encoder_window=3)
    m.theta[:] = rng.uniform(-0.5, 0.5, m.theta.size)
    m.x_mean, m.x_std = np.array([0.3, -1.0]), np.array([2.0, 0.5])
    obs = rng.standard_normal((2, 3, 3, 2))  # complete windows: there the change is exact
    again = renormalised(m, np.array([-0.2, 0.4]), np.array([0.7, 3.0]))
    np.testing.assert_allclose(again.initial_state(obs), m.initial_state(obs), rtol=1e-10, atol=1e-10)
    g = Graph.from_edges(3, RING)
    start = m.initial_state(obs)
    np.testing.assert_allclose(again.rollout(start, g, steps=4), m.rollout(start, g, steps=4), rtol=1e-9, atol=1e-9)


def test_latent_dimensions_are_room_beside_the_data(degraded, tmp_path):
    """--latent-dims K: the model carries K states per node no data measure; its predictions file
    has the data's own dimensions."""
    run = CliRunner().invoke
    model, pred = str(tmp_path / "m.h5"), str(tmp_path / "p.h5")
    res = run(main, ["train", degraded["clean"], "-o", model, "--epochs", "2", "--hidden", "8", "--latent-dims", "2"])
    assert res.exit_code == 0, res.output
    m = Model.load(model)
    assert m.spec.state_dim == 4 and m.latent_dims == 2 and m.spec.encoder_window == 5
    assert list(m.attrs["unmeasured_dims"]) == [2, 3]
    res = run(main, ["eval", model, degraded["clean"], "--warmup", "3", "--predictions", pred, "--reference-sample", "0"])
    assert res.exit_code == 0, res.output
    assert read_trajectories(pred).x.shape == read_trajectories(degraded["clean"]).x.shape


def test_fitting_the_start_through_the_model_recovers_a_state_nobody_measured():
    """Observations made by the model itself from a known start, one dimension hidden: the fit of
    the start through the engine's VJP brings the rollout back onto the observations and finds
    the hidden value it never saw."""
    from mpnode.model.start import fit_initial_state

    rng = np.random.default_rng(11)
    m = Model.create(2, message_dim=2, hidden=16, dt=0.1, dtype=np.float64, seed=3)
    g = Graph.from_edges(3, RING)
    truth = rng.uniform(-1, 1, (4, 3, 2))
    obs = m.rollout(truth, g, steps=7)
    obs[..., 1] = np.nan
    fitted = fit_initial_state(m, obs, batch_graph(g, 4), steps=400)
    filled = m.initial_state(obs)
    assert np.abs(fitted - truth).max() < 0.1 * np.abs(filled - truth).max()


def test_a_gap_too_long_for_the_models_step_is_refused_naming_the_file(tmp_path):
    t = np.array([[0.0, 0.1, 0.2, 50.0]])
    write_trajectories(tmp_path / "gap.h5", x=np.ones((1, 4, 3, 2)), t=t, graph=RING, dt=0.1, system="s")
    Model.create(2, message_dim=2, hidden=4, dt=0.01).save(tmp_path / "m.h5")
    res = CliRunner().invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "gap.h5"), "--reference-sample", "0"])
    assert res.exit_code == 2 and "gap.h5: t: has a gap of 49.8" in res.output and "split the trajectory" in res.output


def test_simulate_continues_a_files_trajectories_from_their_warm_up_as_eval_predicts_them(degraded, tmp_path):
    clean, bad = degraded["clean"], degraded["bad"]
    run = CliRunner().invoke
    model = str(tmp_path / "m.h5")
    assert run(main, ["train", bad, "-o", model, "--epochs", "2", "--hidden", "8"]).exit_code == 0
    pred, sim = str(tmp_path / "p.h5"), str(tmp_path / "s.h5")
    res = run(main, ["eval", model, clean, "--warmup", "4", "--predictions", pred, "--reference-sample", "0"])
    assert res.exit_code == 0, res.output
    res = run(main, ["simulate", model, clean, "-o", sim, "--warmup", "4", "--horizon", "40"])
    assert res.exit_code == 0, res.output
    p, s = read_trajectories(pred), read_trajectories(sim)
    assert s.horizon == 40 and s.attrs["warmup"] == 4
    np.testing.assert_allclose(s.x[:, :21], p.x, rtol=1e-5, atol=1e-6)  # the file's span, then onward
    res = run(main, ["simulate", model, bad, "-o", sim, "--warmup", "4", "-B", "3"])
    assert res.exit_code == 0, res.output
    b = read_trajectories(bad)
    span = np.nanmax(b.t[:3], axis=1) - b.t[:3, 0]
    assert read_trajectories(sim).horizon == int(np.ceil(span.max() / Model.load(model).spec.dt - 1e-9))
    res = run(main, ["simulate", model, "coupled_pendulum", "-o", sim, "--warmup", "4"])
    assert res.exit_code == 2 and "a scene has none" in res.output
