"""What the kernels need to know about a model besides its weights: its kind, sizes,
integration settings and how a node combines its neighbours (`FieldSpec`)."""
from dataclasses import dataclass

import numpy as np

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


@dataclass(frozen=True)
class FieldSpec:
    """What the kernels need to know about a model besides its weights.

    kind : "mpnode" (state [x, m], messages of size message_dim), "l2s" (state x,
        message_dim 0) or "node" (a plain neural ODE of a whole system of ``n_nodes``
        nodes; message_dim 0, the graph is ignored)
    aggregation : "mean", "sum" or "scaled" (the sum divided by ``mean_degree``)
    linear_aggregate : (mpnode only) the field also adds m' @ W_agg, a path linear in the
        aggregate m', so that a denser graph's larger aggregate is not squashed by the
        MLP's tanh units (the gene dynamics are linear in the neighbour sum)
    linear_target : what that path adds to: "all" ([dx/dt, dm/dt], W_agg (dm, dx+dm)) or
        "state" (dx/dt alone, W_agg (dm, dx): the messages' own dynamics then never hear
        the degree, only the MLP's degree-free input)
    linear_aggregation : the aggregate that path reads when it is not the MLP's own m'
        ("mean", "sum" or "scaled"; None: the MLP's).  E.g. aggregation "mean" with
        linear_aggregation "scaled": the MLP sees a degree-free input that stays in range on
        denser graphs, and the degree reaches the field only through the linear path
        (as PNA's degree scalers)
    """

    state_dim: int
    control_dim: int
    message_dim: int
    hidden: int
    dt: float
    substeps: int = 1
    zero_messages: bool = False
    self_messages: bool = False
    kind: str = "mpnode"
    aggregation: str = "mean"
    mean_degree: float = None
    n_nodes: int = None
    linear_aggregate: bool = False
    linear_aggregation: str = None
    linear_target: str = "all"

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, not {self.kind!r}")
        if self.aggregation not in AGGREGATIONS:
            raise ValueError(f"aggregation must be one of {AGGREGATIONS}, not {self.aggregation!r}")
        if self.linear_aggregation is not None and self.linear_aggregation not in AGGREGATIONS:
            raise ValueError(f"linear_aggregation must be one of {AGGREGATIONS} or None, "
                             f"not {self.linear_aggregation!r}")
        if self.linear_target not in LINEAR_TARGETS:
            raise ValueError(f"linear_target must be one of {LINEAR_TARGETS}, not {self.linear_target!r}")
        if self.linear_target != "all" and not self.linear_aggregate:
            raise ValueError("linear_target goes with linear_aggregate (the path it says where to add)")
        if self.linear_aggregation is not None and not self.linear_aggregate:
            raise ValueError("linear_aggregation goes with linear_aggregate (the path it feeds)")
        if ("scaled" in (self.aggregation, self.linear_aggregation)) != (self.mean_degree is not None):
            raise ValueError("mean_degree goes with aggregation or linear_aggregation 'scaled' (and only with it)")
        if self.mean_degree is not None and not self.mean_degree > 0:
            raise ValueError(f"mean_degree must be > 0, not {self.mean_degree}")
        if self.kind != "mpnode" and (self.message_dim or self.zero_messages):
            raise ValueError(f"a {self.kind} model has no message state (message_dim 0, no zero_messages)")
        if (self.kind == "node") != (self.n_nodes is not None):
            raise ValueError("n_nodes goes with kind 'node' (and only with it)")
        if self.linear_aggregate and (self.kind != "mpnode" or not self.message_dim or self.zero_messages):
            raise ValueError("linear_aggregate needs an mpnode model with messages (message_dim > 0, no zero_messages)")

    @property
    def dims(self):
        """The kernels' (kind, dx, du, dm, H, self_msg, zero_msg, linear_agg) tuple (kinds mpnode and l2s);
        linear_agg: flags, 1 the linear path is there, 2 it reads its own aggregate (see Plan.weight),
        4 it adds to dx/dt alone (mpnode.engine.kernels.mpnode_field)."""
        flags = 0
        if self.linear_aggregate:
            flags = 1 | (2 if self.own_linear_aggregation else 0) | (4 if self.linear_target == "state" else 0)
        return (KINDS.index(self.kind), self.state_dim, self.control_dim, self.message_dim, self.hidden,
                int(self.self_messages), int(self.zero_messages), flags)

    @property
    def own_linear_aggregation(self):
        """The linear path's aggregation when it differs from the MLP's, else None."""
        la = self.linear_aggregation
        return la if self.linear_aggregate and la is not None and la != self.aggregation else None

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
