"""mpnode.training and mpnode.training.optim: the training loop, checkpoints, clipping, normalisation."""
import json
import math

import numpy as np
import pytest

from mpnode import training as train
from mpnode.base.graph import Graph
from mpnode.data import Trajectories
from mpnode.model import Model
from mpnode.training import batches
from mpnode.training import log as train_log
from mpnode.training import loop as train_loop
from mpnode.training.optim import Adam, array_slices, clip_gradient

FAST = dict(batch_size=32, lr=1e-2)


def test_training_reduces_validation_loss_tenfold(tiny_linear, fresh):
    traj = tiny_linear()
    r = train.fit(fresh(), [traj], train.TrainConfig(epochs=40, **FAST))
    v0 = r.history[0]["val_loss"]
    assert r.status == "completed" and r.epoch == 40
    assert r.best_val_loss < v0 / 10, (v0, r.best_val_loss)
    # the returned model is the best one: its validation loss is the recorded best
    assert min(h["val_loss"] for h in r.history) == r.best_val_loss


def test_validation_loss_is_the_training_loss_without_noise(tiny_linear, fresh, prepared):
    from mpnode import engine
    from mpnode.training import losses

    m = fresh()
    traj = tiny_linear()
    cfg = train.TrainConfig(noise=0.0)
    tr, va, _ = prepared(m, [traj], cfg)
    x, u, g, _ = tr[0].batch(np.arange(tr[0].n))
    for loss in ("huber", "mse"):
        ref, _, _ = losses.value_and_grad(m.spec, m.theta, x, g, u, loss)
        pred = engine.forward(m.spec, m.theta, x[0], g, u, x.shape[0] - 1)
        assert losses.value(pred, x, loss) == pytest.approx(ref, rel=1e-5)


def test_normalisation_is_fitted_on_the_training_split_only(tiny_linear, fresh, prepared):
    traj = tiny_linear(B=20, offset=0.0)
    traj.x[:, :, :, 0] += np.arange(20)[:, None, None]  # every trajectory has its own level
    m = fresh()
    cfg = train.TrainConfig(val_split=0.3, seed=3)
    _, _, split = prepared(m, [traj], cfg)
    tr, va = split[0]
    assert len(va) == 6 and len(tr) == 14 and not set(tr) & set(va)
    want = traj.x[tr].reshape(-1, 2)
    np.testing.assert_allclose(m.x_mean, want.mean(axis=0))
    np.testing.assert_allclose(m.x_std, want.std(axis=0))
    assert not np.allclose(m.x_mean, traj.x.reshape(-1, 2).mean(axis=0))
    # the split depends on the seed only
    assert np.array_equal(batches.split_indices(20, 0.3, 3)[1], va)
    assert not np.array_equal(batches.split_indices(20, 0.3, 4)[1], va)


def test_finetune_starts_from_exactly_the_given_weights(tmp_path, tiny_linear, fresh, prepared):
    src = fresh(seed=5)
    src.x_mean, src.x_std = np.array([0.1, -0.2]), np.array([0.7, 0.9])
    out = tmp_path / "ft.h5"
    r = train.fit(src, [tiny_linear()], train.TrainConfig(epochs=0, norm="keep"), out)
    saved = Model.load(out)
    assert np.array_equal(saved.theta, src.theta)
    assert np.array_equal(saved.x_mean, src.x_mean) and np.array_equal(saved.x_std, src.x_std)
    # with epochs, epoch 0 is evaluated at the source weights and the source is not modified
    before = src.theta.copy()
    r = train.fit(src, [tiny_linear()], train.TrainConfig(epochs=2, norm="keep", **FAST))
    assert np.array_equal(src.theta, before)
    m0 = src.copy()
    _, va, _ = prepared(m0, [tiny_linear()], train.TrainConfig(norm="keep"))
    assert r.history[0]["val_loss"] == pytest.approx(train_loop.Validator(va, "huber")(m0.spec, m0.theta)[0], rel=1e-12)


def test_refit_finetune_starts_from_the_same_predictions_on_the_new_constants(tmp_path, tiny_linear, fresh, prepared):
    """norm "refit": the constants become the new training split's, the weights change, and
    the saved model (epochs 0) predicts what the source did (float64)."""
    src = fresh(seed=5).copy(np.float64)
    src.x_mean, src.x_std = np.array([0.1, -0.2]), np.array([0.7, 0.9])
    traj = tiny_linear()
    out = tmp_path / "ft.h5"
    train.fit(src, [traj], train.TrainConfig(epochs=0, norm="refit"), out)
    saved = Model.load(out)
    fitted = prepared(fresh(seed=5), [traj], train.TrainConfig(norm="fit"))[2]
    want_mean, want_std = batches.fit_normalization([np.asarray(traj.x)[fitted[0][0]]])
    np.testing.assert_allclose(saved.x_std, want_std)
    np.testing.assert_allclose(saved.x_mean, want_mean)
    assert not np.allclose(saved.theta, src.theta)
    x0 = np.asarray(traj.x)[:, 0]
    np.testing.assert_allclose(saved.rollout(x0, traj.graphs[0], steps=5), src.rollout(x0, traj.graphs[0], steps=5),
                               rtol=1e-10, atol=1e-10)


def test_saved_model_reloads_bit_for_bit_and_rolls_out_identically(tmp_path, tiny_linear, fresh):
    traj = tiny_linear()
    out = tmp_path / "m.h5"
    r = train.fit(fresh(), [traj], train.TrainConfig(epochs=3, **FAST), out)
    saved = Model.load(out)
    assert saved.theta.dtype == r.model.theta.dtype
    assert np.array_equal(saved.theta, r.model.theta)
    assert np.array_equal(saved.x_mean, r.model.x_mean) and np.array_equal(saved.x_std, r.model.x_std)
    a = saved.rollout(traj.x[:5, 0], traj.graphs[0], steps=10)
    b = r.model.rollout(traj.x[:5, 0], traj.graphs[0], steps=10)
    assert np.array_equal(a, b)
    assert saved.attrs["epoch"] == r.best_epoch


def _strip(history):
    return [{k: v for k, v in h.items() if k not in ("seconds", "elapsed")} for h in history]


def test_resume_continues_the_same_run(tmp_path, tiny_linear, fresh):
    traj = tiny_linear()
    cfg = dict(batch_size=8, lr=1e-2, patience=2)  # several batches per epoch, lr cuts happen
    straight = train.fit(fresh(), [traj], train.TrainConfig(epochs=10, **cfg), tmp_path / "a.h5")
    first = train.fit(fresh(), [traj], train.TrainConfig(epochs=5, **cfg), tmp_path / "b.h5")
    assert first.epoch == 5
    # resume takes its settings from the checkpoint; only epochs/time_limit come from the call
    second = train.fit(None, [traj], train.TrainConfig(epochs=10, lr=123.0), tmp_path / "b.h5", resume=True)
    assert second.epoch == 10 and second.lr == straight.lr
    assert np.array_equal(second.model.theta, straight.model.theta)
    assert second.best_epoch == straight.best_epoch
    a, b = Model.load(tmp_path / "a.h5"), Model.load(tmp_path / "b.h5")
    assert np.array_equal(a.theta, b.theta)
    logs = [[json.loads(line) for line in open(str(tmp_path / f) + ".log.jsonl")] for f in ("a.h5", "b.h5")]
    assert _strip(logs[0]) == _strip(logs[1])
    assert [h["epoch"] for h in logs[1]] == list(range(11))


def test_the_logged_validation_nmse_is_what_eval_reports_on_the_validation_split(tmp_path, tiny_linear, fresh):
    from mpnode.evaluation.evaluate import evaluate, subset

    traj = tiny_linear(B=30)
    r = train.fit(fresh(), [traj], train.TrainConfig(epochs=3, **FAST), tmp_path / "m.h5")
    best = r.history[r.best_epoch]
    got = evaluate(r.model, subset(traj, r.split[0][1]), check_stability=False).nmse
    assert best["val_nmse"] == pytest.approx(got, rel=1e-4)  # float32 rollouts, float64 sums


def test_resume_refuses_other_data(tmp_path, tiny_linear, fresh):
    from mpnode.base.errors import InputError

    train.fit(fresh(), [tiny_linear()], train.TrainConfig(epochs=1, **FAST), tmp_path / "m.h5")
    with pytest.raises(InputError, match="other training data"):
        train.fit(None, [tiny_linear(seed=1)], train.TrainConfig(epochs=2), tmp_path / "m.h5", resume=True)


def test_huge_learning_rate_stops_with_a_message_and_a_finite_model(tmp_path, tiny_linear, fresh):
    out = tmp_path / "m.h5"
    messages = []
    r = train.fit(fresh(), [tiny_linear()], train.TrainConfig(epochs=50, batch_size=8, lr=1e3), out,
                  notify=messages.append)
    assert r.status == "diverged" and r.epoch < 50
    assert "diverged" in r.message and "--lr" in r.message
    assert any("learning rate halved" in m for m in messages)
    saved = Model.load(out)  # the reader refuses NaN/inf
    assert np.all(np.isfinite(saved.theta))
    assert np.array_equal(saved.theta, r.model.theta)


def test_non_finite_gradient_is_skipped_and_halves_the_learning_rate(monkeypatch, tiny_linear, fresh):
    from mpnode.training import losses

    real = losses.value_and_grad
    calls = {"n": 0}

    def flaky(*a, **k):
        calls["n"] += 1
        loss, g, gx = real(*a, **k)
        if calls["n"] == 3:
            g = g.copy()
            g[0] = np.nan
        return loss, g, gx

    monkeypatch.setattr(losses, "value_and_grad", flaky)
    msgs = []
    r = train.fit(fresh(), [tiny_linear()], train.TrainConfig(epochs=2, batch_size=8, lr=1e-2), notify=msgs.append)
    assert r.status == "completed"
    assert sum(h["skipped_steps"] for h in r.history[1:]) == 1
    assert r.history[-1]["lr"] == pytest.approx(5e-3)
    assert any("gradient became non-finite" in m for m in msgs)
    assert np.all(np.isfinite(r.model.theta))


def test_clipping_per_array_and_global():
    shapes = {"a": (3,), "b": (2, 2)}
    sl = array_slices(shapes)
    g = np.array([30.0, 40.0, 0.0, 0.1, 0.2, 0.2, 0.0])  # |a| = 50, |b| = 0.3
    per = g.copy()
    norm = clip_gradient(per, 5.0, sl, "per-array")
    assert norm == pytest.approx(np.linalg.norm(g))
    assert np.linalg.norm(per[sl[0]]) == pytest.approx(5.0)
    np.testing.assert_allclose(per[sl[0]], g[sl[0]] / 10)
    assert np.array_equal(per[sl[1]], g[sl[1]])  # below the threshold: untouched
    glob = g.copy()
    clip_gradient(glob, 5.0, sl, "global")
    assert np.linalg.norm(glob) == pytest.approx(5.0)
    np.testing.assert_allclose(glob, g * 5.0 / np.linalg.norm(g))
    off = g.copy()
    clip_gradient(off, 0, sl, "per-array")
    assert np.array_equal(off, g)


def test_clip_mode_changes_training(tmp_path, tiny_linear, fresh):
    traj = tiny_linear()
    a = train.fit(fresh(), [traj], train.TrainConfig(epochs=2, clip=0.5, clip_mode="per-array", **FAST))
    b = train.fit(fresh(), [traj], train.TrainConfig(epochs=2, clip=0.5, clip_mode="global", **FAST))
    assert not np.array_equal(a.model.theta, b.model.theta)


def test_adam_matches_the_textbook_update():
    opt = Adam(3, lr=0.1)
    g = np.array([1.0, -2.0, 0.5])
    step = opt.update(g).copy()
    np.testing.assert_allclose(step, 0.1 * np.sign(g), rtol=1e-6)  # first step: lr * g / |g|
    step2 = opt.update(g).copy()
    m = 0.9 * 0.1 * g + 0.1 * g
    v = 0.999 * 0.001 * g * g + 0.001 * g * g
    np.testing.assert_allclose(step2, 0.1 * (m / (1 - 0.81)) / (np.sqrt(v / (1 - 0.999**2)) + 1e-8))


def test_training_log_is_valid_json_lines(tmp_path, tiny_linear, fresh):
    out = tmp_path / "m.h5"
    train.fit(fresh(), [tiny_linear()], train.TrainConfig(epochs=3, **FAST), out)

    def strict(c):
        raise ValueError(f"non-standard JSON constant {c}")

    lines = open(train_log.log_path(out)).read().splitlines()
    records = [json.loads(line, parse_constant=strict) for line in lines]
    assert [r["epoch"] for r in records] == [0, 1, 2, 3]
    for r in records[1:]:
        assert {"train_loss", "val_loss", "grad_norm", "lr", "seconds"} <= set(r)
        assert math.isfinite(r["train_loss"]) and r["grad_norm"] > 0


def test_epoch_batches_cover_every_trajectory_once_and_mix_files(tiny_linear, fresh, prepared):
    m = fresh()
    a, b = tiny_linear(B=30), tiny_linear(B=12, seed=1)
    tr, _, _ = prepared(m, [a, b], train.TrainConfig(val_split=0.25))
    epoch = batches.epoch_batches(tr, 8, seed=0, epoch=1)
    for p in (0, 1):
        got = np.sort(np.concatenate([s for q, s in epoch if q == p]))
        assert np.array_equal(got, np.arange(tr[p].n))
    assert all(len(s) <= 8 for _, s in epoch)
    assert [q for q, _ in epoch] != sorted(q for q, _ in epoch) or len(set(q for q, _ in epoch)) == 1
    again = batches.epoch_batches(tr, 8, seed=0, epoch=1)
    assert all(p == q and np.array_equal(s, t) for (p, s), (q, t) in zip(epoch, again))


def test_files_with_different_graphs_and_node_counts_train_together(tiny_linear, fresh):
    a = tiny_linear(B=16)
    # a 3-node chain of the same per-node system (not physical, but the same dx/du/dt)
    x3 = np.concatenate([a.x, a.x[:, :, :1]], axis=2)
    b = Trajectories(x=x3, graphs=[Graph.from_edges(3, [(0, 1), (1, 2)])], dt=a.dt, system="tiny_linear")
    r = train.fit(fresh(), [a, b], train.TrainConfig(epochs=2, **FAST))
    assert r.status == "completed" and math.isfinite(r.best_val_loss)


def test_incompatible_files_are_refused(tiny_linear, fresh):
    from mpnode.base.errors import InputError

    a = tiny_linear()
    b = tiny_linear(dt=0.2)
    with pytest.raises(InputError, match="dt"):
        train.fit(fresh(), [a, b], train.TrainConfig(epochs=1), sources=["a.h5", "b.h5"])
    with pytest.raises(InputError, match="state dimensions"):
        train.fit(Model.create(3, 0, message_dim=3, hidden=8, dt=0.1), [a], train.TrainConfig(epochs=1))


# ---------------------------------------------------------------------------
# Schedules, held-out graphs, the time budget
# ---------------------------------------------------------------------------
def test_cosine_schedule_anneals_from_lr_to_min_lr_over_the_epochs_and_resumes_exactly(tmp_path, tiny_linear, fresh):
    traj = tiny_linear()
    cfg = dict(batch_size=8, lr=1e-2, min_lr=1e-4, schedule="cosine")
    r = train.fit(fresh(), [traj], train.TrainConfig(epochs=8, **cfg), tmp_path / "a.h5")
    lrs = [h["lr"] for h in r.history[1:]]  # the rate set for the next epoch, after each epoch
    want = [1e-4 + (1e-2 - 1e-4) * 0.5 * (1 + math.cos(math.pi * e / 8)) for e in range(1, 9)]
    np.testing.assert_allclose(lrs, want, rtol=1e-12)
    assert lrs[-1] == pytest.approx(1e-4)

    def stop_at_3(record):  # an 8-epoch run interrupted after epoch 3 ...
        if record["epoch"] == 3:
            raise KeyboardInterrupt

    cut = train.fit(fresh(), [traj], train.TrainConfig(epochs=8, **cfg), tmp_path / "b.h5", progress=stop_at_3)
    assert cut.status == "interrupted" and cut.epoch == 3
    again = train.fit(None, [traj], train.TrainConfig(epochs=8), tmp_path / "b.h5", resume=True)
    assert np.array_equal(again.model.theta, r.model.theta)  # ... resumes into the same run


def test_a_bad_step_scales_the_cosine_schedule_down(tmp_path, monkeypatch, tiny_linear, fresh):
    from mpnode.training import losses

    real = losses.value_and_grad
    calls = {"n": 0}

    def flaky(*a, **k):
        calls["n"] += 1
        loss, g, gx = real(*a, **k)
        return (math.nan if calls["n"] == 2 else loss), g, gx

    monkeypatch.setattr(losses, "value_and_grad", flaky)
    r = train.fit(fresh(), [tiny_linear()], train.TrainConfig(epochs=4, batch_size=8, lr=1e-2, min_lr=0.0,
                                                              schedule="cosine"))
    want = [0.5 * 1e-2 * 0.5 * (1 + math.cos(math.pi * e / 4)) for e in range(1, 5)]
    np.testing.assert_allclose([h["lr"] for h in r.history[1:]], want, rtol=1e-12)


@pytest.fixture
def multi_graph_file(tiny_linear):
    """multi_graph_file(B=40): tiny_linear dynamics on 4 distinct 2-node graphs (the same edge in
    different node orders)."""
    def make(B=40):
        t = tiny_linear(B=B)
        graphs = [Graph.from_edges(2, [(0, 1)]), Graph.from_edges(2, [(1, 0)], directed=True),
                  Graph.from_edges(2, [(0, 1)], directed=True), Graph.from_edges(2, [])]
        return Trajectories(x=t.x, graphs=graphs, dt=t.dt, system=t.system, graph_index=np.arange(B) % 4)

    return make


def test_val_graphs_holds_out_whole_graphs(tiny_linear, fresh, multi_graph_file, prepared):
    traj = multi_graph_file()
    m = fresh()
    _, _, split = prepared(m, [traj], train.TrainConfig(val_graphs=1, seed=5))
    tr, va = split[0]
    held = set(traj.graph_index[va])
    assert len(held) == 1 and not held & set(traj.graph_index[tr])
    assert len(tr) + len(va) == traj.n_trajectories
    # the same seed holds out the same graph; a file with too few graphs keeps the random split
    assert np.array_equal(prepared(fresh(), [traj], train.TrainConfig(val_graphs=1, seed=5))[2][0][1], va)
    one = tiny_linear(B=20)
    _, _, split = prepared(fresh(), [one], train.TrainConfig(val_graphs=1, val_split=0.25))
    assert len(split[0][1]) == 5


def test_the_time_limit_counts_the_whole_run_across_resumes(tmp_path, tiny_linear, fresh):
    traj = tiny_linear()
    first = train.fit(fresh(), [traj], train.TrainConfig(epochs=3, batch_size=8), tmp_path / "m.h5")
    limit = first.seconds * 0.5  # already spent: a resumed run with this limit stops after one epoch
    again = train.fit(None, [traj], train.TrainConfig(epochs=50, time_limit=limit), tmp_path / "m.h5", resume=True)
    assert again.status == "time_limit" and again.epoch == 4


def test_a_time_limit_without_epochs_is_the_whole_budget(tmp_path, tiny_linear, fresh, monkeypatch):
    from mpnode.training import config

    monkeypatch.setattr(config, "DEFAULT_EPOCHS", 3)
    traj = tiny_linear()
    capped = train.fit(fresh(), [traj], train.TrainConfig(batch_size=8), tmp_path / "c.h5")
    assert capped.status == "completed" and capped.epoch == 3
    timed = train.fit(fresh(), [traj], train.TrainConfig(batch_size=8, time_limit=1.0, schedule="cosine"),
                      tmp_path / "t.h5")
    assert timed.status == "time_limit" and timed.epoch > 3  # not stopped by the cap it was not given
    assert timed.lr < 1e-4  # the cosine decay spread over the time limit reached its end
    told = train.fit(fresh(), [traj], train.TrainConfig(epochs=2, batch_size=8, time_limit=60.0), tmp_path / "e.h5")
    assert told.status == "completed" and told.epoch == 2


def test_the_scaled_aggregation_divides_by_the_training_graphs_mean_in_degree(multi_graph_file):
    from mpnode.model.config import ModelConfig
    from mpnode.runs import run as runs

    traj = multi_graph_file()  # graphs with 2, 1, 1, 0 directed edges on 2 nodes, used in turn
    everything = batches.TrainingData([traj], train.TrainConfig(val_split=0.0))
    assert everything.mean_in_degree(False) == pytest.approx((2 + 1 + 1 + 0) / 4 / 2)
    assert everything.mean_in_degree(True) == pytest.approx((2 + 1 + 1 + 0) / 4 / 2 + 1)
    data = batches.TrainingData([traj], train.TrainConfig(val_graphs=1, seed=5))
    held = set(traj.graph_index[data.split[0][1]])
    edges = [g.n_edges for i, g in enumerate(traj.graphs) if i not in held]
    assert data.mean_in_degree(False) == pytest.approx(sum(edges) / len(edges) / 2)
    m = runs.new_model(data, ModelConfig(aggregation="scaled"))
    assert m.spec.aggregation.mean_degree == pytest.approx(sum(edges) / len(edges) / 2)


@pytest.mark.parametrize("loss", ["huber", "mse"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_loss_pass_matches_numpy_with_unobserved_values_and_both_huber_branches(loss, dtype):
    """The compiled residual pass against the loss written out in NumPy: residuals on both sides
    of Huber's kink, values nobody observed (NaN in the truth) adding nothing, step 0 not scored;
    a non-finite prediction anywhere, even at step 0, makes the validation value inf."""
    from mpnode.training import losses

    rng = np.random.default_rng(3)
    pred = (rng.standard_normal((6, 5, 3)) * 2).astype(dtype)
    x = (rng.standard_normal((6, 5, 3)) * 2).astype(dtype)
    x[rng.random(x.shape) < 0.2] = np.nan
    e = np.nan_to_num(pred[1:].astype(np.float64) - x[1:])
    assert np.any(np.abs(e) > 1) and np.any((np.abs(e) < 1) & (e != 0))
    if loss == "huber":
        want, de = np.where(np.abs(e) <= 1, 0.5 * e * e, np.abs(e) - 0.5).sum() / 5, np.clip(e, -1, 1) / 5
    else:
        want, de = (e * e).sum() / 5, 2 * e / 5
    got, g = losses.LOSSES[loss](pred, x, 5)
    tol = 1e-13 if dtype == np.float64 else 1e-6
    assert got == pytest.approx(want, rel=tol) and g.dtype == dtype
    np.testing.assert_allclose(g[1:], de, rtol=tol, atol=tol)
    assert not np.any(g[0])
    assert losses.value(pred, x, loss) == pytest.approx(want, rel=tol)
    pred[0, 2, 1] = np.nan
    assert losses.value(pred, x, loss) == np.inf
