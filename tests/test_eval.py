"""mpnode.evaluation.evaluate and `mpnode eval`: error metrics, blow-ups, predictions, mismatches, reference timing."""
import json
import re

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode import training as train
from mpnode.base.errors import InputError
from mpnode.data import Trajectories, read_trajectories, write_trajectories
from mpnode.evaluation.evaluate import evaluate, predictions_file, subset
from mpnode.evaluation.metrics import blow_up_mask, nmse_per_step
from mpnode.model import Model


@pytest.fixture
def model_made_data(tiny_linear):
    """model_made_data(model, B=6, T=8, seed=0): trajectories the model produces itself (float64),
    from the tiny system's initial states: a perfect model for them."""
    def make(model, B=6, T=8, seed=0):
        traj = tiny_linear(B=B, T=T, seed=seed)
        x = model.rollout(traj.x[:, 0], traj.graphs[0], steps=T).astype(np.float64)
        return Trajectories(x=x, graphs=traj.graphs, dt=model.spec.dt, system="model_made")

    return make


def test_nmse_is_zero_for_the_model_own_trajectories(fresh, model_made_data):
    m = fresh().copy(dtype=np.float64)
    traj = model_made_data(m)
    r = evaluate(m, traj)
    assert r.nmse < 1e-20 and r.nmse_last < 1e-20 and r.first_bad_step is None and r.n_bad == 0
    assert r.nmse_per_step.shape == (9,) and r.node_steps_per_second > 0 and r.rollout_seconds > 0
    assert r.predictions.shape == traj.x.shape


def test_nmse_definition_and_blow_up_detection():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(4, 6, 3, 2)) * np.array([1.0, 10.0])
    pred = truth + 0.1 * np.array([1.0, 10.0])  # error 0.1 std in each dimension... relative to the std
    var = truth.reshape(-1, 2).var(axis=0)
    want = (0.01 * np.array([1.0, 100.0]) / var).mean()
    err = nmse_per_step(pred, truth)
    np.testing.assert_allclose(err, want)
    # a prediction leaving ten times the data's box, or NaN, blows up from that step on
    bad_pred = truth.copy()
    lo, hi = truth[..., 0].min(), truth[..., 0].max()
    bad_pred[2, 3, 1, 0] = hi + 6 * (hi - lo)
    bad_pred[1, 5, 0, 1] = np.nan
    mask = blow_up_mask(bad_pred, truth)
    assert mask[2, 3:].all() and not mask[2, :3].any() and mask[1, 5] and not mask[0].any()
    err = nmse_per_step(bad_pred, truth, mask)
    assert np.all(np.isinf(err[3:])) and np.all(np.isfinite(err[:3]))
    inside = truth.copy()
    inside[2, 3, 1, 0] = hi + 4 * (hi - lo)  # outside the data but inside ten times its range
    assert not blow_up_mask(inside, truth).any()


def test_eval_error_of_a_converged_model_is_small(tiny_linear, fresh):
    # The linear test system is easy; 150 epochs at lr 1e-2 bring the validation loss below 1e-2
    # (the data's own loss scale is ~5).  A normalised MSE of 0.02 means the rollouts explain 98% of
    # the states' variance over the whole horizon; an untrained model scores ~1 (see the assert).
    traj = tiny_linear(B=40)
    r = train.fit(fresh(), [traj], train.TrainConfig(epochs=150, batch_size=32, lr=1e-2, patience=30))
    on_train = evaluate(r.model, subset(traj, r.split[0][0]))
    on_val = evaluate(r.model, subset(traj, r.split[0][1]))
    untrained = evaluate(fresh().copy(), traj)
    assert on_train.nmse < 0.02, on_train.nmse
    assert on_val.nmse < 0.05, on_val.nmse
    assert untrained.nmse > 0.3


def test_mismatched_dimensions_and_dt_are_input_errors(tiny_linear, fresh):
    m = fresh()
    x3 = np.zeros((2, 4, 2, 3))
    wrong_dx = Trajectories(x=x3, graphs=tiny_linear().graphs, dt=0.1, system="x")
    with pytest.raises(InputError, match="state dimensions"):
        evaluate(m, wrong_dx, source="wrong.h5")
    other_dt = tiny_linear(B=3, dt=0.2)
    with pytest.raises(InputError, match="dt"):
        evaluate(m, other_dt)
    r = evaluate(m, other_dt, allow_dt_mismatch=True)
    assert np.isfinite(r.nmse)


def test_prediction_file_keeps_graphs_and_names_the_model(tmp_path, tiny_linear, fresh):
    m = fresh()
    traj = tiny_linear(B=4)
    r = evaluate(m, traj)
    out = tmp_path / "pred.h5"
    write_trajectories(out, predictions_file(r.predictions, traj.graphs, traj.graph_index, traj.dt, traj.system,
                                             "m.h5"))
    back = read_trajectories(out)
    assert back.attrs["predicted_by"] == "m.h5" and back.system == traj.system and back.dt == traj.dt
    assert back.graphs[0].equals(traj.graphs[0])
    np.testing.assert_array_equal(back.x, r.predictions)
    bad = r.predictions.copy()
    bad[1, 2] = np.nan
    from mpnode.base.errors import NumericalError

    with pytest.raises(NumericalError, match="non-finite"):
        predictions_file(bad, traj.graphs, traj.graph_index, traj.dt, traj.system, "m.h5")


def test_cli_eval_text_json_predictions_and_dx_mismatch(tmp_path, tiny_linear, fresh):
    m = fresh()
    m.save(tmp_path / "m.h5")
    write_trajectories(tmp_path / "d.h5", tiny_linear(B=5))
    runner = CliRunner()
    res = runner.invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "d.h5"), "--predictions",
                               str(tmp_path / "p.h5")])
    assert res.exit_code == 0, res.output
    assert "normalised MSE" in res.output and "node-steps/s" in res.output
    assert "reference: the file names no system" in res.output  # tiny_linear is not a reference system
    assert read_trajectories(tmp_path / "p.h5").x.shape == (5, 11, 2, 2)
    res = runner.invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "d.h5"), "--json"])
    assert res.exit_code == 0
    report = json.loads(res.output)
    assert report["trajectories"] == 5 and len(report["nmse_per_step"]) == 11
    # dx mismatch: exit 2, one clear line, no traceback
    Model.create(3, 0, message_dim=3, hidden=8, dt=0.1).save(tmp_path / "m3.h5")
    res = runner.invoke(main, ["eval", str(tmp_path / "m3.h5"), str(tmp_path / "d.h5")])
    assert res.exit_code == 2
    assert "state dimensions" in res.output and "Traceback" not in res.output
    # dt mismatch: exit 2 unless allowed
    write_trajectories(tmp_path / "d2.h5", tiny_linear(B=3, dt=0.2))
    res = runner.invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "d2.h5")])
    assert res.exit_code == 2 and "dt" in res.output
    res = runner.invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "d2.h5"), "--allow-dt-mismatch"])
    assert res.exit_code == 0
    res = runner.invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "missing.h5")])
    assert res.exit_code == 2


def test_cli_eval_times_the_reference_simulator(tmp_path):
    from dataclasses import replace

    from data_gen import generate, load_scene

    traj = generate(replace(load_scene("coupled_pendulum"), trajectories=4, horizon=10), workers=1)
    write_trajectories(tmp_path / "p.h5", traj)
    Model.create(2, 0, message_dim=3, hidden=8, dt=0.05).save(tmp_path / "m.h5")
    res = CliRunner().invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "p.h5"),
                                    "--reference-sample", "3", "--json"])
    assert res.exit_code == 0, res.output
    ref = json.loads(res.output)["reference"]
    assert ref["sample"] == 3 and ref["reference_seconds_per_trajectory"] > 0 and ref["speedup"] > 0
    # like with like: the chosen setting reaches the model's error on the same trajectories, and is the
    # fastest of the settings tried that do; each family is tried cheapest first up to its first that reaches
    assert ref["reached"] and ref["reference_nmse_vs_file"] <= ref["target_nmse"] == ref["learned_nmse"]
    reaching = [t for t in ref["tried"] if t["nmse"] <= ref["target_nmse"]]
    assert ref["reference_seconds_per_trajectory"] == min(t["seconds_per_trajectory"] for t in reaching)
    for family in ("scipy", "rk4"):
        tried = [t for t in ref["tried"] if t["family"] == family]
        assert all(t["nmse"] > ref["target_nmse"] for t in tried[:-1]) and tried[-1]["nmse"] <= ref["target_nmse"]
    res = CliRunner().invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "p.h5"), "--reference-sample", "2"])
    assert "speed against error" in res.output
    assert re.search(r"speed against error: .* the learned model is [0-9.]+x (faster|SLOWER: at this error, "
                     r"integrating the true equations is cheaper)$", res.output, re.M), res.output


def test_the_reference_at_the_files_own_setting_rebuilds_the_file():
    from dataclasses import replace

    from data_gen import generate, load_scene
    from data_gen.reference import reference_timing

    traj = generate(replace(load_scene("coupled_pendulum"), trajectories=3, horizon=10), workers=1)
    ref = reference_timing(traj, 3, 0.0)  # no error is small enough but the file's own
    assert ref["reached"] and ref["reference_nmse_vs_file"] == 0.0
    assert ref["integrator"] == "scipy DOP853 rtol=1e-09 atol=1e-09"
    assert [t["setting"] for t in ref["tried"] if t["family"] == "scipy"][0] == "scipy DOP853 rtol=0.001 atol=0.001"
    assert all(t["nmse"] > 0 for t in ref["tried"] if t["family"] == "rk4")  # RK4 of any step is not exact


@pytest.mark.parametrize("scene", ["grid10", "ieee14", "kuramoto_het10", "spring_pendulums_het4"])
def test_the_reference_runs_networks_whose_nodes_differ_side_by_side_as_one_batch(scene):
    if scene.startswith("ieee"):
        pytest.importorskip("pypower", reason="the IEEE cases need PYPOWER (the grids extra)")
    from dataclasses import replace

    from data_gen import generate, load_scene
    from data_gen.reference import _Sample, rk4_columns
    from data_gen.systems import trajectory_rhs

    traj = generate(replace(load_scene(scene), trajectories=3, horizon=10), workers=1)
    batched = _Sample(traj, 3).rk4(2)  # a graph per trajectory, or one grid's buses: as one network
    for b in range(3):  # as each trajectory alone
        alone = rk4_columns(trajectory_rhs(traj, b), traj.x[b, 0].reshape(-1, 1), traj.horizon, traj.dt, 2)
        np.testing.assert_allclose(batched[b], alone[..., 0].reshape(traj.x.shape[1:]), rtol=1e-12, atol=1e-12)


def test_eval_holds_the_model_against_holding_the_initial_state_per_state_group(tmp_path, tiny_linear, fresh):
    m = fresh()
    traj = tiny_linear(B=5)
    traj.attrs["state_groups"] = ["position", "velocity"]
    r = evaluate(m, traj)
    x = np.asarray(traj.x, dtype=np.float64)
    var = x.reshape(-1, 2).var(axis=0)
    hold = ((x - x[:, :1]) ** 2 / var).mean(axis=(0, 2))  # (T+1, dx)
    np.testing.assert_allclose(r.hold_per_dim, hold)
    np.testing.assert_allclose(r.per_dim.mean(axis=1), r.nmse_per_step)
    assert r.groups == {"position": [0], "velocity": [1]}
    summary = r.summary()
    np.testing.assert_allclose(summary["hold"]["nmse"], hold[1:].mean())
    assert summary["groups"]["velocity"]["nmse"] == pytest.approx(r.per_dim[1:, 1].mean())
    assert summary["groups"]["position"]["hold_nmse"] == pytest.approx(hold[1:, 0].mean())
    # the first step where the model is not below holding, overall and per group
    worse = np.flatnonzero(r.per_dim[1:, 1] >= hold[1:, 1])
    assert summary["groups"]["velocity"]["first_step_not_below_hold"] == (worse[0] + 1 if len(worse) else None)
    # a model that reproduces the data is below holding at every step
    exact = evaluate(m, Trajectories(x=r.predictions.astype(np.float64), graphs=traj.graphs, dt=traj.dt, system="x",
                                     attrs={"state_groups": ["a", "b"]}))
    assert exact.summary()["hold"]["first_step_not_below"] is None
    assert all(g["first_step_not_below_hold"] is None for g in exact.summary()["groups"].values())
    # the command line shows both, in text and in JSON; a file without groups shows none
    m.save(tmp_path / "m.h5")
    write_trajectories(tmp_path / "d.h5", traj)
    res = CliRunner().invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "d.h5")])
    assert res.exit_code == 0, res.output
    assert "holding the initial state: mean" in res.output and "by state group" in res.output
    assert "    velocity " in res.output and "per step: 1: " in res.output
    res = CliRunner().invoke(main, ["eval", str(tmp_path / "m.h5"), str(tmp_path / "d.h5"), "--json"])
    report = json.loads(res.output)
    assert report["groups"]["position"]["dims"] == [0] and len(report["hold"]["nmse_per_step"]) == 11
    # with a warm-up, every error is scored after it, the groups' and holding's too
    warm = evaluate(m, traj, warmup=3).summary()
    assert warm["groups"]["velocity"]["hold_nmse"] == pytest.approx(hold[3:, 1].mean())
    assert warm["hold"]["first_step_not_below"] in (None, *range(3, 11))
    del traj.attrs["state_groups"]
    assert evaluate(m, traj).summary()["groups"] == {}


def test_state_groups_must_name_every_dimension(tmp_path, tiny_linear):
    traj = tiny_linear(B=2)
    traj.attrs["state_groups"] = ["position"]
    with pytest.raises(InputError, match="state_groups"):
        write_trajectories(tmp_path / "d.h5", traj)
    from mpnode.evaluation.metrics import state_groups

    assert state_groups(["body", "body"], 2) == {}  # one group is the whole state: nothing more to report
    assert state_groups(None, 2) == {}
    traj.attrs["state_groups"] = ["position", "velocity"]
    wider = traj.with_hidden_dims(2)  # a model's latent dimensions form a group of their own
    assert wider.attrs["state_groups"] == ["position", "velocity", "latent", "latent"]
    write_trajectories(tmp_path / "w.h5", wider)
