"""`TrainState`: what changes during a run (weights, Adam, learning rate, counters) and its
checkpoint beside the model file, from which a run resumes bit for bit."""
import dataclasses
import json
import math

import numpy as np

from mpnode.base.atomic import atomic_path
from mpnode.base.errors import InputError
from mpnode.engine.spec import FieldSpec

from .config import TrainConfig, curriculum_stage
from .optim import Adam

STATE_VERSION = 1
#: the checkpoint of a run whose model has kinematics: a reader that knows no kinematics would
#: resume it without them, so it must refuse the file (the model file's version 6 does the same)
KINEMATICS_STATE_VERSION = 2
READABLE_VERSIONS = (STATE_VERSION, KINEMATICS_STATE_VERSION)


def state_path(output):
    """The resume checkpoint beside the model file ``output``."""
    return str(output) + ".state"


# ---------------------------------------------------------------------------
# The state of a run
# ---------------------------------------------------------------------------
class TrainState:
    """What changes during a run -- current and best weights, Adam, learning rate, counters --
    and what a resumed run needs besides the data; saves and loads itself (``OUT.state``).

    model : the Model being trained (its theta is updated in place; its normalisation is
    the run's); best_theta, best_moments (2, P), best_t : the best weights and Adam's state
    then; epoch : finished epochs; ref_loss : the initial validation loss (blow-up test);
    best_files : the validation figures of each file at the best epoch (`Validator`).
    """

    def __init__(self, model, config, data_fingerprint):
        self.model, self.config, self.fingerprint = model, config, data_fingerprint
        self.opt = Adam(model.theta.size, config.lr, config.beta1, config.beta2, config.eps)
        self.best_theta = model.theta.copy()
        self.best_moments, self.best_t = np.stack([self.opt.m, self.opt.v]), 0
        self.epoch = self.best_epoch = self.last_improve = self.bad_streak = 0
        self.best_val = self.ref_loss = math.inf
        self.best_files = []
        self.elapsed = 0.0
        self.lr_scale = 1.0  # bad steps halve it: the schedule's learning rates are scaled by it

    @property
    def theta(self):
        return self.model.theta

    def improve(self, val, files):
        """Record the current weights as the best (validation loss ``val``, per-file figures ``files``)."""
        self.best_val, self.best_epoch, self.last_improve, self.bad_streak = val, self.epoch, self.epoch, 0
        self.best_files = files
        self.best_theta = self.theta.copy()
        self.best_moments, self.best_t = np.stack([self.opt.m, self.opt.v]), self.opt.t

    def restore_best(self):
        """Weights and Adam's moments back to those of the best epoch."""
        self.theta[:] = self.best_theta
        self.opt.m[:], self.opt.v[:], self.opt.t = self.best_moments[0], self.best_moments[1], self.best_t

    def best_model(self, **attrs):
        best = self.model.copy()
        best.theta[:] = self.best_theta
        best.attrs.update(attrs)
        return best

    def snapshot(self):
        """The checkpoint's contents (copies): what `load` needs to continue this run exactly."""
        m = self.model
        version = STATE_VERSION if m.spec.kinematics is None else KINEMATICS_STATE_VERSION
        snap = {"version": np.int64(version), "theta": self.theta.copy(), "best_theta": self.best_theta.copy(),
                "epoch": np.int64(self.epoch), "best_val": np.float64(self.best_val),
                "best_epoch": np.int64(self.best_epoch), "last_improve": np.int64(self.last_improve),
                "bad_streak": np.int64(self.bad_streak), "elapsed": np.float64(self.elapsed),
                "config": json.dumps(dataclasses.asdict(self.config)), "fingerprint": self.fingerprint,
                "spec": json.dumps(m.spec.attrs()), "model_attrs": json.dumps(m.attrs, default=str),
                "x_mean": m.x_mean, "x_std": m.x_std, "u_mean": m.u_mean, "u_std": m.u_std,
                "curriculum_stage": np.int64(curriculum_stage(self.config, max(self.epoch, 1))[0]),
                "best_moments": self.best_moments.copy(), "best_t": np.int64(self.best_t),
                "ref_loss": np.float64(self.ref_loss), "lr_scale": np.float64(self.lr_scale),
                "best_files": json.dumps(self.best_files)}
        snap.update(self.opt.state())
        return snap

    @staticmethod
    def save(path, snap):
        """Write the checkpoint ``snap`` (a `snapshot`) to ``path`` atomically."""
        with atomic_path(path) as tmp:
            TrainState.write(tmp, snap)

    @staticmethod
    def write(path, snap):
        """Write ``snap`` to ``path`` as it is (the caller makes the write atomic)."""
        with open(path, "wb") as f:
            np.savez(f, **snap)

    @classmethod
    def load(cls, path):
        """The state saved at ``path``; InputError if it is missing or unusable."""
        from mpnode.model import Model

        state = load_state(path)
        config = TrainConfig(**json.loads(str(state["config"])))
        spec = FieldSpec.from_attrs(json.loads(str(state["spec"])))
        model = Model(state["theta"].copy(), spec, state["x_mean"], state["x_std"], state["u_mean"], state["u_std"],
                      attrs=json.loads(str(state["model_attrs"])))
        self = cls(model, config, str(state["fingerprint"]))
        self.best_theta = state["best_theta"].astype(model.dtype)
        self.opt.load_state(state)
        self.best_moments, self.best_t = state["best_moments"].copy(), int(state["best_t"])
        for name in ("epoch", "best_epoch", "last_improve", "bad_streak"):
            setattr(self, name, int(state[name]))
        self.best_val, self.ref_loss, self.elapsed = (float(state[k]) for k in ("best_val", "ref_loss", "elapsed"))
        self.lr_scale = float(state.get("lr_scale", 1.0))
        self.best_files = json.loads(str(state.get("best_files", "[]")))
        return self


#: the options a resumed run takes from the command line; every other comes from the checkpoint
RESUME_OPTIONS = ("epochs", "time_limit")


def check_resume_options(path, options):
    """InputError naming the first of ``options`` (the options the user set, under their own
    names) that contradicts the run whose checkpoint is at ``path``: a resumed run keeps its
    settings, so a different value would be silently ignored."""
    state = load_state(path)
    config = json.loads(str(state["config"]))
    spec = FieldSpec.from_attrs(json.loads(str(state["spec"])))
    latent = int(json.loads(str(state["model_attrs"])).get("latent_dims", 0))
    model = model_config_of(spec, state["theta"].dtype, latent)
    for name, value in options.items():
        if name in RESUME_OPTIONS:
            continue
        if name in config:
            was, same = config[name], _plain(config[name]) == _plain(value)
        else:
            was, same = getattr(model, name), _same_model(model, spec, name, value)
        if not same:
            flag = "--" + name.replace("_", "-")
            raise InputError(flag, value, f"contradicts the run being resumed: its checkpoint {path} has "
                             f"{name} = {was}", f"no {flag} with --resume (the run keeps its settings; only "
                             "--epochs and --time-limit change), or another -o to start a new run")


def model_config_of(spec, dtype, latent_dims=0):
    """The ModelConfig that makes ``spec`` (with weights of ``dtype``; ``latent_dims`` of its
    state dimensions beyond the data's)."""
    from mpnode.model.config import ModelConfig

    agg = spec.aggregation
    return ModelConfig(kind=spec.kind, message_dim=spec.message_dim, hidden=spec.hidden, aggregation=agg.mlp,
                       linear_aggregate=spec.linear_path, linear_aggregation=agg.own_linear,
                       linear_target=agg.target, self_messages=spec.self_messages,
                       zero_messages=spec.zero_messages, substeps=spec.substeps, dtype=np.dtype(dtype).name,
                       encoder_window=spec.encoder_window, latent_dims=latent_dims,
                       kinematics=None if spec.kinematics is None else spec.kinematics.text())


def _same_model(model, spec, name, value):
    """Whether setting model option ``name`` to ``value`` leaves the model of ``spec`` as it is."""
    try:
        other = dataclasses.replace(model, **{name: value})
        again = other.spec(spec.state_dim - model.latent_dims, spec.control_dim, spec.dt, spec.n_nodes,
                           spec.aggregation.mean_degree, spec.attr_dim, spec.aggregation.weight_scale)
    except (InputError, TypeError, ValueError):
        return False
    return again == spec and other.dtype == model.dtype


def _plain(value):
    """A value as JSON has it (tuples become lists), so that options compare as the checkpoint stores them."""
    return json.loads(json.dumps(value, default=str))


def load_state(path):
    """The raw checkpoint (dict of arrays and scalars); InputError if unusable."""
    try:
        with np.load(path, allow_pickle=False) as z:
            state = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist",
                         "the .state file an interrupted `mpnode train -o MODEL` leaves beside MODEL") from None
    except (OSError, ValueError) as e:
        raise InputError(path, "file", f"is not a readable checkpoint ({e})", "a .state file written by mpnode") from None
    if int(state.get("version", -1)) not in READABLE_VERSIONS:
        raise InputError(path, "version", f"is {state.get('version')}",
                         f"checkpoint version {' or '.join(map(str, READABLE_VERSIONS))}")
    return state
