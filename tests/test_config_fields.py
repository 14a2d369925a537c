"""Every option of `ModelConfig` and `TrainConfig` does through the Python API what its flag does
through `mpnode train` / `finetune`.  The tests walk the dataclasses' fields: an option added
without a flag, a flag that sets another option or value, a check that one side makes and the
other does not, or a model option that `Model.create` ignores, fails here.

The commands run in this process (click's CliRunner) with the training itself replaced by a
stand-in that keeps the options it was given, except in the one end-to-end comparison."""
import dataclasses
import json

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode import Model
from mpnode.base.errors import InputError
from mpnode.base.options import switches
from mpnode.data import read_trajectories
from mpnode.model.config import ModelConfig
from mpnode.runs import run as runs
from mpnode.training import TrainConfig
from mpnode.training.batches import TrainingData

MODEL_FIELDS = [f.name for f in dataclasses.fields(ModelConfig)]
TRAIN_FIELDS = [f.name for f in dataclasses.fields(TrainConfig)]

#: a value other than the default of every option (for the tiny system: dx 2, one edge, dt 0.1)
SAMPLES = {
    "kind": "l2s", "message_dim": 2, "hidden": 8, "aggregation": "sum", "linear_aggregate": True,
    "linear_aggregation": "scaled", "linear_target": "state", "self_messages": True, "zero_messages": True,
    "substeps": 2, "dtype": "float64", "encoder_window": 2, "latent_dims": 3, "kinematics": "0:1",
    "epochs": 2, "batch_size": 8, "lr": 0.01, "beta1": 0.8, "beta2": 0.99, "eps": 1e-7, "clip": 100.0,
    "clip_mode": "global", "val_split": 0.25, "noise": 0.0, "loss": "mse", "patience": 7, "lr_decay": 0.25,
    "min_lr": 1e-5, "seed": 3, "norm": "refit", "max_bad_steps": 2, "blowup": 50.0, "time_limit": 120.0,
    "checkpoint_seconds": 1.0, "curriculum": (2, 4), "curriculum_epochs": 3, "schedule": "cosine",
    "val_graphs": 1, "ensemble": 2, "bootstrap": True, "split_seed": 5, "input_noise": 0.01, "train_window": 4, "ignore_attrs": True,
}
#: a value each option refuses
BAD = {
    "kind": "graph", "message_dim": -1, "hidden": 0, "aggregation": "max", "linear_aggregate": "yes",
    "linear_aggregation": "max", "linear_target": "messages", "self_messages": "yes", "zero_messages": "yes",
    "substeps": 0, "dtype": "float16", "encoder_window": -1, "latent_dims": -1, "kinematics": "0:x",
    "epochs": -1, "batch_size": 0, "lr": 0.0, "beta1": 1.0, "beta2": -0.5, "eps": -1.0, "clip": -1.0,
    "clip_mode": "sometimes", "val_split": 1.0, "noise": -1.0, "loss": "l1", "patience": 0, "lr_decay": 1.5,
    "min_lr": -1.0, "seed": -1, "norm": "twice", "max_bad_steps": 0, "blowup": -1.0, "time_limit": 0.0,
    "checkpoint_seconds": -1.0, "curriculum": (4, 2), "curriculum_epochs": 0, "schedule": "linear",
    "val_graphs": -1, "ensemble": 0, "bootstrap": "yes", "split_seed": -1, "input_noise": -1.0, "train_window": -1, "ignore_attrs": "yes",
}
#: the one option no `mpnode train` flag sets: fine-tuning's normalisation, `finetune --refit-norm/--keep-norm`
FINETUNE_ONLY = {"norm": {"refit": ["--refit-norm"], "keep": ["--keep-norm"]}}


def test_every_option_has_a_sample_and_a_refused_value():
    assert sorted(SAMPLES) == sorted(BAD) == sorted(MODEL_FIELDS + TRAIN_FIELDS)


def _param(command, name):
    """The click parameter of ``command`` whose value is the option (or switch) ``name``, or None."""
    return next((p for p in main.commands[command].params if p.name == name), None)


def _flag_args(name, value):
    """(command, the arguments that set option ``name`` to ``value``): its flag, its switch's flag
    or its fine-tuning flag, as a user types them."""
    if name in FINETUNE_ONLY:
        return "finetune", FINETUNE_ONLY[name][value]
    switch = [key for key, (option, set_to) in switches(TrainConfig).items() if option == name and set_to == value]
    param = _param("train", switch[0] if switch else name)
    assert param is not None, f"option {name} has no `mpnode train` flag"
    if param.is_flag:
        assert value is True or switch, f"{name}: a flag can only switch it on"
        return "train", [param.opts[0]]
    text = {tuple: lambda v: ",".join(map(str, v)), float: repr}.get(type(value), str)(value)
    if name == "time_limit":
        text = f"{value:g}s"
    return "train", [param.opts[0], text]


class Stop(Exception):
    """The stand-in training was called."""


@pytest.fixture
def cli(tmp_path, tiny_file, monkeypatch):
    """cli(command, args) -> (CliRunner result, the options the library was called with, or None):
    `mpnode train DATA -o OUT ...` or `mpnode finetune MODEL DATA -o OUT ...`, the training replaced
    by a stand-in that keeps its options."""
    import mpnode.runs
    import mpnode.runs.ensemble

    data = tiny_file(tmp_path / "d.h5", B=12, T=10)
    parent = str(tmp_path / "parent.h5")
    Model.create(2, dt=0.1, hidden=8).save(parent)
    given = []

    def keep(paths, output, options, **kwargs):  # train and train_ensemble
        given.append(dict(options))
        raise Stop  # nothing trains

    def keep_finetuned(model_path, paths, output, options, refit_norm=None, **kwargs):
        if refit_norm is not None:  # finetune's own argument: refit_norm=True is norm "refit"
            options = {**options, "norm": "refit" if refit_norm else "keep"}
        keep(paths, output, options)

    monkeypatch.setattr(mpnode.runs, "train", keep)
    monkeypatch.setattr(mpnode.runs.ensemble, "train_ensemble", keep)
    monkeypatch.setattr(mpnode.runs, "finetune", keep_finetuned)

    def invoke(command, args):
        head = ["train", data] if command == "train" else ["finetune", parent, data]
        result = CliRunner().invoke(main, head + ["-o", str(tmp_path / "m.h5")] + [str(a) for a in args])
        return result, (given[-1] if given else None)

    return invoke


@pytest.mark.parametrize("name", MODEL_FIELDS + TRAIN_FIELDS)
def test_each_flag_sets_its_option_and_nothing_else(cli, name):
    command, args = _flag_args(name, SAMPLES[name])
    result, options = cli(command, args)
    assert options is not None, f"{args}: the library was not called ({result.output})"
    model, config = runs.split_options(options)
    expected_model = dataclasses.replace(ModelConfig(), **({name: SAMPLES[name]} if name in MODEL_FIELDS else {}))
    expected = TrainConfig(**({name: SAMPLES[name]} if name in TRAIN_FIELDS else {})).check()
    if command == "finetune":
        expected.ensemble = config.ensemble  # fine-tuning one model: the parent's size, 1
    assert (model, config) == (expected_model, expected), args


@pytest.mark.parametrize("name", MODEL_FIELDS + TRAIN_FIELDS)
def test_the_library_and_the_flag_refuse_the_same_values(cli, name):
    with pytest.raises(InputError) as refused:
        runs.split_options({name: BAD[name]})
    assert name in str(refused.value)
    param = _param("train", name)
    if param is None or param.is_flag:
        return  # a switch (--clip-global, --refit-norm, --self-messages): no other value to give it
    result, options = cli(*_flag_args(name, BAD[name]))
    assert result.exit_code == 2 and options is None, (name, result.output)
    assert param.opts[0] in result.output or name in result.output, result.output


def _data_for(config, tiny_linear):
    """The tiny system's training data as a run prepares them for a model of ``config``."""
    datasets = runs.with_latent_dims([tiny_linear(B=12, T=10)], config)
    return TrainingData(datasets, TrainConfig().check(), ["tiny"])


@pytest.mark.parametrize("name", MODEL_FIELDS)
def test_model_create_makes_the_model_a_run_makes(name, tiny_linear):
    """Model.create(state_dim = the data's dimensions, option=value) is the model `mpnode train
    --option value` starts from (before the normalisation the run fits)."""
    config = runs.split_options({name: SAMPLES[name]})[0]
    data = _data_for(config, tiny_linear)
    from_run = runs.new_model(data, config)
    created = Model.create(state_dim=2, dt=0.1, n_nodes=2 if config.kind == "node" else None,
                           mean_degree=data.mean_in_degree(config.self_messages) if config.uses_mean_degree else None,
                           **{name: SAMPLES[name]})
    created.x_mean, created.x_std = from_run.x_mean, from_run.x_std  # the run's normalisation (kinematics follow it)
    assert created.spec == from_run.spec and created.dtype == from_run.dtype
    assert created.latent_dims == from_run.latent_dims == config.latent_dims
    np.testing.assert_array_equal(created.theta, from_run.theta)  # the same seed, the same weights


def test_model_create_honours_latent_dims():
    model = Model.create(state_dim=2, latent_dims=3)
    assert model.latent_dims == 3 and model.spec.state_dim == 5


def test_a_run_from_flags_is_the_run_from_the_library(tmp_path, tiny_file):
    """Every training option set at once, through the flags and through `mpnode.runs.train`: one
    checkpointed configuration, one model (the ensemble, the fine-tuning normalisation and the
    time limit, which would make the run another kind or its length the clock's, are left out)."""
    data = tiny_file(tmp_path / "d.h5", B=12, T=10)
    options = {k: SAMPLES[k] for k in TRAIN_FIELDS if k not in ("ensemble", "norm", "time_limit")}
    args = [a for k in options for a in _flag_args(k, options[k])[1]]
    result = CliRunner().invoke(main, ["train", data, "-o", str(tmp_path / "cli.h5"), "--hidden", "8", *args])
    assert result.exit_code == 0, result.output
    runs.train([data], str(tmp_path / "lib.h5"), {**options, "hidden": 8})
    configs = [json.loads(str(np.load(tmp_path / f"{w}.h5.state")["config"])) for w in ("cli", "lib")]
    assert configs[0] == configs[1]
    assert {k: configs[0][k] for k in options} == json.loads(json.dumps(options))
    np.testing.assert_array_equal(Model.load(tmp_path / "cli.h5").theta, Model.load(tmp_path / "lib.h5").theta)


def test_one_model_options_refuse_an_ensemble_where_a_run_is_one_model(tmp_path, tiny_file):
    """An ensemble is K models into one file: `runs.train` and a sweep's run refuse ``ensemble`` > 1
    before any work (the command line routes it to mpnode.runs.ensemble.train_ensemble)."""
    from mpnode.runs.sweep import read_sweep

    data = tiny_file(tmp_path / "d.h5", B=12, T=10)
    with pytest.raises(InputError, match="ensemble"):
        runs.train([data], str(tmp_path / "m.h5"), {"ensemble": 2})
    sweep = tmp_path / "s.toml"
    sweep.write_text('data = ["d.h5"]\n[train]\nepochs = 1\nensemble = 2\n')
    with pytest.raises(InputError, match="ensemble"):
        read_sweep(sweep)
    assert not (tmp_path / "m.h5").exists()


def test_the_sweep_parses_curriculum_and_clipping_as_the_flags_do(tmp_path, tiny_file):
    from mpnode.runs.sweep import read_sweep

    tiny_file(tmp_path / "d.h5", B=12, T=10)
    sweep = tmp_path / "s.toml"
    sweep.write_text('data = ["d.h5"]\n[train]\nepochs = 1\ncurriculum = "2,4,full"\nclip_global = true\n')
    options = read_sweep(sweep).runs[0].options
    assert options["curriculum"] == (2, 4) and options["clip_mode"] == "global"
    sweep.write_text('data = ["d.h5"]\n[train]\ncurriculum = "4,2"\n')
    with pytest.raises(InputError, match="curriculum"):
        read_sweep(sweep)
