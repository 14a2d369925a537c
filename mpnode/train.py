"""Training an MP-NODE on trajectory data: the seed code's recipe, resumable and leak-free.

The recipe (MPNODE.jl `configs/empode_sys_32_3.toml` + `exps/train_pipeline.jl`):
full-horizon single shooting from each trajectory's first state, Huber loss on z-scored
states summed over dimensions and steps and averaged over nodes, Adam(1e-3) behind a
gradient clip-norm of 500 applied to each parameter array separately, batches of 128
trajectories, a random 70/30 train/validation split, Gaussian noise (std 1e-4) added to
the normalised training states, the learning rate halved after ``patience`` epochs
without a new best validation loss, and the best-validation weights kept.

Deviations, on purpose:
- the z-score constants are fitted on the training split only (the seed code fitted them
  on everything before splitting, leaking the validation set into the model);
- the noise is drawn once per run (from the seed) and added to every normalised state of
  the training trajectories, initial states and targets alike -- what the seed code's
  ``addnoise`` does to its training set -- so each epoch sees the same noisy data and a
  resumed run is the same run;
- a bad step -- non-finite loss, gradient or update, or a batch loss above ``blowup``
  (100) times the initial validation loss -- is skipped, the weights (and Adam moments)
  go back to the best-validation ones, and the learning rate is halved; ``max_bad_steps``
  (5) bad steps without a new best validation loss in between stop the run with status
  "diverged".  (Flux would have
  written NaN into the weights.  The tanh MLP's output is bounded, so a far too large
  learning rate gives huge but finite losses: the blow-up test is what catches it.)

Batches: every batch comes from one file (one node count N per file, so one block-
diagonal graph per batch); each epoch shuffles every file's training trajectories,
cuts them into batches and shuffles the order of all batches together, so several files
are interleaved in proportion to their size.  The shuffle of epoch e depends only on
(seed, e), which is what makes ``resume`` reproduce an uninterrupted run exactly.

Horizon curriculum (the seed code's ``horizonwindow``; ``TrainConfig.curriculum``): with
window lengths w1 < w2 < ..., the first ``curriculum_epochs`` epochs train on windows of
w1 steps, the next ``curriculum_epochs`` on windows of w2, ..., and the remaining epochs on
the full horizon, so a chaotic system (Lorenz) is learned without the exploding gradients
of long rollouts from random weights.  Every training trajectory of T steps is cut into
consecutive windows of w steps, each starting from its own (noisy) true state: starts
0, w, 2w, ... and, when w does not divide T, one last window ending at T (overlapping
the one before), so every transition is trained on and the epoch is deterministic --
which keeps resume exact (the stage is a function of the epoch number alone); random
windows would add sampling noise for no gain in coverage.  A batch holds
``batch_size`` windows.  Validation (model selection, learning-rate cuts) stays on the
full horizon: the saved model is the best one at the job it is for.  The loss sums over
steps, so the logged train_loss is comparable within a stage only; every log line
records its ``window`` (steps per rollout) and ``stage``.

Files beside the output model ``OUT``: ``OUT.log.jsonl`` (one JSON object per epoch) and
``OUT.state`` (a NumPy .npz written atomically: current and best weights, Adam moments,
learning rate, counters, configuration, normalisation and a fingerprint of the data).
This module knows nothing of any particular system.
"""
import dataclasses
import json
import math
import os
import time
import zlib
from dataclasses import dataclass, field

import numpy as np

from . import integrate, mlp
from .atomic import atomic_path
from .errors import InputError, NumericalError
from .graph import block_diagonal
from .optim import CLIP_MODES, Adam, array_slices, clip_gradient

STATE_VERSION = 1


@dataclass
class TrainConfig:
    """Everything that decides a training run besides the model and the data.

    time_limit is in seconds (None: no limit); norm is "fit" (z-score constants fitted on
    the training split) or "keep" (the model's own constants, for finetuning).
    """

    epochs: int = 4000
    batch_size: int = 128
    lr: float = 1e-3
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    clip: float = 500.0
    clip_mode: str = "per-array"
    val_split: float = 0.3
    noise: float = 1e-4
    loss: str = "huber"
    patience: int = 500
    lr_decay: float = 0.5
    min_lr: float = 1e-6
    seed: int = 0
    norm: str = "fit"
    max_bad_steps: int = 5
    blowup: float = 100.0
    time_limit: float = None
    checkpoint_seconds: float = 10.0
    curriculum: tuple = ()
    curriculum_epochs: int = 100

    def check(self):
        """Raise InputError naming the option for a value that cannot work."""
        def bad(name, problem, expected):
            raise InputError("training options", name, problem, expected)

        self.curriculum = tuple(int(w) for w in self.curriculum)
        if any(w < 1 for w in self.curriculum):
            bad("curriculum", f"is {list(self.curriculum)}", "window lengths >= 1 (steps)")
        if self.curriculum_epochs < 1:
            bad("curriculum_epochs", f"is {self.curriculum_epochs}", "an integer >= 1")

        if self.epochs < 0:
            bad("epochs", f"is {self.epochs}", "an integer >= 0")
        if self.batch_size < 1:
            bad("batch_size", f"is {self.batch_size}", "an integer >= 1")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            bad("lr", f"is {self.lr}", "a finite number > 0")
        if not (0 <= self.val_split < 1):
            bad("val_split", f"is {self.val_split}", "a fraction in [0, 1)")
        if not (self.noise >= 0):
            bad("noise", f"is {self.noise}", "a number >= 0")
        if self.loss not in integrate.LOSSES:
            bad("loss", f"is {self.loss!r}", " or ".join(integrate.LOSSES))
        if self.clip_mode not in CLIP_MODES:
            bad("clip_mode", f"is {self.clip_mode!r}", " or ".join(CLIP_MODES))
        if self.norm not in ("fit", "keep"):
            bad("norm", f"is {self.norm!r}", "'fit' or 'keep'")
        if self.patience < 1:
            bad("patience", f"is {self.patience}", "an integer >= 1")
        if not (0 < self.lr_decay <= 1):
            bad("lr_decay", f"is {self.lr_decay}", "a factor in (0, 1]")
        if self.max_bad_steps < 1:
            bad("max_bad_steps", f"is {self.max_bad_steps}", "an integer >= 1")
        if not self.blowup >= 0:
            bad("blowup", f"is {self.blowup}", "a factor >= 0 (0: off)")
        if self.time_limit is not None and not self.time_limit > 0:
            bad("time_limit", f"is {self.time_limit}", "a number of seconds > 0")
        return self


@dataclass
class TrainResult:
    """What `fit` returns.

    model : the best-validation Model (normalisation included)
    status : "completed" | "time_limit" | "diverged" | "interrupted"
    """

    model: object
    status: str
    message: str
    best_val_loss: float
    best_epoch: int
    epoch: int
    lr: float
    seconds: float
    history: list = field(default_factory=list)
    split: list = field(default_factory=list)


def log_path(output):
    """The JSON-lines training log beside the model file ``output``."""
    return os.fspath(output) + ".log.jsonl"


def state_path(output):
    """The resume checkpoint beside the model file ``output``."""
    return os.fspath(output) + ".state"


# ---------------------------------------------------------------------------
# Data checks, splits and normalisation
# ---------------------------------------------------------------------------
def check_data(model, datasets, sources, allow_dt_mismatch=False):
    """Raise InputError unless every file fits the model (dx, du) and its dt (unless allowed).

    datasets : list of Trajectories; sources : their file names (for the messages).
    """
    s = model.spec
    for traj, src in zip(datasets, sources):
        if traj.state_dim != s.state_dim:
            raise InputError(src, "x", f"has {traj.state_dim} state dimensions per node but the model has "
                             f"{s.state_dim}", f"a file of the system the model was trained on (dx = {s.state_dim})")
        if traj.control_dim != s.control_dim:
            raise InputError(src, "u", f"has {traj.control_dim} control dimensions per node but the model has "
                             f"{s.control_dim}", f"du = {s.control_dim}")
        if not allow_dt_mismatch and not math.isclose(traj.dt, s.dt, rel_tol=1e-9, abs_tol=0.0):
            raise InputError(src, "dt", f"is {traj.dt:g} but the model was trained with dt = {s.dt:g}",
                             f"data saved every {s.dt:g} (or pass the flag that allows another dt)")


def check_same_kind(datasets, sources):
    """Several training files must agree on dx, du and dt (graphs and N may differ)."""
    first, src0 = datasets[0], sources[0]
    for traj, src in zip(datasets[1:], sources[1:]):
        for what, a, b in (("x", traj.state_dim, first.state_dim), ("u", traj.control_dim, first.control_dim)):
            if a != b:
                raise InputError(src, what, f"has {a} dimensions per node but {src0} has {b}",
                                 "files of one system (same dx and du)")
        if not math.isclose(traj.dt, first.dt, rel_tol=1e-9, abs_tol=0.0):
            raise InputError(src, "dt", f"is {traj.dt:g} but {src0} has dt = {first.dt:g}", "the same dt in every file")


def split_indices(n, val_split, seed, file_index=0):
    """A random (train, val) split of range(n), the same for the same (n, val_split, seed, file).

    round(val_split * n) trajectories go to validation, but at least one trajectory stays
    in training.  Returns two sorted int64 arrays.
    """
    rng = np.random.default_rng([seed, 2, file_index])
    perm = rng.permutation(n)
    n_val = min(int(round(val_split * n)), n - 1)
    return np.sort(perm[n_val:]).astype(np.int64), np.sort(perm[:n_val]).astype(np.int64)


def fit_normalization(arrays):
    """Per-dimension mean and std over all entries of ``arrays`` (each (..., d)).

    A dimension with zero spread gets std 1.  Returns (mean, std), float64 shape (d,).
    """
    d = arrays[0].shape[-1]
    count = sum(a.size // d for a in arrays)
    total = sum(a.reshape(-1, d).sum(axis=0, dtype=np.float64) for a in arrays)
    mean = total / count
    sq = sum(((a.reshape(-1, d) - mean) ** 2).sum(axis=0) for a in arrays)
    std = np.sqrt(sq / count)
    std[~(std > 1e-12 * np.maximum(1.0, np.abs(mean)))] = 1.0
    return mean, std


def fingerprint(datasets):
    """A JSON string identifying the training data (shapes, dt, checksums), for resume."""
    out = []
    for traj in datasets:
        x = np.ascontiguousarray(traj.x)
        out.append({"shape": list(x.shape), "du": traj.control_dim, "dt": float(traj.dt),
                    "x_crc": zlib.crc32(x.view(np.uint8)),
                    "graphs": [zlib.crc32(np.ascontiguousarray(g.indices).view(np.uint8)) for g in traj.graphs]})
    return json.dumps(out, sort_keys=True)


# ---------------------------------------------------------------------------
# Prepared data: normalised, time-major, split, noise added -- once per run
# ---------------------------------------------------------------------------
class _Part:
    """The trajectories of one file on one side of the split, ready for the kernels.

    x : ndarray, shape (T+1, B, N, dx) normalised, model dtype;  u : (T, B, N, du) or None
    gi : ndarray, shape (B,) graph of each;  graphs : the file's graphs
    """

    def __init__(self, traj, idx, model, noise_std, rng):
        self.graphs = traj.graphs
        self.index = idx
        self.gi = np.asarray(traj.graph_index)[idx]
        x = model.normalize_x(np.asarray(traj.x)[idx])
        if noise_std > 0 and len(idx):
            x = (x + rng.standard_normal(x.shape) * noise_std).astype(model.dtype)
        self.x = np.ascontiguousarray(x.transpose(1, 0, 2, 3))
        self.u = None
        if traj.u is not None:
            self.u = np.ascontiguousarray(model.normalize_u(np.asarray(traj.u)[idx]).transpose(1, 0, 2, 3))
        self.n = len(idx)
        self.n_nodes = traj.n_nodes
        self.single_graph = len(self.graphs) == 1 or len(np.unique(self.gi)) <= 1
        self._graph_cache = {}

    def batch(self, sel):
        """(x (T+1, b*N, dx), u (T, b*N, du) or None, graph) for local trajectory numbers ``sel``.

        Trajectories are grouped by graph inside the batch (the loss is a sum, so order is
        free): runs of copies of one small graph let the kernels aggregate densely.
        """
        if not self.single_graph:
            sel = sel[np.argsort(self.gi[sel], kind="stable")]
        b = len(sel)
        t1, _, n, dx = self.x.shape
        x = np.take(self.x, sel, axis=1).reshape(t1, b * n, dx)
        u = None if self.u is None else np.take(self.u, sel, axis=1).reshape(t1 - 1, b * n, -1)
        return x, u, self.graph(sel)

    def graph(self, sel):
        b = len(sel)
        if self.single_graph:
            g = self._graph_cache.get(b)
            if g is None:
                one = self.graphs[int(self.gi[0])] if len(self.gi) else self.graphs[0]
                g = self._graph_cache[b] = block_diagonal([one] * b)
            return g
        return block_diagonal([self.graphs[int(i)] for i in self.gi[sel]])


def prepare(model, datasets, config):
    """Split, normalise (fitting the constants on the training split if config.norm == "fit")
    and add noise; returns (train parts, val parts, split) with split[f] = (train idx, val idx).

    Modifies ``model``'s normalisation constants when fitting.
    """
    split = [split_indices(t.n_trajectories, config.val_split, config.seed, f) for f, t in enumerate(datasets)]
    if config.norm == "fit":
        model.x_mean, model.x_std = fit_normalization([np.asarray(t.x)[tr] for t, (tr, _) in zip(datasets, split)])
        if model.spec.control_dim:
            model.u_mean, model.u_std = fit_normalization([np.asarray(t.u)[tr] for t, (tr, _) in zip(datasets, split)])
    train, val = [], []
    for f, (traj, (tr, va)) in enumerate(zip(datasets, split)):
        rng = np.random.default_rng([config.seed, 3, f])
        train.append(_Part(traj, tr, model, config.noise, rng))
        val.append(_Part(traj, va, model, 0.0, None))
    return train, [v for v in val if v.n], split


def curriculum_stage(config, epoch):
    """(stage, window) of epoch ``epoch`` (1-based): window is None in the full-horizon stage."""
    stage = min((epoch - 1) // config.curriculum_epochs, len(config.curriculum)) if config.curriculum else 0
    return stage, (config.curriculum[stage] if stage < len(config.curriculum) else None)


def window_starts(horizon, window):
    """Start steps of the windows of ``window`` steps covering 0..horizon (see the module docstring).

    Consecutive windows 0, w, 2w, ...; when w does not divide T a last window ends at T.
    ``window >= horizon`` gives the whole trajectory: [0].
    """
    if window >= horizon:
        return np.zeros(1, dtype=np.int64)
    starts = list(range(0, horizon - window + 1, window))
    if starts[-1] + window < horizon:
        starts.append(horizon - window)
    return np.asarray(starts, dtype=np.int64)


def window_part(part, window):
    """The windows of ``window`` steps of every trajectory of ``part`` as a new _Part.

    Window j of trajectory b becomes trajectory b * n_windows + j: x (w+1, B*n_windows, N, dx).
    """
    t = part.x.shape[0] - 1
    starts = window_starts(t, window)
    w = min(window, t)
    out = object.__new__(_Part)
    out.__dict__.update(part.__dict__)
    nw = len(starts)
    t1, b, n, dx = part.x.shape
    out.x = np.ascontiguousarray(np.stack([part.x[a:a + w + 1] for a in starts], axis=2)).reshape(w + 1, b * nw, n, dx)
    if part.u is not None:
        out.u = np.ascontiguousarray(np.stack([part.u[a:a + w] for a in starts], axis=2)).reshape(w, b * nw, n, -1)
    out.gi = np.repeat(part.gi, nw)
    out.index = np.repeat(part.index, nw)
    out.starts = starts
    out.n = b * nw
    out._graph_cache = {}
    return out


def epoch_batches(train_parts, batch_size, seed, epoch):
    """The batches of one epoch: list of (part number, local indices), shuffled."""
    rng = np.random.default_rng([seed, 1, epoch])
    out = []
    for p, part in enumerate(train_parts):
        perm = rng.permutation(part.n)
        out += [(p, perm[i:i + batch_size]) for i in range(0, part.n, batch_size)]
    order = rng.permutation(len(out))
    return [out[i] for i in order]


def rollout_loss(pred, x, loss):
    """The training loss of predictions against truth, both (T+1, M, dx) normalised.

    Huber (delta 1) or squared error summed over dimensions and steps 1..T, divided by M.
    Returns a float (inf when a prediction is non-finite).
    """
    d = pred[1:].astype(np.float64) - x[1:]
    if not np.all(np.isfinite(d)):
        return math.inf
    if loss == "huber":
        a = np.abs(d)
        value = np.where(a <= 1.0, 0.5 * d * d, a - 0.5).sum()
    else:
        value = (d * d).sum()
    return float(value) / x.shape[1]


class _Validator:
    """The validation loss: full-horizon rollouts of the validation split, no noise."""

    def __init__(self, parts, loss, chunk=8192):
        self.loss = loss
        self.jobs = []
        for part in parts:
            size = max(1, chunk // part.n_nodes)
            for i in range(0, part.n, size):
                sel = np.arange(i, min(i + size, part.n))
                x, u, g = part.batch(sel)
                self.jobs.append((x, u, g))
        self.n_nodes = sum(x.shape[1] for x, _, _ in self.jobs)

    def __call__(self, spec, theta):
        if not self.jobs:
            return None
        total = 0.0
        for x, u, g in self.jobs:
            pred = integrate.rollout(spec, theta, x[0], g, u, x.shape[0] - 1)
            total += rollout_loss(pred, x, self.loss) * x.shape[1]
        return total / self.n_nodes


# ---------------------------------------------------------------------------
# Checkpoints
# ---------------------------------------------------------------------------
def _save_state(path, snap):
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **snap)


def load_state(path):
    """The checkpoint written beside a model (dict of arrays and scalars); InputError if unusable."""
    try:
        with np.load(path, allow_pickle=False) as z:
            state = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist",
                         "the .state file an interrupted `mpnode train -o MODEL` leaves beside MODEL") from None
    except (OSError, ValueError) as e:
        raise InputError(path, "file", f"is not a readable checkpoint ({e})", "a .state file written by mpnode") from None
    if int(state.get("version", -1)) != STATE_VERSION:
        raise InputError(path, "version", f"is {state.get('version')}", f"checkpoint version {STATE_VERSION}")
    return state


def _model_from_state(state):
    from .model import Model

    spec = integrate.FieldSpec(**json.loads(str(state["spec"])))
    return Model(state["theta"].copy(), spec, state["x_mean"], state["x_std"], state["u_mean"], state["u_std"],
                 attrs=json.loads(str(state["model_attrs"])))


def _jsonable(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, np.generic):
        return _jsonable(v.item())
    return v


# ---------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------
def fit(model, datasets, config=None, output=None, *, sources=None, resume=False, progress=None, notify=None,
        model_attrs=None):
    """Train ``model`` on ``datasets`` (list of Trajectories); return a TrainResult.

    output : model file path, or None (nothing written).  When given, the best model is
        saved there atomically whenever the validation loss improves (and at epoch 0), the
        log goes to `log_path(output)` and the checkpoint to `state_path(output)`.
    resume : continue the run whose checkpoint is beside ``output``: weights, optimiser,
        learning rate, counters, split and normalisation come from it, and so does the
        configuration except ``epochs`` and ``time_limit`` (taken from ``config``).
        ``model`` may be None then.
    progress : called after every epoch (and once for epoch 0) with the log record (dict).
    notify : called with a one-line message for events (skipped steps, learning-rate drops).
    model_attrs : extra attributes stored in the saved model (e.g. the training files).
    Raises InputError for incompatible data or a checkpoint that does not match them.
    """
    config = (config or TrainConfig())
    sources = list(sources or [f"data[{i}]" for i in range(len(datasets))])
    notify = notify or (lambda msg: None)
    datasets = list(datasets)
    if not datasets:
        raise InputError("training data", "files", "none given", "at least one trajectory file")
    check_same_kind(datasets, sources)
    fp = fingerprint(datasets)

    state = None
    if resume:
        if output is None:
            raise InputError("--resume", "output", "resume needs the output model path", "-o MODEL.h5")
        state = load_state(state_path(output))
        if str(state["fingerprint"]) != fp:
            raise InputError(state_path(output), "fingerprint", "the checkpoint was made with other training data",
                             "the same data files, in the same order, as the interrupted run")
        stored = TrainConfig(**json.loads(str(state["config"])))
        config = dataclasses.replace(stored, epochs=config.epochs, time_limit=config.time_limit)
        model = _model_from_state(state)
    config.check()
    check_data(model, datasets, sources)

    model = model.copy()
    if resume:
        config = dataclasses.replace(config, norm="keep")  # the stored constants are the fitted ones
    train_parts, val_parts, split = prepare(model, datasets, config)
    if resume:
        config = dataclasses.replace(config, norm=json.loads(str(state["config"]))["norm"])
    spec, dtype = model.spec, model.dtype
    theta = model.theta  # updated in place
    slices = array_slices(mlp.param_shapes(spec.state_dim, spec.control_dim, spec.message_dim, spec.hidden))
    opt = Adam(theta.size, config.lr, config.beta1, config.beta2, config.eps)
    validate = _Validator(val_parts, config.loss)
    config_json = json.dumps(dataclasses.asdict(config))
    spec_json = json.dumps(dataclasses.asdict(spec))
    attrs = dict(model_attrs or {})

    def train_loss_now():  # the loss on the training split, for runs without validation data
        return _Validator(train_parts, config.loss)(spec, theta)

    def val_loss_now():
        v = validate(spec, theta)
        return train_loss_now() if v is None else v

    if state is not None:
        theta[:] = state["theta"]
        best_theta = state["best_theta"].astype(dtype)
        opt.load_state(state)
        epoch = int(state["epoch"])
        best_val = float(state["best_val"])
        best_epoch = int(state["best_epoch"])
        last_improve = int(state["last_improve"])
        bad_streak = int(state["bad_streak"])
        ref_loss = float(state["ref_loss"])
        elapsed_before = float(state["elapsed"])
        history = _truncate_log(log_path(output), epoch)
        notify(f"resuming at epoch {epoch} (best validation loss {best_val:.6g} at epoch {best_epoch}, "
               f"learning rate {opt.lr:g})")
    else:
        epoch, bad_streak, elapsed_before = 0, 0, 0.0
        v0 = val_loss_now()
        best_val = v0 if v0 is not None and math.isfinite(v0) else math.inf
        ref_loss = best_val
        best_theta, best_epoch, last_improve = theta.copy(), 0, 0
        history = []
        record = {"epoch": 0, "train_loss": None, "val_loss": v0, "best_val_loss": best_val, "grad_norm": None,
                  "lr": opt.lr, "seconds": 0.0, "elapsed": 0.0, "skipped_steps": 0, "improved": True,
                  "window": None, "stage": None}
        if output is not None:
            with atomic_path(log_path(output)) as tmp, open(tmp, "w") as f:
                f.write(json.dumps({k: _jsonable(v) for k, v in record.items()}) + "\n")
        history.append(record)
        if progress:
            progress(record)

    def save_best():
        if output is None:
            return
        m = model.copy()
        m.theta[:] = best_theta
        m.save(output, **attrs, epoch=best_epoch, val_loss=best_val, loss=config.loss, seed=config.seed)

    def snapshot():
        snap = {"version": np.int64(STATE_VERSION), "theta": theta.copy(), "best_theta": best_theta.copy(),
                "epoch": np.int64(epoch), "best_val": np.float64(best_val), "best_epoch": np.int64(best_epoch),
                "last_improve": np.int64(last_improve), "bad_streak": np.int64(bad_streak),
                "elapsed": np.float64(elapsed_before + (time.perf_counter() - t_start)),
                "config": config_json, "fingerprint": fp, "spec": spec_json, "model_attrs": json.dumps(model.attrs, default=str),
                "x_mean": model.x_mean, "x_std": model.x_std, "u_mean": model.u_mean, "u_std": model.u_std,
                "curriculum_stage": np.int64(curriculum_stage(config, max(epoch, 1))[0])}
        snap.update(opt.state())
        snap.update(best_moments=best_moments.copy(), best_t=np.int64(best_t), ref_loss=np.float64(ref_loss))
        return snap

    grad = np.empty(theta.size)
    new_theta = np.empty(theta.size, dtype=dtype)
    if state is not None:
        best_moments, best_t = state["best_moments"].copy(), int(state["best_t"])
    else:
        best_moments, best_t = np.stack([opt.m, opt.v]), opt.t
    t_start = time.perf_counter()
    if state is None:
        save_best()
    last_state_save = -math.inf
    snap = snapshot()
    status, message = "completed", f"trained {config.epochs} epochs"
    log_fd = os.open(log_path(output), os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644) if output is not None else None
    horizons = {p.x.shape[0] - 1 for p in train_parts}
    full_window = horizons.pop() if len(horizons) == 1 else None
    windowed = {}  # stage -> windowed training parts (only the current stage is kept)
    announced = None
    try:
        while epoch < config.epochs:
            t0 = time.perf_counter()
            tl_sum, tl_nodes, gn_sum, gn_max, n_steps, skipped = 0.0, 0, 0.0, 0.0, 0, 0
            stop_now = False
            stage, window = curriculum_stage(config, epoch + 1)
            parts = train_parts
            if window is None:
                windowed = {}
            else:
                if stage not in windowed:
                    windowed = {stage: [window_part(part, window) for part in train_parts]}
                parts = windowed[stage]
            if config.curriculum and stage != announced:
                announced = stage
                notify(f"epoch {epoch + 1}: curriculum stage {stage + 1} of {len(config.curriculum) + 1}: "
                       + (f"windows of {window} steps" if window is not None else "the full horizon"))
            for p, sel in epoch_batches(parts, config.batch_size, config.seed, epoch + 1):
                x, u, g = parts[p].batch(sel)
                loss, gtheta, _ = integrate.loss_and_grad(spec, theta, x, g, u, config.loss)
                grad[:] = gtheta
                if not math.isfinite(loss):
                    what = "the loss became non-finite"
                elif config.blowup and loss > config.blowup * ref_loss:
                    what = f"the loss {loss:.3g} exceeds {config.blowup:g}x the initial loss {ref_loss:.3g}"
                elif not np.all(np.isfinite(grad)):
                    what = "the gradient became non-finite"
                else:
                    what = None
                    norm = clip_gradient(grad, config.clip, slices, config.clip_mode)
                    step = opt.update(grad)
                    np.subtract(theta, step, out=new_theta, casting="unsafe")
                    if not np.all(np.isfinite(new_theta)):
                        what = "the updated weights became non-finite"
                if what is not None:
                    # back to the best weights (and their optimiser state), with half the learning rate
                    theta[:] = best_theta
                    opt.m[:], opt.v[:], opt.t = best_moments[0], best_moments[1], best_t
                    skipped += 1
                    bad_streak += 1
                    opt.lr *= 0.5
                    notify(f"epoch {epoch + 1}: {what}; step skipped, weights reset to the best (epoch "
                           f"{best_epoch}), learning rate halved to {opt.lr:g} ({bad_streak} since the last "
                           f"improvement)")
                    if bad_streak >= config.max_bad_steps:
                        status = "diverged"
                        message = (f"training diverged at epoch {epoch + 1}: {bad_streak} bad steps without a new "
                                   f"best validation loss (last: {what}; learning rate now {opt.lr:g}). The saved "
                                   f"model is the best finite one (epoch {best_epoch}). Try a smaller --lr.")
                        stop_now = True
                        break
                    continue
                theta[:] = new_theta
                tl_sum += loss * x.shape[1]
                tl_nodes += x.shape[1]
                gn_sum += norm
                gn_max = max(gn_max, norm)
                n_steps += 1
            if stop_now:
                break
            epoch += 1
            val = val_loss_now()
            improved = val is not None and math.isfinite(val) and val < best_val
            if improved:
                best_val, best_epoch, last_improve = val, epoch, epoch
                best_theta = theta.copy()
                best_moments, best_t = np.stack([opt.m, opt.v]), opt.t
                bad_streak = 0
            elif epoch - last_improve >= config.patience and opt.lr > config.min_lr:
                opt.lr *= config.lr_decay
                last_improve = epoch
                notify(f"epoch {epoch}: no new best validation loss for {config.patience} epochs; "
                       f"learning rate now {opt.lr:g}")
            now = time.perf_counter()
            record = {"epoch": epoch, "train_loss": tl_sum / tl_nodes if tl_nodes else None, "val_loss": val,
                      "best_val_loss": best_val, "grad_norm": gn_sum / n_steps if n_steps else None,
                      "grad_norm_max": gn_max if n_steps else None, "lr": opt.lr, "seconds": now - t0,
                      "elapsed": elapsed_before + now - t_start, "skipped_steps": skipped, "improved": improved,
                      "window": full_window if window is None else min(window, full_window or window),
                      "stage": stage}
            history.append(record)
            if log_fd is not None:
                _append_line(log_fd, json.dumps({k: _jsonable(v) for k, v in record.items()}))
            snap = snapshot()
            if improved:
                save_best()
            if output is not None and (improved or now - last_state_save >= config.checkpoint_seconds):
                _save_state(state_path(output), snap)
                last_state_save = now
            if progress:
                progress(record)
            if config.time_limit is not None and now - t_start >= config.time_limit and epoch < config.epochs:
                status = "time_limit"
                message = f"time limit reached after epoch {epoch}"
                break
    except KeyboardInterrupt:
        status, message = "interrupted", f"interrupted during epoch {epoch + 1}; the last finished epoch is saved"
    finally:
        if log_fd is not None:
            os.close(log_fd)
    if output is not None:
        _save_state(state_path(output), snap)  # the last finished epoch: resume continues from here
    best = model.copy()
    best.theta[:] = best_theta
    best.attrs.update(attrs, epoch=best_epoch, val_loss=best_val)
    if status == "completed" and config.epochs == epoch and state is not None and epoch == int(state["epoch"]):
        message = f"nothing to do: the run already has {epoch} epochs (raise --epochs to continue)"
    return TrainResult(best, status, message, best_val, best_epoch, epoch, opt.lr,
                       elapsed_before + time.perf_counter() - t_start, history, split)


def _append_line(fd, line):
    """Append one log line with a single write() on an O_APPEND descriptor.

    A run killed at any moment (SIGKILL, power) leaves whole lines only: the line is
    written by one system call, never half by a buffered writer flushing in pieces.
    """
    data = (line + "\n").encode()
    written = os.write(fd, data)
    while written < len(data):  # not seen for regular files; finish rather than tear the line
        written += os.write(fd, data[written:])


def read_log(path):
    """The records of a training log (list of dicts), skipping a line a crash could have cut.

    `fit` writes every line with one write(), so a cut line should not occur; the reader
    still tolerates one (the last line, without its newline) rather than fail on it.
    """
    records = []
    with open(path) as f:
        for line in f:
            try:
                records.append(json.loads(line))
            except ValueError:
                if line.endswith("\n"):
                    raise
    return records


def _truncate_log(path, epoch):
    """Keep the log lines of epochs <= ``epoch`` (a resumed run redoes the later ones)."""
    kept, records = [], []
    try:
        with open(path) as f:
            for line in f:
                try:
                    r = json.loads(line)
                except ValueError:
                    continue  # a line cut by a kill
                if r.get("epoch", math.inf) <= epoch:
                    kept.append(line if line.endswith("\n") else line + "\n")
                    records.append(r)
    except FileNotFoundError:
        pass
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.writelines(kept)
    return records


def raise_if_diverged(result):
    """NumericalError with the result's message when training diverged (for callers that want it)."""
    if result.status == "diverged":
        raise NumericalError(result.message)
    return result
