"""Which node or line changed: fit a network's node attributes or edge weights to observed
trajectories through a trained model, and rank the nodes (lines) by how far the fit moved them
from the nominal network.

The loss is the mean squared error of the model's rollouts, each from its trajectory's first
observation, against every later observed value, in the model's normalised units (as training
measures it).  Its gradient with respect to the attributes or weights is exact and costs one
rollout and one VJP of the engine (`engine.forward_with_vjp`'s node_attrs / edge_weights
cotangents), however many there are.  scipy's L-BFGS-B minimises it from the nominal values
within bounds, each parameter in units of its own nominal size, so that an inertia of 0.6 and
one of 8 move alike, and a departure is relative: (fitted - nominal) / nominal.  An edge and
its reverse of the same nominal weight (both directions of an undirected line) are one parameter.

A model is only as good a witness as it is accurate: a parameter the observations hardly
constrain, or one that takes up the model's own error, moves too.  Observations of the nominal
network (``reference``: from before the change) are fitted alike, and the departures then
measured between the two fits: what the model gets wrong moves both and drops out
(docs/fit-network.md says what each way measured).
"""
import os
import time
from dataclasses import dataclass, replace

import numpy as np

from mpnode import engine
from mpnode.base.arguments import check_int
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine.backend import single_threaded_blas
from mpnode.model import Model, batch_graph, check_data
from mpnode.model.ensemble import models_of
from mpnode.model.inputs import attrs_as_controls
from mpnode.model.model import node_intervals, to_time_major
from mpnode.model.simulator import check_weighting

#: what a fit changes
WHAT = ("node_attrs", "edge_weights")
SOURCE = "fit_network"


@dataclass
class NetworkFit:
    """What `fit_network` found.

    what : "node_attrs" or "edge_weights"
    nominal, fitted : (N, dp) every node attribute (those not fitted stay nominal), or (E,) every
        edge weight in the graph's CSR order
    baseline : what departures are measured from, like fitted: the nominal values, or the fit to
        the reference observations when `fit_network` was given them
    attr_names : the model's attributes (the columns of nominal and fitted; [] for edge weights)
    columns : the names of the attributes fitted ([] for edge weights)
    lines : (L, 2) the two nodes of each line (an undirected edge once, lower node first; a
        one-way edge as (receiver, sender)); None for node attributes
    line_of : (E,) the line of each edge; None for node attributes
    change : (N, len(columns)) or (L,): (fitted - baseline) / the parameter's nominal size
    departure : (N,) or (L,) |change| (a node's: the largest over its fitted columns)
    ranking : node (line) indices by departure, most departed first
    loss_nominal, loss : the loss at the start (the nominal values, within the bounds) and at the fit
    reference_loss : the loss of the reference's fit, None without a reference
    iterations, evaluations, message : the optimiser's;  seconds : of the fit (and the reference's)
    """

    what: str
    nominal: np.ndarray
    fitted: np.ndarray
    baseline: np.ndarray
    attr_names: list
    columns: list
    lines: np.ndarray
    line_of: np.ndarray
    change: np.ndarray
    departure: np.ndarray
    ranking: np.ndarray
    loss_nominal: float
    loss: float
    reference_loss: float
    iterations: int
    evaluations: int
    seconds: float
    message: str

    def to_dict(self):
        """A JSON-ready dict of every field (arrays as lists)."""
        return {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in self.__dict__.items()}

    def describe(self, top=5):
        """Lines of text: the ``top`` most departed nodes (lines), each with its baseline and fitted values."""
        out = []
        for k in self.ranking[:top]:
            if self.lines is None:
                values = ", ".join(f"{name} {self.baseline[k, c]:.4g} -> {self.fitted[k, c]:.4g}"
                                   for name, c in ((a, self.attr_names.index(a)) for a in self.columns))
                out.append(f"node {k}: {values} (departure {self.departure[k]:.3g})")
            else:
                i, j = self.lines[k]
                edge = int(np.flatnonzero(self.line_of == k)[0])
                out.append(f"line {i}-{j}: weight {self.baseline[edge]:.4g} -> {self.fitted[edge]:.4g} "
                           f"(departure {self.departure[k]:.3g})")
        return out


def fit_network(model, data, what="node_attrs", attrs=None, node_attrs=None, graph=None, bounds=None,
                iterations=100, reference=None, window=None):
    """Fit the node attributes (``what="node_attrs"``) or edge weights (``"edge_weights"``) of the
    one network behind ``data`` through ``model``, from the nominal network: a NetworkFit whose
    ``ranking`` names the nodes (lines) that moved most, relative to nominal.

    model : a Model or Ensemble (or its file) that hears node attributes / weighted graphs
    data : Trajectories (or a trajectory file) observed on that network, with their controls
    attrs : the names of the attributes to fit (default all of ``model.attr_names``); the others
        stay at their nominal values
    node_attrs : (N, dp) the nominal attributes in the data's units (default the data's own)
    graph : the nominal Graph, weighted for a model of weighted graphs (default the data's)
    bounds : (low, high) in the parameters' units: numbers, or arrays broadcastable to
        (N, len(attrs)) or to one per line (`NetworkFit.lines`); None for no bound on that side.
        Default: >= 0 for an attribute column whose nominal values are all positive and for
        weights that are all >= 0, none otherwise.
    iterations : L-BFGS-B's iterations at most
    reference : None, or trajectories (a file) observed on the nominal network (before the
        change), or the NetworkFit of such trajectories (fitted once, compared with many): the
        departures are then measured from that fit instead of from the nominal values.  What the
        model gets wrong moves both fits alike and drops out of the difference.
    window : None (each rollout runs the whole trajectory), or K: the trajectories cut into windows
        of K steps, each rolled out from its own first observation (messages from 0, as training's
        windows start): a model that drifts over a long rollout is still right over a short one
    """
    if what not in WHAT:
        raise InputError(SOURCE, "what", f"is {what!r}", " or ".join(repr(w) for w in WHAT))
    iterations = check_int(iterations, SOURCE, "iterations", 1)
    window = None if window is None else check_int(window, SOURCE, "window", 1)
    model = (Model.load(model) if isinstance(model, (str, bytes, os.PathLike)) else model).copy(np.float64)
    traj = _data(model, data, window)
    nominal = _nominal_attrs(model, traj, node_attrs), _nominal_graph(model, traj, graph)
    params, p, loss_nominal, res, seconds = _fitted(model, traj, nominal, what, attrs, bounds, iterations)
    base, reference_loss = params.p0, None
    if isinstance(reference, NetworkFit):
        base, reference_loss = params.flat(_checked_reference(reference, params, what)), reference.loss
    elif reference is not None:
        _, base, _, ref, ref_seconds = _fitted(model, _data(model, reference, window), nominal, what, attrs, bounds,
                                               iterations)
        reference_loss, seconds = float(ref.fun), seconds + ref_seconds
    change = params.shaped((p - base) / params.scale)
    departure = np.abs(change).max(axis=1) if change.ndim == 2 else np.abs(change)
    return NetworkFit(what, params.nominal, params.quantity(p), params.quantity(base), params.attr_names,
                      params.columns, params.lines, params.line_of, change, departure,
                      np.argsort(-departure, kind="stable"), loss_nominal, float(res.fun), reference_loss,
                      int(res.nit), int(res.nfev), seconds, str(res.message))


def _checked_reference(reference, params, what):
    """The fitted values of a reference NetworkFit, when it fitted what this fit does on the same network."""
    same = reference.what == what and reference.columns == params.columns
    same = same and np.shape(reference.nominal) == np.shape(params.nominal)
    if not same or not np.array_equal(reference.nominal, params.nominal):
        raise InputError(SOURCE, "reference", f"is a fit of {reference.what} {', '.join(reference.columns)} "
                         "from another nominal network", f"a fit of the same {what} from the same nominal network")
    return reference.fitted


def _data(model, data, window):
    """Trajectories (read from their file when given as a path) with room for the model's latent
    dimensions, cut into windows of ``window`` steps (None: whole)."""
    if isinstance(data, (str, bytes, os.PathLike)):
        from mpnode.data.files import read_trajectories

        data = read_trajectories(data)
    return model.fitted(_windows(data, window))


def _windows(traj, k):
    """``traj`` cut into windows of k steps from every k-th observation, each a trajectory of its own
    (those that start after their trajectory's end left out); ``traj`` when k is None or not shorter."""
    if k is None or k >= traj.horizon:
        return traj
    starts = range(0, traj.horizon - k + 1, k)

    def cut(a, extra):
        return None if a is None else np.concatenate([np.asarray(a)[:, s:s + k + extra] for s in starts])

    t = cut(traj.t, 1)
    keep = slice(None) if t is None else np.isfinite(t[:, 0])
    attrs = None if traj.node_attrs is None else np.concatenate([traj.node_attrs] * len(starts))[keep]
    return replace(traj, x=cut(traj.x, 1)[keep], u=None if traj.u is None else cut(traj.u, 0)[keep],
                   t=None if t is None else t[keep], truth=None, x_std=None, node_attrs=attrs,
                   graph_index=np.tile(traj.graph_index, len(starts))[keep])


def _fitted(model, traj, nominal, what, attrs, bounds, iterations):
    """One fit of ``traj`` from the ``nominal`` (node attributes, graph): (the parameters, their
    fitted values, the loss at the start, scipy's result, seconds)."""
    attrs_nominal, graph = nominal
    view = traj if attrs_nominal is None else replace(traj, node_attrs=attrs_nominal, attr_names=model.attr_names)
    check_data(model, [attrs_as_controls(view)], [SOURCE])  # dimensions, dt, nodes: the data as the model hears them
    problem = _Problem(model, traj, attrs_nominal, graph)
    params = _AttrParameters(problem, attrs) if what == "node_attrs" else _WeightParameters(problem)
    low, high = params.box(bounds)
    start = time.perf_counter()
    p, loss_nominal, res = _minimise(params.loss, params.p0, params.scale, low, high, iterations)
    return params, p, loss_nominal, res, time.perf_counter() - start


def _nominal_attrs(model, traj, node_attrs):
    """The nominal node attributes (N, dp) float64, or None for a model without them."""
    if not model.spec.attr_dim:
        if node_attrs is not None:
            raise InputError(SOURCE, "node_attrs", "are given, but the model was trained without node attributes",
                             "None")
        return None
    if node_attrs is None:
        if list(traj.attr_names or []) != model.attr_names:
            raise InputError(SOURCE, "data", f"has node attributes {traj.attr_names or 'none'}",
                             f"the model's: {', '.join(model.attr_names)} (or give node_attrs)")
        a = np.asarray(traj.node_attrs, dtype=np.float64)
        if np.any(a != a[:1]):
            raise InputError(SOURCE, "data", "holds trajectories of different node attributes",
                             "trajectories of one network (or give node_attrs)")
        return a[0].copy()
    return np.array(model.controls_of(None, node_attrs, 1, traj.n_nodes, 1, SOURCE)[0, 0])


def _nominal_graph(model, traj, graph):
    """The nominal Graph, checked against the model's weighting and the data's nodes."""
    if graph is None:
        if any(not g.equals(traj.graphs[0]) for g in traj.graphs[1:]):
            raise InputError(SOURCE, "data", f"holds {len(traj.graphs)} different graphs",
                             "trajectories of one network (or give graph)")
        graph = traj.graphs[0]
    if not isinstance(graph, Graph):
        raise InputError(SOURCE, "graph", f"is a {type(graph).__name__}", "an mpnode.Graph")
    graph.validate(SOURCE, "graph")
    if graph.n_nodes != traj.n_nodes:
        raise InputError(SOURCE, "graph", f"has {graph.n_nodes} nodes, the data {traj.n_nodes}",
                         "the nominal graph of the data's network")
    check_weighting(model, graph, SOURCE)
    return graph


class _Problem:
    """The observed trajectories as the model's rollouts take them, and the loss of a network's
    node attributes and edge weights, with its gradient with respect to either."""

    def __init__(self, model, traj, attrs, graph):
        self.model, self.members = model, models_of(model)
        self.attrs, self.graph = attrs, graph
        b, n, dx = traj.n_trajectories, traj.n_nodes, model.spec.state_dim
        self.shape, self.steps, self.u = (b, n), traj.horizon, traj.u
        x = np.asarray(traj.x, dtype=np.float64)
        seen = to_time_major(traj.observed())
        seen[0] = False  # where each rollout starts
        self.target = np.where(seen, to_time_major(model.normalize_x(x)), 0.0)
        self.seen, self.count = seen, max(int(seen.sum()), 1)
        k = min(model.spec.encoder_window or 1, traj.horizon + 1)
        times = None if traj.regular else traj.times()
        x0 = model.initial_state(x[:, :k], None if times is None else times[:, :k])
        self.x0 = model.normalize_x(x0).reshape(b * n, dx)
        self.intervals = None if times is None else np.repeat(node_intervals(times), n, axis=1)
        self.flat = batch_graph(graph, b)

    def loss(self, attrs=None, weights=None):
        """(loss, gradient) at node attributes ``attrs`` (N, dp) or edge weights ``weights`` (E,),
        the other at its nominal value: the gradient's shape is that of the one given."""
        m, (b, n) = self.model, self.shape
        graph = self.flat if weights is None else block_diagonal([self.graph.reweighted(weights)] * b)
        u = m.controls_of(self.u, self.attrs if attrs is None else attrs, b, n, self.steps, SOURCE)
        un = None if u is None else to_time_major(m.normalize_u(np.asarray(u)))
        driver = "auto" if weights is None else "blocks"  # the weights' cotangent needs the block drivers
        runs = [engine.forward_with_vjp(one.spec, one.theta, self.x0, graph, un, self.steps, driver=driver,
                                        intervals=self.intervals) for one in self.members]
        residual = np.where(self.seen, np.mean([x for x, _ in runs], axis=0) - self.target, 0.0)
        value = float(np.sum(residual * residual)) / self.count
        if not np.isfinite(value):  # a rollout blew up: L-BFGS-B's line search steps back
            return np.inf, np.zeros(np.shape(attrs if weights is None else weights))
        gx = 2 * residual / (self.count * len(runs))
        if weights is None:
            ga = sum(vjp(gx, node_attrs=True)[2] for _, vjp in runs)
            return value, ga.reshape(b, n, -1).sum(axis=0) / m.u_std[m.spec.control_dim - m.spec.attr_dim:]
        gw = sum(vjp(gx, edge_weights=True)[2] for _, vjp in runs)
        return value, gw.reshape(b, -1).sum(axis=0)


def _scale(nominal):
    """Each parameter's nominal size: |nominal|, or where that is 0 the mean of the others' (1 if all are 0)."""
    size = np.abs(nominal)
    typical = size[size > 0].mean() if np.any(size > 0) else 1.0
    return np.where(size > 0, size, typical)


def _broadcast_bound(value, shape, fill, field):
    """A bound as a float array of ``shape``, ``fill`` where None; InputError when it does not broadcast."""
    if value is None:
        return np.full(shape, fill)
    try:
        b = np.broadcast_to(np.asarray(value, dtype=np.float64), shape).astype(np.float64)
    except (ValueError, TypeError):
        raise InputError(SOURCE, field, f"has shape {np.shape(value)}",
                         f"a number, or an array broadcastable to {shape}") from None
    return np.where(np.isnan(b), fill, b)


def _box(bounds, shape, low_default):
    """(low, high) flat arrays of the parameters' bounds (see fit_network)."""
    if bounds is None:
        return low_default.ravel(), np.full(low_default.size, np.inf)
    if not isinstance(bounds, (tuple, list)) or len(bounds) != 2:
        raise InputError(SOURCE, "bounds", f"is {bounds!r}", "a pair (low, high), either side None")
    low = _broadcast_bound(bounds[0], shape, -np.inf, "bounds[0]")
    high = _broadcast_bound(bounds[1], shape, np.inf, "bounds[1]")
    if np.any(low > high):
        raise InputError(SOURCE, "bounds", "has a low bound above its high one", "low <= high")
    return low.ravel(), high.ravel()


class _AttrParameters:
    """Some columns of the node attributes (N, dp), flat node-major, as the fitted parameters."""

    lines = line_of = None

    def __init__(self, problem, attrs):
        self.problem, self.nominal = problem, problem.attrs
        if self.nominal is None:
            raise InputError(SOURCE, "what", "is 'node_attrs', but the model was trained without node attributes",
                             "'edge_weights', or a model with node attributes")
        self.attr_names = names = problem.model.attr_names
        self.columns = list(names) if attrs is None else [attrs] if isinstance(attrs, str) else list(attrs)
        unknown = [a for a in self.columns if a not in names]
        if unknown or not self.columns or len(set(self.columns)) < len(self.columns):
            raise InputError(SOURCE, "attrs", f"is {attrs!r}", f"distinct names among {', '.join(names)}")
        self.cols = [names.index(a) for a in self.columns]
        self.p0 = self.nominal[:, self.cols].ravel()
        self.scale = np.stack([_scale(self.nominal[:, c]) for c in self.cols], axis=1).ravel()

    def box(self, bounds):
        positive = np.all(self.nominal[:, self.cols] > 0, axis=0)
        low = np.broadcast_to(np.where(positive, 0.0, -np.inf), (len(self.nominal), len(self.cols)))
        return _box(bounds, low.shape, low)

    def quantity(self, p):
        a = self.nominal.copy()
        a[:, self.cols] = self.shaped(p)
        return a

    def shaped(self, p):
        return np.asarray(p).reshape(len(self.nominal), len(self.cols))

    def flat(self, quantity):
        return np.asarray(quantity)[:, self.cols].ravel()

    def loss(self, p):
        value, g = self.problem.loss(attrs=self.quantity(p))
        return value, g[:, self.cols].ravel()


class _WeightParameters:
    """The lines' weights (an edge and its reverse of equal nominal weight: one line) as the fitted parameters."""

    columns, attr_names = [], []

    def __init__(self, problem):
        model, graph = problem.model, problem.graph
        if model.spec.aggregation.weight_scale is None or model.kind == "node":
            raise InputError(SOURCE, "what", "is 'edge_weights', but the model does not hear edge weights",
                             "'node_attrs', or a model trained on weighted graphs")
        self.problem, self.nominal = problem, graph.weights.copy()
        self.line_of, self.lines = lines_of(graph)
        self.p0 = np.zeros(len(self.lines))
        self.p0[self.line_of] = self.nominal
        self.scale = _scale(self.p0)

    def box(self, bounds):
        low = np.full(len(self.p0), 0.0 if np.all(self.p0 >= 0) else -np.inf)
        return _box(bounds, low.shape, low)

    def quantity(self, p):
        return np.asarray(p)[self.line_of]

    def shaped(self, p):
        return np.asarray(p)

    def flat(self, quantity):
        p = np.zeros(len(self.p0))
        p[self.line_of] = quantity
        return p

    def loss(self, p):
        value, g = self.problem.loss(weights=self.quantity(p))
        return value, np.bincount(self.line_of, weights=g, minlength=len(self.p0))


def lines_of(graph):
    """(the line of each edge (E,), the lines' node pairs (L, 2)): an edge and its reverse of the
    same weight are one line, lower node first; any other edge is a line of its own, (receiver, sender)."""
    n, edges = graph.n_nodes, graph.edges()
    w = graph.weights if graph.weighted else np.ones(graph.n_edges)
    key, back = edges[:, 0] * n + edges[:, 1], edges[:, 1] * n + edges[:, 0]
    order = np.argsort(key, kind="stable")
    at = np.minimum(np.searchsorted(key, back, sorter=order), len(key) - 1)
    reverse = order[at] if len(key) else at
    tied = (key[reverse] == back) & (w[reverse] == w) if len(key) else np.zeros(0, bool)
    pair = np.where(tied, np.minimum(key, back), key)
    ids, line_of = np.unique(pair, return_inverse=True)
    return line_of.reshape(-1), np.stack([ids // n, ids % n], axis=1)


def _minimise(loss, p0, scale, low, high, iterations):
    """L-BFGS-B on p / scale from p0: (p, the loss at p0, scipy's result)."""
    from scipy.optimize import minimize

    first = []

    def scaled(z):
        value, g = loss(z * scale)
        if not first:
            first.append(value)
        return value, g * scale

    with single_threaded_blas():  # small vectors: a BLAS thread pool would only spin the other core
        res = minimize(scaled, p0 / scale, jac=True, method="L-BFGS-B", bounds=list(zip(low / scale, high / scale)),
                       options={"maxiter": iterations, "ftol": 1e-12, "gtol": 1e-9})
    return res.x * scale, first[0], res
