"""Figures: mpnode.plot and `--plot` on eval, simulate, train and finetune; the swarm figure
beside its benchmark.  Without matplotlib, --plot must stop before any work with the hint."""
import importlib.util
import os
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode.base.graph import Graph
from mpnode.data import Trajectories, read_trajectories, write_trajectories
from mpnode.model import Model

ROOT = Path(__file__).resolve().parents[1]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def png_size(path):
    """(width, height) from the PNG header, after checking it is a PNG."""
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def assert_report_figure(path):
    assert png_size(path) == (1200, 800)
    assert 8_000 < os.path.getsize(path) < 1_000_000  # one empty axes: ~5 kB


@pytest.fixture
def model_and_data(tmp_path, tiny_file, fresh):
    fresh().save(tmp_path / "m.h5")
    return tmp_path / "m.h5", tiny_file(tmp_path / "d.h5", B=5)


# ---- the commands ------------------------------------------------------------------------

def test_eval_plot(tmp_path, model_and_data):
    pytest.importorskip("matplotlib")
    model, data = model_and_data
    res = run("eval", model, data, "--plot", tmp_path / "e.png", "--reference-sample", 0,
              "--predictions", tmp_path / "p.h5")
    assert res.exit_code == 0, res.output
    assert f"wrote {tmp_path / 'e.png'}" in res.output
    assert_report_figure(tmp_path / "e.png")
    assert os.path.exists(tmp_path / "p.h5")


def test_simulate_plot(tmp_path):
    pytest.importorskip("matplotlib")
    Model.create(2, 0, message_dim=3, hidden=8, dt=0.05).save(tmp_path / "m.h5")
    res = run("simulate", tmp_path / "m.h5", "coupled_pendulum", "-o", tmp_path / "s.h5", "-B", 3, "-T", 20,
              "--plot", tmp_path / "s.png")
    assert res.exit_code == 0, res.output
    assert_report_figure(tmp_path / "s.png")
    s = read_trajectories(tmp_path / "s.h5")
    assert s.x.shape == (3, 21, 2, 2)
    assert s.attrs["state_names"] == ["angle (rad)", "angular velocity (rad/s)"]  # the scene's system names them


def test_train_and_finetune_plot(tmp_path, tiny_file):
    pytest.importorskip("matplotlib")
    data = tiny_file(tmp_path / "d.h5")
    res = run("train", data, "-o", tmp_path / "m.h5", "--epochs", 4, "--hidden", 8, "--batch-size", 32,
              "--plot", tmp_path / "t.png")
    assert res.exit_code == 0, res.output
    assert "wrote" in res.output and "(training curves)" in res.output
    assert_report_figure(tmp_path / "t.png")
    res = run("finetune", tmp_path / "m.h5", data, "-o", tmp_path / "f.h5", "--epochs", 2, "--plot",
              tmp_path / "f.svg")
    assert res.exit_code == 0, res.output
    assert Path(tmp_path / "f.svg").read_text().lstrip().startswith("<?xml")


def test_a_diverged_run_still_gets_its_figure(tmp_path, tiny_file):
    pytest.importorskip("matplotlib")
    data = tiny_file(tmp_path / "d.h5")
    res = run("train", data, "-o", tmp_path / "m.h5", "--epochs", 50, "--batch-size", 8, "--lr", 1e3,
              "--plot", tmp_path / "t.png")
    assert res.exit_code == 3 and "diverged" in res.output
    assert_report_figure(tmp_path / "t.png")


def hide_matplotlib(monkeypatch):
    """Make `import matplotlib` fail as it does where the extra is not installed."""
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)


def test_without_matplotlib_plot_stops_before_any_work(tmp_path, model_and_data, monkeypatch):
    model, data = model_and_data
    hide_matplotlib(monkeypatch)
    commands = {
        "eval": ["eval", model, data, "--plot", tmp_path / "e.png", "--predictions", tmp_path / "p.h5"],
        "simulate": ["simulate", model, "coupled_pendulum", "-o", tmp_path / "s.h5", "--plot", tmp_path / "s.png"],
        "train": ["train", data, "-o", tmp_path / "t.h5", "--epochs", 1, "--plot", tmp_path / "t.png"],
        "finetune": ["finetune", model, data, "-o", tmp_path / "f.h5", "--epochs", 1, "--plot", tmp_path / "f.png"],
    }
    before = sorted(os.listdir(tmp_path))
    for name, args in commands.items():
        res = run(*args)
        assert res.exit_code == 2, (name, res.output)
        assert "--plot" in res.output and "pip install 'mpnode[plot]'" in res.output, res.output
        assert "Traceback" not in res.output
    assert sorted(os.listdir(tmp_path)) == before  # nothing written: no model, log, predictions
    # without --plot nothing changes
    assert run("eval", model, data, "--reference-sample", 0).exit_code == 0


def test_bad_plot_paths_exit_2_before_any_work(tmp_path, model_and_data, tiny_file):
    pytest.importorskip("matplotlib")
    model, data = model_and_data
    res = run("eval", model, data, "--plot", tmp_path / "e.h5")
    assert res.exit_code == 2 and "not a figure format" in res.output and ".png" in res.output
    res = run("eval", model, data, "--plot", tmp_path / "x.png", "--predictions", tmp_path / "x.png")
    assert res.exit_code == 2 and "one would overwrite the other" in res.output
    odd = tiny_file(tmp_path / "data.png", B=2)  # a trajectory file with an image's name
    res = run("eval", model, odd, "--plot", odd)
    assert res.exit_code == 2 and "destroy the input" in res.output
    assert read_trajectories(odd).n_trajectories == 2
    res = run("train", data, "-o", tmp_path / "n.h5", "--plot", tmp_path / "nowhere" / "t.png")
    assert res.exit_code == 2 and "does not exist" in res.output
    assert not os.path.exists(tmp_path / "n.h5")


# ---- the library functions ---------------------------------------------------------------

def texts(fig):
    """Every piece of text on the figure: titles, axis labels, tick labels, legends."""
    return {t.get_text().strip() for t in fig.findobj(lambda a: hasattr(a, "get_text")) if t.get_text().strip()}


def test_eval_figure_shows_names_time_units_and_the_horizon(tmp_path, tiny_linear, fresh):
    pytest.importorskip("matplotlib")
    from mpnode.evaluation.evaluate import evaluate
    from mpnode.plot import plot_eval

    traj = tiny_linear(B=6, T=20)
    traj.attrs["state_names"] = ["position (m)", "velocity (m/s)"]
    result = evaluate(fresh(), traj)
    fig = plot_eval(traj, result, tmp_path / "e.png", trajectories=3, nodes=2)
    words = texts(fig)
    assert {"position (m)", "velocity (m/s)", "t (dt = 0.1)", "trajectory 0", "trajectory 2", "node 1",
            "truth", "prediction", "error over time"} <= words
    assert any(w.startswith("horizon, nMSE > 0.1: ") for w in words)
    assert len(fig.axes) == 2 * 3 + 1  # dims x trajectories, and the error panel
    # a blown-up prediction is drawn, not an error; its first blow-up is marked
    result.predictions[0, 5:] = np.inf
    result.first_bad_step = 5
    fig = plot_eval(traj, result, tmp_path / "b.png")
    assert "first blow-up: t = 0.5" in texts(fig)
    assert png_size(tmp_path / "b.png") == (1200, 800)


def test_a_model_with_latent_dimensions_gets_its_eval_figure(tiny_linear):
    pytest.importorskip("matplotlib")
    from mpnode.evaluation.evaluate import evaluate
    from mpnode.plot import plot_eval

    traj = tiny_linear(B=3)
    result = evaluate(Model.create(2, 0, message_dim=3, hidden=8, dt=0.1, latent_dims=1), traj)
    assert result.predictions.shape[-1] == 3  # the data's two dimensions and the model's own
    words = texts(plot_eval(traj, result))
    assert "x[1]" in words and "x[2]" not in words


def test_simulation_figure_defaults_to_numbered_dimensions(tmp_path):
    pytest.importorskip("matplotlib")
    from mpnode.plot import plot_simulation

    x = np.cumsum(np.random.default_rng(0).normal(size=(3, 30, 8, 6)), axis=1)
    fig = plot_simulation(x, 0.01, tmp_path / "s.png", nodes=4, dims=3)
    words = texts(fig)
    assert {"x[0]", "x[1]", "x[2]", "t (dt = 0.01)", "node 3"} <= words and "x[3]" not in words
    assert any("the first 4 of 8 nodes" in w and "of 6 state dimensions shown" in w for w in words)
    assert_report_figure(tmp_path / "s.png")


def test_training_figure_marks_the_best_epoch_and_curriculum_stages(tmp_path):
    pytest.importorskip("matplotlib")
    from mpnode.plot import plot_training

    records = [{"epoch": 0, "train_loss": None, "val_loss": 10.0, "lr": 1e-3, "window": None, "stage": None}]
    for e in range(1, 31):
        stage = 0 if e <= 10 else 1 if e <= 20 else 2
        records.append({"epoch": e, "train_loss": 10.0 / e, "val_loss": 12.0 / e + (0.5 if e > 25 else 0),
                        "lr": 1e-3 * (0.5 if e > 15 else 1), "window": (5, 10, 40)[stage], "stage": stage,
                        "elapsed": 3.0 * e})
    fig = plot_training(records, tmp_path / "t.png", loss="huber")
    words = texts(fig)
    assert {"window 5 steps", "window 10 steps", "full horizon (40 steps)", "learning rate", "epoch",
            "huber loss per node\n(normalised states)"} <= words
    assert len(fig.axes) == 2  # a log without the validation nMSE (written before it was logged)
    assert "best validation: 0.48 at epoch 25" in words
    assert any("30 epochs in 90 s" in w for w in words)
    assert_report_figure(tmp_path / "t.png")
    for r in records:
        r["val_nmse"] = r["val_loss"] / 20
    fig = plot_training(records)
    assert len(fig.axes) == 3 and "validation\nnormalised MSE" in texts(fig)


def test_figures_are_written_atomically(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    from mpnode.plot import plot_simulation

    (tmp_path / "s.png").write_bytes(b"old")

    def fail(self, *args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(Figure, "savefig", fail)
    with pytest.raises(RuntimeError):
        plot_simulation(np.zeros((1, 3, 2, 1)), 0.1, tmp_path / "s.png")
    assert sorted(os.listdir(tmp_path)) == ["s.png"] and (tmp_path / "s.png").read_bytes() == b"old"


# ---- the quadrotor swarm figure (benchmarks/studies/quadrotor/swarm.py) --------------------------

def _swarm(path, x, load=None):
    aux = {} if load is None else {"load": load}
    write_trajectories(path, Trajectories(x=x, graphs=[Graph.complete(x.shape[2])], dt=0.1, system="quadrotor_load",
                                          u=np.zeros(x.shape[:1] + (x.shape[1] - 1,) + x.shape[2:3] + (4,)), aux=aux))


def test_swarm_figure_beside_its_benchmark(tmp_path):
    pytest.importorskip("matplotlib")
    spec = importlib.util.spec_from_file_location("swarm", ROOT / "benchmarks" / "studies" / "quadrotor" / "swarm.py")
    swarm = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(swarm)

    rng = np.random.default_rng(0)
    B, T, N = 2, 10, 3
    x = np.zeros((B, T + 1, N, 13))
    x[..., 0:3] = np.cumsum(rng.normal(0, 0.1, (B, T + 1, N, 3)), axis=1) + [0, 0, 1]
    x[..., 3] = 1.0  # unit quaternion
    load = np.zeros((B, T + 1, 6))
    load[..., 0] = np.linspace(0, 1, T + 1)
    _swarm(tmp_path / "true.h5", x, load)
    _swarm(tmp_path / "pred.h5", x + 0.05)  # predictions carry no load
    out = swarm.plot_swarm(tmp_path / "true.h5", tmp_path / "pred.h5", trajectory=1, out=tmp_path / "s.png")
    assert png_size(out)[0] > 1000 and os.path.getsize(out) > 10_000
    with pytest.raises(IndexError):
        swarm.plot_swarm(tmp_path / "true.h5", tmp_path / "pred.h5", trajectory=5, out=tmp_path / "t.png")


def test_every_built_in_system_names_its_dimensions():
    from dataclasses import replace

    from data_gen import generate, load_scene
    from data_gen.systems import SYSTEMS

    for system in SYSTEMS.values():
        assert len(system.state_names) == system.state_dim and all(system.state_names), system.name
    traj = generate(replace(load_scene("lorenz3"), trajectories=1, horizon=2), workers=1)
    assert traj.attrs["state_names"] == ["x", "y", "z"]
