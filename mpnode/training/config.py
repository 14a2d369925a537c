"""`TrainConfig`: every option of a training run besides the model and the data, its defaults
and its checks (the command line's training flags and the sweep's keys are these fields)."""
import math
import numbers
from dataclasses import dataclass

from mpnode.base.arguments import check_bool, check_int, check_number
from mpnode.base.errors import InputError
from mpnode.base.options import option

from . import losses
from .optim import CLIP_MODES

SCHEDULES = ("plateau", "cosine")
#: how training treats the model's normalisation constants (mpnode.training.batches.prepare)
NORMS = ("fit", "refit", "keep")


#: the passes over the training trajectories of a run given neither ``epochs`` nor a time limit (the
#: MP-NODE paper's)
DEFAULT_EPOCHS = 4000


def epoch_cap(epochs, time_limit):
    """The passes a run may make: ``epochs`` when given; unset, none beyond the time limit when
    there is one (the budget the user gave), else DEFAULT_EPOCHS.  None: no cap."""
    if epochs is not None:
        return epochs
    return None if time_limit is not None else DEFAULT_EPOCHS


@dataclass(kw_only=True)
class TrainConfig:
    """Everything that decides a training run besides the model and the data.

    time_limit is the run's total training time in seconds (None: no limit; a resumed run
    counts the time before it, as epochs counts the epochs before it); epochs None: as many
    as the time limit allows, or DEFAULT_EPOCHS without one (`epoch_cap`); norm is "fit"
    (z-score constants fitted on the training split), "refit" (the same for a trained model,
    whose weights are changed to compute what they did) or "keep" (the model's own constants,
    for finetuning); schedule is "plateau" (cut the learning rate by lr_decay after
    ``patience`` epochs without a new best) or "cosine" (from lr down to min_lr over the
    budget: the epochs, or the time limit when that comes first); val_graphs: hold out
    that many whole graphs of every file with more graphs for validation (mpnode.training.batches).
    input_noise and train_window are the long-rollout options (mpnode.training.loop).
    ignore_attrs: learn as if the data had neither node attributes nor edge weights.
    The defaults are the command line's (`mpnode train --help` says what each does).
    """

    epochs: int = None
    batch_size: int = 128
    lr: float = 1e-3
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    clip: float = 500.0
    clip_mode: str = option("per-array", switches={"clip_global": "global"})
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
    curriculum: tuple = option((), aliases=("horizon_curriculum",))
    curriculum_epochs: int = 100
    schedule: str = "plateau"
    val_graphs: int = 0
    ensemble: int = 1
    bootstrap: bool = False
    split_seed: int = None
    input_noise: float = 0.0
    train_window: int = 0
    ignore_attrs: bool = False

    def check(self):
        """Raise InputError naming the option for a value that cannot work."""
        def bad(name, problem, expected):
            raise InputError("training options", name, problem, expected)

        self._check_types()
        self.curriculum = parse_curriculum(self.curriculum)
        if self.curriculum_epochs < 1:
            bad("curriculum_epochs", f"is {self.curriculum_epochs}", "an integer >= 1")

        if self.batch_size < 1:
            bad("batch_size", f"is {self.batch_size}", "an integer >= 1")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            bad("lr", f"is {self.lr}", "a finite number > 0")
        if not (0 <= self.val_split < 1):
            bad("val_split", f"is {self.val_split}", "a fraction in [0, 1)")
        if not (self.noise >= 0):
            bad("noise", f"is {self.noise}", "a number >= 0")
        if self.loss not in losses.LOSSES:
            bad("loss", f"is {self.loss!r}", " or ".join(losses.LOSSES))
        if self.clip_mode not in CLIP_MODES:
            bad("clip_mode", f"is {self.clip_mode!r}", " or ".join(CLIP_MODES))
        if self.norm not in NORMS:
            bad("norm", f"is {self.norm!r}", " or ".join(map(repr, NORMS)))
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
        if self.schedule not in SCHEDULES:
            bad("schedule", f"is {self.schedule!r}", " or ".join(SCHEDULES))
        if self.val_graphs < 0:
            bad("val_graphs", f"is {self.val_graphs}", "an integer >= 0")
        if self.ensemble < 1:
            bad("ensemble", f"is {self.ensemble}", "an integer >= 1 (the number of members; 1: one model)")
        return self

    @property
    def epoch_cap(self):
        """The passes this run may make (None: as many as its time limit allows)."""
        return epoch_cap(self.epochs, self.time_limit)

    @property
    def split_by(self):
        """The seed of the train/validation split: ``split_seed``, or the run's seed."""
        return self.seed if self.split_seed is None else self.split_seed

    def _check_types(self):
        """Every option of the right type and sign (the ranges that need more are checked in `check`)."""
        where = "training options"
        if self.epochs is not None:
            self.epochs = check_int(self.epochs, where, "epochs", 0)
        for name in ("batch_size", "patience", "max_bad_steps", "seed", "curriculum_epochs", "val_graphs",
                     "ensemble", "train_window"):
            setattr(self, name, check_int(getattr(self, name), where, name, 0))
        if self.split_seed is not None:
            self.split_seed = check_int(self.split_seed, where, "split_seed", 0)
        self.bootstrap = check_bool(self.bootstrap, where, "bootstrap")
        self.ignore_attrs = check_bool(self.ignore_attrs, where, "ignore_attrs")
        for name in ("lr", "beta1", "beta2", "eps", "clip", "val_split", "noise", "input_noise", "lr_decay", "min_lr",
                     "blowup", "checkpoint_seconds"):
            setattr(self, name, check_number(getattr(self, name), where, name, least=0))
        for name in ("beta1", "beta2"):
            if not getattr(self, name) < 1:
                raise InputError(where, name, f"is {getattr(self, name)}", "a number in [0, 1)")
        if self.time_limit is not None:
            self.time_limit = check_number(self.time_limit, where, "time_limit", positive=True)


def parse_curriculum(value, source="training options"):
    """The window lengths of a curriculum: increasing integers >= 1 (steps), from a sequence
    ((5, 10)) or the command line's text ("5,10,full": "full", the full horizon, only last and
    implied); None: none.  InputError for anything else."""
    items = [v.strip().lower() for v in value.split(",") if v.strip()] if isinstance(value, str) else value
    if items is None:
        return ()
    if not isinstance(items, (tuple, list)):
        raise InputError(source, "curriculum", f"is {value!r}", "window lengths, e.g. (5, 10) or \"5,10,full\"")
    items = list(items[:-1]) if items and items[-1] == "full" else list(items)
    windows = []
    for w in items:
        if isinstance(w, str) and w.isascii() and w.isdigit():
            w = int(w)
        if not (isinstance(w, numbers.Integral) and not isinstance(w, bool) and w >= 1 and w > max(windows, default=0)):
            raise InputError(source, "curriculum", f"is {value!r}",
                             "increasing window lengths >= 1 (steps), e.g. (5, 10) or \"5,10,full\"")
        windows.append(int(w))
    return tuple(windows)


def curriculum_stage(config, epoch):
    """(stage, window) of epoch ``epoch`` (1-based): window is None in the full-horizon stage
    (``train_window`` steps there when set)."""
    stage = min((epoch - 1) // config.curriculum_epochs, len(config.curriculum)) if config.curriculum else 0
    return stage, (config.curriculum[stage] if stage < len(config.curriculum) else config.train_window or None)
