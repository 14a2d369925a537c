"""Everything a sweep's runs can check before the first one starts (docs/sweep-format.md).

A sweep promises that a value that cannot work stops it before any run: not after one run
has trained its whole budget.  So every file is read and checked once (the trajectory
format), and for every run: its data files agree with one another (and with its parent's),
its test files fit the model it will train (dx, du, dt, and N for a node model), the data
can be learned (mpnode.training.learnable), the training fits in memory, and nothing it
reads lies where the sweep writes.  Test files of another system than the training data
(with the same sizes) are allowed -- a transfer may be meant -- and come back as warnings.
"""
import os

from mpnode.base.errors import InputError
from mpnode.data import read_trajectories
from mpnode.model.config import configured
from mpnode.training.batches import TrainingData, check_same_kind, split_settings
from mpnode.training.recipes import recipe
from mpnode.training.sizes import check_training_memory

from .run import MODEL_OPTIONS, split_options


def check_runs(plans, path):
    """InputError for the first run (RunPlans, parents first) that could not train or be
    evaluated; returns the warnings (sentences)."""
    files, prepared, models, warnings = {}, {}, {}, []

    def load(f):  # each file read once
        if f not in files:
            files[f] = read_trajectories(f)
        return files[f]

    for p in plans:
        own = {k: v for k, v in p.options.items() if k in MODEL_OPTIONS}
        models[p.name] = own if p.parent is None else {**models[p.parent], **own}
        parent_data = [] if p.parent is None else next(q.data[:1] for q in plans if q.name == p.parent)
        warnings += _check_run(p, configured(models[p.name]), parent_data, load, prepared, f"{path}: run {p.name}")
    return list(dict.fromkeys(warnings))


def _check_run(p, model, parent_data, load, prepared, where):
    """The checks of one run (module docstring); returns its warnings."""
    datasets = [load(f) for f in parent_data + p.data]
    check_same_kind(datasets, [os.path.relpath(f) for f in parent_data + p.data])
    if model.kind == "node" and len({t.n_nodes for t in datasets}) > 1:
        raise InputError(where, "data", f"the files have {sorted({t.n_nodes for t in datasets})} nodes",
                         "one node count for a plain neural ODE (kind node)")
    warnings = [w for t in p.test for w in _check_test(load(t), os.path.relpath(t), datasets[0], model.kind)]
    _check_points_schedule(p, model, datasets[0].system, where)
    config = split_options(p.options, where)[1]
    key = (tuple(p.data), split_settings(config))
    if key not in prepared:  # runs on the same data and split share the checks of their data
        prepared[key] = TrainingData([load(f) for f in p.data], config, [os.path.relpath(f) for f in p.data])
    first = datasets[0]
    spec = model.spec(first.state_dim, first.control_dim, first.dt, first.n_nodes if model.kind == "node" else None,
                      1.0 if model.uses_mean_degree else None)
    check_training_memory(spec, prepared[key], config, model.dtype)
    return warnings


def _check_points_schedule(p, model, system, where):
    """InputError for test points on a run whose recipe chooses the cosine schedule (the sweep
    refuses a cosine set in the file itself): the run trains in segments, each would end it."""
    if not p.test_points or p.parent is not None or "schedule" in p.options:
        return
    if recipe(p.recipe, system, model.kind, model.messages).get("schedule") == "cosine":
        raise InputError(where, "test_points", f"cannot be used with the cosine schedule recipe {p.recipe} chooses "
                         f"for {system} data (the run trains in segments, and each would end the schedule)",
                         'schedule = "plateau" for the run, or no test_points')


def _check_test(test, name, data, kind):
    """InputError when the model trained on ``data`` could not be evaluated on ``test``; the
    warning when the systems differ."""
    for what, a, b in (("x", test.state_dim, data.state_dim), ("u", test.control_dim, data.control_dim)):
        if a != b:
            raise InputError(name, what, f"has {a} dimensions per node but the training data have {b}",
                             "test files of the system the runs train on")
    if abs(test.dt - data.dt) > 1e-9 * abs(data.dt):
        raise InputError(name, "dt", f"is {test.dt:g} but the training data have dt = {data.dt:g}",
                         "test files saved at the training data's dt")
    if kind == "node" and test.n_nodes != data.n_nodes:
        raise InputError(name, "x", f"has {test.n_nodes} nodes but a node model runs on its training data's "
                         f"{data.n_nodes} only", "test files of the training data's size (or an mpnode model)")
    if test.system != data.system:
        return [f"test file {name} holds {test.system} data, the runs train on {data.system}"]
    return []


def check_out_folder(sweep, out):
    """InputError when a file the sweep reads (its file, data, test files) lies where it
    writes: in a run's folder under OUT/runs/ (emptied when the run starts) or as OUT's summary."""
    runs = os.path.realpath(os.path.join(out, "runs"))
    written = {os.path.realpath(os.path.join(out, name)) for name in ("summary.csv", "summary.md")}
    inputs = [("sweep file", sweep.path)] + [(f"run {p.name}", f) for p in sweep.runs for f in p.data + p.test]
    for owner, f in inputs:
        real = os.path.realpath(f)
        if real in written or real.startswith(runs + os.sep):
            raise InputError(sweep.path, owner, f"reads {f}, which lies where the sweep writes ({out}): a run's "
                             "folder is emptied when it starts, the summary rewritten as runs finish",
                             "input files outside the output folder's runs/ and summary files (move them, or "
                             "choose another -o)")
