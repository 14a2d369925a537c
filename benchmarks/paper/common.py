"""What every experiment of the paper suite shares: modes, cached data, training runs, evaluation.

An experiment module (exp_*.py) declares

- ``NAME``, ``TITLE``;
- ``runs(mode)``: the training runs it needs (`RunSpec`; a run another experiment also
  declares is trained once -- same name, same settings; runs_shared.py defines those);
- ``analyse(ctx)``: evaluates the trained models, draws its figures and returns its
  section of RESULTS.md (markdown), and the numbers behind it (a dict, saved as JSON).

`main` hands the runs of the chosen experiments to the library's sweep (mpnode.runs.sweep:
keys, parents before fine-tuned children, test points, results on disk), which trains them on
a pool of processes (one numba thread each: two single-threaded trainings use the 2 cores
better than one two-threaded one) or, with ``--scheduler``, on Dask (mpnode.runs.executors);
then it runs the analyses in order and assembles RESULTS.md from every section present.

Everything is cached under OUT/work (data files; runs/NAME/ with the model, its log, its
test points and result.json, each run keyed by everything that decided it), so a rerun only
redoes what changed (``--force``: everything), and on the pool a training that was killed
resumes from its checkpoint.
"""
import argparse
import dataclasses
import json
import math
import os
import platform
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: the experiments, in the order of RESULTS.md
EXPERIMENTS = ("exp_messages", "exp_topologies", "exp_more_nodes", "exp_finetune", "exp_message_size", "exp_speed",
               "exp_aggregation", "exp_schedule",
               "exp_quadrotor", "exp_node", "exp_integrator", "exp_tables", "exp_batch")
PAPER_EPOCHS = 4000


# ---------------------------------------------------------------------------
# Mode
# ---------------------------------------------------------------------------
#: the share of the full run's epochs and wall-time budgets that a short run trains
SHORT_SHARE = 0.25


@dataclass(frozen=True)
class Mode:
    """The suite's size.  full: RESULTS.md (about 6 hours on 2 cores from nothing); short: every
    table and figure on the full run's data with a quarter of its epochs and wall-time budgets
    (about 85 minutes from nothing on 2 cores: under-trained, a check of the directions); quick: a CI-sized
    smoke run."""

    name: str = "full"

    @property
    def quick(self):
        return self.name == "quick"

    def pick(self, full, quick):
        """A data size or count: the full run's (a short run's too) or the quick run's."""
        return quick if self.quick else full

    def epochs(self, full, quick):
        """An epoch count: a short run trains SHORT_SHARE of the full run's."""
        if self.name == "short":
            return max(1, round(full * SHORT_SHARE))
        return self.pick(full, quick)

    def minutes(self, full):
        """A wall-time budget in minutes (a quick run has none: it counts epochs)."""
        return None if self.quick else full * (SHORT_SHARE if self.name == "short" else 1)

    def wall_time(self, full_minutes):
        """The words for a wall-time budget of ``full_minutes`` in the full run (e.g. "2.5 minutes")."""
        m = self.minutes(full_minutes)
        return f"{m:g} minute{'' if m == 1 else 's'} of wall time"

    def time_limit(self, full_minutes):
        """The `mpnode train` options of a wall-time budget of ``full_minutes`` in the full run."""
        return () if self.quick else (("time_limit", self.minutes(full_minutes) * 60),)


# ---------------------------------------------------------------------------
# Data
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class DataSpec:
    """A generated trajectory file: a built-in scene with B trajectories from ``seed``.

    graph_seeds: build the scene's random graphs with these networkx seeds instead (fresh,
    unseen topologies).  Trajectory b depends only on (seed, b), so the first 50 of a
    500-trajectory file are the 50-trajectory file.
    """

    scene: str
    trajectories: int
    seed: int
    graph_seeds: tuple = None

    @property
    def key(self):
        g = "" if self.graph_seeds is None else "_g" + "-".join(map(str, self.graph_seeds))
        return f"{self.scene}_B{self.trajectories}_s{self.seed}{g}"

    def describe(self):
        g = "" if self.graph_seeds is None else f", graph seeds {list(self.graph_seeds)}"
        return f"{self.scene} (B={self.trajectories}, seed {self.seed}{g})"


def data_path(work, spec):
    return Path(work) / "data" / f"{spec.key}.h5"


def make_data(work, spec, workers=1, scheduler=None):
    """Generate ``spec``'s file unless it is there; return its path."""
    from data_gen.scenes import load_scene
    from data_gen.simulate import generate
    from mpnode.data import write_trajectories

    path = data_path(work, spec)
    if path.exists():
        return path
    scene = dataclasses.replace(load_scene(spec.scene), trajectories=spec.trajectories, seed=spec.seed)
    if spec.graph_seeds is not None:
        scene = dataclasses.replace(scene, graph=dataclasses.replace(scene.graph, seeds=tuple(spec.graph_seeds)))
    traj = generate(scene, workers=workers, scheduler=scheduler)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_trajectories(path, traj)  # atomic
    return path


def load_data(work, spec):
    from mpnode.data import read_trajectories

    return read_trajectories(make_data(work, spec))


# ---------------------------------------------------------------------------
# Training runs: declared here, trained by the library's sweep (mpnode.runs.sweep)
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class RunSpec:
    """One training run (scratch, or finetuning the model of run ``init_from``).

    test / test_points: evaluate the best-validation model on ``test`` at epoch 0 and at
    ``test_points`` evenly spaced epochs (the sweep's test points) -- the test-error curve of Fig. 5.
    kind, aggregation: the model (mpnode.runs options; aggregation None: the recipe's);
    recipe: "paper" (the paper's settings) or "auto"; extra: further `mpnode train` options
    as (name, value) pairs, e.g. (("schedule", "cosine"), ("val_graphs", 1)).
    """

    name: str
    train: tuple
    epochs: int
    message_dim: int = 3
    hidden: int = 32
    zero_messages: bool = False
    curriculum: tuple = ()
    curriculum_epochs: int = 100
    init_from: str = None
    test: DataSpec = None
    test_points: int = 0
    seed: int = 0
    lr: float = 1e-3
    recipe: str = "paper"
    kind: str = "mpnode"
    aggregation: str = None
    extra: tuple = ()

    def options(self):
        """The `mpnode train` options of this run (mpnode.runs), model options only from scratch."""
        opts = {"epochs": self.epochs, "seed": self.seed, "lr": self.lr, "curriculum": tuple(self.curriculum),
                "curriculum_epochs": self.curriculum_epochs, **dict(self.extra)}
        if not self.init_from:
            opts.update(kind=self.kind, message_dim=self.message_dim, hidden=self.hidden,
                        zero_messages=self.zero_messages)
            if self.aggregation:
                opts["aggregation"] = self.aggregation
        return opts

    def plan(self, work):
        """This run as a run of the library's sweep (its data files those of ``work``)."""
        from mpnode.runs.sweep import RunPlan

        return RunPlan(self.name, self.options(), [str(data_path(work, d)) for d in self.train], self.recipe,
                       parent=self.init_from, settings=", ".join(d.describe() for d in self.train),
                       test=[str(data_path(work, self.test))] if self.test is not None else [],
                       test_points=self.test_points)


def declared(specs):
    """{name: RunSpec} of ``specs``; ValueError for a name declared twice with other settings or a
    run starting from a run no experiment declares."""
    by_name = {}
    for s in specs:
        if s.name in by_name and by_name[s.name] != s:
            raise ValueError(f"two experiments declare run {s.name!r} with different settings")
        by_name[s.name] = s
    for s in by_name.values():
        if s.init_from and s.init_from not in by_name:
            raise ValueError(f"run {s.name} starts from {s.init_from!r}, which no experiment declares")
    return by_name


def run_dir(work, name):
    return Path(work) / "runs" / name


def train_runs(specs, work, jobs=2, force=False, scheduler=None):
    """Train every run of ``specs`` whose result in WORK/runs is missing or was made otherwise, on the
    library's sweep: ``jobs`` at a time on a local pool (one numba thread each, a run killed there
    resuming from its checkpoint next time) or on the Dask ``scheduler``.  Runs others start from
    go first, then the longest (epochs x trajectories as a rough cost), so the pool does not end
    on one long run.  Exits naming the runs that failed."""
    from mpnode.runs.executors import open_executor
    from mpnode.runs.sweep import FINISHED, load_finished, make_sweep, run_sweep

    by_name = declared(specs)
    parents = {s.init_from for s in by_name.values()}
    order = sorted(by_name.values(), key=lambda s: (s.name not in parents,
                                                    -s.epochs * sum(d.trajectories for d in s.train)))
    sweep = make_sweep(str(Path(work) / "paper-suite"), [s.plan(work) for s in order])
    if force:
        for p in sweep.runs:
            shutil.rmtree(run_dir(work, p.name), ignore_errors=True)
    todo = [p.name for p in sweep.runs if load_finished(work, p) is None]
    if not todo:
        return
    started = time.perf_counter()
    with open_executor(scheduler, jobs, one_thread=True) as farm:
        print(f"training {len(todo)} run(s) ({farm.workers} at a time): {', '.join(todo)}", flush=True)
        done = []

        def report(r):
            done.append(r)
            what = (f"{r['epochs']} epochs, best val loss {r['best_val_loss']:.4g} (epoch {r['best_epoch']}), "
                    f"{r['seconds']:.0f} s" if r["status"] in FINISHED else r.get("error"))
            print(f"  [{len(done)}/{len(todo)}] {r['name']}: {r['status']}, {what} "
                  f"[{time.perf_counter() - started:.0f} s in all]", flush=True)

        records = run_sweep(sweep, work, farm, progress=report)
    failed = [r for r in records.values() if r["status"] not in FINISHED]
    if failed:
        sys.exit("runs did not finish (see work/summary.md): "
                 + "; ".join(f"{r['name']}: {r['status']} {r.get('error') or ''}" for r in failed))


def read_run(work, spec, test=None):
    """A finished run as the analyses read it: the sweep's result.json with the run's declaration
    (``spec``), its training log (``history``), its training data, and its test curve as
    [[epoch, nMSE], ...] and, evaluated from each point's model on ``test`` (the Trajectories of
    spec.test), in the paper's units (`paper_units`)."""
    from mpnode.model import Model
    from mpnode.training.log import log_path, read_log

    folder = run_dir(work, spec.name)
    res = json.loads((folder / "result.json").read_text())
    res.update(spec=dataclasses.asdict(spec), history=read_log(log_path(folder / "model.h5")),
               train_data=[d.describe() for d in spec.train],
               train_trajectories=sum(d.trajectories for d in spec.train))
    points = res.pop("test_curve")
    res["test_curve"] = [[p["epoch"], p["nmse"]] for p in points]
    res["test_curve_paper_units"] = [
        [p["epoch"], paper_units(test, evaluate_nmse(Model.load(folder / p["model"]), test).predictions)]
        for p in points]
    return res


def load_model(work, name):
    from mpnode.model import Model

    return Model.load(run_dir(work, name) / "model.h5")


# ---------------------------------------------------------------------------
# Analysis context and helpers
# ---------------------------------------------------------------------------
@dataclass
class Context:
    """What the analyses share; results, models and data files are read once (the analyses only
    copy them).  specs: every run any experiment declares, by name."""

    mode: Mode
    out: Path
    work: Path
    figures: Path
    specs: dict = field(default_factory=dict)
    _read: dict = field(default_factory=dict)

    def result(self, name):
        """The run's result (`read_run`), or None when it has not finished."""
        if ("result", name) not in self._read:
            spec, res = self.specs[name], None
            if (run_dir(self.work, name) / "result.json").exists():
                res = read_run(self.work, spec, self.data(spec.test) if spec.test is not None else None)
            self._read["result", name] = res
        return self._read["result", name]

    def model(self, name):
        if ("model", name) not in self._read:
            self._read["model", name] = load_model(self.work, name)
        return self._read["model", name]

    def data(self, spec):
        if spec not in self._read:
            self._read[spec] = load_data(self.work, spec)
        return self._read[spec]

    def figure(self, fig, name):
        """Save a matplotlib figure as figures/NAME.png; returns the markdown link."""
        import matplotlib.pyplot as plt

        from mpnode.base.atomic import atomic_path

        self.figures.mkdir(parents=True, exist_ok=True)
        with atomic_path(self.figures / f"{name}.png") as tmp:
            fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
        plt.close(fig)
        return f"![{name}](figures/{name}.png)"


def pyplot():
    """matplotlib.pyplot on the Agg backend; a clear message when the plot extra is missing."""
    try:
        import matplotlib
    except ImportError:
        sys.exit("the paper suite draws figures with matplotlib: pip install '.[plot]'")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def evaluate_nmse(model, traj):
    """The evaluation of `mpnode eval` (EvalResult): nMSE per step and over steps 1..T."""
    from mpnode.evaluation.evaluate import evaluate

    return evaluate(model, traj, check_stability=False)


def zscore_mse(model, traj, pred):
    """Mean squared error in the model's own z-scored units (the units of the training loss), steps 1..T."""
    x = np.asarray(traj.x, dtype=np.float64)
    e = (np.asarray(pred, dtype=np.float64)[:, 1:] - x[:, 1:]) / model.x_std
    return float(np.mean(e * e))


def paper_units(traj, pred):
    """The paper's loss: Huber (delta 1) of the z-scored error, summed over steps 1..T and state
    dimensions, averaged over nodes and trajectories.  The z-score is the test set's own (per state
    dimension, over trajectories, steps and nodes), the scale a model trained on such data uses: one
    scale per test set, so a fine-tuned model (which keeps its source's normalisation) and one
    trained from scratch are measured alike."""
    from mpnode.training.losses import huber

    x = np.asarray(traj.x, dtype=np.float64)
    mean, std = x.mean(axis=(0, 1, 2)), x.std(axis=(0, 1, 2))
    x, p = (x - mean) / std, (np.asarray(pred, dtype=np.float64) - mean) / std
    b, t1, n, d = x.shape
    flat = lambda a: a.transpose(1, 0, 2, 3).reshape(t1, b * n, d)  # noqa: E731 -- the engine's layout
    return huber(flat(p), flat(x), b * n)[0]


def hold_nmse(traj):
    """nMSE of holding the initial state: what a model must beat to be of any use."""
    from mpnode.evaluation.metrics import nmse

    x = np.asarray(traj.x, dtype=np.float64)
    return nmse(np.broadcast_to(x[:, :1], x.shape)[:, 1:], x[:, 1:], spread=x)


def table(headers, rows):
    """A markdown table; floats are shown with 3 significant digits."""
    def cell(v):
        if isinstance(v, float):
            return "inf" if math.isinf(v) else f"{v:.3g}"
        return str(v)

    lines = ["| " + " | ".join(headers) + " |", "| " + " | ".join("---" for _ in headers) + " |"]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def curve(res, key):
    """(epochs, values) of a logged quantity of a run (None entries dropped)."""
    h = [r for r in res["history"] if r.get(key) is not None]
    return np.array([r["epoch"] for r in h]), np.array([r[key] for r in h], dtype=float)


def model_curve(res, key="test_curve"):
    """A test curve (``key``: test_curve in nMSE, test_curve_paper_units in the paper's units) as
    [[epoch the evaluated model was trained to, error], ...].

    A point evaluated at epoch e is the best-validation model at e, i.e. the weights of the last
    strict validation improvement at or before e (fit's rule).  A scratch run's epoch-0 point is
    dropped (`test_curve`).
    """
    best, best_at, trained_to = float("inf"), 0, {}
    for r in res["history"]:
        if r["val_loss"] is not None and r["val_loss"] < best:
            best, best_at = r["val_loss"], r["epoch"]
        trained_to[r["epoch"]] = best_at
    return [[trained_to.get(int(e), int(e)), float(v)] for e, v in zip(*test_curve(res, key))]


def efficiency(curve):
    """(min test error, first epoch reaching it, their product) of a test curve [[epoch, error], ...]:
    the paper's Table 2 metric (lower is better on both counts)."""
    c = np.asarray(curve, dtype=float)
    i = int(np.argmin(c[:, 1]))
    return float(c[i, 1]), int(c[i, 0]), float(c[i, 1] * max(c[i, 0], 1))


def first_epoch_below(curve, level):
    """The first evaluated epoch whose test error is <= level (None: never)."""
    for e, v in curve:
        if v <= level:
            return int(e)
    return None


def test_curve(res, key="test_curve"):
    """(epochs, test error) of a run's test curve (``key``: test_curve in nMSE, test_curve_paper_units)
    at its evaluation epochs; a scratch run's epoch-0 point (evaluated before fit fitted the
    normalisation) is dropped."""
    c = np.asarray(res[key], dtype=float).reshape(-1, 2)
    if not res["spec"]["init_from"]:
        c = c[c[:, 0] > 0]
    return c[:, 0], c[:, 1]


def figure_block(link, caption, ours):
    """A figure as RESULTS.md shows one the paper has: the image, the paper's caption quoted, and
    one sentence of what ours shows (computed by the caller)."""
    return f"{link}\n\nPaper's caption: \"{caption}\"\n\nOurs: {ours}"


def flatness(res, key="val_loss", frac=0.2):
    """Relative improvement of the best ``key`` over the last ``frac`` of the epochs (small: flattened)."""
    e, v = curve(res, key)
    if len(v) < 5:
        return float("nan")
    cut = e.max() * (1 - frac)
    before, after = np.min(v[e <= cut]), np.min(v)
    return float((before - after) / before) if before > 0 else float("nan")


def run_line(res):
    """Seeds, data size and epochs of a run, for the tables of RESULTS.md."""
    s = res["spec"]
    bits = [f"{res['train_trajectories']} trajectories ({', '.join(res['train_data'])})",
            f"{res['epochs']} epochs" + (f" (curriculum {s['curriculum']} x {s['curriculum_epochs']})"
                                         if s["curriculum"] else ""),
            f"seed {s['seed']}", f"lr {s['lr']:g}",
            (f"dm {s['message_dim']}" + (", zero messages" if s["zero_messages"] else "")
             if s["kind"] == "mpnode" else f"kind {s['kind']}"),
            f"{res['seconds'] / 60:.1f} min"]
    if s["init_from"]:
        bits.append(f"from {s['init_from']}")
    if res["status"] == "time_limit":
        bits.append("ended by its time limit")
    elif res["status"] != "completed":
        bits.append(f"**{res['status'].upper()}**: {res['message']}")
    return "; ".join(bits)


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------
def parse_args(argv, description):
    p = argparse.ArgumentParser(description=description)
    tier = p.add_mutually_exclusive_group()
    tier.add_argument("--quick", action="store_true", help="CI-sized smoke run (tiny data, a few epochs)")
    tier.add_argument("--short", action="store_true",
                      help=f"every table and figure with {SHORT_SHARE:.0%} of the full run's epochs and wall-time "
                           "budgets, on the same data (about 85 minutes on 2 cores from nothing)")
    p.add_argument("--out", type=Path, default=None,
                   help="where RESULTS.md, figures/ and work/ go (default: benchmarks/paper for the full "
                        "run, benchmarks/paper/short or benchmarks/paper/quick for the others)")
    p.add_argument("--jobs", type=int, default=2, help="trainings at once on the local pool (each single-threaded)")
    p.add_argument("--force", action="store_true", help="retrain and regenerate even what is cached")
    p.add_argument("--scheduler", default=os.environ.get("MPNODE_SCHEDULER"),
                   help="run data generation and trainings on Dask: local, tcp://HOST:8786 or a scheduler file "
                        "(default $MPNODE_SCHEDULER, else the local pool); a training stopped on Dask starts over")
    args = p.parse_args(argv)
    args.tier = "quick" if args.quick else "short" if args.short else "full"
    if args.out is None:
        args.out = HERE if args.tier == "full" else HERE / args.tier
    return args


def main(experiments, argv=None, description="MP-NODE paper suite"):
    """Train the runs of ``experiments`` (module names), analyse them, write OUT/RESULTS.md."""
    import importlib

    from mpnode.runs.sweep import json_default

    args = parse_args(argv, description)
    mode = Mode(args.tier)
    out = args.out.resolve()
    work = out / "work"
    every = declared(s for name in EXPERIMENTS for s in importlib.import_module(name).runs(mode))
    ctx = Context(mode, out, work, out / "figures", every)
    modules = [importlib.import_module(name) for name in experiments]
    t0 = time.perf_counter()
    specs = [s for m in modules for s in m.runs(mode)]
    needed = {d for s in specs for d in s.train} | {s.test for s in specs if s.test is not None}
    needed |= {d for m in modules for d in getattr(m, "data", lambda mode: [])(mode)}
    missing = [d for d in sorted(needed, key=lambda d: d.key) if args.force or not data_path(work, d).exists()]
    if args.force:
        for d in missing:
            data_path(work, d).unlink(missing_ok=True)
    for i, d in enumerate(missing, 1):
        t = time.perf_counter()
        make_data(work, d, workers=2, scheduler=args.scheduler)
        print(f"data [{i}/{len(missing)}] {d.describe()}: {time.perf_counter() - t:.1f} s", flush=True)
    train_runs(specs, work, jobs=args.jobs, force=args.force, scheduler=args.scheduler)
    (out / "sections").mkdir(parents=True, exist_ok=True)
    (out / "results").mkdir(parents=True, exist_ok=True)
    for m in modules:
        t = time.perf_counter()
        print(f"analysing {m.NAME} ...", flush=True)
        text, numbers = m.analyse(ctx)
        _write(out / "sections" / f"{m.__name__}.md", f"## {m.TITLE}\n\n{text.strip()}\n")
        _write(out / "results" / f"{m.NAME}.json", json.dumps(numbers, indent=1, default=json_default))
        print(f"  {m.NAME}: {time.perf_counter() - t:.0f} s", flush=True)
    write_results(out, mode, argv if argv is not None else sys.argv[1:], time.perf_counter() - t0, args.jobs)
    print(f"wrote {out / 'RESULTS.md'} ({(time.perf_counter() - t0) / 60:.1f} min)", flush=True)


def _write(path, text):
    from mpnode.base.atomic import atomic_path

    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def write_results(out, mode, argv, seconds, jobs):
    """RESULTS.md: how it was made, the hand-written reading (full run), then every section present."""
    import numba

    cmd = " ".join(["python benchmarks/paper/run_all.py", *argv]).strip()
    results = [json.loads(p.read_text()) for p in sorted((out / "work" / "runs").glob("*/result.json"))]
    train_min = sum(r["seconds"] for r in results) / 60
    head = [f"# MP-NODE paper results on mpnode ({mode.name} run)", "",
            f"Made by `{cmd}`; the last invocation took {seconds / 60:.1f} min "
            f"(cached runs are not retrained). Machine: {platform.machine()}, {os.cpu_count()} CPUs, Python "
            f"{platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}. "
            + (f"Trainings ran {jobs} at a time, one numba thread each. " if jobs > 1 else "")
            + f"The {len(results)} trainings took {train_min:.0f} core-minutes in all. "
            + "Numbers per experiment are in `results/*.json`.", ""]
    if mode.name == "short":
        head += [f"A short run: {SHORT_SHARE:.0%} of the full run's epochs and wall-time budgets, on the same data, so "
                 "its models are under-trained. Section titles and the reading name the full run's budgets; each "
                 "section's text states what this run used. `benchmarks/paper/RESULTS.md` (the full run) is the "
                 "reference; this one shows which of its directions already hold at a quarter of the cost.", ""]
    reading = HERE / "reading.md"
    if mode.name == "full" and reading.exists() and out == HERE:
        head += [reading.read_text().strip(), ""]
    sections = [out / "sections" / f"{name}.md" for name in EXPERIMENTS]
    body = [p.read_text().strip() + "\n" for p in sections if p.exists()]
    _write(out / "RESULTS.md", "\n".join(head) + "\n" + "\n".join(body))
