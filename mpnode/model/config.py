"""`ModelConfig`: what a user chooses for a new model, with its defaults and checks.

The one source of the model options: `Model.create` takes them, `mpnode train`'s model flags
and a sweep file's keys are these fields (an option's older names are in its ``aliases``),
and `spec` turns them, with what the data decide (dx, du, dt, N, the mean in-degree), into
the engine's FieldSpec, whose constructor holds every rule that ties them together.
"""
import dataclasses
import numbers
from dataclasses import dataclass

import numpy as np

from mpnode.base.arguments import check_bool, check_int, check_mapping, check_number
from mpnode.base.errors import InputError
from mpnode.base.options import defaults, option, option_names
from mpnode.engine.kinematics import Kinematics
from mpnode.engine.spec import AGGREGATIONS, KINDS, LINEAR_TARGETS, Aggregation, FieldSpec, default_aggregation

DTYPES = ("float32", "float64")


@dataclass(frozen=True, kw_only=True)
class ModelConfig:
    """The options of a new model (``mpnode train --help`` says what each does).

    kind : "mpnode" (one network per node, learned messages), "l2s" (the paper's graph-network
        ODE baseline) or "node" (one network for a whole system of fixed size)
    message_dim, hidden : dm (mpnode only) and the hidden width H of the tanh layers
    aggregation : how a node combines its neighbours' messages: "mean", "sum" or "scaled"
        (None: the kind's own, the mean; the sum for l2s)
    linear_aggregate, linear_aggregation, linear_target : the path linear in the aggregate
        around the MLP (mpnode.engine.spec.Aggregation); either of the last two implies it
    self_messages : a node also hears its own message;  zero_messages : messages held at 0
    substeps : RK4 steps per dt;  dtype : "float32" or "float64"
    encoder_window : W > 0: the model estimates a trajectory's whole initial state from its first
        W observations (mpnode.model.encoder: values nobody measured, noise); 0: a rollout starts
        from the first observation as it is
    latent_dims : K more state dimensions per node beyond the data's, never observed: room for
        what the data do not show (the encoder estimates their start)
    kinematics : the state derivatives the physics fixes, as text (mpnode.engine.kinematics:
        e.g. "0:7,1:8,2:9,q3:10"), computed exactly instead of learned; "none" (or None): all learned
    """

    kind: str = option("mpnode", aliases=("model",))
    message_dim: int = 3
    hidden: int = 32
    aggregation: str = option(None, aliases=("aggregate",))
    linear_aggregate: bool = False
    linear_aggregation: str = None
    linear_target: str = "all"
    self_messages: bool = False
    zero_messages: bool = False
    substeps: int = 1
    dtype: str = "float32"
    encoder_window: int = 0
    latent_dims: int = 0
    kinematics: str = None

    def __post_init__(self):
        _check_choice("kind", self.kind, KINDS)
        for name, least in (("message_dim", 0), ("hidden", 1), ("substeps", 1), ("encoder_window", 0),
                            ("latent_dims", 0)):
            object.__setattr__(self, name, _check_int(name, getattr(self, name), least))
        _check_choice("aggregation", self.aggregation, (None,) + AGGREGATIONS)
        _check_choice("linear_aggregation", self.linear_aggregation, (None,) + AGGREGATIONS)
        _check_choice("linear_target", self.linear_target, LINEAR_TARGETS)
        for name in ("linear_aggregate", "self_messages", "zero_messages"):
            object.__setattr__(self, name, check_bool(getattr(self, name), "model options", name))
        try:
            dtype = np.dtype(self.dtype).name
        except TypeError:
            dtype = None
        _check_choice("dtype", dtype, DTYPES)
        object.__setattr__(self, "dtype", dtype)
        kinematics = Kinematics.parse(self.kinematics, "model options")
        object.__setattr__(self, "kinematics", None if kinematics is None else kinematics.text())
        # the rules between options; the terms' indices are checked once the data give dx
        self._spec(1, 0, 1.0, n_nodes=1 if self.kind == "node" else None,
                   mean_degree=1.0 if self.uses_mean_degree else None,
                   kinematics=None if kinematics is None else Kinematics())

    @property
    def messages(self):
        """Whether the model will have message states (an mpnode model with dm > 0, not held at 0)."""
        return self.kind == "mpnode" and self.message_dim > 0 and not self.zero_messages

    @property
    def uses_mean_degree(self):
        """Whether the model needs the training graphs' mean in-degree (a "scaled" aggregation)."""
        return "scaled" in (self.aggregation, self.linear_aggregation)

    def spec(self, state_dim, control_dim, dt, n_nodes=None, mean_degree=None, attr_dim=0, weight_scale=None):
        """The engine's FieldSpec of a model of these options for data with ``state_dim``,
        ``control_dim`` and ``dt`` (a node model: ``n_nodes``; "scaled": ``mean_degree``; the last
        ``attr_dim`` controls node attributes; weighted graphs: their ``weight_scale``): its
        state is the data's ``state_dim`` dimensions and then the ``latent_dims``."""
        state_dim = check_int(state_dim, "model", "state_dim", 1)
        return self._spec(state_dim + self.latent_dims, control_dim, dt, n_nodes, mean_degree,
                          Kinematics.parse(self.kinematics), attr_dim, weight_scale)

    def _spec(self, state_dim, control_dim, dt, n_nodes=None, mean_degree=None, kinematics=None, attr_dim=0,
              weight_scale=None):
        state_dim, control_dim = check_int(state_dim, "model", "state_dim", 1), check_int(control_dim, "model",
                                                                                           "control_dim", 0)
        dt = check_number(dt, "model", "dt", positive=True)
        n_nodes = None if n_nodes is None else check_int(n_nodes, "model", "n_nodes", 1)
        mean_degree = None if mean_degree is None else check_number(mean_degree, "model", "mean_degree", least=0)
        mpnode = self.kind == "mpnode"
        aggregation = Aggregation.from_options(self.aggregation or default_aggregation(self.kind),
                                               self.linear_aggregate, self.linear_aggregation, self.linear_target,
                                               mean_degree if self.uses_mean_degree else None,
                                               weight_scale if self.kind != "node" else None)
        return FieldSpec(kind=self.kind, state_dim=state_dim, control_dim=control_dim, attr_dim=attr_dim,
                         message_dim=self.message_dim if mpnode else 0, hidden=self.hidden, dt=dt,
                         substeps=self.substeps, self_messages=self.self_messages,
                         zero_messages=self.zero_messages and mpnode, aggregation=aggregation, n_nodes=n_nodes,
                         encoder_window=self.encoder_window, kinematics=kinematics)


def configured(options=None, base=None):
    """``base`` (default: the defaults) with ``options`` set ({option or older name: value});
    InputError for an option ModelConfig does not have."""
    names = option_names(ModelConfig)
    if base is not None and not isinstance(base, ModelConfig):
        raise InputError("model options", "config", f"is a {type(base).__name__}", "a ModelConfig (or None)")
    options = check_mapping(options, "model options", "options")
    unknown = sorted(k for k in (options or {}) if k not in names)
    if unknown:
        raise InputError("model options", unknown[0], "is not a model option", "one of " + ", ".join(
            sorted(defaults(ModelConfig))))
    return dataclasses.replace(base or ModelConfig(), **{names[k]: v for k, v in (options or {}).items()})


def _check_int(name, value, least):
    """``value`` as a Python int (NumPy's would not go into a file's JSON) if it is an integer >= least."""
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= least):
        raise InputError("model options", name, f"is {value!r}", f"an integer >= {least}")
    return int(value)


def _check_choice(name, value, allowed):
    if value not in allowed:
        raise InputError("model options", name, f"is {value!r}", " or ".join(map(str, allowed)))
