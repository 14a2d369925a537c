"""Ensembles: one file of K members (format version 5), their mean and calibrated spread, the
coverage of the spread's bands, and `train --ensemble K` / `eval --json` / `--predictions`."""
import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode import Model
from mpnode.base.errors import InputError
from mpnode.data import read_trajectories
from mpnode.evaluation import evaluate
from mpnode.model import Ensemble
from mpnode.model import file as model_file
from mpnode.model.ensemble import coverage, fitted_scale


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture
def ensemble(fresh):
    return Ensemble([fresh(seed=s, hidden=8) for s in range(3)], [1.5, 2.0],
                    attrs={"system": "tiny_linear"}, member_info={"member_seed": np.arange(3)})


def test_file_round_trip_is_version_5_and_keeps_members(tmp_path, ensemble, tiny_linear):
    path = tmp_path / "e.h5"
    ensemble.save(path)
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == model_file.ENSEMBLE_VERSION and f.attrs["ensemble_size"] == 3
        assert f["params/W1"].shape[0] == 3
    back = Model.load(path)
    assert isinstance(back, Ensemble) and back.size == 3
    np.testing.assert_array_equal(back.spread_scale, [1.5, 2.0])
    for a, b in zip(back.members, ensemble.members):
        np.testing.assert_array_equal(a.theta, b.theta)
    traj = tiny_linear(B=4, T=6)
    x0, g = traj.x[:, 0], traj.graphs[0]
    members = np.stack([m.rollout(x0, g, steps=6) for m in ensemble.members]).astype(np.float64)
    mean, spread = back.predict(x0, g, steps=6)
    np.testing.assert_allclose(mean, members.mean(axis=0), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(spread, members.std(axis=0, ddof=1) * [1.5, 2.0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(back.rollout(x0, g, steps=6), members.mean(axis=0), rtol=1e-5, atol=1e-6)


def test_version_and_ensemble_size_must_agree(tmp_path, ensemble):
    path = tmp_path / "e.h5"
    ensemble.save(path)
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 2
    with pytest.raises(InputError, match="format_version.*5 exactly for an ensemble"):
        Model.load(path)
    with h5py.File(path, "r+") as f:  # an older reader knows versions 1 to 4 only: 5 is refused
        f.attrs["format_version"] = 5
        del f["ensemble/spread_scale"]
    with pytest.raises(InputError, match="ensemble/spread_scale"):
        Model.load(path)


def test_fitted_scale_makes_the_90_band_cover_90_percent():
    rng = np.random.default_rng(0)
    std = rng.uniform(0.5, 2.0, (4000, 2))
    truth = rng.normal(0.0, 3.0 * std)  # the members underestimate by 3x
    mean = np.zeros_like(truth)
    assert coverage(truth, mean, std, 90) < 0.5
    scale = fitted_scale(truth, mean, std)
    np.testing.assert_allclose(scale, 3.0, rtol=0.1)
    assert abs(coverage(truth, mean, std * scale, 90) - 0.9) < 0.01
    assert abs(coverage(truth, mean, std * scale, 50) - 0.5) < 0.05


def test_evaluate_reports_coverage_and_spread(ensemble, tiny_linear):
    traj = tiny_linear(B=5, T=8)
    r = evaluate(ensemble, traj, check_stability=False)
    s = r.summary()
    assert 0 <= s["coverage_50"] <= s["coverage_90"] <= 1
    assert np.array(s["spread_per_node"]).shape == (2, 2) and len(s["spread_per_trajectory"]) == 5
    assert r.spread.shape == r.predictions.shape
    inside = np.abs(r.scored[:, 1:] - r.predictions[:, 1:]) <= 1.6448536269514722 * r.spread[:, 1:]
    assert s["coverage_90"] == pytest.approx(inside.mean())
    single = evaluate(ensemble.members[0], traj, check_stability=False).summary()
    assert single["coverage_90"] is None


def test_eval_json_and_predictions_hold_mean_and_spread(tmp_path, ensemble, tiny_file):
    model, data, pred = tmp_path / "e.h5", tiny_file(tmp_path / "d.h5", B=4, T=6), tmp_path / "p.h5"
    ensemble.save(model)
    res = run("eval", model, data, "--json", "--reference-sample", 0, "--predictions", pred)
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)  # one JSON object and nothing else
    assert {"coverage_50", "coverage_90", "spread_per_node"} <= set(report)
    p = read_trajectories(pred)
    assert p.x_std is not None and p.x_std.shape == p.x.shape and np.all(p.x_std >= 0)
    r = evaluate(ensemble, read_trajectories(data), check_stability=False)
    np.testing.assert_allclose(p.x_std, r.spread, rtol=1e-5, atol=1e-7)


def test_train_ensemble_writes_one_calibrated_file(tmp_path, tiny_file):
    data, out = tiny_file(tmp_path / "d.h5", B=16, T=6), tmp_path / "e.h5"
    res = run("train", data, "-o", out, "--ensemble", 2, "--epochs", 2, "--hidden", 4, "--message-dim", 1,
              "--val-split", 0.25)
    assert res.exit_code == 0, res.output
    e = Model.load(out)
    assert isinstance(e, Ensemble) and e.size == 2
    assert list(e.member_info["member_seed"]) == [0, 1]
    assert not np.array_equal(e.members[0].theta, e.members[1].theta)
    assert np.all(e.spread_scale > 0) and not np.all(e.spread_scale == 1)
    res = run("train", data, "-o", tmp_path / "f.h5", "--ensemble", 2, "--resume")
    assert res.exit_code == 2 and "--resume" in res.output
    res = run("finetune", out, data, "-o", tmp_path / "g.h5", "--epochs", 1)  # each member continues its own
    assert res.exit_code == 0, res.output
    g = Model.load(tmp_path / "g.h5")
    assert isinstance(g, Ensemble) and g.size == 2
    assert not np.array_equal(g.members[0].theta, e.members[0].theta)
    res = run("finetune", out, data, "-o", tmp_path / "h.h5", "--ensemble", 3)
    assert res.exit_code == 2 and "ensemble_size" in res.output


def test_simulator_steps_every_member_and_gives_the_spread(ensemble, tiny_linear):
    from mpnode import Simulator

    traj = tiny_linear(B=3, T=5)
    x0, g = traj.x[:, 0], traj.graphs[0]
    mean, spread = ensemble.predict(x0, g, steps=5)
    sim = Simulator(ensemble, g)
    sim.reset(x0)
    for t in range(5):
        x = sim.step()
    np.testing.assert_allclose(x, mean[:, -1], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(sim.spread, spread[:, -1], rtol=1e-4, atol=1e-6)
    assert sim.messages.shape == (3, 3, 2, 3)  # K, B, N, dm


def test_inspect_and_plot_of_an_ensemble(tmp_path, ensemble, tiny_file):
    pytest.importorskip("matplotlib")
    model, data, fig = tmp_path / "e.h5", tiny_file(tmp_path / "d.h5", B=3, T=5), tmp_path / "f.png"
    ensemble.save(model)
    res = run("inspect", model)
    assert res.exit_code == 0 and "3 members" in res.output, res.output
    res = run("eval", model, data, "--reference-sample", 0, "--plot", fig)
    assert res.exit_code == 0 and fig.stat().st_size > 0, res.output
    assert "90% band" in res.output


def test_members_share_the_split_and_a_bootstrap_resamples_only_training(tiny_linear):
    from mpnode.training import TrainConfig
    from mpnode.training.batches import TrainingData, bootstrap_sample

    data = [tiny_linear(B=40, T=4)]
    a = TrainingData(data, TrainConfig(seed=0, split_seed=0, bootstrap=True).check())
    b = TrainingData(data, TrainConfig(seed=1, split_seed=0, bootstrap=True).check())
    (tr, va), = a.split
    np.testing.assert_array_equal(tr, b.split[0][0])  # one validation split for every member
    draws = [bootstrap_sample(tr, seed) for seed in (0, 1)]
    for d in draws:
        assert len(d) == len(tr) and set(d) <= set(tr) and len(set(d)) < len(tr)  # with replacement
        assert not set(d) & set(va)
    assert not np.array_equal(*draws)


def test_one_run_refuses_to_drop_an_ensemble_silently(tmp_path, tiny_file):
    from mpnode.runs import train

    with pytest.raises(InputError, match="ensemble"):
        train([tiny_file(tmp_path / "d.h5", B=8, T=4)], str(tmp_path / "m.h5"), {"ensemble": 3, "epochs": 1})
