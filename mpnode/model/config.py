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

from mpnode.base.errors import InputError
from mpnode.base.options import defaults, option, option_names
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

    def __post_init__(self):
        _check_choice("kind", self.kind, KINDS)
        _check_int("message_dim", self.message_dim, 0)
        _check_int("hidden", self.hidden, 1)
        _check_int("substeps", self.substeps, 1)
        _check_int("encoder_window", self.encoder_window, 0)
        _check_int("latent_dims", self.latent_dims, 0)
        _check_choice("aggregation", self.aggregation, (None,) + AGGREGATIONS)
        _check_choice("linear_aggregation", self.linear_aggregation, (None,) + AGGREGATIONS)
        _check_choice("linear_target", self.linear_target, LINEAR_TARGETS)
        try:
            dtype = np.dtype(self.dtype).name
        except TypeError:
            dtype = None
        _check_choice("dtype", dtype, DTYPES)
        object.__setattr__(self, "dtype", dtype)
        self.spec(1, 0, 1.0, n_nodes=1 if self.kind == "node" else None,
                  mean_degree=1.0 if self.uses_mean_degree else None)  # the rules between options

    @property
    def messages(self):
        """Whether the model will have message states (an mpnode model with dm > 0, not held at 0)."""
        return self.kind == "mpnode" and self.message_dim > 0 and not self.zero_messages

    @property
    def uses_mean_degree(self):
        """Whether the model needs the training graphs' mean in-degree (a "scaled" aggregation)."""
        return "scaled" in (self.aggregation, self.linear_aggregation)

    def spec(self, state_dim, control_dim, dt, n_nodes=None, mean_degree=None):
        """The engine's FieldSpec of a model of these options for data with ``state_dim``,
        ``control_dim`` and ``dt`` (a node model: ``n_nodes``; "scaled": ``mean_degree``)."""
        mpnode = self.kind == "mpnode"
        aggregation = Aggregation.from_options(self.aggregation or default_aggregation(self.kind),
                                               self.linear_aggregate, self.linear_aggregation, self.linear_target,
                                               mean_degree if self.uses_mean_degree else None)
        return FieldSpec(kind=self.kind, state_dim=int(state_dim), control_dim=int(control_dim),
                         message_dim=self.message_dim if mpnode else 0, hidden=self.hidden, dt=float(dt),
                         substeps=self.substeps, self_messages=bool(self.self_messages),
                         zero_messages=bool(self.zero_messages) and mpnode, aggregation=aggregation,
                         n_nodes=None if n_nodes is None else int(n_nodes), encoder_window=self.encoder_window)


def configured(options=None, base=None):
    """``base`` (default: the defaults) with ``options`` set ({option or older name: value});
    InputError for an option ModelConfig does not have."""
    names = option_names(ModelConfig)
    unknown = sorted(k for k in (options or {}) if k not in names)
    if unknown:
        raise InputError("model options", unknown[0], "is not a model option", "one of " + ", ".join(
            sorted(defaults(ModelConfig))))
    return dataclasses.replace(base or ModelConfig(), **{names[k]: v for k, v in (options or {}).items()})


def _check_int(name, value, least):
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= least):
        raise InputError("model options", name, f"is {value!r}", f"an integer >= {least}")


def _check_choice(name, value, allowed):
    if value not in allowed:
        raise InputError("model options", name, f"is {value!r}", " or ".join(map(str, allowed)))
