"""A model you can step: one dt at a time, for closed loops (controllers, RL environments, planners).

`Model.rollout` needs every control in advance; a closed loop chooses the next control
from the current state.  A Simulator keeps the full integrated state (x and, for an
MP-NODE, the messages) between calls, so T calls of `step` give bit for bit the rollout
of T steps.  Everything that does not change between steps (the batch graph, the
engine's plan, the normalisation) is prepared once in `reset`.
"""
import os

import numpy as np

from mpnode import engine
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph, as_graph, is_networkx

from .model import Model, batch_graph


class Simulator:
    """Step B copies of a networked system through a learned model.

    model : a Model, or the path of a model file (any kind: mpnode, l2s, node)
    graph : an mpnode Graph or a networkx graph (nodes 0..N-1), shared by the B copies
    backend : "auto", "numba" or "numpy" (as Model.rollout)

    >>> sim = Simulator("model.h5", graph)
    >>> x = sim.reset(x0)                  # (B, N, dx)
    >>> for t in range(T):
    ...     x = sim.step(controller(x))    # u (B, N, du), or step() without controls
    """

    def __init__(self, model, graph, backend="auto"):
        self.model = model if isinstance(model, Model) else Model.load(os.fspath(model))
        self.graph = _as_graph(graph)
        self.model.check_nodes(self.graph.n_nodes)
        self.backend = engine.resolve_backend(backend)
        self.steps = 0  # steps taken since reset
        self._z = None

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
        if x0.ndim != 3 or x0.shape[1:] != (n, spec.state_dim):
            raise ValueError(f"x0 has shape {x0.shape}, expected (B, {n}, {spec.state_dim}): "
                             f"B copies of the graph's {n} nodes")
        self._shape = x0.shape
        self._flat = batch_graph(self.graph, x0.shape[0])  # the batch graph rollout uses: same plan
        self._z = engine.initial_state(spec, m.normalize_x(x0).reshape(-1, spec.state_dim), m.dtype)
        self.steps = 0
        return self.state

    def step(self, u=None):
        """Advance every copy by one dt under controls u (B, N, du) held over the step (None
        for a model without controls); returns the next state (B, N, dx) in data units."""
        if self._z is None:
            raise RuntimeError("call reset(x0) before step()")
        m, spec = self.model, self.model.spec
        u = None if u is None else self._controls(u)[None]
        _, self._z = engine.integrate(spec, m.theta, self._z, self._flat, u, 1, backend=self.backend)
        self.steps += 1
        return self.state

    def jacobians(self, u=None, sparse=False):
        """The derivatives of the state after the next step, (Jx, Ju): with respect to the
        current state (messages held at their current values) and to the controls u (B, N, du)
        held over the step (None for a model without controls), as `step` takes them.

        In the data's units and the model's dtype, node-major: Jx (B, N*dx, N*dx), Ju
        (B, N*dx, N*du); with ``sparse`` two lists of B scipy CSR arrays, whose pattern
        follows the graph (a node's next state hears nodes a few hops away within one step:
        `mpnode.engine.jacobians`), for large N.  Exact (the step's own discrete adjoint); it
        does not advance the simulator.  Needs numba.
        """
        from mpnode.engine.jacobians import step_jacobians

        self._require_reset()
        m, spec = self.model, self.model.spec
        un = None if u is None else self._controls(u)
        jx, ju = step_jacobians(spec, m.theta, self._z, self.graph, un, sparse)
        n = self.graph.n_nodes
        sx = np.tile(m.x_std, n)  # node-major scales: d x / d xn = std
        su = np.tile(m.u_std, n)
        if sparse:
            return ([_scaled(j, sx, 1 / sx, m.dtype) for j in jx], [_scaled(j, sx, 1 / su, m.dtype) for j in ju])
        return (jx * (sx[:, None] * (1 / sx))).astype(m.dtype), (ju * (sx[:, None] * (1 / su))).astype(m.dtype)

    @property
    def state(self):
        """The current state (B, N, dx) in the data's units and the model's dtype."""
        self._require_reset()
        x = self._z[:, :self.model.spec.state_dim].reshape(self._shape)
        return self.model.denormalize_x(x).astype(self.model.dtype)

    @property
    def messages(self):
        """The current messages (B, N, dm) of an MP-NODE (in the model's own units: messages
        have no physical ones), a copy; None for kinds without messages (l2s, node)."""
        self._require_reset()
        spec = self.model.spec
        if spec.kind != "mpnode":
            return None
        return self._z[:, spec.state_dim:].reshape(self._shape[:2] + (spec.message_dim,)).copy()

    def _controls(self, u):
        """u (B, N, du) in data units as the engine takes it: normalised, flat (B*N, du)."""
        u = np.asarray(u)
        want = self._shape[:2] + (self.model.spec.control_dim,)
        if u.shape != want:
            raise ValueError(f"u has shape {u.shape}, expected {want}")
        return self.model.normalize_u(u).reshape(-1, want[2])

    def _require_reset(self):
        if self._z is None:
            raise RuntimeError("call reset(x0) first")


def _as_graph(graph):
    """An mpnode Graph from a Graph or a networkx graph; InputError otherwise."""
    if isinstance(graph, Graph):
        return graph.validate()
    if is_networkx(graph):
        return as_graph(graph, graph.number_of_nodes(), directed=graph.is_directed())
    raise InputError("graph", "graph", f"is a {type(graph).__name__}", "an mpnode.Graph or a networkx graph")


def _scaled(j, rows, cols, dtype):
    """diag(rows) @ j @ diag(cols) for a scipy CSR array, in ``dtype``."""
    out = j.copy()
    out.data = (out.data * (rows[np.repeat(np.arange(j.shape[0]), np.diff(j.indptr))] * cols[j.indices])).astype(dtype)
    return out
