"""One training run from files and options: the function behind `mpnode train` and `finetune`,
the sweeps and the paper suite, so that each of them trains a model the same way.

Options are one dict of the model's options (`ModelConfig`'s fields) and the training's
(`TrainConfig`'s, ``time_limit`` in seconds), each under its name, an older one or a switch
of it (``clip_global``: True is ``clip_mode`` "global").  What the
options leave unset comes from a recipe (mpnode.training.recipes: ``auto``, the best measured
for the data's system, or ``paper``), then from the defaults.
"""
import os

from mpnode.base.arguments import check_bool, check_mapping, check_path, check_paths
from mpnode.base.errors import InputError
from mpnode.base.options import defaults, option_names, switches
from mpnode.data import read_trajectories
from mpnode.engine import numba_problem
from mpnode.model import Model
from mpnode.model.config import ModelConfig, configured
from mpnode.model.ensemble import Ensemble
from mpnode.model.inputs import for_model
from mpnode.model.provenance import system_mismatch
from mpnode.model.ranges import KEY as RANGES
from mpnode.model.ranges import training_ranges
from mpnode.training import TrainConfig, fit, state_path
from mpnode.training.batches import TrainingData
from mpnode.training.recipes import finetune_recipe, recipe
from mpnode.training.sizes import check_training_memory
from mpnode.training.state import check_resume_options

#: the options of a run and their defaults: the model's and the training's
MODEL_OPTIONS = defaults(ModelConfig)
TRAIN_OPTIONS = defaults(TrainConfig)
#: every name an option is known by (older names too) -> the option
OPTION_NAMES = {**option_names(ModelConfig), **option_names(TrainConfig)}
#: the keys that switch an option to one value -> (the option, the value)
SWITCHES = {**switches(ModelConfig), **switches(TrainConfig)}


def canonical(options, source="options"):
    """``options`` with every key under its option's name (a switch set: its option at its
    value; left false: nothing); InputError names an unknown key."""
    out = {}
    for key, value in (options or {}).items():
        if key in SWITCHES:
            if check_bool(value, source, key):
                out[SWITCHES[key][0]] = SWITCHES[key][1]
        elif key in OPTION_NAMES:
            out[OPTION_NAMES[key]] = value
        else:
            raise InputError(source, key, "is not a training option",
                             "one of " + ", ".join(sorted(MODEL_OPTIONS) + sorted(TRAIN_OPTIONS) + sorted(SWITCHES)))
    return out


def split_options(options, source="options"):
    """(ModelConfig, TrainConfig) of one dict of options; InputError names an unknown option or
    a value that cannot work."""
    options = canonical(options, source)
    train = {k: v for k, v in options.items() if k in TRAIN_OPTIONS}
    try:
        model = configured({k: v for k, v in options.items() if k in MODEL_OPTIONS})
        config = TrainConfig(**train).check()
    except InputError as e:
        raise InputError(source, e.field, e.problem, e.expected) from None
    except TypeError as e:
        raise InputError(source, "options", str(e), "training options with values of the right type") from None
    return model, config


def new_model(data, config, train_config=None):
    """A fresh model of ``config`` (a ModelConfig) for the system of ``data`` (a TrainingData, its
    trajectories with room for the config's latent dimensions: `with_latent_dims`): its dx, du
    and dt, a node model its N, and from the training split the normalisation and, for the
    "scaled" aggregation, the mean in-degree.  InputError first when training it under
    ``train_config`` (default: the defaults) would need more memory than the machine has."""
    train_config = train_config or TrainConfig()
    first = data.datasets[0]
    dx = first.state_dim - config.latent_dims  # the data's own: the model adds its latent dimensions
    n_nodes = None
    if config.kind == "node":
        sizes = {t.n_nodes for t in data.datasets}
        if len(sizes) > 1:
            raise InputError("training data", "N", f"the files have {sorted(sizes)} nodes",
                             "one node count for a plain neural ODE (kind node)")
        n_nodes = sizes.pop()
    mean_degree = data.mean_in_degree(config.self_messages) if config.uses_mean_degree else None
    spec = config.spec(dx, first.control_dim, first.dt, n_nodes, mean_degree, len(data.attr_names),
                       data.weight_scale)  # the data's controls: node attributes included (TrainingData)
    check_training_memory(spec, data, train_config, config.dtype)
    model = Model.create(dx, first.control_dim - len(data.attr_names), dt=first.dt, seed=train_config.seed, n_nodes=n_nodes,
                         mean_degree=mean_degree, config=config, attr_names=data.attr_names,
                         weight_scale=data.weight_scale)
    x_mean, x_std, u_mean, u_std = data.normalization()
    model.x_mean, model.x_std = x_mean, x_std
    if u_mean is not None:
        model.u_mean, model.u_std = u_mean, u_std
    return model


def read_all(paths):
    return [read_trajectories(p) for p in paths]


def with_latent_dims(datasets, config):
    """``datasets`` with room for the latent dimensions of ``config`` (a ModelConfig): never
    observed, so the recipe and the split see them as the model will."""
    return [t.with_hidden_dims(config.latent_dims) for t in datasets]


def _attrs(paths, datasets, **more):
    return {"trained_on": ";".join(os.path.abspath(p) for p in paths), "system": datasets[0].system, **more}


def with_recipe(options, name, datasets):
    """(options completed by recipe ``name`` for the system of ``datasets``, the recipe's settings used)."""
    options = canonical(options)
    model = configured({k: v for k, v in options.items() if k in MODEL_OPTIONS})
    complete = all(t.complete for t in datasets)
    ignore_attrs = check_bool(options.get("ignore_attrs", False), "options", "ignore_attrs")
    weighted = any(t.weighted for t in datasets) and not ignore_attrs
    return fill_unset(options, recipe(name, datasets[0].system, model.kind, model.messages, complete, weighted))


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
    paths, output, options, resume = _arguments("mpnode.runs.train", paths, output, options, resume)
    require_numba()
    datasets = datasets or read_all(paths)
    if resume:
        check_resume_options(state_path(output), canonical(options))
    datasets = with_latent_dims(datasets, split_options(options)[0])
    options, chosen = with_recipe(options, recipe_name, datasets)
    model_config, config = split_options(options)
    one_model(config)
    names = list(map(str, names or paths))
    data = TrainingData(datasets, config, names)
    model = None if resume else new_model(data, model_config, config)
    if not resume:  # once every check has passed
        _announce(notify, chosen, f"recipe {recipe_name} for {datasets[0].system}")
    hidden = [int(k) for k in data.unmeasured_dims()]
    attrs = _attrs(names, datasets, recipe=recipe_name, schedule=config.schedule,
                   **({"unmeasured_dims": hidden} if hidden else {}))
    return with_ranges(fit(model, data, config, output, resume=resume, progress=progress, notify=notify,
                           model_attrs=attrs), data.datasets, output)


def finetune(model_path, paths, output, options=None, *, refit_norm=None, recipe_name="auto", resume=False,
             progress=None, notify=None, datasets=None, names=None, parent_name=None):
    """Continue training the model in ``model_path`` on ``paths``: exactly its weights and settings;
    model options other than substeps are the model's.  refit_norm : fit the normalisation on the
    new training split (True) or keep the model's (False); None: as the recipe says (``norm``).
    The training options the user leaves unset come from ``recipe_name``'s fine-tuning settings.
    names, parent_name : what to call the data files and the model in attributes (see `train`)."""
    paths, output, options, resume = _arguments("mpnode.runs.finetune", paths, output, options, resume)
    model_path = check_path(model_path, "mpnode.runs.finetune", "model_path")
    if refit_norm is not None:
        refit_norm = check_bool(refit_norm, "mpnode.runs.finetune", "refit_norm")
    require_numba()
    datasets = datasets or read_all(paths)
    options = canonical(options)
    fixed = {k for k in options if k in MODEL_OPTIONS and k != "substeps"}
    if fixed:
        raise InputError("options", sorted(fixed)[0], "cannot change when fine-tuning",
                         "only training options (and substeps); the model keeps its kind and sizes")
    if refit_norm is not None:
        options["norm"] = "refit" if refit_norm else "keep"
    if resume:
        check_resume_options(state_path(output), options)
    model = None if resume else Model.load(model_path)
    if isinstance(model, Ensemble):
        raise InputError(model_path, "ensemble_size", f"is an ensemble of {model.size} models",
                         "mpnode.runs.ensemble.train_ensemble (the command line: finetune --ensemble K)")
    names = list(map(str, names or paths))
    if model is not None:
        datasets = [model.fitted(t) for t in datasets]
        check_finetune_inputs(model, datasets, names, check_bool(options.get("ignore_attrs", False), "options",
                                                                 "ignore_attrs"))
    if not resume:
        options, chosen = fill_unset(options, finetune_recipe(recipe_name, model.kind, datasets[0].system))
        _announce(notify, chosen, f"recipe {recipe_name} for fine-tuning")
        warning = system_mismatch(model, datasets[0].system, names[0])
        if warning and notify:
            notify(f"warning: {warning}")
    model_config, config = split_options({"norm": "keep", **options})
    one_model(config)
    if model is not None and "substeps" in options:
        model = model.with_spec(substeps=model_config.substeps)
    attrs = _attrs(names, datasets, finetuned_from=parent_name or os.path.abspath(model_path),
                   finetune_recipe=recipe_name)
    data = TrainingData(datasets, config, names)
    return with_ranges(fit(model, data, config, output, resume=resume, progress=progress, notify=notify,
                           model_attrs=attrs), data.datasets, output)


def check_finetune_inputs(model, datasets, names, ignore_attrs):
    """InputError, before any work, unless the files' node attributes and edge weights are the
    model's (as `mpnode eval` checks them: mpnode.model.inputs.for_model); ``ignore_attrs`` leaves
    out those of a model trained without them, and a model that hears attributes cannot."""
    heard = ([f"node attributes ({', '.join(model.attr_names)})"] if model.attr_names else []) + \
        (["edge weights"] if model.spec.aggregation.weight_scale is not None else [])
    if ignore_attrs and heard:
        raise InputError("options", "ignore_attrs", f"is set, but the model hears {' and '.join(heard)}",
                         "no --ignore-attrs: fine-tuning keeps what the model hears")
    for traj, name in zip(datasets, names):
        for_model(model, traj, name, ignore_attrs)


def with_ranges(result, datasets, output):
    """``result`` with what its model saw in training recorded (mpnode.model.ranges), in the
    model and in its file at ``output``: eval, simulate and the Simulator warn beyond them."""
    seen = training_ranges(result.model, datasets, result.split)
    result.model.attrs[RANGES] = seen
    saved = Model.load(output)
    saved.attrs[RANGES] = seen
    saved.save(output)
    return result


def one_model(config, source="options"):
    """InputError for ``ensemble`` > 1: `train` and `finetune` make one model (a sweep key or an
    options dict asking for more would otherwise be dropped silently)."""
    if config.ensemble > 1:
        raise InputError(source, "ensemble", f"is {config.ensemble}", "1 here; K members into one file: "
                         "mpnode.runs.ensemble.train_ensemble (mpnode train --ensemble K)")


def _arguments(where, paths, output, options, resume):
    """The common arguments of `train` and `finetune`, checked as the command line checks them."""
    return (check_paths(paths, where), check_path(output, where, "output"), check_mapping(options, where, "options"),
            check_bool(resume, where, "resume"))


def require_numba():
    """ImportError saying why, before anything is read or written, where numba cannot be
    imported: training needs its compiled gradients (evaluation and simulation do not)."""
    problem = numba_problem()
    if problem is not None:
        raise ImportError(f"training needs numba, which cannot be imported here ({problem}): install it "
                          "(pip install numba); evaluating and simulating models work without it")


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
