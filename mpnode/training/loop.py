"""Training a model on trajectory data: resumable bit for bit, and never writing a non-finite weight.

The recipe (docs/design.md says where each part comes from): full-horizon single shooting
from each trajectory's first state; Huber loss on z-scored states, summed over dimensions
and steps and averaged over nodes (mpnode.training.losses); Adam behind a gradient clip norm applied
to each parameter array; batches of ``batch_size`` trajectories (mpnode.training.batches); a random 70/30
train/validation split with the z-score constants fitted on the training split only;
Gaussian noise (std 1e-4) added once to the normalised training states; the learning rate
halved after ``patience`` epochs without a new best validation loss; the best-validation
weights kept.

A *bad step* -- a non-finite loss, gradient or update, or a batch loss above ``blowup``
(100) times the initial validation loss -- is skipped: the weights and Adam's moments go
back to the best ones and the learning rate halves; ``max_bad_steps`` in a row without a
new best stop the run ("diverged").  (The tanh network's output is bounded, so a far too
large learning rate gives huge but finite losses: the blow-up test is what catches it.)

Horizon curriculum (``TrainConfig.curriculum``): with window lengths w1 < w2 < ..., the
first ``curriculum_epochs`` epochs train on windows of w1 steps (mpnode.training.batches), the next
on w2, ..., the rest on the full horizon, so a chaotic system is learned without the
exploding gradients of long rollouts from random weights.  Validation stays on the full
horizon.  The stage is a function of the epoch number alone, which keeps resume exact.

Long rollouts (both off by default): ``input_noise`` adds fresh Gaussian noise, drawn from the
epoch number, to the initial state of every training rollout (the targets stay clean), so the
model learns to return towards the data from states a little off them, as its own long rollouts
are; ``train_window`` trains on windows of that many steps once any curriculum is over, while
validation, which chooses the model, stays on the full horizon.

Files beside the output model ``OUT``: ``OUT.log.jsonl`` (mpnode.training.log) and
``OUT.state``, the `TrainState` checkpoint.  This module knows nothing of any particular system.
"""
import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from mpnode import engine
from mpnode.base.atomic import atomic_paths
from mpnode.base.errors import InputError
from mpnode.base.oserrors import FileSystemError, file_error
from mpnode.engine import layouts
from mpnode.evaluation import metrics
from mpnode.model import check_data, encoder
from mpnode.model.inputs import check_training_inputs

from . import losses
from .batches import TrainingData, epoch_batches, split_settings
from .config import TrainConfig, curriculum_stage
from .log import TrainLog
from .optim import array_slices, clip_gradient
from .state import TrainState, state_path


@dataclass
class TrainResult:
    """What `fit` returns.

    model : the best-validation Model (normalisation included)
    status : "completed" | "time_limit" | "diverged" | "interrupted"
    validation : per validation file at the best epoch: {"file", "trajectories", "nmse" (mean over
        steps 1..T), "nmse_last"}, the normalised MSE `mpnode eval` reports on those trajectories
    config : the run's TrainConfig (a resumed run's: its checkpoint's)
    split : every file's (train idx, val idx)
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
    validation: list = field(default_factory=list)
    config: TrainConfig = None
    split: list = field(default_factory=list)

    @property
    def val_nmse(self):
        """The validation normalised MSE at the best epoch over all files (weighted by trajectories)."""
        return weighted_nmse(self.validation)



# ---------------------------------------------------------------------------
# One epoch, one bad step
# ---------------------------------------------------------------------------
class Diverged(Exception):
    """Too many bad steps without a new best validation loss (the message says what happened)."""


@dataclass
class EpochStats:
    loss_sum: float = 0.0
    nodes: int = 0
    norm_sum: float = 0.0
    norm_max: float = 0.0
    steps: int = 0
    skipped: int = 0

    def add(self, loss, nodes, norm):
        self.loss_sum += loss * nodes
        self.nodes += nodes
        self.norm_sum += norm
        self.norm_max = max(self.norm_max, norm)
        self.steps += 1


def run_epoch(state, parts, notify):
    """One pass over the shuffled batches of ``parts``: an Adam step per batch, bad steps
    rolled back (`bad_step`).  Returns the epoch's EpochStats; raises Diverged."""
    config, spec, theta = state.config, state.model.spec, state.theta
    slices = array_slices(layouts.param_shapes(spec))
    grad = np.empty(theta.size)
    new_theta = np.empty_like(theta)
    stats = EpochStats()
    rng = np.random.default_rng([config.seed, 5, state.epoch + 1])
    noise_rng = np.random.default_rng([config.seed, 7, state.epoch + 1])
    for p, sel in epoch_batches(parts, config.batch_size, config.seed, state.epoch + 1):
        batch = parts[p].batch(sel)
        visible = warmups(rng, spec.encoder_window, len(sel), parts[p].n_nodes)
        kick = start_noise(noise_rng, config.input_noise, batch.x.shape[1:])
        loss, gtheta = losses.batch_value_and_grad(spec, theta, batch, config.loss, visible, kick)
        grad[:] = gtheta
        problem = bad_loss(loss, grad, state.ref_loss, config)
        if problem is None:
            norm = clip_gradient(grad, config.clip, slices, config.clip_mode)
            np.subtract(theta, state.opt.update(grad), out=new_theta, casting="unsafe")
            if not np.all(np.isfinite(new_theta)):
                problem = "the updated weights became non-finite"
        if problem is not None:
            stats.skipped += 1
            bad_step(state, problem, notify)
            continue
        theta[:] = new_theta
        stats.add(loss, batch.x.shape[1], norm)
    return stats


def start_noise(rng, std, shape):
    """Fresh Gaussian noise (std ``std``, normalised units) on the initial states of a batch's
    rollouts, or None: the inputs perturbed and the targets clean, so the model learns to come
    back towards the data from states a little off them, as its own long rollouts will be."""
    return rng.standard_normal(shape) * std if std > 0 else None


def warmups(rng, window, n_trajectories, n_nodes):
    """How many of its first observations the initial-state encoder sees, per node of a batch:
    1..W at random per trajectory, so that it learns to start from a warm-up of any length up
    to its window (0 for a model without an encoder)."""
    if not window:
        return 0
    return np.repeat(rng.integers(1, window + 1, size=n_trajectories), n_nodes)


def bad_loss(loss, grad, ref_loss, config):
    """Why this batch's step must not be taken (a sentence), or None."""
    if not math.isfinite(loss):
        return "the loss became non-finite"
    if config.blowup and loss > config.blowup * ref_loss:
        return f"the loss {loss:.3g} exceeds {config.blowup:g}x the initial loss {ref_loss:.3g}"
    if not np.all(np.isfinite(grad)):
        return "the gradient became non-finite"
    return None


def bad_step(state, problem, notify):
    """Skip a step: back to the best weights, half the learning rate; Diverged after too many."""
    state.restore_best()
    state.bad_streak += 1
    state.opt.lr *= 0.5
    state.lr_scale *= 0.5
    epoch = state.epoch + 1
    notify(f"epoch {epoch}: {problem}; step skipped, weights reset to the best (epoch {state.best_epoch}), learning "
           f"rate halved to {state.opt.lr:g} ({state.bad_streak} since the last improvement)")
    if state.bad_streak >= state.config.max_bad_steps:
        raise Diverged(f"training diverged at epoch {epoch}: {state.bad_streak} bad steps without a new best "
                       f"validation loss (last: {problem}; learning rate now {state.opt.lr:g}). The saved model is "
                       f"the best finite one (epoch {state.best_epoch}). Try a smaller --lr.")


def end_of_epoch(state, val, files, notify):
    """Keep the weights if ``val`` is a new best; set the next epoch's learning rate (the cosine
    schedule, or a cut after ``patience`` flat epochs).  Returns whether the epoch improved."""
    config = state.config
    improved = val is not None and math.isfinite(val) and val < state.best_val
    if improved:
        state.improve(val, files)
    if config.schedule == "cosine":
        state.opt.lr = state.lr_scale * cosine_lr(config, budget_used(state))
    elif not improved and state.epoch - state.last_improve >= config.patience and state.opt.lr > config.min_lr:
        state.opt.lr *= config.lr_decay
        state.last_improve = state.epoch
        notify(f"epoch {state.epoch}: no new best validation loss for {config.patience} epochs; "
               f"learning rate now {state.opt.lr:g}")
    return improved


def budget_used(state):
    """The fraction of the run's budget spent: epochs, or the time limit when that binds first."""
    config = state.config
    cap = config.epoch_cap
    used = 0.0  # no cap: the time limit is the budget
    if cap is not None:
        used = state.epoch / cap if cap else 1.0
    if config.time_limit is not None:
        used = max(used, state.elapsed / config.time_limit)
    return min(used, 1.0)


def cosine_lr(config, used):
    """The cosine schedule: lr at the start of the budget, min_lr at its end."""
    return config.min_lr + (config.lr - config.min_lr) * 0.5 * (1.0 + math.cos(math.pi * used))


# ---------------------------------------------------------------------------
# Validation and the curriculum
# ---------------------------------------------------------------------------
class Validator:
    """Full-horizon rollouts of the validation parts (no noise): the loss per node, and per file
    the normalised MSE `mpnode eval` would report (mpnode.evaluation.metrics: the observed values
    of steps 1..T).  A model with an initial-state encoder sees each trajectory's whole window."""

    def __init__(self, parts, loss, chunk=8192):
        self.loss = loss
        self.parts = []  # (source, trajectories, variance per dimension, [Batch chunks])
        for part in parts:
            size = max(1, chunk // part.n_nodes)
            jobs = [part.batch(np.arange(i, min(i + size, part.n))) for i in range(0, part.n, size)]
            self.parts.append((part.source, part.n, metrics.variance(part.x), jobs))
        self.n_nodes = sum(b.x.shape[1] for *_, jobs in self.parts for b in jobs)

    def __call__(self, spec, theta):
        """(loss, per-file figures); the loss is inf when a rollout is non-finite."""
        total, files = 0.0, []
        for source, n, var, jobs in self.parts:
            sums, counts = 0.0, 0
            for b in jobs:
                x0, _ = encoder.start(spec, theta, b.x, b.intervals, spec.encoder_window)
                pred = engine.forward(spec, theta, x0, b.graph, b.u, b.x.shape[0] - 1, intervals=b.intervals)
                total += losses.value(pred, b.x, self.loss) * b.x.shape[1]
                err = metrics.normalised_sq_error(pred[1:], b.x[1:], var=var)
                sums = sums + np.where(np.isnan(err), 0, err).sum(axis=(1, 2))
                counts = counts + (~np.isnan(err)).sum(axis=(1, 2))
            with np.errstate(invalid="ignore"):
                files.append({"file": source, "trajectories": n, "nmse": float(sums.sum() / counts.sum()),
                              "nmse_last": float(sums[-1] / counts[-1])})
        return total / self.n_nodes, files


def weighted_nmse(files):
    """The trajectory-weighted mean of the files' normalised MSE (inf when any is; None without files)."""
    n = sum(f["trajectories"] for f in files)
    return sum(f["trajectories"] * f["nmse"] for f in files) / n if n else None


class Curriculum:
    """The training parts of each epoch: the windows of its curriculum stage (only the current
    stage's are kept), or the full trajectories."""

    def __init__(self, config, parts, notify):
        self.config, self.parts, self.notify = config, parts, notify
        self.stage, self.windowed = None, None
        horizons = {p.x.shape[0] - 1 for p in parts}
        self.full = horizons.pop() if len(horizons) == 1 else None

    def parts_for(self, epoch):
        """(parts, stage, window length in steps or None) for epoch ``epoch`` (1-based)."""
        stage, window = curriculum_stage(self.config, epoch)
        if stage != self.stage:
            self.stage = stage
            self.windowed = None if window is None else [p.windows(window) for p in self.parts]
            if self.config.curriculum:
                self.notify(f"epoch {epoch}: curriculum stage {stage + 1} of {len(self.config.curriculum) + 1}: "
                            + (f"windows of {window} steps" if window is not None else "the full horizon"))
        logged = self.full if window is None else min(window, self.full or window)
        return (self.parts if window is None else self.windowed), stage, logged


# ---------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------
def fit(model, data, config=None, output=None, *, sources=None, resume=False, progress=None, notify=None,
        model_attrs=None):
    """Train ``model`` on ``data`` (a TrainingData, or a list of Trajectories); return a TrainResult.

    output : model file path, or None (nothing written).  When given, the best model is
        saved there atomically (at epoch 0, then with the checkpoint `state_path(output)` at
        most every config.checkpoint_seconds, and at the end); the log goes to
        `log_path(output)`, one line per epoch.
    resume : continue the run whose checkpoint is beside ``output``: weights, optimiser,
        learning rate, counters, split and normalisation come from it, and so does the
        configuration except ``epochs`` and ``time_limit`` (taken from ``config``).
        ``model`` may be None then.
    sources : the files' names in messages (a list of Trajectories; a TrainingData has its own).
    progress : called after every epoch (and once for epoch 0) with the log record (dict).
    notify : called with a one-line message for events (skipped steps, learning-rate drops).
    model_attrs : extra attributes stored in the saved model (e.g. the training files).
    Raises InputError for incompatible data or a checkpoint that does not match them.
    """
    notify = notify or (lambda msg: None)
    state, data = start_state(model, data, config or TrainConfig(), output, resume, sources)
    config = state.config
    train_parts, val_parts = data.parts(state.model, "keep" if resume else config.norm)  # resumed: fitted before
    _compile_ahead(state.model, train_parts, config)
    validate = Validator(val_parts or train_parts, config.loss)
    attrs = dict(model_attrs or {})
    log = TrainLog(output)
    if resume:
        history = log.start(keep_epochs=state.epoch)
        notify(f"resuming at epoch {state.epoch} (best validation loss {state.best_val:.6g} at epoch "
               f"{state.best_epoch}, learning rate {state.opt.lr:g})")
    else:
        history = log.start(first_record=first_epoch(state, validate))
    loop = _Loop(state, Curriculum(config, train_parts, notify), validate, log, output, attrs, progress, notify,
                 resume)
    try:
        if not resume:
            loop.save(force=True)  # epoch 0: the model and the checkpoint, so that they always agree
            loop.last_save = -math.inf  # and the first epoch's at once: a run killed early resumes from it
            if progress:
                progress(history[0])
        status, message = loop.run(history)
        loop.save(force=True)  # the best model, and the last finished epoch for resume
    except FileSystemError as e:
        raise loop.stopped(e) from None
    finally:
        log.close()
    if status == "completed" and resume and loop.epochs_run == 0:
        message = f"nothing to do: the run already has {state.epoch} epochs (raise --epochs to continue)"
    return TrainResult(state.best_model(**attrs, epoch=state.best_epoch, val_loss=state.best_val), status, message,
                       state.best_val, state.best_epoch, state.epoch, state.opt.lr, loop.elapsed(), history,
                       state.best_files if val_parts else [], config, data.split)


def _compile_ahead(model, parts, config):
    """The training step's VJP compiles on the other core while the first validation compiles
    the rollout (nothing happens when both are compiled: mpnode.engine.compiling)."""
    part = next((p for p in parts if p.n), None)
    if part is not None:
        sel = np.arange(min(config.batch_size, part.n))
        engine.compile_vjp_ahead(model.spec, model.dtype, part.graph(sel), part.x.shape[0] - 1)


def start_state(model, data, config, output, resume, sources):
    """(a new TrainState for ``model``, or the one saved beside ``output`` (resume), the
    TrainingData under the run's configuration), checked against each other; ``config``'s
    epochs and time_limit apply to a resumed run too."""
    if resume:
        if output is None:
            raise InputError("--resume", "output", "resume needs the output model path", "-o MODEL.h5")
        state = TrainState.load(state_path(output))
        state.config = dataclasses.replace(state.config, epochs=config.epochs, time_limit=config.time_limit)
    else:
        state = TrainState(model.copy(), config, None)
    state.config.check()
    data = as_training_data(data, state.config, sources)
    if resume and state.fingerprint != data.fingerprint:
        raise InputError(state_path(output), "fingerprint", "the checkpoint was made with other training data",
                         "the same data files, in the same order, as the interrupted run")
    state.fingerprint = data.fingerprint
    check_training_inputs(state.model, data)
    check_data(state.model, data.datasets, data.sources)
    return state, data


def as_training_data(data, config, sources=None):
    """``data`` as a TrainingData split under ``config`` (a list of Trajectories is prepared here;
    a TrainingData prepared under another split, e.g. before a resume read its checkpoint, again)."""
    if isinstance(data, TrainingData):
        if data.split_settings == split_settings(config):
            return data
        sources, data = data.sources, data.datasets
    return TrainingData(data, config, sources)


def first_epoch(state, validate):
    """Epoch 0: the initial validation loss becomes the first best and the blow-up reference."""
    v0, files = validate(state.model.spec, state.theta)
    state.best_val = state.ref_loss = v0 if math.isfinite(v0) else math.inf
    state.best_files = files
    state.best_theta = state.theta.copy()  # the weights just validated: a refit changed them since the state was made
    return {"epoch": 0, "train_loss": None, "val_loss": v0, "val_nmse": weighted_nmse(files), "best_val_loss": state.best_val,
            "best_val_nmse": weighted_nmse(files),
            "grad_norm": None,
            "lr": state.opt.lr, "seconds": 0.0, "elapsed": 0.0, "skipped_steps": 0, "improved": True,
            "window": None, "stage": None}


def save_best(state, output, attrs):
    if output is not None:
        c = state.config
        state.best_model().save(output, **attrs, epoch=state.best_epoch, val_loss=state.best_val, loss=c.loss,
                                seed=c.seed)


class _Loop:
    """The epochs of `fit`: run, validate, log, save, until the budget or a stop."""

    def __init__(self, state, curriculum, validate, log, output, attrs, progress, notify, resumed):
        self.state, self.curriculum, self.validate, self.log = state, curriculum, validate, log
        self.output, self.attrs, self.progress, self.notify = output, attrs, progress, notify
        self.t_start, self.elapsed_before = time.perf_counter(), state.elapsed
        self.snap = state.snapshot()
        self.epochs_run = 0
        # what is on disk: a resumed run's checkpoint and model; nothing yet of a new run
        self.saved_epoch = state.epoch if resumed else None
        self.last_save, self.saved_best = -math.inf, state.best_epoch if resumed else None

    def elapsed(self):
        return self.elapsed_before + time.perf_counter() - self.t_start

    def save(self, force=False):
        """The checkpoint, and the best model with it when that changed, at most every
        checkpoint_seconds unless forced: writing both after every improving epoch costs a small
        run a large share of each epoch.  The two are written as a pair (mpnode.base.atomic):
        a failure (a full disk) leaves the previous pair, which agree."""
        now = time.perf_counter()
        if self.output is None or not (force or now - self.last_save >= self.state.config.checkpoint_seconds):
            return
        checkpoint = state_path(self.output)
        if self.state.best_epoch == self.saved_best:
            TrainState.save(checkpoint, self.snap)
        else:
            with atomic_paths(self.output, checkpoint) as (model_tmp, checkpoint_tmp):
                save_best(self.state, model_tmp, self.attrs)
                TrainState.write(checkpoint_tmp, self.snap)
            self.saved_best = self.state.best_epoch
        self.last_save, self.saved_epoch = now, int(self.snap["epoch"])

    def stopped(self, error):
        """``error`` (a file that could not be written) saying where the run stopped and what is on disk."""
        if self.saved_epoch is None:
            left = "Training stopped before anything was saved"
            self.log.remove()
        else:
            left = (f"Training stopped after epoch {self.state.epoch}; {self.output} and its checkpoint "
                    f"{state_path(self.output)} are those of epoch {self.saved_epoch}, written together: once the "
                    "file can be written, continue with the same command plus --resume")
        return file_error(error, error.filename, error.doing, left=left)

    def run(self, history):
        """Returns (status, message): completed, time_limit, diverged or interrupted."""
        state, config = self.state, self.state.config
        cap = config.epoch_cap
        try:
            while cap is None or state.epoch < cap:
                t0 = time.perf_counter()
                parts, stage, window = self.curriculum.parts_for(state.epoch + 1)
                stats = run_epoch(state, parts, self.notify)
                state.epoch += 1
                self.epochs_run += 1
                val, files = self.validate(state.model.spec, state.theta)
                state.elapsed = self.elapsed()
                improved = end_of_epoch(state, val, files, self.notify)
                now = time.perf_counter()
                record = epoch_record(state, stats, val, weighted_nmse(files), improved, now - t0, window, stage)
                history.append(record)
                self.log.append(record)
                self.snap = state.snapshot()
                self.save()
                if self.progress:
                    self.progress(record)
                if config.time_limit is not None and state.elapsed >= config.time_limit \
                        and (cap is None or state.epoch < cap):
                    return "time_limit", f"time limit reached after epoch {state.epoch}"
        except Diverged as e:
            return "diverged", str(e)
        except KeyboardInterrupt:
            return "interrupted", f"interrupted during epoch {state.epoch + 1}; the last finished epoch is saved"
        return "completed", f"trained {cap} epochs"


def epoch_record(state, stats, val, nmse, improved, seconds, window, stage):
    """The log line of a finished epoch."""
    return {"epoch": state.epoch, "train_loss": stats.loss_sum / stats.nodes if stats.nodes else None,
            "val_loss": val, "val_nmse": nmse, "best_val_loss": state.best_val,
            "best_val_nmse": weighted_nmse(state.best_files),
            "grad_norm": stats.norm_sum / stats.steps if stats.steps else None,
            "grad_norm_max": stats.norm_max if stats.steps else None, "lr": state.opt.lr, "seconds": seconds,
            "elapsed": state.elapsed, "skipped_steps": stats.skipped, "improved": improved, "window": window,
            "stage": stage}
