"""What the kernels need to know about a model besides its weights: its kind, sizes,
integration settings and how a node combines its neighbours (`FieldSpec`)."""
from dataclasses import dataclass

import numpy as np

from mpnode.base.errors import InputError

from . import dims as slots
from .kinematics import Kinematics

#: the model kinds the engine integrates (docs/model-format.md)
KINDS = ("mpnode", "l2s", "node")
#: how a node combines what its neighbours send (model-format.md, "Aggregation")
AGGREGATIONS = ("mean", "sum", "scaled")
#: what the linear aggregate path adds to: every output, or dx/dt alone (model-format.md)
LINEAR_TARGETS = ("all", "state")


def default_aggregation(kind):
    """The aggregation a kind has when nothing says otherwise: the sum for l2s (as the Julia
    code's SegmentedSum), else the paper's mean."""
    return "sum" if kind == "l2s" else "mean"


def _one_of(value, allowed, field, source="model"):
    if value not in allowed:
        raise InputError(source, field, f"is {value!r}", " or ".join(map(str, allowed)))


@dataclass(frozen=True)
class Aggregation:
    """How a node combines what its neighbours send (model-format.md, "Aggregation").

    mlp : what the node's network hears, m' = weight_i * (the sum of its neighbours'
        messages): "mean" (weight 1/degree), "sum" (1) or "scaled" (1/mean_degree)
    linear : None, or the aggregate a path linear in it reads (k += that aggregate @ W_agg,
        around the MLP, whose tanh units cannot follow the larger aggregates of denser
        graphs; the gene dynamics are linear in the neighbour sum).  Equal to ``mlp``: the
        MLP's own m'; another rule: s_i m'_i with s_i the ratio of the two weights, e.g. mean
        for the MLP and scaled for the path (the MLP hears a degree-free input that stays in
        range on denser graphs; the degree reaches the field only through the path, as
        PNA's degree scalers do)
    target : what the path adds to: "all" ([dx/dt, dm/dt]) or "state" (dx/dt alone, so the
        messages' own dynamics never hear the degree)
    mean_degree : the training graphs' mean in-degree, which "scaled" divides by
    weight_scale : None for a model of unweighted graphs; else the typical size of the training
        graphs' edge weights, which every weight is divided by: node i then hears
        (w_ij / weight_scale) m_j from neighbour j, a sum of inputs of order one whatever the
        weights' units (a negative weight turns the neighbour's message around)
    """

    mlp: str = "mean"
    linear: str = None
    target: str = "all"
    mean_degree: float = None
    weight_scale: float = None

    def __post_init__(self):
        _one_of(self.mlp, AGGREGATIONS, "aggregation")
        _one_of(self.linear, (None,) + AGGREGATIONS, "linear_aggregation")
        _one_of(self.target, LINEAR_TARGETS, "linear_target")
        if self.target != "all" and self.linear is None:
            raise InputError("model", "linear_target", f"is {self.target!r} without a linear path",
                             "'all', or a linear aggregate path (the path it says where to add)")
        if self.uses_mean_degree != (self.mean_degree is not None):
            raise InputError("model", "mean_degree", f"is {self.mean_degree!r} with aggregations "
                             f"{self.mlp}/{self.linear}", "a number with a 'scaled' aggregation, and only with it")
        if self.mean_degree is not None and not self.mean_degree > 0:
            raise InputError("model", "mean_degree", f"is {self.mean_degree!r}", "a number > 0")
        if self.weight_scale is not None and not (np.isfinite(self.weight_scale) and self.weight_scale > 0):
            raise InputError("model", "weight_scale", f"is {self.weight_scale!r}", "a finite number > 0")

    @classmethod
    def from_options(cls, aggregation, linear_aggregate=False, linear_aggregation=None, linear_target="all",
                     mean_degree=None, weight_scale=None):
        """The Aggregation of the options a user (or a model file) gives: ``linear_aggregation``
        or a ``linear_target`` other than "all" imply the linear path (``linear_aggregate``),
        which otherwise reads the MLP's own aggregate."""
        target = linear_target or "all"
        on = bool(linear_aggregate or linear_aggregation or target != "all")
        linear = (linear_aggregation or aggregation) if on else None
        return cls(aggregation, linear, target, None if mean_degree is None else float(mean_degree),
                   None if weight_scale is None else float(weight_scale))

    def options(self):
        """The inverse of `from_options`: the attributes a model file records (absent ones left out)."""
        out = {"aggregation": self.mlp}
        if self.mean_degree is not None:
            out["mean_degree"] = float(self.mean_degree)
        if self.weight_scale is not None:
            out["weight_scale"] = float(self.weight_scale)
        if self.linear is not None:
            out["linear_aggregate"] = 1
            if self.linear != self.mlp:
                out["linear_aggregation"] = self.linear
            if self.target != "all":
                out["linear_target"] = self.target
        return out

    @property
    def uses_mean_degree(self):
        return "scaled" in (self.mlp, self.linear)

    @property
    def own_linear(self):
        """The linear path's rule when it differs from the MLP's (it then reads s_i m'_i), else None."""
        return self.linear if self.linear not in (None, self.mlp) else None

    def kernel_flags(self):
        """dims[LINEAR] of the kernels (mpnode.engine.dims)."""
        if self.linear is None:
            return 0
        return (slots.LINEAR_ON | (slots.LINEAR_OWN if self.own_linear else 0)
                | (slots.LINEAR_STATE if self.target == "state" else 0))

    def weights(self, graph, self_messages, dtype):
        """The kernels' weight array on ``graph``: node i's factor on the sum of its row
        (rule_weights of ``mlp``), followed, when the path has its own rule, by s_i, the factor
        from the MLP's aggregate to the path's (0 for a node that hears nobody)."""
        w = rule_weights(graph, self_messages, self.mlp, self.mean_degree, dtype)
        if self.own_linear is None:
            return w
        w64 = rule_weights(graph, self_messages, self.mlp, self.mean_degree, np.float64)
        wl = rule_weights(graph, self_messages, self.own_linear, self.mean_degree, np.float64)
        scale = np.zeros(graph.n_nodes, dtype=dtype)
        np.divide(wl, w64, out=scale, where=w64 > 0, casting="unsafe")
        return np.concatenate([w, scale])


def rule_weights(graph, self_messages, rule, mean_degree, dtype):
    """Each node's factor on the sum over its row [and itself]: mean 1 / that count, sum 1,
    scaled 1 / mean_degree; 0 for a node that hears nobody (its aggregate is 0)."""
    d = graph.degrees() + (1 if self_messages else 0)
    out = np.zeros(graph.n_nodes, dtype=dtype)
    if rule == "mean":
        np.divide(1.0, d, out=out, where=d > 0, casting="unsafe")
    else:
        out[d > 0] = 1.0 if rule == "sum" else 1.0 / mean_degree
    return out


@dataclass(frozen=True, kw_only=True)
class FieldSpec:
    """What the kernels need to know about a model besides its weights.

    kind : "mpnode" (state [x, m], messages of size message_dim), "l2s" (state x,
        message_dim 0) or "node" (a plain neural ODE of a whole system of ``n_nodes``
        nodes; message_dim 0, the graph is ignored)
    state_dim, control_dim, message_dim, hidden : dx, du, dm and the hidden width H
    attr_dim : dp, how many of the control_dim columns (the last ones) are the node's static
        attributes (its length, mass, natural frequency): the network hears them as it hears
        its controls, held over every step (mpnode.model appends them); the kernels never
        tell them apart
    dt, substeps : the time a step advances and the RK4 steps it takes
    self_messages : every node also hears its own message;  zero_messages : messages held
        at 0 (the paper's ablation)
    aggregation : how a node combines its neighbours (`Aggregation`; default: the kind's)
    encoder_window : W > 0 when the model estimates a trajectory's initial state from its first W
        observations (mpnode.model.encoder; its weights follow the field's, the kernels never
        read them), 0 when a rollout starts from the state it is given
    kinematics : the derivatives the physics fixes (mpnode.engine.kinematics.Kinematics; a
        node's for kind "node"), or None: the network gives every derivative
    """

    kind: str = "mpnode"
    state_dim: int
    control_dim: int = 0
    attr_dim: int = 0
    message_dim: int = 0
    hidden: int
    dt: float
    substeps: int = 1
    self_messages: bool = False
    zero_messages: bool = False
    aggregation: Aggregation = None
    n_nodes: int = None
    encoder_window: int = 0
    kinematics: Kinematics = None

    def __post_init__(self):
        _one_of(self.kind, KINDS, "kind")
        if self.aggregation is None:
            object.__setattr__(self, "aggregation", Aggregation(default_aggregation(self.kind)))
        if self.kind != "mpnode" and self.message_dim:
            raise InputError("model", "message_dim", f"is {self.message_dim} for a {self.kind} model",
                             "0 (only an mpnode model has message states)")
        if self.kind != "mpnode" and self.zero_messages:
            raise InputError("model", "zero_messages", f"is set for a {self.kind} model",
                             "0 (only an mpnode model has message states)")
        if (self.kind == "node") != (self.n_nodes is not None):
            raise InputError("model", "n_nodes", f"is {self.n_nodes!r} for a {self.kind} model",
                             "the system's node count for kind node, and only for it")
        if not (isinstance(self.encoder_window, (int, np.integer)) and self.encoder_window >= 0):
            raise InputError("model", "encoder_window", f"is {self.encoder_window!r}", "an integer >= 0")
        if self.aggregation.linear is not None and (self.kind != "mpnode" or not self.message_dim
                                                    or self.zero_messages):
            raise InputError("model", "linear_aggregate", f"is asked for a {self.kind} model with message_dim "
                             f"{self.message_dim}{' and zero_messages' if self.zero_messages else ''}",
                             "an mpnode model with messages (message_dim > 0, no zero_messages)")

        if not (isinstance(self.attr_dim, (int, np.integer)) and 0 <= self.attr_dim <= self.control_dim):
            raise InputError("model", "attr_dim", f"is {self.attr_dim!r} with control_dim {self.control_dim}",
                             "an integer from 0 to control_dim (the last control columns that are node attributes)")
        if self.kinematics is not None:
            if self.kind == "l2s":
                raise InputError("model", "kinematics", "is set for an l2s model",
                                 "an mpnode or node model (the l2s field has no kinematics)")
            self.kinematics.check(self.state_dim)

    def attrs(self):
        """The spec as the plain attributes of a model file (docs/model-format.md)."""
        out = {"kind": self.kind, "state_dim": self.state_dim, "control_dim": self.control_dim,
               "message_dim": self.message_dim, "hidden": self.hidden, "dt": float(self.dt),
               "substeps": self.substeps, "self_messages": int(self.self_messages),
               "zero_messages": int(self.zero_messages), **self.aggregation.options()}
        if self.n_nodes is not None:
            out["n_nodes"] = self.n_nodes
        if self.attr_dim:
            out["attr_dim"] = self.attr_dim
        if self.encoder_window:
            out["encoder_window"] = self.encoder_window
        if self.kinematics is not None:
            out["kinematics"] = self.kinematics.text()
        return out

    @classmethod
    def from_attrs(cls, a):
        """The spec of a model file's attributes (`attrs`; absent optional ones take their defaults)."""
        kind = a.get("kind", "mpnode")
        aggregation = Aggregation.from_options(a.get("aggregation", default_aggregation(kind)),
                                               bool(a.get("linear_aggregate", 0)), a.get("linear_aggregation"),
                                               a.get("linear_target", "all"), a.get("mean_degree"),
                                               a.get("weight_scale"))
        return cls(kind=kind, state_dim=int(a["state_dim"]), control_dim=int(a["control_dim"]),
                   attr_dim=int(a.get("attr_dim", 0)),
                   message_dim=int(a.get("message_dim", 0)), hidden=int(a["hidden"]), dt=float(a["dt"]),
                   substeps=int(a["substeps"]), self_messages=bool(a.get("self_messages", 0)),
                   zero_messages=bool(a.get("zero_messages", 0)), aggregation=aggregation,
                   n_nodes=None if a.get("n_nodes") is None else int(a["n_nodes"]),
                   encoder_window=int(a.get("encoder_window", 0)), kinematics=Kinematics.parse(a.get("kinematics")))

    @property
    def dims(self):
        """The kernels' tuple of integers (its slots: mpnode.engine.dims)."""
        d = [0] * slots.N_SLOTS
        d[slots.KIND] = slots.L2S if self.kind == "l2s" else slots.MPNODE
        d[slots.DX], d[slots.DU], d[slots.DM], d[slots.HIDDEN] = (self.state_dim, self.control_dim,
                                                                  self.message_dim, self.hidden)
        d[slots.SELF_MSG], d[slots.ZERO_MSG] = int(self.self_messages), int(self.zero_messages)
        d[slots.LINEAR] = self.aggregation.kernel_flags()
        d[slots.KINEMATICS] = 0 if self.kinematics is None else self.kinematics.width()
        return tuple(d)

    @property
    def linear_path(self):
        """Whether the field has the linear aggregate path (and the weights W_agg)."""
        return self.aggregation.linear is not None

    @property
    def state_width(self):
        """Columns of the integrated state z: dx + dm."""
        return self.state_dim + self.message_dim


def checked_controls(spec, graph, u, n_steps, n_nodes, dtype):
    """u as a contiguous (n_steps, M, du) array in ``dtype`` (width 0 for None), after checking
    that the parameters' dtype, u and the graph fit the states (ValueError, TypeError)."""
    if dtype not in (np.float32, np.float64):
        raise TypeError(f"parameters must be float32 or float64, not {dtype}")
    if u is None:
        if spec.control_dim:
            raise ValueError(f"the model takes controls (du={spec.control_dim}) but u is None")
        u = np.zeros((n_steps, n_nodes, 0), dtype=dtype)
    u = np.ascontiguousarray(u, dtype=dtype)
    if u.shape != (n_steps, n_nodes, spec.control_dim):
        raise ValueError(f"u has shape {u.shape}, expected {(n_steps, n_nodes, spec.control_dim)}")
    if graph.n_nodes != n_nodes:
        raise ValueError(f"graph has {graph.n_nodes} nodes but the states have {n_nodes}")
    return u
