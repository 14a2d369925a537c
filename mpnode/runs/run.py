"""One training run from files and options: the function behind `mpnode train` and `finetune`,
the sweeps and the paper suite, so that each of them trains a model the same way.

Options are the command line's, with underscores: the model's (``kind``, ``message_dim``,
``hidden``, ``zero_messages``, ``self_messages``, ``aggregation``, ``linear_aggregate``,
``linear_aggregation``, ``linear_target``, ``substeps``, ``dtype``) and every `TrainConfig` field, ``time_limit``
in seconds.  What the options leave unset comes from a recipe (mpnode.training.recipes: ``auto``, the
best measured for the data's system, or ``paper``), then from the defaults.
"""
import dataclasses
import os

import numpy as np

from mpnode.base.errors import InputError
from mpnode.data import read_trajectories
from mpnode.evaluation.evaluate import evaluate, subset
from mpnode.model import Model
from mpnode.training import TrainConfig, fit
from mpnode.training.batches import make_split
from mpnode.training.recipes import finetune_recipe, recipe

#: the model options and their defaults (TrainConfig's fields are the training options)
MODEL_OPTIONS = {"kind": "mpnode", "message_dim": 3, "hidden": 32, "zero_messages": False, "self_messages": False,
                 "aggregation": None, "linear_aggregate": False, "linear_aggregation": None,
                 "linear_target": "all", "substeps": 1,
                 "dtype": "float32"}
TRAIN_OPTIONS = {f.name: f.default for f in dataclasses.fields(TrainConfig)}


def split_options(options, source="options"):
    """(model options, TrainConfig) from one dict of options; InputError names an unknown one."""
    model, train = dict(MODEL_OPTIONS), {}
    for key, value in (options or {}).items():
        if key in MODEL_OPTIONS:
            model[key] = value
        elif key in TRAIN_OPTIONS:
            train[key] = value
        else:
            raise InputError(source, key, "is not a training option",
                             "one of " + ", ".join(sorted(MODEL_OPTIONS) + sorted(TRAIN_OPTIONS)))
    try:
        config = TrainConfig(**train)
    except TypeError as e:
        raise InputError(source, "options", str(e), "training options with values of the right type") from None
    return model, config.check()


def mean_in_degree(datasets, self_messages, split=None):
    """The mean in-degree over every node of every training trajectory of ``datasets`` (+1 when
    nodes hear themselves): the ``scaled`` aggregation's divisor.  split: each file's (train
    idx, val idx) (mpnode.training.batches.make_split), or None for all trajectories."""
    total = count = 0
    for f, traj in enumerate(datasets):
        gi = np.asarray(traj.graph_index)
        if split is not None:
            gi = gi[split[f][0]]
        used = np.bincount(gi, minlength=len(traj.graphs))
        for g, times in zip(traj.graphs, used):
            total += times * (g.n_edges + (g.n_nodes if self_messages else 0))
            count += times * g.n_nodes
    return total / count


def new_model(datasets, kind="mpnode", message_dim=3, hidden=32, zero_messages=False, self_messages=False,
              aggregation=None, linear_aggregate=False, linear_aggregation=None, linear_target="all", substeps=1,
              dtype="float32", seed=0, split=None):
    """A fresh model for the system of ``datasets`` (their dx, du and dt; a node model their N;
    the scaled aggregation's mean degree from the training split ``split``, see mean_in_degree)."""
    first = datasets[0]
    n_nodes = None
    if kind == "node":
        sizes = {t.n_nodes for t in datasets}
        if len(sizes) > 1:
            raise InputError("training data", "N", f"the files have {sorted(sizes)} nodes",
                             "one node count for a plain neural ODE (kind node)")
        n_nodes = sizes.pop()
    scaled = "scaled" in (aggregation, linear_aggregation)
    mean_degree = mean_in_degree(datasets, self_messages, split) if scaled else None
    return Model.create(first.state_dim, first.control_dim, message_dim, hidden, first.dt, substeps, zero_messages,
                        self_messages, seed=seed, dtype=np.dtype(dtype), kind=kind, aggregation=aggregation,
                        mean_degree=mean_degree, n_nodes=n_nodes, linear_aggregate=linear_aggregate,
                        linear_aggregation=linear_aggregation, linear_target=linear_target)


def read_all(paths):
    return [read_trajectories(p) for p in paths]


def _attrs(paths, datasets, **more):
    return {"trained_on": ";".join(os.path.abspath(p) for p in paths), "system": datasets[0].system, **more}


def with_recipe(options, name, system):
    """(options completed by recipe ``name`` for ``system``, the recipe's settings used)."""
    options = dict(options or {})
    messages = options.get("message_dim", MODEL_OPTIONS["message_dim"]) != 0 and not options.get("zero_messages")
    return fill_unset(options, recipe(name, system, options.get("kind", MODEL_OPTIONS["kind"]), messages))


def fill_unset(options, settings):
    """(``options`` completed by the ``settings`` they leave unset, the settings used)."""
    used = {k: v for k, v in settings.items() if k not in options}
    return {**used, **options}, used


def _announce(notify, chosen, what):
    """Tell the user which settings a recipe chose (none: say nothing)."""
    if notify and chosen:
        notify(f"{what}: " + ", ".join(f"{k} {v}" for k, v in chosen.items()) + " (each has its own option)")


def train(paths, output, options=None, *, recipe_name="auto", resume=False, progress=None, notify=None,
          datasets=None, names=None):
    """Train a new model on the trajectory files ``paths`` (or continue the run beside ``output``).

    options : see the module docstring; what they leave unset comes from ``recipe_name``
    (the model records the recipe and what it chose).  Returns the TrainResult (its model is
    the best one, also saved at ``output`` with the log and the checkpoint beside it).
    names : what to call the files in the model's attributes and in messages (default: ``paths``;
    a sweep's worker trains on copies and names the originals).
    """
    datasets = datasets or read_all(paths)
    options, chosen = with_recipe(options, recipe_name, datasets[0].system)
    if not resume:
        _announce(notify, chosen, f"recipe {recipe_name} for {datasets[0].system}")
    model_options, config = split_options(options)
    model = None
    if not resume:
        model = new_model(datasets, **model_options, seed=config.seed, split=make_split(datasets, config))
    names = names or paths
    attrs = _attrs(names, datasets, recipe=recipe_name, schedule=config.schedule)
    return fit(model, datasets, config, output, sources=list(map(str, names)), resume=resume, progress=progress,
               notify=notify, model_attrs=attrs)


def finetune(model_path, paths, output, options=None, *, refit_norm=False, recipe_name="auto", resume=False,
             progress=None, notify=None, datasets=None, names=None, parent_name=None):
    """Continue training the model in ``model_path`` on ``paths``: exactly its weights, settings
    and (unless ``refit_norm``) normalisation; model options other than substeps are the model's.
    The training options the user leaves unset come from ``recipe_name``'s fine-tuning settings.
    names, parent_name : what to call the data files and the model in attributes (see `train`)."""
    datasets = datasets or read_all(paths)
    options = dict(options or {})
    fixed = {k for k in options if k in MODEL_OPTIONS and k != "substeps"}
    if fixed:
        raise InputError("options", sorted(fixed)[0], "cannot change when fine-tuning",
                         "only training options (and substeps); the model keeps its kind and sizes")
    model = None if resume else Model.load(model_path)
    if not resume:
        options, chosen = fill_unset(options, finetune_recipe(recipe_name, model.kind))
        _announce(notify, chosen, f"recipe {recipe_name} for fine-tuning")
    model_options, config = split_options({"norm": "refit" if refit_norm else "keep", **options})
    if model is not None and "substeps" in options:
        model = model.with_spec(substeps=int(model_options["substeps"]))
    names = names or paths
    attrs = _attrs(names, datasets, finetuned_from=parent_name or os.path.abspath(model_path),
                   finetune_recipe=recipe_name)
    return fit(model, datasets, config, output, sources=list(map(str, names)), resume=resume, progress=progress,
               notify=notify, model_attrs=attrs)


def validation_errors(result, datasets, sources):
    """Normalised MSE of the best model on each file's validation split:
    list of (source, trajectories, nmse over steps, nmse at the last step)."""
    out = []
    for traj, src, (_, val) in zip(datasets, sources, result.split):
        if len(val):
            r = evaluate(result.model, subset(traj, val), source=src, check_stability=False)
            out.append((src, len(val), r.nmse, r.nmse_last))
    return out


def parse_duration(value, source="--time-limit"):
    """Seconds of a duration: a number of minutes ("10", 10) or a number with a unit ("90s",
    "5m", "1.5h"); None stays None.  InputError for anything else or a value <= 0."""
    if value is None:
        return None
    text = str(value).strip().lower()
    scale = {"s": 1.0, "m": 60.0, "h": 3600.0}.get(text[-1:], None)
    number = text[:-1] if scale else text
    try:
        seconds = float(number) * (scale or 60.0)
    except ValueError:
        seconds = float("nan")
    if not seconds > 0 or seconds == float("inf"):
        raise InputError(source, str(value), "is not a duration", "minutes (10), or a number with s, m or h (90s, 1.5h)")
    return seconds
