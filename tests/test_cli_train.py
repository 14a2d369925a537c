"""`mpnode train`, `finetune`, `simulate` end to end through click (tiny data, few epochs)."""
import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode.data import read_trajectories
from mpnode.model import Model

QUICK = ["--batch-size", "32", "--lr", "1e-2"]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_train_writes_model_log_and_checkpoint(tmp_path, tiny_file):
    data = tiny_file(tmp_path / "d.h5")
    out = tmp_path / "m.h5"
    res = run("train", data, "-o", out, "--epochs", 3, "--hidden", 8, "--message-dim", 2, "--dtype", "float64",
              "--self-messages", *QUICK)
    assert res.exit_code == 0, res.output
    assert "completed" in res.output and "validation normalised MSE" in res.output
    m = Model.load(out)
    assert m.spec.hidden == 8 and m.spec.message_dim == 2 and m.spec.self_messages and m.dtype == np.float64
    assert m.attrs["trained_on"].endswith("d.h5")
    lines = open(f"{out}.log.jsonl").read().splitlines()
    assert [json.loads(line)["epoch"] for line in lines] == [0, 1, 2, 3]
    assert os.path.exists(f"{out}.state")


def test_resume_through_the_cli_matches_a_straight_run(tmp_path, tiny_file):
    data = tiny_file(tmp_path / "d.h5")
    assert run("train", data, "-o", tmp_path / "a.h5", "--epochs", 6, *QUICK).exit_code == 0
    assert run("train", data, "-o", tmp_path / "b.h5", "--epochs", 3, *QUICK).exit_code == 0
    res = run("train", data, "-o", tmp_path / "b.h5", "--epochs", 6, "--resume")
    assert res.exit_code == 0, res.output
    assert "resuming at epoch 3" in res.output
    assert np.array_equal(Model.load(tmp_path / "a.h5").theta, Model.load(tmp_path / "b.h5").theta)
    res = run("train", data, "-o", tmp_path / "c.h5", "--epochs", 6, "--resume")
    assert res.exit_code == 2 and "does not exist" in res.output


def test_resume_refuses_a_checkpoint_of_an_unknown_version(tmp_path, tiny_file):
    data, out = tiny_file(tmp_path / "d.h5"), tmp_path / "m.h5"
    assert run("train", data, "-o", out, "--epochs", 1, *QUICK).exit_code == 0
    with np.load(f"{out}.state") as z:
        checkpoint = {k: z[k] for k in z.files}
    assert int(checkpoint["version"]) == 1  # a run without kinematics stays readable by older versions
    checkpoint["version"] = np.int64(3)  # one from a newer mpnode
    with open(f"{out}.state", "wb") as f:
        np.savez(f, **checkpoint)
    res = run("train", data, "-o", out, "--epochs", 2, "--resume")
    assert res.exit_code == 2 and "version" in res.output and "is 3" in res.output, res.output
    assert "Traceback" not in res.output


def test_finetune_keeps_weights_and_normalisation(tmp_path, tiny_file):
    data = tiny_file(tmp_path / "d.h5")
    other = tiny_file(tmp_path / "e.h5", seed=4, offset=0.5)
    assert run("train", data, "-o", tmp_path / "m.h5", "--epochs", 2, *QUICK).exit_code == 0
    src = Model.load(tmp_path / "m.h5")
    res = run("finetune", tmp_path / "m.h5", other, "-o", tmp_path / "f0.h5", "--epochs", 0)
    assert res.exit_code == 0, res.output
    f0 = Model.load(tmp_path / "f0.h5")
    assert np.array_equal(f0.theta, src.theta) and np.array_equal(f0.x_mean, src.x_mean)
    res = run("finetune", tmp_path / "m.h5", other, "-o", tmp_path / "f1.h5", "--epochs", 2, "--refit-norm", *QUICK)
    assert res.exit_code == 0, res.output
    f1 = Model.load(tmp_path / "f1.h5")
    assert not np.allclose(f1.x_mean, src.x_mean)
    assert f1.attrs["finetuned_from"].endswith("m.h5")


def test_huge_learning_rate_exits_3_with_a_clear_message(tmp_path, tiny_file):
    data = tiny_file(tmp_path / "d.h5")
    res = run("train", data, "-o", tmp_path / "m.h5", "--epochs", 50, "--batch-size", 8, "--lr", 1e3)
    assert res.exit_code == 3
    assert "diverged" in res.output and "--lr" in res.output and "Traceback" not in res.output
    assert np.all(np.isfinite(Model.load(tmp_path / "m.h5").theta))


def test_bad_inputs_exit_2(tmp_path, tiny_file):
    data = tiny_file(tmp_path / "d.h5")
    res = run("train", tmp_path / "nope.h5", "-o", tmp_path / "m.h5")
    assert res.exit_code == 2 and "nope.h5" in res.output
    res = run("train", data, "-o", tmp_path / "no_such_dir" / "m.h5")
    assert res.exit_code == 2
    other_dt = tiny_file(tmp_path / "e.h5", dt=0.2)
    res = run("train", data, other_dt, "-o", tmp_path / "m.h5", "--epochs", 1)
    assert res.exit_code == 2 and "dt" in res.output
    assert not os.path.exists(tmp_path / "m.h5")


def test_simulate_a_scene_with_a_trained_model(tmp_path):
    Model.create(2, 0, message_dim=3, hidden=8, dt=0.05).save(tmp_path / "m.h5")
    res = run("simulate", tmp_path / "m.h5", "coupled_pendulum", "-o", tmp_path / "s.h5", "-B", 5, "-T", 7)
    assert res.exit_code == 0, res.output
    s = read_trajectories(tmp_path / "s.h5")
    assert s.x.shape == (5, 8, 2, 2) and s.attrs["predicted_by"].endswith("m.h5")
    assert s.attrs["scene"] == "coupled_pendulum"
    # initial states are the ones `mpnode generate` draws for the same scene and seed
    from dataclasses import replace

    from data_gen import generate, load_scene

    ref = generate(replace(load_scene("coupled_pendulum"), trajectories=2, horizon=1), workers=1)
    np.testing.assert_allclose(s.x[:2, 0], ref.x[:, 0], rtol=1e-6)
    res = run("simulate", tmp_path / "m.h5", "lorenz3", "-o", tmp_path / "l.h5", "-B", 2)
    assert res.exit_code == 2 and "state dimensions" in res.output


def test_train_a_scene_in_one_command(tmp_path):
    out = tmp_path / "m.h5"
    res = run("train", "coupled_pendulum", "-o", out, "--trajectories", 10, "--epochs", 2, "--hidden", 8)
    assert res.exit_code == 0, res.output
    assert os.path.exists(f"{out}.data.h5") and read_trajectories(f"{out}.data.h5").n_trajectories == 10
    assert "speed against error" in res.output and "fresh coupled_pendulum" in res.output


def test_train_a_scene_set_in_one_command(tmp_path, monkeypatch):
    from cli import train_cmd

    monkeypatch.setattr(train_cmd, "SCENE_EVAL_TRAJECTORIES", 2)
    out = tmp_path / "swarm.h5"
    res = run("train", "quad3-5", "-o", out, "--trajectories", 2, "--epochs", 1, "--hidden", 4, "--seed", 7)
    assert res.exit_code == 0, res.output
    files = [f"{out}.quad{n}.data.h5" for n in (3, 4, 5)]
    assert [read_trajectories(f).n_nodes for f in files] == [3, 4, 5]
    assert [read_trajectories(f).attrs["seed"] for f in files] == [7, 8, 9]
    assert Model.load(out).attrs["trained_on"].count(".data.h5") == 3
    assert "2 fresh quad6 trajectories (seed 10)" in res.output and "by state group" in res.output
    # the swarm model runs on any number of carriers, in the scene's closed loop
    res = run("simulate", out, "quad8", "-o", tmp_path / "s8.h5", "-B", 2, "-T", 3)
    assert res.exit_code == 0, res.output
    s8 = read_trajectories(tmp_path / "s8.h5")
    assert s8.x.shape == (2, 4, 8, 13) and s8.u.shape == (2, 3, 8, 4)
    assert s8.attrs["state_groups"][3] == "attitude"


def test_generate_a_scene_set_writes_one_file_per_scene(tmp_path):
    res = run("generate", "quad3-5", "-o", tmp_path / "sw", "-B", 2, "-T", 2, "--seed", 5, "--workers", 1)
    assert res.exit_code == 0, res.output
    assert [read_trajectories(tmp_path / f"sw_quad{n}.h5").attrs["seed"] for n in (3, 4, 5)] == [5, 6, 7]
    (tmp_path / "d").mkdir()
    assert run("generate", "quad3-5", "-o", f"{tmp_path / 'd'}/", "-B", 2, "-T", 2, "--workers", 1).exit_code == 0
    assert sorted(os.listdir(tmp_path / "d")) == ["quad3.h5", "quad4.h5", "quad5.h5"]
    res = run("generate", "quad3", "-o", tmp_path / "d", "-B", 2)
    assert res.exit_code == 2 and "folder" in res.output


def gene_file(path, B=6, T=4):
    from dataclasses import replace

    from data_gen import generate, load_scene
    from mpnode.data import write_trajectories

    write_trajectories(path, generate(replace(load_scene("gene16_ba"), trajectories=B, horizon=T), workers=1))
    return path


def training_config(model_path):
    """The TrainConfig a run beside ``model_path`` used (from its checkpoint)."""
    from mpnode.training.state import TrainState, state_path

    return TrainState.load(state_path(model_path)).config


def test_the_recipe_fills_what_the_user_leaves_unset(tmp_path):
    data = gene_file(tmp_path / "g.h5")
    res = run("train", data, "-o", tmp_path / "auto.h5", "--epochs", 1, "--hidden", 8)
    assert res.exit_code == 0, res.output
    assert "recipe auto for gene: aggregation mean" in res.output and "linear_aggregation scaled" in res.output
    assert "linear_target state" in res.output and "val_graphs 1" in res.output
    auto = Model.load(tmp_path / "auto.h5").spec
    assert (auto.aggregation.mlp, auto.aggregation.linear, auto.aggregation.target) == ("mean", "scaled", "state")
    assert auto.aggregation.mean_degree == pytest.approx(8.0)  # BA(16, 8): 64 edges, both directions, over 16 nodes
    assert Model.load(tmp_path / "auto.h5").attrs["recipe"] == "auto"
    res = run("train", data, "-o", tmp_path / "paper.h5", "--epochs", 1, "--hidden", 8, "--recipe", "paper")
    paper = Model.load(tmp_path / "paper.h5").spec
    assert res.exit_code == 0 and (paper.aggregation.mlp, paper.linear_path) == ("mean", False)
    res = run("train", data, "-o", tmp_path / "zero.h5", "--epochs", 1, "--hidden", 8, "--zero-messages")
    assert res.exit_code == 0, res.output  # the recipe's linear path needs messages: left out, not refused
    assert not Model.load(tmp_path / "zero.h5").spec.linear_path
    res = run("train", data, "-o", tmp_path / "sum.h5", "--epochs", 1, "--hidden", 8, "--aggregate", "sum")
    assert res.exit_code == 0 and Model.load(tmp_path / "sum.h5").spec.aggregation.mlp == "sum"


def test_the_recipes_batch_sizes_fill_train_and_finetune(tmp_path, tiny_file):
    from mpnode.training.recipes import finetune_recipe, recipe

    data = tiny_file(tmp_path / "d.h5")
    train_batch = recipe("auto", "tiny_linear")["batch_size"]
    finetune_batch = finetune_recipe("auto")["batch_size"]
    assert train_batch < 128 and finetune_batch < 128  # the paper's 128 is one batch of this file
    res = run("train", data, "-o", tmp_path / "src.h5", "--epochs", 1, "--hidden", 8)
    assert res.exit_code == 0 and f"batch_size {train_batch}" in res.output, res.output
    assert training_config(tmp_path / "src.h5").batch_size == train_batch
    res = run("train", data, "-o", tmp_path / "l2s.h5", "--epochs", 1, "--hidden", 8, "--model", "l2s")
    assert res.exit_code == 0 and training_config(tmp_path / "l2s.h5").batch_size == train_batch
    res = run("train", data, "-o", tmp_path / "node.h5", "--epochs", 1, "--hidden", 8, "--model", "node")
    assert res.exit_code == 0 and training_config(tmp_path / "node.h5").batch_size == 128  # a tie there: the paper's
    res = run("train", data, "-o", tmp_path / "p.h5", "--epochs", 1, "--hidden", 8, "--recipe", "paper")
    assert res.exit_code == 0 and training_config(tmp_path / "p.h5").batch_size == 128
    res = run("finetune", tmp_path / "src.h5", data, "-o", tmp_path / "ft.h5", "--epochs", 1)
    assert res.exit_code == 0, res.output
    assert f"recipe auto for fine-tuning: batch_size {finetune_batch}" in res.output
    assert training_config(tmp_path / "ft.h5").batch_size == finetune_batch
    assert Model.load(tmp_path / "ft.h5").attrs["finetune_recipe"] == "auto"
    res = run("finetune", tmp_path / "src.h5", data, "-o", tmp_path / "ft.h5", "--epochs", 2, "--resume")
    assert res.exit_code == 0 and training_config(tmp_path / "ft.h5").batch_size == finetune_batch  # the run's own
    res = run("finetune", tmp_path / "src.h5", data, "-o", tmp_path / "paper.h5", "--epochs", 1, "--recipe", "paper")
    assert res.exit_code == 0 and "for fine-tuning:" not in res.output
    assert training_config(tmp_path / "paper.h5").batch_size == 128
    res = run("finetune", tmp_path / "src.h5", data, "-o", tmp_path / "own.h5", "--epochs", 1, "--batch-size", 3)
    assert res.exit_code == 0 and training_config(tmp_path / "own.h5").batch_size == 3


@pytest.mark.parametrize("kind", ["l2s", "node"])
def test_every_command_takes_every_kind(tmp_path, kind, tiny_file):
    data = tiny_file(tmp_path / "d.h5")
    out = tmp_path / f"{kind}.h5"
    res = run("train", data, "-o", out, "--model", kind, "--epochs", 2, "--hidden", 8, *QUICK)
    assert res.exit_code == 0, res.output
    m = Model.load(out)
    assert m.kind == kind
    res = run("eval", out, data, "--predictions", tmp_path / "p.h5", "--reference-sample", 0)
    assert res.exit_code == 0, res.output
    res = run("finetune", out, data, "-o", tmp_path / "f.h5", "--epochs", 1)
    assert res.exit_code == 0 and Model.load(tmp_path / "f.h5").kind == kind
    res = run("train", data, "-o", out, "--model", kind, "--epochs", 3, "--resume")
    assert res.exit_code == 0 and "resuming at epoch 2" in res.output
    res = run("simulate", out, "coupled_pendulum", "-o", tmp_path / "s.h5", "-B", 2, "-T", 3)
    assert res.exit_code == 0, res.output  # two nodes: the graph of tiny_file, the pendulum pair's size
    res = run("inspect", out)
    assert res.exit_code == 0 and f"kind:        {kind}" in res.output


def test_a_node_model_refuses_a_scene_of_another_size(tmp_path):
    Model.create(3, 0, message_dim=0, hidden=8, dt=0.05, kind="node", n_nodes=3).save(tmp_path / "n.h5")
    res = run("simulate", tmp_path / "n.h5", "lorenz7", "-o", tmp_path / "s.h5", "-B", 2)
    assert res.exit_code == 2 and "exactly 3 nodes" in res.output and "Traceback" not in res.output


def test_the_quadrotor_recipe_and_its_fine_tuning_normalisation(tmp_path):
    from mpnode.training.recipes import finetune_recipe

    for n, seed in ((3, 1), (4, 2)):
        res = run("generate", f"quad{n}", "-o", tmp_path / f"q{n}.h5", "-B", 4, "-T", 2, "--seed", seed,
                  "--workers", 1)
        assert res.exit_code == 0, res.output
    res = run("train", tmp_path / "q3.h5", "-o", tmp_path / "src.h5", "--epochs", 1, "--hidden", 4)
    assert res.exit_code == 0 and "message_dim 13" in res.output, res.output
    src = Model.load(tmp_path / "src.h5")
    assert src.spec.message_dim == 13 and training_config(tmp_path / "src.h5").lr == 1e-2
    assert training_config(tmp_path / "src.h5").schedule == "cosine"  # decays over the user's budget
    # fine-tuning a swarm model on a new size refits its normalisation unless told to keep it
    assert finetune_recipe("auto", "mpnode", "quadrotor_load")["norm"] == "refit"
    assert "norm" not in finetune_recipe("auto", "mpnode", "lorenz") and finetune_recipe("paper") == {}
    res = run("finetune", tmp_path / "src.h5", tmp_path / "q4.h5", "-o", tmp_path / "refit.h5", "--epochs", 1)
    assert res.exit_code == 0 and "norm refit" in res.output, res.output
    refit = Model.load(tmp_path / "refit.h5")
    q4 = np.asarray(read_trajectories(tmp_path / "q4.h5").x)
    assert not np.allclose(refit.x_mean, src.x_mean) and np.all(refit.x_mean >= q4.min(axis=(0, 1, 2)) - 1e-6)
    res = run("finetune", tmp_path / "src.h5", tmp_path / "q4.h5", "-o", tmp_path / "keep.h5", "--epochs", 1,
              "--keep-norm")
    assert res.exit_code == 0 and "norm refit" not in res.output, res.output
    np.testing.assert_array_equal(Model.load(tmp_path / "keep.h5").x_mean, src.x_mean)
