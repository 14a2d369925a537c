"""The model object: a kind, its weights, integration settings and data normalisation together.

A `Model` is what a model file (docs/model-format.md) holds; `rollout` works in the
data's own units (it z-scores inputs and undoes it on outputs), so a model file alone
reproduces mpnode's simulation.  Three kinds share this class and the engine:
``mpnode`` (MP-NODE: one network per node, learned messages), ``l2s`` (the paper's
graph-network ODE baseline) and ``node`` (one network for a whole system of fixed size).
"""
import functools
import math
from dataclasses import replace

import numpy as np

from mpnode import engine
from mpnode.base.arguments import check_int
from mpnode.base.errors import InputError, NumericalError
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import layouts
from mpnode.engine.schedule import MAX_STEPS_PER_INTERVAL

from . import encoder
from . import file as model_file
from .config import configured
from .ensemble import Ensemble


class Model:
    """A trained (or freshly initialised) model of any kind.

    theta : ndarray, shape (P,) -- flat parameters, float32 or float64 (mpnode.engine.layouts)
    spec : mpnode.engine.FieldSpec -- kind, dimensions, dt, substeps, aggregation, message switches
    x_mean, x_std : ndarray, shape (dx,) -- the model works on (x - x_mean) / x_std
    u_mean, u_std : ndarray, shape (du,) -- the same for controls (the node attributes, when the
        model has them, are its last spec.attr_dim control columns: normalised like them)
    attrs : dict -- extra attributes saved with the model (history, provenance, seed)
    """

    def __init__(self, theta, spec, x_mean=None, x_std=None, u_mean=None, u_std=None, attrs=None):
        theta = np.ascontiguousarray(theta)
        if theta.dtype not in (np.float32, np.float64):
            raise TypeError(f"parameters must be float32 or float64, not {theta.dtype}")
        want = layouts.n_params(spec)
        if theta.shape != (want,):
            raise ValueError(f"theta has shape {theta.shape}, the dimensions need ({want},)")
        self.theta = theta
        self._spec = spec
        self._scaled = (None, spec)  # (the normalisation it was scaled for, the spec): see `spec`
        dx, du = spec.state_dim, spec.control_dim
        self.x_mean = np.zeros(dx) if x_mean is None else np.asarray(x_mean, dtype=np.float64)
        self.x_std = np.ones(dx) if x_std is None else np.asarray(x_std, dtype=np.float64)
        self.u_mean = np.zeros(du) if u_mean is None else np.asarray(u_mean, dtype=np.float64)
        self.u_std = np.ones(du) if u_std is None else np.asarray(u_std, dtype=np.float64)
        self.attrs = dict(attrs or {})

    # ---- construction ----------------------------------------------------
    @classmethod
    def create(cls, state_dim, control_dim=0, *, dt=0.05, seed=0, n_nodes=None, mean_degree=None, config=None,
               attr_names=(), weight_scale=None, **options):
        """A new model with Glorot-uniform weights and zero biases drawn from ``seed``.

        options : `ModelConfig`'s fields (kind, message_dim, hidden, aggregation, latent_dims, ...),
        over ``config``'s (default: the defaults).  What the data decide: ``state_dim`` (the data's
        dimensions: the model's state adds its latent ones), dt, ``n_nodes`` (a node model's
        system size), ``mean_degree`` (the "scaled" aggregation's divisor), the node attributes'
        ``attr_names`` (heard after the ``control_dim`` controls) and weighted graphs'
        ``weight_scale`` (mpnode.model.inputs).
        """
        config = configured(options, config)
        controls = control_dim + len(attr_names) if attr_names else control_dim  # checked by spec
        spec = config.spec(state_dim, controls, dt, n_nodes, mean_degree, len(attr_names), weight_scale)
        seed = check_int(seed, "Model.create", "seed", 0)
        attrs = {"seed": seed, **({"latent_dims": config.latent_dims} if config.latent_dims else {})}
        if attr_names:
            attrs["attr_names"] = list(attr_names)
        return cls(layouts.glorot_init(spec, seed=seed, dtype=np.dtype(config.dtype)), spec, attrs=attrs)

    @classmethod
    def load(cls, path):
        """Read and validate a model file; raises InputError naming the file and field.  An
        ensemble file (version 5) gives an `mpnode.model.ensemble.Ensemble`, which every reader
        uses as a Model (its rollout is the members' mean) and which adds the spread."""
        held = model_file.read_model(path)
        if "ensemble" in held:
            return Ensemble.from_file(held, path, cls)
        return cls(**held)

    def save(self, path, **attrs):
        """Write the model file atomically (extra ``attrs`` beside the model's own); refuses
        non-finite weights or normalisation (NumericalError)."""
        self.check_finite()
        norm = {"x_mean": self.x_mean, "x_std": self.x_std, "u_mean": self.u_mean, "u_std": self.u_std}
        model_file.write_model(path, self.spec, self.params, norm, {**self.attrs, **attrs})

    # ---- views -----------------------------------------------------------
    @property
    def spec(self):
        """The field's FieldSpec; its kinematics, if any, in this model's normalised units (the
        kernels' own), so they follow the normalisation when it changes.  Scaled again only then:
        a Simulator step or an MPC evaluation reads it on every call."""
        kinematics = self._spec.kinematics
        if kinematics is None:
            return self._spec
        norm = self.x_mean.tobytes() + self.x_std.tobytes()
        if self._scaled[0] != norm:
            self._scaled = (norm, replace(self._spec, kinematics=kinematics.scaled(self.x_mean, self.x_std)))
        return self._scaled[1]

    @property
    def kind(self):
        return self.spec.kind

    @property
    def latent_dims(self):
        """The state dimensions beyond the data's (never observed); the data have state_dim - them."""
        return int(self.attrs.get("latent_dims", 0))

    def fitted(self, traj):
        """``traj`` with room for this model's latent dimensions (mpnode.data.Trajectories.with_hidden_dims)."""
        return traj.with_hidden_dims(self.latent_dims) if traj.state_dim + self.latent_dims == self.spec.state_dim \
            else traj

    @property
    def dtype(self):
        return self.theta.dtype

    @property
    def attr_names(self):
        """The node attributes the model hears (their names, as in the data it learned from)."""
        return list(self.attrs.get("attr_names", []))[:self.spec.attr_dim]

    def controls_of(self, u, node_attrs, b, n, steps, source="node_attrs"):
        """The controls the network hears, (B, T, N, du + dp) in the data's units: u, then the
        node attributes held over every step (None when the model has neither).

        node_attrs : (B, N, dp) or (N, dp) (shared by the B trajectories), or None when the model
        has none or u holds them already (its last columns: mpnode.model.inputs.for_model's data)."""
        dp = self.spec.attr_dim
        if node_attrs is None:
            if dp and np.shape(u)[-1:] != (self.spec.control_dim,):
                raise InputError(source, "node_attrs", "is missing",
                                 f"the {dp} node attributes this model was trained with: {', '.join(self.attr_names)}")
            return u
        a = np.asarray(node_attrs, dtype=np.float64)
        if not dp:
            raise InputError(source, "node_attrs", f"has {a.shape[-1] if a.ndim else 0} attributes per node, but the "
                             "model was trained without node attributes", "no node attributes (or --ignore-attrs)")
        if a.ndim == 2:
            a = np.broadcast_to(a, (b,) + a.shape)
        if a.shape != (b, n, dp) or not np.all(np.isfinite(a)):
            what = f"has shape {a.shape}" if a.shape != (b, n, dp) else "is not finite everywhere"
            raise InputError(source, "node_attrs", what, f"finite numbers of shape ({b}, {n}, {dp}) or ({n}, {dp})")
        held = np.broadcast_to(a[:, None], (b, steps, n, dp))
        return held if u is None else np.concatenate([np.asarray(u, dtype=np.float64), held], axis=3)

    @property
    def params(self):
        """Named views into theta (W1 b1 W2 b2 W3 b3, or the l2s arrays)."""
        return layouts.split(self.theta, layouts.param_shapes(self.spec))

    def copy(self, dtype=None):
        """An independent copy, optionally in another precision."""
        theta = self.theta.astype(dtype or self.dtype, copy=True)
        return Model(theta, self.spec, self.x_mean.copy(), self.x_std.copy(), self.u_mean.copy(),
                     self.u_std.copy(), dict(self.attrs))

    def with_spec(self, **changes):
        """The same weights with other settings, e.g. ``with_spec(substeps=4)``."""
        return Model(self.theta, replace(self.spec, **changes), self.x_mean, self.x_std, self.u_mean,
                     self.u_std, dict(self.attrs))

    # ---- normalisation ---------------------------------------------------
    def normalize_x(self, x):
        return ((x - self.x_mean) / self.x_std).astype(self.dtype)

    def denormalize_x(self, xn):
        return xn * self.x_std + self.x_mean

    def normalize_u(self, u):
        return None if u is None else ((u - self.u_mean) / self.u_std).astype(self.dtype)

    # ---- simulation ------------------------------------------------------
    def check_nodes(self, n_nodes, source="graph", field="nodes"):
        """InputError unless the model can run on systems of ``n_nodes`` nodes (a node model: its own N)."""
        if self.kind == "node" and n_nodes != self.spec.n_nodes:
            raise InputError(source, field, f"has {n_nodes} nodes per system, but this plain neural ODE "
                             f"(kind node) was trained on {self.spec.n_nodes}",
                             f"systems of exactly {self.spec.n_nodes} nodes (an mpnode or l2s model runs on any graph)")

    def rollout(self, x0, graph, u=None, steps=None, backend="auto", times=None, node_attrs=None):
        """Simulate B trajectories from their initial states (messages start at 0).

        x0 : ndarray, shape (B, N, dx) or (N, dx), finite (for observations with values nobody
            measured, or noisy ones, `initial_state` estimates it)
        graph : Graph shared by all B trajectories, or a list of B Graphs (each on N nodes); a
            model of weighted graphs hears each neighbour by its edge's weight (Graph.weights)
        u : ndarray, shape (B, T, N, du), or None when the model has no controls (with the
            attributes held as its last columns when node_attrs is None)
        node_attrs : (B, N, dp) or (N, dp) the nodes' static attributes, for a model that has
            them (`attr_names`), else None
        steps : T (defaults to u's length, or to times')
        times : (B, T+1) the times of the outputs (NaN after a trajectory's end), or None: every dt
        backend : "auto" (the compiled kernels; the NumPy path when numba cannot be
            imported), "numba" or "numpy" (mpnode.engine.numpy_path: no numba, slower)
        returns x : ndarray, shape (B, T+1, N, dx) (or (T+1, N, dx) for a 2-D x0), in the
        model's dtype and the data's units.
        """
        x0 = np.asarray(x0)
        single = x0.ndim == 2
        if single:
            x0, u = x0[None], None if u is None else np.asarray(u)[None]
            times = None if times is None else np.asarray(times)[None]
        if x0.ndim != 3 or x0.shape[2] != self.spec.state_dim:
            raise ValueError(f"x0 has shape {x0.shape}, expected (B, N, {self.spec.state_dim})")
        steps = _steps(steps, u, times)
        b, n, dx = x0.shape
        self.check_nodes(n)
        u = self.controls_of(u, node_attrs, b, n, steps)
        flat = batch_graph(graph, b)
        un = None if u is None else to_time_major(self.normalize_u(np.asarray(u)))
        iv = None if times is None else np.repeat(node_intervals(times), n, axis=1)
        xs = engine.forward(self.spec, self.theta, self.normalize_x(x0).reshape(b * n, dx), flat, un, steps,
                            backend=backend, intervals=iv)
        x = self.denormalize_x(xs.reshape(steps + 1, b, n, dx).transpose(1, 0, 2, 3)).astype(self.dtype)
        return x[0] if single else x

    def initial_state(self, observations, times=None):
        """(B, N, dx) where rollouts of these trajectories start, in the data's units and the
        model's dtype: the first of the K observations (B, K, N, dx), NaN where not observed,
        with a model's initial-state encoder applied to all K (times (B, K), or None: every dt);
        without an encoder, the first observation with its missing values at the data's mean."""
        obs = np.asarray(observations, dtype=np.float64)
        if obs.shape[-1] + self.latent_dims == self.spec.state_dim:  # the data's dimensions: room for the latent ones
            obs = np.concatenate([obs, np.full(obs.shape[:-1] + (self.latent_dims,), np.nan)], axis=-1)
        obs = self.normalize_x(obs)
        b, k, n, dx = obs.shape
        x = to_time_major(obs)
        iv = None if times is None else np.repeat(node_intervals(times), n, axis=1)
        z0, _ = encoder.start(self.spec, self.theta, x, iv, min(k, self.spec.encoder_window or 1))
        return self.denormalize_x(z0.reshape(b, n, dx)).astype(self.dtype)

    def summary(self):
        """A JSON-ready description: kind, sizes, settings, parameter count, normalisation, attrs."""
        s, agg = self.spec, self.spec.aggregation
        return {"kind": s.kind, "state_dim": s.state_dim, "control_dim": s.control_dim,
                "message_dim": s.message_dim, "hidden": s.hidden, "n_nodes": s.n_nodes,
                "aggregation": agg.mlp, "mean_degree": agg.mean_degree, "linear_aggregate": s.linear_path,
                "linear_aggregation": agg.own_linear, "linear_target": agg.target if s.linear_path else None,
                "dt": s.dt, "substeps": s.substeps, "encoder_window": s.encoder_window,
                "kinematics": None if s.kinematics is None else s.kinematics.text(),
                "self_messages": s.self_messages, "zero_messages": s.zero_messages, "dtype": str(self.dtype),
                "parameters": int(self.theta.size),
                "arrays": {name: list(a.shape) for name, a in self.params.items()},
                "x_mean": self.x_mean.tolist(), "x_std": self.x_std.tolist(),
                "attrs": {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in self.attrs.items()}}

    def check_finite(self):
        """Raise NumericalError if any weight or normalisation constant is NaN/inf."""
        for name, a in [("theta", self.theta), ("x_mean", self.x_mean), ("x_std", self.x_std),
                        ("u_mean", self.u_mean), ("u_std", self.u_std)]:
            if not np.all(np.isfinite(a)):
                raise NumericalError(f"model {name} contains non-finite values; refusing to use or save it")


@functools.lru_cache(maxsize=16)
def _copies(graph, n_batch):
    """B copies of one graph, kept for reuse: the engine's plan for a graph is then built once per
    graph and batch size (building it costs a good part of a short rollout).  Training batches
    and rollouts both come through here."""
    return block_diagonal([graph] * n_batch)


def node_intervals(times):
    """(T, B) the time from each output to the next, of B trajectories' times (B, T+1), 0 after
    a trajectory's end (its times NaN)."""
    return np.nan_to_num(np.diff(np.asarray(times, dtype=np.float64), axis=1), nan=0.0).T


def _steps(steps, u, times):
    """The number of output steps a rollout is asked for: steps, or u's or times' length."""
    if steps is not None:
        return steps
    if u is not None:
        return np.shape(u)[1]
    if times is not None:
        return np.shape(times)[1] - 1
    raise ValueError("give steps= (or controls u or output times, whose length sets it)")


def to_time_major(a):
    """(B, T, N, d) -> contiguous (T, B*N, d): the kernels' layout."""
    b, t, n, d = a.shape
    return np.ascontiguousarray(a.transpose(1, 0, 2, 3)).reshape(t, b * n, d)


def batch_graph(graph, n_batch):
    """One block-diagonal graph for a batch: B copies of ``graph`` or the B graphs given."""
    if isinstance(graph, Graph):
        return graph if n_batch == 1 else _copies(graph, n_batch)
    graphs = list(graph)
    if len(graphs) != n_batch:
        raise InputError("graph", "graph", f"{len(graphs)} graphs for {n_batch} trajectories",
                         "one Graph, or one per trajectory")
    return block_diagonal(graphs)


def check_data(model, datasets, sources, allow_dt_mismatch=False):
    """Raise InputError unless every file fits the model (dx, du, N for a node model) and its dt.

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
        model.check_nodes(traj.n_nodes, src, "x")
        _check_gaps(traj, s, src)
        if not allow_dt_mismatch and not math.isclose(traj.dt, s.dt, rel_tol=1e-9, abs_tol=0.0):
            raise InputError(src, "dt", f"is {traj.dt:g} but the model was trained with dt = {s.dt:g}",
                             f"data saved every {s.dt:g}; or, to evaluate the model at the file's dt, "
                             "`mpnode eval --allow-dt-mismatch` (allow_dt_mismatch=True in Python)")


def _check_gaps(traj, spec, source):
    """InputError when a gap between two observations would take the model more RK4 steps than
    the engine allows in one interval (mpnode.engine.schedule)."""
    if traj.regular:
        return
    longest = float(traj.intervals().max(initial=0.0))
    steps = math.ceil(longest * spec.substeps / spec.dt - 1e-9)
    if steps > MAX_STEPS_PER_INTERVAL:
        raise InputError(source, "t", f"has a gap of {longest:g}, {steps} RK4 steps of this model's "
                         f"dt / substeps = {spec.dt / spec.substeps:g}",
                         f"gaps of at most {MAX_STEPS_PER_INTERVAL} of the model's steps: split the trajectory "
                         "at the gap, or a model with a larger dt")
