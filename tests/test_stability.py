"""Numerical stability on hard cases: --substeps auto (step doubling), "step too large",
the predictable horizon, the horizon curriculum and a SIGKILLed training run."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode.data import Trajectories, read_trajectories, write_trajectories
from mpnode.evaluation.evaluate import evaluate, predictable_horizon
from mpnode.evaluation.stepsize import choose_substeps, doubling_estimate


@pytest.fixture
def fast_model(fresh):
    """fast_model(scale): the tiny test model with its output layer scaled: dx/dt ~ scale, so the
    ODE is fast (stiff for RK4)."""
    def make(scale):
        m = fresh(hidden=16).copy()
        p = m.params
        p["W3"][:] *= scale
        p["b3"][:] = 0.3 * scale
        return m

    return make


@pytest.fixture
def oscillator_model(fresh):
    """oscillator_model(w, damping=0.5, eps=0.05): a model whose field is (nearly) linear:
    dx/dt = A x with A = [[-damping, w], [-w, -damping]] per node.

    Small first-layer weights keep both tanh layers in their linear range; the output layer
    undoes the scale.  For w = 40 and dt = 0.1, h w = 4 is outside RK4's stability interval
    on the imaginary axis (|z| <= 2.83): one substep blows up, two do not.
    """
    def make(w, damping=0.5, eps=0.05):
        m = fresh(hidden=16).copy()
        p = m.params
        for a in p.values():
            a[:] = 0
        A = np.array([[-damping, w], [-w, -damping]])
        p["W1"][:2, :2] = eps * np.eye(2)
        p["W2"][:] = np.eye(16)
        p["W3"][:2, :2] = A.T / eps
        return m

    return make


def fine_rollout(model, x0, graph, steps, substeps=64):
    return model.with_spec(substeps=substeps).copy(dtype=np.float64).rollout(x0, graph, steps=steps)


# ---------------------------------------------------------------------------
# --substeps auto
# ---------------------------------------------------------------------------
def test_auto_substeps_on_a_fast_field_matches_a_fine_reference(tiny_linear, fast_model):
    traj = tiny_linear(B=8, T=20)
    m = fast_model(20)
    s, report = choose_substeps(m, traj.x[:, 0], traj.graphs[0], tol=1e-4, horizon=20)
    assert s > 1 and report["reached"] and report["substeps"] == s
    assert report["estimate"] <= 1e-4 and report["probe_steps"] == 20
    assert set(report["estimates"]) == {str(2 ** j) for j in range(s.bit_length())}  # 1, 2, ..., s tried
    got = m.with_spec(substeps=s).copy(dtype=np.float64).rollout(traj.x[:, 0], traj.graphs[0], steps=20)
    ref = fine_rollout(m, traj.x[:, 0], traj.graphs[0], 20, substeps=128)
    err = np.abs(got - ref).max() / m.x_std.min()
    assert err < 2e-4, err  # the step-doubling estimate is the error, to ~15/16
    # one step coarser misses the tolerance: auto did not over-refine
    coarse = m.with_spec(substeps=s // 2).copy(dtype=np.float64).rollout(traj.x[:, 0], traj.graphs[0], steps=20)
    assert np.abs(coarse - ref).max() > 1e-4


def test_auto_substeps_on_a_slow_field_is_one_and_reports_when_the_tolerance_is_out_of_reach(tiny_linear, fast_model):
    traj = tiny_linear(B=8, T=20)
    s, report = choose_substeps(fast_model(1), traj.x[:, 0], traj.graphs[0], horizon=20)
    assert s == 1 and report["reached"] and list(report["estimates"]) == ["1"]
    s, report = choose_substeps(fast_model(80), traj.x[:, 0], traj.graphs[0], tol=1e-9, max_substeps=8)
    assert s == 8 and not report["reached"] and "no substep count" in report["message"]
    assert doubling_estimate(np.array([np.nan]), np.array([0.0]), np.ones(1)) == np.inf


# ---------------------------------------------------------------------------
# A step too large for stability
# ---------------------------------------------------------------------------
@pytest.fixture
def fast_data(oscillator_model, tiny_linear):
    """fast_data(tmp_path, w=40, T=20): a fast oscillator model saved to m.h5 and its own fine
    (64-substep) trajectories in d.h5."""
    def make(tmp_path, w=40, T=20):
        m = oscillator_model(w)
        base = tiny_linear(B=6, T=T)
        x = fine_rollout(m, base.x[:, 0], base.graphs[0], T)
        traj = Trajectories(x=x, graphs=base.graphs, dt=m.spec.dt, system="fast_model")
        m.save(tmp_path / "m.h5")
        write_trajectories(tmp_path / "d.h5", traj)
        return m, traj

    return make


def test_step_too_large_is_detected_and_more_substeps_fix_it(tmp_path, fast_model, fast_data):
    m, traj = fast_data(tmp_path)
    r = evaluate(m, traj)
    assert r.n_bad > 0 and r.substeps == 1
    st = r.stability
    assert st["step_too_large"] and st["stable_substeps"] > 1 and st["suggested_substeps"] >= st["stable_substeps"]
    assert st["stable_substeps"] == 2  # |R(4i)| = 7.6 > 1, |R(2i)| = 0.75 < 1
    assert f"--substeps {st['suggested_substeps']}" in st["message"] and "h = 0.1" in st["message"]
    fixed = evaluate(m, traj, substeps=st["suggested_substeps"])
    assert fixed.n_bad == 0 and not fixed.stability["step_too_large"] and fixed.nmse < 1e-6
    auto = evaluate(m, traj, substeps="auto")
    assert auto.substeps > 1 and auto.n_bad == 0 and auto.substeps_report["reached"]
    # a blow-up that more substeps do not cure is not blamed on the step
    slow = fast_model(1)
    wild = Trajectories(x=traj.x * 1e-3, graphs=traj.graphs, dt=traj.dt, system="x")  # tiny data box
    r = evaluate(slow, wild)
    assert r.n_bad > 0 and not r.stability["step_too_large"] and "not a step-size problem" in r.stability["message"]


def test_cli_eval_reports_step_too_large_and_auto_substeps(tmp_path, fast_data):
    fast_data(tmp_path)
    runner = CliRunner()
    m, d = str(tmp_path / "m.h5"), str(tmp_path / "d.h5")
    res = runner.invoke(main, ["eval", m, d, "--json"])
    assert res.exit_code == 0, res.output
    rep = json.loads(res.output)
    assert rep["step_too_large"] is True and rep["suggested_substeps"] > 1 and rep["substeps"] == 1
    res = runner.invoke(main, ["eval", m, d])
    assert res.exit_code == 0
    assert "is too large for this model on this data" in res.output and "try --substeps" in res.output
    res = runner.invoke(main, ["eval", m, d, "--substeps", "auto", "--json", "--predictions", str(tmp_path / "p.h5")])
    assert res.exit_code == 0, res.output
    rep = json.loads(res.output)
    assert rep["substeps"] > 1 and rep["substeps_auto"]["reached"] and rep["step_too_large"] is False
    assert rep["blown_up_trajectories"] == 0
    p = read_trajectories(tmp_path / "p.h5")
    assert p.attrs["substeps"] == rep["substeps"] and p.attrs["substeps_auto"] == 1
    assert p.attrs["substeps_tol"] == pytest.approx(1e-4)
    res = runner.invoke(main, ["eval", m, d, "--substeps", "auto"])
    assert f"auto chose {rep['substeps']}" in res.output
    res = runner.invoke(main, ["eval", m, d, "--substeps", "zero"])
    assert res.exit_code == 2 and "auto" in res.output
    assert "step-doubling" in runner.invoke(main, ["eval", "--help"]).output


def test_cli_simulate_auto_substeps_and_step_too_large(tmp_path, oscillator_model):
    oscillator_model(80).with_spec(dt=0.05).save(tmp_path / "m.h5")
    runner = CliRunner()
    args = ["simulate", str(tmp_path / "m.h5"), "coupled_pendulum", "-B", "4", "-T", "40"]
    res = runner.invoke(main, args + ["-o", str(tmp_path / "s.h5")])
    assert "too large" in res.output and "--substeps" in res.output, res.output
    res = runner.invoke(main, args + ["-o", str(tmp_path / "a.h5"), "--substeps", "auto"])
    assert res.exit_code == 0, res.output
    a = read_trajectories(tmp_path / "a.h5")
    assert a.attrs["substeps"] > 1 and a.attrs["substeps_auto"] == 1 and np.all(np.isfinite(a.x))


# ---------------------------------------------------------------------------
# Predictable horizon
# ---------------------------------------------------------------------------
def test_predictable_horizon_on_a_known_divergence():
    rng = np.random.default_rng(0)
    B, T = 6, 16
    truth = rng.normal(size=(B, T + 1, 3, 2)) * np.array([1.0, 5.0])
    std = truth.reshape(-1, 2).std(axis=0)
    t = np.arange(T + 1)
    # trajectory b's normalised MSE is 1e-6 * 4**(t - b): above 0.1 from t = 9 + b, above 1 from t = 10 + b
    amp = np.sqrt(1e-6 * 4.0 ** (t[None, :] - np.arange(B)[:, None]))
    pred = truth + amp[:, :, None, None] * std
    pred[5] = truth[5]  # one trajectory never diverges
    h = predictable_horizon(pred, truth, dt=0.5, thresholds=(0.1, 1.0))
    assert h["0.1"]["first_step"] == [9, 10, 11, 12, 13, None]
    assert h["1"]["first_step"] == [10, 11, 12, 13, 14, None]
    assert h["0.1"]["median_step"] == 11 and h["0.1"]["median_time"] == 5.5  # lower median of 9..13, beyond
    assert h["0.1"]["beyond_horizon"] == 1
    # a blow-up exceeds every threshold at once; most trajectories beyond T: the median is "beyond"
    bad = np.zeros((B, T + 1), bool)
    bad[5, 3:] = True
    h = predictable_horizon(pred, truth, 0.5, (0.1,), bad)
    assert h["0.1"]["first_step"][5] == 3
    h = predictable_horizon(truth, truth, 0.5, (0.1,))
    assert h["0.1"]["median_step"] is None and h["0.1"]["beyond_horizon"] == B


def test_eval_reports_the_predictable_horizon(tmp_path, fast_data):
    m, traj = fast_data(tmp_path, w=20, T=30)
    runner = CliRunner()
    res = runner.invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "d.h5"), "--json"])
    assert res.exit_code == 0, res.output
    hz = json.loads(res.output)["predictable_horizon"]
    want = predictable_horizon(evaluate(m, traj).predictions, traj.x, traj.dt)
    assert hz == json.loads(json.dumps(want))
    assert set(hz) == {"0.1", "1"}
    res = runner.invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "d.h5")])
    assert "predictable horizon" in res.output


# ---------------------------------------------------------------------------
# Horizon curriculum
# ---------------------------------------------------------------------------
def test_window_starts_cover_the_horizon_with_consecutive_windows():
    from mpnode.training.batches import window_starts

    assert list(window_starts(10, 5)) == [0, 5]
    assert list(window_starts(10, 3)) == [0, 3, 6, 7]  # the last window ends at T
    assert list(window_starts(10, 10)) == [0] and list(window_starts(10, 50)) == [0]
    assert list(window_starts(10, 1)) == list(range(10))


def test_window_part_cuts_every_trajectory_into_windows_from_true_states(tiny_linear, fresh, prepared):
    from mpnode import training as train

    traj = tiny_linear(B=6, T=10)
    m = fresh()
    tr, _, _ = prepared(m, [traj], train.TrainConfig(val_split=0.0, noise=0.0))
    part = tr[0]
    w = part.windows(4)  # starts 0, 4, 6
    assert w.x.shape == (5, 6 * 3, 2, 2) and w.n == 18 and w.gi.shape == (18,)
    for b in range(6):
        for j, a in enumerate([0, 4, 6]):
            np.testing.assert_array_equal(w.x[:, b * 3 + j], part.x[a:a + 5, b])
    x, u, g, _ = w.batch(np.array([0, 4, 17]))
    assert x.shape == (5, 3 * 2, 2) and u is None and g.n_nodes == 6
    np.testing.assert_array_equal(x[:, 4:6], part.x[6:11, 5])


CURRICULUM = dict(batch_size=8, lr=1e-2, curriculum=(2, 5), curriculum_epochs=2)


def test_curriculum_trains_logs_window_lengths_and_resumes_bit_for_bit(tmp_path, tiny_linear, fresh):
    from mpnode import training as train
    from mpnode.training import log as train_log
    from mpnode.training import state as train_state

    traj = tiny_linear(B=16, T=10)
    straight = train.fit(fresh(), [traj], train.TrainConfig(epochs=6, **CURRICULUM), tmp_path / "a.h5")
    assert straight.status == "completed" and np.isfinite(straight.best_val_loss)
    log = train_log.read_log(train_log.log_path(tmp_path / "a.h5"))
    assert [r["window"] for r in log[1:]] == [2, 2, 5, 5, 10, 10]
    assert [r["stage"] for r in log[1:]] == [0, 0, 1, 1, 2, 2]
    assert all(r["grad_norm"] > 0 and r["grad_norm_max"] >= r["grad_norm"] for r in log[1:])
    # the curriculum changes training (short windows first) ...
    plain = train.fit(fresh(), [traj], train.TrainConfig(epochs=2, batch_size=8, lr=1e-2))
    assert not np.array_equal(plain.model.theta, train.fit(fresh(), [traj], train.TrainConfig(
        epochs=2, **CURRICULUM)).model.theta)
    # ... and a run stopped mid-curriculum (stage 1, epoch 3) resumes into the same run
    train.fit(fresh(), [traj], train.TrainConfig(epochs=3, **CURRICULUM), tmp_path / "b.h5")
    assert int(train_state.load_state(train.state_path(tmp_path / "b.h5"))["curriculum_stage"]) == 1
    again = train.fit(None, [traj], train.TrainConfig(epochs=6), tmp_path / "b.h5", resume=True)
    assert np.array_equal(again.model.theta, straight.model.theta)
    strip = lambda rs: [{k: v for k, v in r.items() if k not in ("seconds", "elapsed")} for r in rs]  # noqa: E731
    assert strip(train_log.read_log(train_log.log_path(tmp_path / "b.h5"))) == strip(log)


def test_cli_horizon_curriculum_flags(tmp_path, tiny_file):
    data = tiny_file(tmp_path / "d.h5", B=12, T=10)
    out = tmp_path / "m.h5"
    res = CliRunner().invoke(main, ["train", data, "-o", str(out), "--epochs", "3", "--batch-size", "8",
                                    "--horizon-curriculum", "3,full", "--curriculum-epochs", "2"])
    assert res.exit_code == 0, res.output
    assert "curriculum stage 2 of 2" in res.output
    lines = [json.loads(line) for line in open(f"{out}.log.jsonl")]
    assert [r["window"] for r in lines[1:]] == [3, 3, 10]
    for bad in ("5,3", "0,full", "full,5", "x"):
        res = CliRunner().invoke(main, ["train", data, "-o", str(out), "--horizon-curriculum", bad])
        assert res.exit_code == 2 and "horizon-curriculum" in res.output, (bad, res.output)


# ---------------------------------------------------------------------------
# A training run killed with SIGKILL
# ---------------------------------------------------------------------------
def test_sigkilled_training_leaves_a_loadable_model_a_readable_log_and_resumes(tmp_path, tiny_file):
    import os
    import signal
    import subprocess
    import sys
    import time

    from mpnode import training as train
    from mpnode.model import Model
    from mpnode.training import log as train_log
    from mpnode.training import state as train_state

    data = tiny_file(tmp_path / "d.h5", B=64, T=10)
    out = tmp_path / "m.h5"
    args = [data, "-o", str(out), "--batch-size", "4", "--lr", "1e-2", "--hidden", "8"]
    # cwd: from the repository root, `python -c` would import the source mpnode/, which has no cli/
    # (setup.cfg installs cli/ as cli); the installed package is what a user runs.
    proc = subprocess.Popen([sys.executable, "-c", "from cli.main import main; main()", "train", *args,
                             "--epochs", "100000"], stdout=subprocess.DEVNULL,
                            stderr=open(tmp_path / "stderr.txt", "w"), cwd=tmp_path)
    log, state = train_log.log_path(out), train.state_path(out)
    try:
        deadline = time.monotonic() + 120  # generous: a cold numba cache compiles first
        while time.monotonic() < deadline and proc.poll() is None:
            if os.path.exists(state) and os.path.exists(log) and open(log).read().count("\n") >= 5:
                break
            time.sleep(0.02)
        time.sleep(0.05)  # into the next epoch
        assert proc.poll() is None, f"training ended before it could be killed: {(tmp_path / 'stderr.txt').read_text()[-2000:]}"
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    m = Model.load(out)
    assert np.all(np.isfinite(m.theta))
    text = open(log).read()
    assert text.endswith("\n")  # no torn last line

    def strict(c):
        raise ValueError(f"non-standard JSON constant {c}")

    records = [json.loads(line, parse_constant=strict) for line in text.splitlines()]
    assert [r["epoch"] for r in records] == list(range(len(records))) and len(records) >= 5
    done = int(train_state.load_state(state)["epoch"])
    assert 1 <= done <= records[-1]["epoch"]
    res = CliRunner().invoke(main, ["train", *args, "--epochs", str(done + 2), "--resume"])
    assert res.exit_code == 0, res.output
    assert f"resuming at epoch {done}" in res.output
    after = train_log.read_log(log)
    assert [r["epoch"] for r in after] == list(range(done + 3))
    assert np.all(np.isfinite(Model.load(out).theta))


def test_read_log_tolerates_only_a_cut_last_line(tmp_path):
    from mpnode.training import log as train_log

    p = tmp_path / "m.h5.log.jsonl"
    p.write_text('{"epoch": 0}\n{"epoch": 1}\n{"epo')
    assert train_log.read_log(p) == [{"epoch": 0}, {"epoch": 1}]
    p.write_text('{"epoch": 0}\n{"epo\n{"epoch": 2}\n')
    with pytest.raises(ValueError):
        train_log.read_log(p)


def test_learned_lorenz_model_stays_bounded_over_a_long_horizon_and_eval_finds_its_horizon():
    """A model trained on Lorenz3 (T = 50) rolled out to T = 400 stays finite and inside the bound
    the architecture guarantees, and eval reports where it leaves the chaotic truth.

    |dx_i/dt| <= sum_j |W3[j, i]| + |b3[i]| for a tanh MLP (|tanh| <= 1), and an RK4 step moves the
    state by h times a weighted mean of four such values: the normalised state can move at most
    t * bound by time t.  A NaN, an overflow or an unstable integrator would break it.
    """
    import dataclasses

    from data_gen.scenes import load_scene
    from data_gen.simulate import generate
    from mpnode.evaluation.evaluate import evaluate
    from mpnode.model import Model
    from mpnode.training import TrainConfig, fit

    scene = load_scene("lorenz3")
    train = generate(dataclasses.replace(scene, trajectories=32), workers=1)
    longrun = generate(dataclasses.replace(scene, trajectories=8, horizon=400, seed=7), workers=1)
    model = Model.create(3, message_dim=3, hidden=16, dt=scene.dt, self_messages=True, seed=0)
    fit(model, [train], TrainConfig(epochs=40, batch_size=16, lr=3e-3))

    result = evaluate(model, longrun, source="lorenz3-long", check_stability=False)
    pred = result.predictions
    assert pred.shape == longrun.x.shape and np.all(np.isfinite(pred))
    W3, b3 = model.params["W3"], model.params["b3"]
    bound = (np.abs(W3).sum(axis=0) + np.abs(b3))[:3]  # per normalised state dimension
    moved = np.abs(model.normalize_x(pred) - model.normalize_x(pred[:, :1]))  # (B, T+1, N, dx)
    t = np.arange(pred.shape[1])[None, :, None, None] * scene.dt
    assert np.all(moved <= t * bound * (1 + 1e-5) + 1e-5)
    # Chaos: the error crosses the thresholds early, and eval says at which step.
    horizon = result.horizons["0.1"]
    assert horizon["median_step"] is not None and 1 <= horizon["median_step"] < 400
