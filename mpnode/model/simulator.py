"""A model you can step: one dt at a time, for closed loops (controllers, RL environments, planners).

`Model.rollout` needs every control in advance; a closed loop chooses the next control
from the current state.  A Simulator keeps the full integrated state (x and, for an
MP-NODE, the messages) between calls, so T calls of `step` give bit for bit the rollout
of T steps.  Everything that does not change between steps (the batch graph, the
engine's plan, the normalisation) is prepared once in `reset`.
"""

import numpy as np

from mpnode import engine
from mpnode.base.arguments import check_path
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph, as_graph, is_networkx

from .ensemble import Ensemble, models_of
from .model import Model, batch_graph, node_intervals, to_time_major
from .ranges import Watch


class Simulator:
    """Step B copies of a networked system through a learned model.

    model : a Model or an Ensemble, or the path of a model file (any kind: mpnode, l2s, node;
        an ensemble steps every member: `state` is their mean, `spread` the calibrated spread)
    graph : an mpnode Graph or a networkx graph (nodes 0..N-1), shared by the B copies; weighted
        (Graph.weights, a networkx edge attribute ``weight``) exactly when the model was trained
        on weighted graphs
    node_attrs : (N, dp) shared by the B copies or (B, N, dp) one set per copy, the nodes' static
        attributes (`Model.attr_names`) for a model that has them, else None: the model hears
        them after the controls on every step, as `Model.rollout(..., node_attrs=...)` does
    backend : "auto", "numba" or "numpy" (as Model.rollout)

    >>> sim = Simulator("model.h5", graph)
    >>> x = sim.reset(x0)                  # (B, N, dx)
    >>> for t in range(T):
    ...     x = sim.step(controller(x))    # u (B, N, du), or step() without controls

    An input that leaves the range the model saw in training (a state, the in-degree, an
    aggregate, the number of nodes) is warned of once (mpnode.model.ranges.OffRangeWarning)
    and listed in ``sim.off_range``.
    """

    def __init__(self, model, graph, node_attrs=None, backend="auto"):
        if not isinstance(model, (Model, Ensemble)):
            model = Model.load(check_path(model, "Simulator", "model"))
        self.model = model
        self._models = models_of(model)
        self.graph = _as_graph(graph)
        self.model.check_nodes(self.graph.n_nodes)
        check_weighting(model, self.graph, "Simulator")
        self.node_attrs = held_attrs(model, node_attrs, None, self.graph.n_nodes, "Simulator")
        if backend not in engine.BACKENDS:
            raise InputError("Simulator", "backend", f"is {backend!r}", " or ".join(engine.BACKENDS))
        self.backend = engine.resolve_backend(backend)
        self.steps = 0  # steps taken since reset
        self._zs = None  # every member's integrated state

    @property
    def dt(self):
        """Time advanced by one step (the model's dt; its substeps happen inside)."""
        return self.model.spec.dt

    def reset(self, x0):
        """Start B copies from x0 (B, N, dx), in the data's units, messages at 0; returns the
        state as the model sees it (x0 through its normalisation and back, in its dtype)."""
        m, spec = self.model, self.model.spec
        x0 = np.asarray(x0)
        n = self.graph.n_nodes
        if x0.ndim != 3 or x0.shape[1:] != (n, spec.state_dim) or not x0.shape[0]:
            raise InputError("Simulator.reset", "x0", f"has shape {x0.shape}",
                             f"(B, {n}, {spec.state_dim}): B >= 1 copies of the graph's {n} nodes")
        if x0.dtype.kind not in "iuf" or not np.all(np.isfinite(x0)):
            raise InputError("Simulator.reset", "x0", "holds non-finite or non-numeric values", "finite numbers")
        self._shape = x0.shape
        self._attrs = held_attrs(m, self.node_attrs, x0.shape[0], n, "Simulator")
        self._flat = batch_graph(self.graph, x0.shape[0])  # the batch graph rollout uses: same plan
        self._zs = [engine.initial_state(spec, m.normalize_x(x0).reshape(-1, spec.state_dim), m.dtype)
                    for _ in self._models]
        self.steps = 0
        self._watch = Watch(self._models[0], self.graph, x0.shape[0])  # an ensemble: its first member's inputs
        self._watch(self._zs[0], None, 0)
        return self.state

    def warm_up(self, observations, times=None, u=None):
        """Start B copies from their first K observations (B, K, N, dx), in the data's units, NaN
        where not observed (times (B, K), or None: every dt; u (B, K-1, N, du) between them): the
        model estimates where they started from all K (its initial-state encoder sees them) and
        integrates through them, so the simulator stands at the last observation, ready to step.
        Returns that state (B, N, dx)."""
        m, spec = self.model, self.model.spec
        obs = np.asarray(observations, dtype=np.float64)
        self.reset(m.initial_state(obs, times))
        b, k, n = obs.shape[:3]
        if k > 1:
            iv = None if times is None else np.repeat(node_intervals(times), n, axis=1)
            u = m.controls_of(None if u is None else np.asarray(u), self._attrs, b, n, k - 1, "Simulator.warm_up")
            un = None if u is None else to_time_major(m.normalize_u(np.asarray(u)))
            self._zs = [engine.integrate(spec, one.theta, z, self._flat, un, k - 1, backend=self.backend,
                                         intervals=iv)[1] for one, z in zip(self._models, self._zs)]
            self._watch(self._zs[0], None if un is None else un[-1], 0)
        return self.state

    def step(self, u=None):
        """Advance every copy by one dt under controls u (B, N, du) held over the step (None
        for a model without controls); returns the next state (B, N, dx) in data units."""
        if self._zs is None:
            raise RuntimeError("call reset(x0) before step()")
        m, spec = self.model, self.model.spec
        u = self._controls(u, "Simulator.step")
        u = None if u is None else u[None]
        self._zs = [engine.integrate(spec, one.theta, z, self._flat, u, 1, backend=self.backend)[1]
                    for one, z in zip(self._models, self._zs)]
        self.steps += 1
        self._watch(self._zs[0], None if u is None else u[0], self.steps)
        return self.state

    def jacobians(self, u=None, sparse=False, attrs=False):
        """The derivatives of the state after the next step, (Jx, Ju): with respect to the
        current state (messages held at their current values) and to the controls u (B, N, du)
        held over the step (None for a model without controls), as `step` takes them.

        In the data's units and the model's dtype, node-major: Jx (B, N*dx, N*dx), Ju
        (B, N*dx, N*du); with ``sparse`` two lists of B scipy CSR arrays, whose pattern
        follows the graph (a node's next state hears nodes a few hops away within one step:
        `mpnode.engine.jacobians`), for large N.  Ju has the user's du columns only: a model's
        node attributes are no control (``attrs``: a third matrix, Ja (B, N*dx, N*dp), the
        derivatives with respect to them, for fitting a network's parameters).  Exact (the
        step's own discrete adjoint); it does not advance the simulator.  Needs numba.
        """
        from mpnode.engine.jacobians import step_jacobians

        self._require_reset()
        m, spec = self.model, self.model.spec
        if isinstance(m, Ensemble):
            raise InputError("Simulator.jacobians", "model", f"is an ensemble of {m.size} members",
                             "one model (an ensemble's members each have their own state: e.g. "
                             "Simulator(ensemble.members[0], graph))")
        if attrs and not spec.attr_dim:
            raise InputError("Simulator.jacobians", "attrs", "is True, but the model has no node attributes",
                             "attrs=False")
        un = self._controls(u, "Simulator.jacobians")
        jx, jc = step_jacobians(spec, m.theta, self._zs[0], self.graph, un, sparse)
        n = self.graph.n_nodes
        sx = np.tile(m.x_std, n)  # node-major scales: d x / d xn = std
        du = spec.control_dim - spec.attr_dim
        out = (_scaled(jx, sx, 1 / sx, m.dtype, sparse), self._columns(jc, range(du), sx, sparse))
        return out + (self._columns(jc, range(du, spec.control_dim), sx, sparse),) if attrs else out

    def _columns(self, jc, which, sx, sparse):
        """Of a step's Jacobian jc with respect to all the controls the network hears (node-major,
        node j's control_dim columns together), the columns ``which`` of every node, in data units."""
        m, n, dc = self.model, self.graph.n_nodes, self.model.spec.control_dim
        which = np.asarray(which, dtype=np.int64)
        if len(which) < dc:  # the attributes' columns, or the controls' beside them
            keep = (np.arange(n)[:, None] * dc + which).ravel()
            jc = [j[:, keep] for j in jc] if sparse else jc[:, :, keep]
        return _scaled(jc, sx, 1 / np.tile(m.u_std[which], n), m.dtype, sparse)

    @property
    def off_range(self):
        """The inputs that have left what the model saw in training since ``reset`` (each quantity
        once, where it first did: dicts as `mpnode.eval --json`'s ``off_range``); each was also
        warned of (mpnode.model.ranges.OffRangeWarning).  [] for a model without recorded ranges."""
        self._require_reset()
        return list(self._watch.entries.values())

    @property
    def state(self):
        """The current state (B, N, dx) in the data's units and the model's dtype."""
        return np.mean(self._member_states(), axis=0).astype(self.model.dtype)

    @property
    def spread(self):
        """An ensemble's calibrated spread of the current state (B, N, dx), data units, float64
        (mpnode.model.ensemble); None for one model."""
        if len(self._models) < 2:
            self._require_reset()
            return None
        return self.model.spread(self._member_states())

    def _member_states(self):
        """(K, B, N, dx) every member's current state in data units (K = 1 for one model)."""
        self._require_reset()
        dx = self.model.spec.state_dim
        return np.stack([self.model.denormalize_x(z[:, :dx].reshape(self._shape)) for z in self._zs])

    @property
    def messages(self):
        """The current messages (B, N, dm) of an MP-NODE (in the model's own units: messages
        have no physical ones), a copy; an ensemble's (K, B, N, dm); None for kinds without
        messages (l2s, node)."""
        self._require_reset()
        spec = self.model.spec
        if spec.kind != "mpnode":
            return None
        out = [z[:, spec.state_dim:].reshape(self._shape[:2] + (spec.message_dim,)).copy() for z in self._zs]
        return out[0] if len(out) == 1 else np.stack(out)

    def _controls(self, u, where):
        """u (B, N, du) in data units as the engine takes it, the node attributes after it:
        normalised, flat (B*N, du + dp); None for a model without either.  InputError naming
        ``where`` otherwise."""
        spec = self.model.spec
        want = self._shape[:2] + (spec.control_dim - spec.attr_dim,)
        if u is None:
            if want[2]:
                raise InputError(where, "u", f"is None, but the model takes controls (du = {want[2]})",
                                 f"controls of shape {want}")
        else:
            u = np.asarray(u)
            if u.shape != want or u.dtype.kind not in "iuf" or not np.all(np.isfinite(u)):
                raise InputError(where, "u", f"has shape {u.shape} and dtype {u.dtype}",
                                 f"finite numbers of shape {want}")
        full = self.model.controls_of(None if u is None else u[:, None], self._attrs, *want[:2], 1, where)
        return None if full is None else self.model.normalize_u(full[:, 0]).reshape(-1, spec.control_dim)

    @property
    def _z(self):
        """The first (for one model: the) member's integrated state (B*N, dx+dm)."""
        return None if self._zs is None else self._zs[0]

    @_z.setter
    def _z(self, z):
        self._zs = [z] if self._zs is None else [z] + self._zs[1:]

    def _require_reset(self):
        if self._zs is None:
            raise RuntimeError("call reset(x0) first")


def _as_graph(graph):
    """An mpnode Graph from a Graph or a networkx graph; InputError otherwise."""
    if isinstance(graph, Graph):
        return graph.validate()
    if is_networkx(graph):
        return as_graph(graph, graph.number_of_nodes(), directed=graph.is_directed())
    raise InputError("graph", "graph", f"is a {type(graph).__name__}", "an mpnode.Graph or a networkx graph")


def check_weighting(model, graph, source):
    """InputError unless ``graph`` is weighted exactly when ``model`` hears weighted graphs (a
    node model reads no graph): mpnode.model.inputs.for_model's rule for a graph of one's own."""
    weighted_model = model.spec.aggregation.weight_scale is not None
    if graph.weighted and not weighted_model:
        raise InputError(source, "graph", "has edge weights but the model was trained on unweighted graphs",
                         "an unweighted graph (graph.reweighted(None), or a networkx graph without 'weight')")
    if weighted_model and not graph.weighted and model.kind != "node":
        raise InputError(source, "graph", "has no edge weights, but the model was trained on weighted graphs",
                         "a weight on every edge (Graph.weights, or a networkx edge attribute 'weight')")


def held_attrs(model, node_attrs, b, n, source):
    """The node attributes of B copies of N nodes as (B, N, dp) float64 (b None: as given, checked
    for any B), or None for a model without them; InputError naming ``source`` when the model
    has attributes and they are missing, or has none and they are given, or their shape is wrong."""
    if node_attrs is None and not model.spec.attr_dim:
        return None
    if b is None:
        b = np.shape(node_attrs)[0] if np.ndim(node_attrs) == 3 else 1
        model.controls_of(None, node_attrs, b, n, 1, source)
        return np.asarray(node_attrs, dtype=np.float64)
    return np.ascontiguousarray(model.controls_of(None, node_attrs, b, n, 1, source)[:, 0])


def _scaled(j, rows, cols, dtype, sparse):
    """diag(rows) @ j @ diag(cols) of (B, r, c) dense Jacobians, or of a list of scipy CSR arrays,
    in ``dtype``."""
    if not sparse:
        return (j * (rows[:, None] * cols)).astype(dtype)
    return [_scaled_csr(one, rows, cols, dtype) for one in j]


def _scaled_csr(j, rows, cols, dtype):
    """diag(rows) @ j @ diag(cols) for a scipy CSR array, in ``dtype``."""
    out = j.tocsr(copy=True)
    row_of = np.repeat(np.arange(j.shape[0]), np.diff(out.indptr))
    out.data = (out.data * (rows[row_of] * cols[out.indices])).astype(dtype)
    return out
