"""A sweep: many training runs from one TOML file, run as independent tasks (docs/sweep-format.md).

    data = ["train.h5"]      # training files; every run trains on all of them
    [train]                  # settings shared by every run: any `mpnode train` option, with underscores
    epochs = 300
    [grid]                   # every combination is one run
    message_dim = [1, 3, 7]
    seed = [0, 1]

Each run is one task (`run_task`) on an mpnode.runs.executors Farm (a local process pool or
Dask).  It trains with the library function behind `mpnode train` / `finetune` (mpnode.runs),
evaluates the best model (with ``test_points``, also at evenly spaced epochs along the way)
and returns the evaluation.  On the local pool it trains in the run's own folder OUT/runs/NAME/,
so a run whose process was killed resumes from its checkpoint next time; on Dask it receives
the data files' bytes (no shared filesystem is assumed), trains in a temporary folder and
sends back the model file, its log and the models of its test points.  The client
(`run_sweep`) writes the result under OUT/runs/NAME/ and rewrites OUT/summary.csv and
OUT/summary.md as each run finishes; a run whose result is on disk with the same settings
and data is not redone, so an interrupted sweep continues where it stopped.  A run that
raises is reported in the summary (and redone next time) while the others go on; a
fine-tune child starts when its parent has finished.  Runs declared in Python (the paper
suite's) become a Sweep through `make_sweep`.
"""
import csv
import dataclasses
import hashlib
import io
import itertools
import json
import math
import os
import shutil
import tempfile
from concurrent.futures import FIRST_COMPLETED, wait
from concurrent.futures.process import BrokenProcessPool

from mpnode.base.atomic import atomic_path
from mpnode.base.errors import InputError
from mpnode.base.tomlfile import load_toml
from mpnode.training import recipes, state_path
from mpnode.training.config import DEFAULT_EPOCHS, parse_curriculum
from mpnode.training.log import log_path

from .preflight import check_out_folder, check_runs
from .run import MODEL_OPTIONS, OPTION_NAMES, canonical, one_model, parse_duration, split_options

#: what a sweep file may hold at its top level
TOP_KEYS = ("data", "test", "test_points", "recipe", "train", "grid", "run")
#: keys of a [[run]] table that are not training options
RUN_KEYS = ("name", "from", "data", "test", "test_points", "refit_norm", "recipe")
#: times a run is resubmitted after the process running it died (Dask reschedules on its own)
LOST_RETRIES = 2
#: statuses of a finished training (fit's), as opposed to "failed" (the task raised) and "pending"
FINISHED = ("completed", "time_limit", "diverged")
#: a run's files in its folder (OUT/runs/NAME/): the model, and while it trains on the local pool,
#: the key of the training under way (a rerun resumes it when the key is the same) and its test points
MODEL, STARTED, POINTS = "model.h5", "started.json", "test_points.jsonl"


@dataclasses.dataclass
class RunPlan:
    """One run: ``options`` are mpnode.runs options; ``parent`` the run it fine-tunes (or None)."""

    name: str
    options: dict
    data: list
    recipe: str = "auto"
    parent: str = None
    refit_norm: bool = None  # None: the recipe decides
    settings: str = ""  # what sets this run apart, for the summary
    parent_model: str = None  # where the parent's model file is on the client (for the model's attributes)
    key: str = ""  # digest of everything that decides the run (settings, data contents, parent's key)
    test: list = None  # test files its best model is evaluated on
    test_points: int = 0  # evaluations on them at evenly spaced epochs besides epoch 0 (0: at the end only)
    folder: str = None  # where it trains: its folder on the client (local pool), or None (a temporary one)


@dataclasses.dataclass
class Sweep:
    path: str
    runs: list  # RunPlan, parents before children
    test: list  # the sweep's test files (a run may have its own)
    warnings: list = dataclasses.field(default_factory=list)  # what the checks allow but a user should know


# ---------------------------------------------------------------------------
# Reading the file
# ---------------------------------------------------------------------------
def read_sweep(path):
    """The Sweep of TOML file ``path``; InputError naming the key for anything that cannot run."""
    path = os.fspath(path)
    doc = load_toml(path, "a sweep file (docs/sweep-format.md)")
    for key in doc:
        if key not in TOP_KEYS:
            raise InputError(path, key, "is not a sweep key", "one of " + ", ".join(TOP_KEYS))
    folder = os.path.dirname(os.path.abspath(path))
    data = _files(doc, "data", path, folder, required=True)
    test = _files(doc, "test", path, folder, required=False)
    shared = _table(doc, "train", path)
    recipe = _text(doc.get("recipe", shared.pop("recipe", "auto")), path, "recipe")
    plans = _grid_runs(doc, shared, data, recipe, path) + _listed_runs(doc, shared, data, recipe, path, folder)
    for p in plans:  # what a run does not set itself, the sweep sets
        p.test = test if p.test is None else p.test
        p.test_points = doc.get("test_points", 0) if p.test_points is None else p.test_points
    return make_sweep(path, plans, test)


def make_sweep(path, plans, test=()):
    """The Sweep of ``plans`` (RunPlans: read from a file, or declared in Python as the paper
    suite does): each checked, with its files (mpnode.runs.preflight), parents before children,
    each keyed.  ``path`` names the sweep (the summary's title; test files are named relative
    to its folder)."""
    plans = _order(plans, path)
    for p in plans:
        _check_plan(p, path)
    warnings = check_runs(plans, path)
    files = {f for p in plans for f in p.data + p.test}
    digests = {f: file_digest(f) for f in sorted(files)}
    keys = {}
    for p in plans:
        decided = {"options": p.options, "recipe": [p.recipe, recipes.tables(p.recipe)], "refit_norm": p.refit_norm,
                   "data": [digests[f] for f in p.data], "test": [digests[f] for f in p.test],
                   "parent": keys.get(p.parent)}
        if p.test_points:  # only then: the keys of sweeps without test points stay what they were
            decided["test_points"] = p.test_points
        p.key = _digest(decided)
        keys[p.name] = p.key
    return Sweep(path, plans, list(test), warnings)


def _check_plan(p, path):
    """InputError for a run that cannot run as declared (its options, its test points)."""
    p.test = list(p.test or [])
    where = f"run {p.name}"
    one_model(split_options(p.options, f"{path}: {where}")[1], f"{path}: {where}")  # a run is one model
    points = p.test_points or 0
    if isinstance(points, bool) or not isinstance(points, int) or points < 0:
        raise InputError(path, f"{where}.test_points", f"is {points!r}", "a whole number of evaluations >= 0")
    if points and not p.test:
        raise InputError(path, f"{where}.test_points", "needs test files", "a `test` list for the run or the sweep")
    if points and p.options.get("schedule") == "cosine":
        raise InputError(path, f"{where}.test_points", "cannot be used with the cosine schedule (the run trains "
                         "in segments, and each would end the schedule)", "schedule plateau, or no test_points")
    p.test_points = points


def _files(doc, key, path, folder, required):
    value = doc.get(key)
    if value is None and not required:
        return []
    if isinstance(value, str):
        value = [value]
    if not value or not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise InputError(path, key, f"is {value!r}", "a list of trajectory files, e.g. [\"train.h5\"]")
    out = []
    for v in value:
        p = os.path.normpath(os.path.join(folder, os.path.expanduser(v)))
        if not os.path.isfile(p):
            raise InputError(path, key, f"{v!r} does not exist (looked for {p})",
                             "trajectory files, relative to the sweep file's folder")
        out.append(p)
    return out


def _table(doc, key, path):
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise InputError(path, key, f"is {value!r}", f"a table [{key}]")
    return {OPTION_NAMES.get(k, k): v for k, v in value.items()}


def _text(value, path, field):
    if not isinstance(value, str):
        raise InputError(path, field, f"is {value!r}", "a string")
    return value


def _grid_runs(doc, shared, data, recipe, path):
    grid = _table(doc, "grid", path)
    if not grid and doc.get("run"):
        return []
    for k, values in grid.items():
        if not isinstance(values, list) or not values:
            raise InputError(path, f"grid.{k}", f"is {values!r}", "a non-empty list of values, one per run")
    plans = []
    for combo in itertools.product(*grid.values()):
        own = dict(zip(grid, combo))
        name = ",".join(f"{k}={_label(v)}" for k, v in own.items()) or "run"
        options = {**shared, **own}
        run_recipe = _text(options.pop("recipe", recipe), path, f"grid.recipe ({name})")
        plans.append(RunPlan(name, _options(options, path, f"grid ({name})"), data, run_recipe,
                             settings=_describe(own), test_points=None))
    return plans


def _listed_runs(doc, shared, data, recipe, path, folder):
    runs = doc.get("run", [])
    if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
        raise InputError(path, "run", f"is {runs!r}", "[[run]] tables")
    plans = []
    for i, table in enumerate(runs):
        where = f"run[{i}]"
        table = {OPTION_NAMES.get(k, k): v for k, v in table.items()}
        name = table.pop("name", None)
        if not isinstance(name, str) or not name or "/" in name or name.startswith("."):
            raise InputError(path, f"{where}.name", f"is {name!r}", "a name for the run's folder (no '/')")
        parent = table.pop("from", None)
        files = _files(table, "data", path, folder, required=False) or data
        tests = _files(table, "test", path, folder, required=False) if "test" in table else None
        points = table.pop("test_points", None)
        table.pop("data", None), table.pop("test", None)
        refit = table.pop("refit_norm", None)
        if refit is not None and not isinstance(refit, bool):
            raise InputError(path, f"{where}.refit_norm", f"is {refit!r}", "true or false (absent: the recipe's)")
        run_recipe = _text(table.pop("recipe", recipe), path, f"{where}.recipe")
        base = shared if parent is None else {k: v for k, v in shared.items() if k not in MODEL_OPTIONS}
        options = _options({**base, **table}, path, f"{where} ({name})", finetune=parent is not None)
        settings = _describe(table) + (f" from {parent}" if parent else "")
        plans.append(RunPlan(name, options, files, run_recipe, parent, refit, settings.strip(), test=tests,
                             test_points=points))
    return plans


def _options(options, path, where, finetune=False):
    """The options checked now (so a typo fails before any run starts), in mpnode.runs' form."""
    options = canonical(options, f"{path}: {where}")
    if "time_limit" in options:
        options["time_limit"] = parse_duration(options["time_limit"], f"{path}: {where}.time_limit")
    if "curriculum" in options:
        options["curriculum"] = parse_curriculum(options["curriculum"], f"{path}: {where}")
    if finetune:
        fixed = sorted(k for k in options if k in MODEL_OPTIONS and k != "substeps")
        if fixed:
            raise InputError(path, f"{where}.{fixed[0]}", "cannot change when fine-tuning",
                             "only training options (and substeps); the model keeps its kind and sizes")
    try:
        split_options(options, f"{path}: {where}")
    except TypeError as e:
        raise InputError(path, where, f"an option has a value of the wrong type ({e})",
                         "the types `mpnode train --help` shows") from None
    return options


def _order(plans, path):
    """Parents before their children; InputError for a duplicate name, an unknown parent or a cycle."""
    by_name = {}
    for p in plans:
        if p.name in by_name:
            raise InputError(path, "run", f"two runs are named {p.name!r}", "distinct names")
        by_name[p.name] = p
    ordered, placed = [], set()
    while len(ordered) < len(plans):
        ready = [p for p in plans if p.name not in placed and (p.parent is None or p.parent in placed)]
        if not ready:
            stuck = next(p for p in plans if p.name not in placed)
            what = "is not a run of this sweep" if stuck.parent not in by_name else "starts a cycle"
            raise InputError(path, f"run {stuck.name}.from", f"{stuck.parent!r} {what}", "the name of another run")
        ordered += ready
        placed |= {p.name for p in ready}
    return ordered


def _label(v):
    text = ",".join(map(str, v)) if isinstance(v, list) else str(v)
    return text.replace("/", "-").replace(",", "-").replace(" ", "")


def _describe(own):
    return " ".join(f"{k}={_label(v)}" for k, v in own.items())


def _digest(obj):
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def file_digest(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# ---------------------------------------------------------------------------
# The task (runs on a worker)
# ---------------------------------------------------------------------------
def run_task(plan, test_names, parent, *files):
    """Train ``plan`` (a RunPlan as a dict) and evaluate it; runs wherever the farm puts it.

    parent : the parent's model file (bytes, or a path on this machine) or None;
    files : the plan's data files then its test files, each bytes or a local path.
    The run trains in ``plan["folder"]`` (resuming the training under way there when it has
    the same key: `_prepare`), or in a temporary folder whose files are sent back.
    Returns {"result": dict (see `_result`)}, and with a temporary folder "files":
    {name in the run's folder: bytes} (the model, its log, the models of the test points).
    """
    from mpnode.evaluation.evaluate import evaluate

    from . import run as runs

    with tempfile.TemporaryDirectory(prefix="mpnode-sweep-") as tmp:
        local = [_local(f, os.path.join(tmp, f"data{i}.h5")) for i, f in enumerate(files)]
        n_data = len(local) - len(test_names)
        paths = local[:n_data]
        datasets = [_read(p, name) for p, name in zip(paths, plan["data"])]
        tests = [_read(p, name) for p, name in zip(local[n_data:], test_names)]
        if plan["parent"] is not None:
            parent = _local(parent, os.path.join(tmp, "parent.h5"))
        folder = plan["folder"] or os.path.join(tmp, "run")
        resume = _prepare(folder, plan)

        def segment(epochs, resume):  # train (on) to ``epochs``
            options, output = {**plan["options"], "epochs": epochs}, os.path.join(folder, MODEL)
            common = dict(recipe_name=plan["recipe"], resume=resume, datasets=datasets, names=plan["data"])
            if plan["parent"] is None:
                return runs.train(paths, output, options, **common)
            return runs.finetune(parent, paths, output, options, refit_norm=plan["refit_norm"],
                                 parent_name=plan["parent_model"], **common)

        result, points = _train(plan, segment, resume, tests, test_names, folder)
        val = result.validation
        test = [(name, evaluate(result.model, t, source=name, check_stability=False))
                for name, t in zip(test_names, tests)]
        answer = {"result": _result(plan, result, val, test, points)}
        if plan["folder"] is None:
            answer["files"] = _run_files(folder)
    return answer


def point_epochs(epochs, test_points):
    """The epochs a run trains to in turn: with test points, 0 and ``test_points`` evenly spaced
    epochs up to ``epochs`` (unset: DEFAULT_EPOCHS; its best model is evaluated at each), else
    ``epochs`` alone (unset: the run's own cap)."""
    if not test_points:
        return [epochs]
    epochs = DEFAULT_EPOCHS if epochs is None else epochs
    return sorted({0} | {round(epochs * k / test_points) for k in range(1, test_points + 1)})


def _train(plan, segment, resume, tests, test_names, folder):
    """Train to each of `point_epochs` in turn (resuming between them), recording a test point
    after each; points already recorded in ``folder`` are kept.  Returns (TrainResult, points)."""
    points = _read_points(folder) if resume else []
    done = {p["epoch"] for p in points}
    result = None
    for stop in point_epochs(plan["options"].get("epochs"), plan["test_points"]):
        if stop in done:
            continue
        result = segment(stop, resume)
        resume = True
        if result.status == "interrupted":  # Ctrl-C: no point here; the next invocation resumes
            break
        if plan["test_points"]:
            points.append(_test_point(result, tests, test_names, folder))
        if result.status != "completed":
            break
    if result is None:  # stopped after its last point was recorded: the finished training, as it is
        result = segment(plan["options"].get("epochs"), True)
    return result, points


def _test_point(result, tests, test_names, folder):
    """Evaluate the best model so far on the test files; keep it as points/epoch-E.h5 and the
    point as a line of the folder's POINTS file (the line last: a line means its model is there)."""
    from mpnode.evaluation.evaluate import evaluate

    evals = [evaluate(result.model, t, source=name, check_stability=False) for t, name in zip(tests, test_names)]
    point = {"epoch": result.epoch, "best_epoch": result.best_epoch,
             "nmse": _mean([(r.n_trajectories, r.nmse) for r in evals]),
             "nmse_last": _mean([(r.n_trajectories, r.nmse_last) for r in evals]),
             "model": f"points/epoch-{result.epoch}.h5"}
    os.makedirs(os.path.join(folder, "points"), exist_ok=True)
    result.model.save(os.path.join(folder, point["model"]))
    with open(os.path.join(folder, POINTS), "a") as f:
        f.write(json.dumps(point, default=json_default) + "\n")
    return point


def _read_points(folder):
    """The test points recorded in ``folder`` (a line cut by a kill is dropped)."""
    points = []
    try:
        with open(os.path.join(folder, POINTS)) as f:
            for line in f:
                if line.endswith("\n"):
                    points.append(json.loads(line))
    except FileNotFoundError:
        pass
    return points


def _prepare(folder, plan):
    """Whether the run resumes the training under way in ``folder``: one with the same key that
    left a checkpoint.  Otherwise the folder is emptied and marked as this training's."""
    marker = os.path.join(folder, STARTED)
    try:
        with open(marker) as f:
            same = json.load(f).get("key") == plan["key"]
    except (FileNotFoundError, json.JSONDecodeError):
        same = False
    if same and os.path.exists(state_path(os.path.join(folder, MODEL))):
        return True
    shutil.rmtree(folder, ignore_errors=True)
    os.makedirs(folder)
    with atomic_path(marker) as tmp, open(tmp, "w") as f:
        json.dump({"name": plan["name"], "key": plan["key"]}, f)
    return False


def _run_files(folder):
    """{name: bytes} of what a finished run keeps in its folder: the model, its log, the points' models."""
    names = [MODEL, os.path.basename(log_path(MODEL))]
    if os.path.isdir(os.path.join(folder, "points")):
        names += [f"points/{n}" for n in sorted(os.listdir(os.path.join(folder, "points")))]
    out = {}
    for name in names:
        with open(os.path.join(folder, name), "rb") as f:
            out[name] = f.read()
    return out


def _read(path, name):
    """The trajectories at ``path`` (a worker's copy); errors name the sweep's file ``name``."""
    from mpnode.data import read_trajectories

    try:
        return read_trajectories(path)
    except InputError as e:
        if e.source != path:
            raise
        raise InputError(name, e.field, e.problem, e.expected) from None


def _local(ref, path):
    """A path on this machine holding ``ref`` (bytes are written to ``path``)."""
    if isinstance(ref, (bytes, bytearray)):
        with open(path, "wb") as f:
            f.write(ref)
        return path
    return ref


def _mean(pairs):
    """Trajectory-weighted mean of (count, value) pairs (None when there are none)."""
    total = sum(n for n, _ in pairs)
    return sum(n * v for n, v in pairs) / total if total else None


def _result(plan, result, val, test, points):
    return {"name": plan["name"], "key": plan["key"], "status": result.status, "message": result.message,
            "epochs": result.epoch, "best_epoch": result.best_epoch, "best_val_loss": result.best_val_loss,
            "seconds": result.seconds, "val_nmse": _mean([(f["trajectories"], f["nmse"]) for f in val]), "val": val,
            "test_nmse": _mean([(r.n_trajectories, r.nmse) for _, r in test]),
            "test_nmse_last": _mean([(r.n_trajectories, r.nmse_last) for _, r in test]),
            "test": [{"file": name, "trajectories": r.n_trajectories, "nmse": r.nmse, "nmse_last": r.nmse_last,
                      "blown_up": r.n_bad} for name, r in test],
            "test_curve": points,
            "options": {k: v for k, v in plan["options"].items()}, "recipe": plan["recipe"],
            "from": plan["parent"], "data": plan["data"], "test_points": plan["test_points"]}


# ---------------------------------------------------------------------------
# The client: submit, collect, write
# ---------------------------------------------------------------------------
def run_dir(out, name):
    return os.path.join(out, "runs", name)


def load_finished(out, plan):
    """The result of ``plan`` on disk (dict) if it finished with the same key, else None."""
    try:
        with open(os.path.join(run_dir(out, plan.name), "result.json")) as f:
            res = json.load(f)
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    ok = res.get("key") == plan.key and res.get("status") in FINISHED
    return res if ok and os.path.exists(os.path.join(run_dir(out, plan.name), MODEL)) else None


def run_sweep(sweep, out, farm, progress=None):
    """Run every unfinished run of ``sweep`` on ``farm``; write OUT/runs/NAME/ and the summary.

    progress : called with each run's record (dict with name, status, ...) as it finishes,
    or None.  Returns {name: record} for every run (status "failed" with an "error" when its
    task raised; "skipped" when its parent failed).  Ctrl-C: cancels what is running; what
    finished is on disk, and on the local pool a training under way resumes next time.
    """
    check_out_folder(sweep, out)
    os.makedirs(os.path.join(out, "runs"), exist_ok=True)
    records = {p.name: load_finished(out, p) or {"name": p.name, "status": "pending"} for p in sweep.runs}
    todo = {p.name: p for p in sweep.runs if records[p.name]["status"] == "pending"}
    write_summary(out, sweep, records)
    base = os.path.dirname(os.path.abspath(sweep.path))
    shared = {}

    def ref(path):  # what a task gets for a file: a path in the pool, the bytes (sent once) on Dask
        if not farm.is_dask:
            return path
        if path not in shared:
            with open(path, "rb") as f:
                shared[path] = farm.share(f.read())
        return shared[path]

    def submit(p):
        parent = None
        if p.parent is not None:
            parent = os.path.join(run_dir(out, p.parent), MODEL)
            if farm.is_dask:
                with open(parent, "rb") as f:
                    parent = f.read()
        plan = dataclasses.asdict(p)
        if p.parent is not None:
            plan["parent_model"] = os.path.abspath(os.path.join(run_dir(out, p.parent), MODEL))
        plan["folder"] = None if farm.is_dask else os.path.abspath(run_dir(out, p.name))  # a pool runs here
        tests = [os.path.relpath(t, base) for t in p.test]
        return farm.submit(run_task, plan, tests, parent, *[ref(f) for f in p.data + p.test])

    running, lost = {}, {}
    # the pool gets no more than it runs (a queued task would start after Ctrl-C); Dask queues them itself
    limit = math.inf if farm.is_dask else farm.workers
    try:
        while todo or running:
            for name in [n for n, p in todo.items() if p.parent is None or records[p.parent]["status"] in FINISHED]:
                if len(running) >= limit:
                    break
                running[submit(todo.pop(name))] = name
            waiting = set(todo) | set(running.values())
            for name in [n for n, p in todo.items() if p.parent is not None and p.parent not in waiting
                         and records[p.parent]["status"] not in FINISHED]:  # its parent will not finish
                records[name] = _failed(name, f"not run: its parent {todo.pop(name).parent} did not finish", "skipped")
                _announce(out, sweep, records, name, progress)
            if not running:
                continue
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                name = running.pop(fut)
                try:
                    records[name] = _keep(out, fut.result())
                except BrokenProcessPool:  # a pool process died: every running task is lost with it
                    for lost_name in [name, *running.values()]:
                        lost[lost_name] = lost.get(lost_name, 0) + 1
                        todo[lost_name] = next(p for p in sweep.runs if p.name == lost_name)
                    running.clear()
                    for lost_name in [n for n in list(todo) if lost.get(n, 0) > LOST_RETRIES]:
                        del todo[lost_name]
                        records[lost_name] = _failed(lost_name, f"the process running it died {lost[lost_name]} times")
                        _announce(out, sweep, records, lost_name, progress)
                    farm.restart()
                    break
                except Exception as e:  # noqa: BLE001 -- a failing run is reported, the sweep goes on
                    records[name] = _failed(name, f"{type(e).__name__}: {e}")
                _announce(out, sweep, records, name, progress)
    finally:
        for fut in running:
            fut.cancel()
        write_summary(out, sweep, records)
    return records


def _failed(name, error, status="failed"):
    lines = error.strip().splitlines()
    return {"name": name, "status": status, "error": lines[-1] if lines else error}


def _announce(out, sweep, records, name, progress):
    write_summary(out, sweep, records)
    if progress is not None:
        progress(records[name])


def _keep(out, answer):
    """Write a finished run's result, and the files a worker sent back from its temporary folder
    (each atomically; the result last, so a result on disk means the model beside it is
    complete); then the files of the training under way go.  An interrupted training (Ctrl-C
    reached the worker) is not kept: it is redone next time, resumed where it trained here."""
    res = answer["result"]
    if res["status"] not in FINISHED:
        return {"name": res["name"], "status": "pending"}
    folder = run_dir(out, res["name"])
    if "files" in answer:  # trained elsewhere: the folder becomes what the worker sent back
        shutil.rmtree(folder, ignore_errors=True)
    for name, blob in answer.get("files", {}).items():
        path = os.path.join(folder, name)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            f.write(blob)
    os.makedirs(folder, exist_ok=True)
    with atomic_path(os.path.join(folder, "result.json")) as tmp, open(tmp, "w") as f:
        json.dump(res, f, indent=1, default=json_default)
    for name in (STARTED, POINTS, os.path.basename(state_path(MODEL))):
        if os.path.exists(os.path.join(folder, name)):
            os.remove(os.path.join(folder, name))
    return res


def json_default(v):
    """``default`` of json.dump for results: NumPy numbers and arrays as numbers and lists, anything
    else json does not know as its text."""
    if hasattr(v, "tolist"):
        return v.tolist()
    return str(v)


# ---------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------
COLUMNS = ("run", "status", "settings", "epochs", "best_epoch", "val_nmse", "test_nmse", "test_nmse_last",
           "minutes", "error")


def summary_rows(sweep, records):
    rows = []
    for p in sweep.runs:
        r = records.get(p.name, {})
        minutes = r.get("seconds")
        rows.append({"run": p.name, "status": r.get("status", "pending"), "settings": p.settings,
                     "epochs": r.get("epochs"), "best_epoch": r.get("best_epoch"), "val_nmse": r.get("val_nmse"),
                     "test_nmse": r.get("test_nmse"), "test_nmse_last": r.get("test_nmse_last"),
                     "minutes": None if minutes is None else minutes / 60,
                     "error": r.get("error") or (r.get("message") if r.get("status") == "diverged" else None)})
    return rows


def write_summary(out, sweep, records):
    """OUT/summary.csv and OUT/summary.md: one row per run of the sweep, in the file's order."""
    rows = summary_rows(sweep, records)
    buf = io.StringIO()
    w = csv.DictWriter(buf, COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows({k: ("" if v is None else v) for k, v in r.items()} for r in rows)
    _write(os.path.join(out, "summary.csv"), buf.getvalue())
    done = sum(r["status"] in FINISHED for r in rows)
    lines = [f"# Sweep {os.path.basename(sweep.path)}", "",
             f"{done} of {len(rows)} runs finished. nMSE: normalised mean squared error over the predicted steps "
             "(validation: each file's held-out split; test: the run's test files).", "",
             "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_cell(r[c]) for c in COLUMNS) + " |" for r in rows]
    _write(os.path.join(out, "summary.md"), "\n".join(lines) + "\n")


def _cell(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return "inf" if math.isinf(v) else f"{v:.4g}"
    return str(v).replace("|", "\\|")


def _write(path, text):
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write(text)
