"""Rollouts that hold: fresh noise on the initial states of the training rollouts (--input-noise)
and training on windows while the model is chosen by the full horizon (--train-window) -- the
gradient stays exact, the runs resume bit for bit, the options are checked and reach the CLI."""

import numpy as np
import pytest
from click.testing import CliRunner
from engine_helpers import spec_

from cli.main import main
from mpnode import InputError
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import layouts
from mpnode.training import TrainConfig, fit, losses
from mpnode.training.batches import Batch
from mpnode.training.config import curriculum_stage
from mpnode.training.log import log_path, read_log
from mpnode.training.loop import start_noise

RING = [(0, 1), (1, 2), (2, 0)]


def test_the_gradient_from_noisy_initial_states_is_exact_and_the_targets_stay_clean():
    """Against central finite differences in float64 (with an encoder, whose weights the noise
    must not cut off), and the loss is that of the rollout from the perturbed start against the
    unperturbed data."""
    rng = np.random.default_rng(5)
    spec = spec_(control_dim=0, encoder_window=2)
    g = block_diagonal([Graph.from_edges(3, RING)] * 2)
    T, M = 4, 6
    theta = rng.uniform(-0.6, 0.6, layouts.n_params(spec))
    x = rng.standard_normal((T + 1, M, spec.state_dim))
    batch = Batch(x, None, g, None)
    visible = np.repeat([1, 2], 3)
    kick = start_noise(np.random.default_rng(1), 0.3, (M, spec.state_dim))
    value, grad = losses.batch_value_and_grad(spec, theta, batch, "mse", visible, kick)
    assert value != losses.batch_value_and_grad(spec, theta, batch, "mse", visible)[0]
    picks = np.concatenate([rng.choice(theta.size - 50, 12, replace=False), theta.size - 1 - np.arange(6)])
    eps = 1e-6
    for i in picks:
        plus, minus = theta.copy(), theta.copy()
        plus[i] += eps
        minus[i] -= eps
        fd = (losses.batch_value_and_grad(spec, plus, batch, "mse", visible, kick)[0]
              - losses.batch_value_and_grad(spec, minus, batch, "mse", visible, kick)[0]) / (2 * eps)
        assert abs(grad[i] - fd) <= 1e-6 * max(1.0, abs(fd)), (i, grad[i], fd)
    assert np.any(grad[-6:] != 0)  # the encoder still learns

    plain = spec_(control_dim=0)
    theta = rng.uniform(-0.6, 0.6, layouts.n_params(plain))
    value = losses.batch_value_and_grad(plain, theta, batch, "mse", 0, kick)[0]
    direct = losses.value_and_grad(plain, theta, x, g, loss="mse", x0=x[0] + kick)[0]
    assert value == pytest.approx(direct, rel=1e-12)


def test_start_noise_is_fresh_every_epoch_and_off_at_zero():
    def draw(epoch):
        return start_noise(np.random.default_rng([0, 7, epoch]), 0.1, (500, 2))

    a, b = draw(1), draw(2)
    assert not np.array_equal(a, b) and np.array_equal(a, draw(1))
    assert 0.09 < a.std() < 0.11 and abs(a.mean()) < 0.02
    assert start_noise(np.random.default_rng(0), 0.0, (5, 2)) is None


def test_input_noise_changes_training_and_a_stopped_run_resumes_bit_for_bit(tmp_path, tiny_linear, fresh):
    traj = tiny_linear(B=16, T=6)
    config = {"batch_size": 8, "lr": 1e-2, "input_noise": 0.05}
    straight = fit(fresh(), [traj], TrainConfig(epochs=4, **config), tmp_path / "a.h5")
    plain = fit(fresh(), [traj], TrainConfig(epochs=4, batch_size=8, lr=1e-2))
    assert not np.array_equal(straight.model.theta, plain.model.theta)
    fit(fresh(), [traj], TrainConfig(epochs=2, **config), tmp_path / "b.h5")
    again = fit(None, [traj], TrainConfig(epochs=4), tmp_path / "b.h5", resume=True)
    assert again.config.input_noise == 0.05
    assert np.array_equal(again.model.theta, straight.model.theta)


def test_train_window_trains_on_windows_and_chooses_the_model_on_the_full_horizon(tmp_path, tiny_linear, fresh):
    traj = tiny_linear(B=16, T=10)
    result = fit(fresh(), [traj], TrainConfig(epochs=3, batch_size=8, lr=1e-2, train_window=3), tmp_path / "m.h5")
    log = read_log(log_path(tmp_path / "m.h5"))
    assert [r["window"] for r in log[1:]] == [3, 3, 3]
    full = fit(fresh(), [traj], TrainConfig(epochs=3, batch_size=8, lr=1e-2))
    assert not np.array_equal(result.model.theta, full.model.theta)
    # validation (what chooses the model) is the same full-horizon figure in both runs: the
    # untrained model's epoch-0 validation loss agrees
    assert log[0]["val_loss"] == full.history[0]["val_loss"]
    # a window as long as the data (or longer) is the full horizon, bit for bit: recipe auto's
    # Lorenz window of 50 leaves training on 50-step data as it was
    same = fit(fresh(), [traj], TrainConfig(epochs=3, batch_size=8, lr=1e-2, train_window=10))
    assert np.array_equal(same.model.theta, full.model.theta)
    # after a curriculum, the window is train_window rather than the full horizon
    config = TrainConfig(curriculum=(2,), curriculum_epochs=2, train_window=5)
    assert [curriculum_stage(config, e) for e in (1, 2, 3, 9)] == [(0, 2), (0, 2), (1, 5), (1, 5)]
    assert curriculum_stage(TrainConfig(), 7) == (0, None)


@pytest.mark.parametrize("field, value", [("input_noise", -0.1), ("input_noise", "x"), ("train_window", -1),
                                          ("train_window", 2.5)])
def test_bad_long_rollout_options_name_the_option(field, value):
    with pytest.raises(InputError) as e:
        TrainConfig(**{field: value}).check()
    assert e.value.field == field


def test_cli_flags_reach_training_and_bad_values_exit_2(tmp_path, tiny_file):
    data = tiny_file(tmp_path / "d.h5", B=12, T=8)
    out = tmp_path / "m.h5"
    res = CliRunner().invoke(main, ["train", data, "-o", str(out), "--epochs", "2", "--batch-size", "8",
                                    "--input-noise", "0.02", "--train-window", "4"])
    assert res.exit_code == 0, res.output
    assert [r["window"] for r in read_log(log_path(out))][1:] == [4, 4]
    for flag, bad in (("--input-noise", "-1"), ("--train-window", "-2"), ("--train-window", "x")):
        res = CliRunner().invoke(main, ["train", data, "-o", str(tmp_path / "n.h5"), flag, bad])
        assert res.exit_code == 2 and flag in res.output and "Traceback" not in res.output, (flag, res.output)
        assert not (tmp_path / "n.h5").exists()
    helptext = CliRunner().invoke(main, ["train", "--help"]).output
    assert "--input-noise" in helptext and "--train-window" in helptext
