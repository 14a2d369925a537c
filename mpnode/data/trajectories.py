"""`Trajectories`: the in-memory form of trajectory data every part of mpnode passes around.

Data as they come (docs/trajectory-format.md, version 2): observation times ``t`` per
trajectory (regular data have none: the k-th state is at k dt), NaN in ``x`` for a value
nobody observed, trajectories of different lengths in one set (the shorter ones padded: their
times end in NaN), and, for data degraded on purpose, the clean ``truth`` behind ``x``.
Networks as they are (version 3): weighted edges (on the graphs) and static attributes of each
node (``node_attrs``: a gene's degradation rate, a pendulum's length), named by ``attr_names``.
`from_arrays` builds one from plain arrays and validates it (mpnode.data.rules).
"""
from dataclasses import dataclass, field

import numpy as np

from mpnode.base.arguments import check_bool, check_mapping
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph, as_graph, is_networkx
from mpnode.base.h5 import one_line

from .rules import validate_trajectories


@dataclass
class Trajectories:
    """A set of trajectories of one homogeneous networked system.

    x : ndarray, shape (B, T+1, N, dx) -- node states, x[b, 0] the first observation; NaN
        where a value was not observed
    u : ndarray, shape (B, T, N, du), or None when du = 0 -- controls held from one
        observation time to the next
    graphs : list of Graph, each on N nodes
    graph_index : ndarray, shape (B,), int -- graph of each trajectory
    dt : float -- time between saved states (with ``t``: the nominal step, the model's)
    system : str -- the generating system, e.g. "lorenz"
    t : ndarray, shape (B, T+1), or None -- observation times, strictly increasing; a shorter
        trajectory ends in NaN (padding); None: t[b, k] = k dt
    truth : ndarray like x, or None -- the clean states behind x (data degraded on purpose)
    x_std : ndarray like x, or None -- of predictions: how far each value may be off (an
        ensemble's calibrated spread, in x's units)
    attrs : dict -- further root attributes (parameters, seed, solver, tolerances)
    params : dict name -> ndarray -- the `params/` group (system parameters)
    aux : dict name -> ndarray -- the `aux/` group (e.g. the quadrotor load)
    node_attrs : ndarray, shape (B, N, dp), float64, or None -- static attributes of each node in
        each trajectory (the same for all: a read-only broadcast of one (N, dp) array)
    attr_names : list of dp str, or None -- a name for each attribute (required with node_attrs)
    """

    x: np.ndarray
    graphs: list
    dt: float
    system: str
    u: np.ndarray = None
    graph_index: np.ndarray = None
    attrs: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    aux: dict = field(default_factory=dict)
    t: np.ndarray = None
    truth: np.ndarray = None
    x_std: np.ndarray = None
    node_attrs: np.ndarray = None
    attr_names: list = None

    def __post_init__(self):
        if self.graph_index is None:
            self.graph_index = np.zeros(self.x.shape[0], dtype=np.int64)
        if self.node_attrs is not None and np.ndim(self.node_attrs) == 2:  # one (N, dp) array: every trajectory's
            self.node_attrs = np.broadcast_to(self.node_attrs, (self.x.shape[0],) + np.shape(self.node_attrs))

    @property
    def n_trajectories(self):
        return self.x.shape[0]

    @property
    def horizon(self):
        return self.x.shape[1] - 1

    @property
    def n_nodes(self):
        return self.x.shape[2]

    @property
    def state_dim(self):
        return self.x.shape[3]

    @property
    def control_dim(self):
        return 0 if self.u is None else self.u.shape[3]

    @property
    def attr_dim(self):
        """dp, the number of static attributes per node (0 without node_attrs)."""
        return 0 if self.node_attrs is None else np.shape(self.node_attrs)[-1]

    @property
    def weighted(self):
        """Whether the graphs carry edge weights (a valid set's graphs all do, or none)."""
        return any(g.weighted for g in self.graphs)

    def graph_of(self, b):
        """The Graph trajectory ``b`` ran on."""
        return self.graphs[int(self.graph_index[b])]

    # ---- data as they come --------------------------------------------------
    @property
    def regular(self):
        """One dt between all observations, every trajectory as long as the longest."""
        return self.t is None

    @property
    def complete(self):
        """Every value of every trajectory observed (no NaN) and regular."""
        return self.regular and not np.isnan(np.asarray(self.x)).any()

    @property
    def lengths(self):
        """(B,) the number of observation times of each trajectory (T+1 when regular)."""
        if self.t is None:
            return np.full(self.n_trajectories, self.horizon + 1, dtype=np.int64)
        return np.isfinite(np.asarray(self.t)).sum(axis=1).astype(np.int64)

    def times(self):
        """(B, T+1) float64 observation times (k dt when regular; NaN after a trajectory's end)."""
        if self.t is None:
            return np.broadcast_to(np.arange(self.horizon + 1) * float(self.dt),
                                   (self.n_trajectories, self.horizon + 1)).astype(np.float64)
        return np.asarray(self.t, dtype=np.float64)

    def intervals(self):
        """(B, T) time from each observation to the next; 0 after a trajectory's end."""
        if self.t is None:
            return np.full((self.n_trajectories, self.horizon), float(self.dt))
        return np.nan_to_num(np.diff(np.asarray(self.t, dtype=np.float64), axis=1), nan=0.0)

    def observed(self):
        """Boolean like x: the value was observed (finite, and within its trajectory's length)."""
        seen = np.isfinite(np.asarray(self.x))
        if self.t is not None:
            seen &= (np.arange(self.horizon + 1)[None, :] < self.lengths[:, None])[:, :, None, None]
        return seen

    def unmeasured_dims(self):
        """The state dimensions observed nowhere in the set (the model carries them as hidden states)."""
        return np.flatnonzero(~self.observed().any(axis=(0, 1, 2)))

    def with_hidden_dims(self, k):
        """The same trajectories with ``k`` more state dimensions per node, never observed (NaN):
        room for a model's latent states (named "latent 1", ... and grouped as "latent" where the others are)."""
        if not k:
            return self
        pad = lambda a: None if a is None else np.concatenate(  # noqa: E731
            [a, np.full(np.shape(a)[:3] + (k,), np.nan, dtype=np.asarray(a).dtype)], axis=3)
        attrs = dict(self.attrs)
        if "state_names" in attrs:
            attrs["state_names"] = list(attrs["state_names"]) + [f"latent {i + 1}" for i in range(k)]
        if "state_groups" in attrs:
            attrs["state_groups"] = list(attrs["state_groups"]) + ["latent"] * k
        return Trajectories(x=pad(np.asarray(self.x, dtype=np.float64)), graphs=self.graphs, dt=self.dt,
                            system=self.system, u=self.u, graph_index=self.graph_index, attrs=attrs, params=self.params,
                            aux=self.aux, t=self.t, truth=pad(self.truth), node_attrs=self.node_attrs,
                            attr_names=self.attr_names)

    @classmethod
    def from_arrays(cls, x, graph, dt=None, system=None, u=None, graph_index=None, directed=False, attrs=None,
                    params=None, aux=None, t=None, truth=None, node_attrs=None, attr_names=None, source="arrays"):
        """Trajectories from plain arrays (your own simulator's or experiment's), validated.

        x : (B, T+1, N, dx) states, x[:, :, i] node i, NaN where a value was not observed;
        or a list of B arrays (T_b+1, N, dx) of different lengths (then ``t`` a list too);
        t : observation times (B, T+1), or (T+1,) shared by all, or a list of (T_b+1,) arrays;
        None: every dt;  u : (B, T, N, du) controls held between observation times, or None;
        graph : one graph for every trajectory -- an mpnode.Graph, a networkx graph or an
        edge list of (sender, receiver) pairs (E, 2) or (sender, receiver, weight) triples (E, 3),
        undirected unless ``directed`` -- or a list of them with ``graph_index`` (B,) naming each
        trajectory's (weighted graphs differing only in their weights too; every graph weighted, or
        none);  node_attrs : static attributes of each node, (B, N, dp) per trajectory or (N, dp)
        shared by all;  attr_names : their dp names (default "attr 1", ...);  dt : time between
        saved states (with ``t``: default the median interval, the model's step);  system : a
        name for the system;  truth : the clean states behind x, if known;  attrs : further
        root attributes (``state_names``: one name per state dimension, used by the figures;
        ``state_groups``: the group of each, whose errors `mpnode eval` reports).
        Integer arrays become float64.  Raises InputError naming ``source`` and the field.
        """
        directed = check_bool(directed, source, "directed")
        attrs, params, aux = (check_mapping(v, source, k) for k, v in (("attrs", attrs), ("params", params), ("aux", aux)))
        x, t = _padded(x, t, source)
        x, u = _float_array(x, "x", source), None if u is None else _float_array(u, "u", source)
        if x.ndim != 4:
            raise InputError(source, "x", f"has shape {x.shape}",
                             "a 4-D array [B, T+1, N, dx] (one trajectory: x[None])")
        t = _times(t, x.shape[:2], source)
        specs, field_of = _graph_specs(graph, source)
        graphs = [as_graph(g, x.shape[2], directed, source, field_of(k)) for k, g in enumerate(specs)]
        _all_or_none_weighted(graphs, field_of, source)
        if graph_index is None and len(graphs) > 1:
            raise InputError(source, "graph_index", f"is missing, but there are {len(graphs)} graphs",
                             f"an integer array of shape ({x.shape[0]},) naming the graph of each trajectory")
        if graph_index is not None:
            graph_index = np.asarray(graph_index)
            if graph_index.dtype.kind == "f" and np.all(graph_index == np.round(graph_index)):
                graph_index = graph_index.astype(np.int64)
        node_attrs = None if node_attrs is None else shared_attrs(_float64(node_attrs, "node_attrs", source),
                                                                  x.shape, source)
        traj = cls(x=x, graphs=graphs, dt=_plain_scalar(dt) if dt is not None else _median_interval(t),
                   system=system, u=u, graph_index=graph_index, attrs=attrs, params=params, aux=aux, t=t,
                   truth=None if truth is None else _float_array(truth, "truth", source), node_attrs=node_attrs,
                   attr_names=_attr_names(attr_names, node_attrs))
        return validate_trajectories(traj, source)


def shared_attrs(a, shape, source):
    """Node attributes (B, N, dp) of x's ``shape``: one (N, dp) array is every trajectory's
    (broadcast, not copied); other shapes are left to the rules, which name what is wrong."""
    if a.ndim != 2:
        return a
    B, N = shape[0], shape[2]
    if a.shape[0] != N or a.shape[1] < 1:
        raise InputError(source, "node_attrs", f"has shape {a.shape}",
                         f"[N, dp] = [{N}, dp >= 1] shared by every trajectory, or [B, N, dp] = [{B}, {N}, dp]")
    return np.broadcast_to(a, (B,) + a.shape)


def _attr_names(names, node_attrs):
    """The names as a list of str: one string is one name, none given with attributes are
    "attr 1", "attr 2", ..."""
    if names is None:
        if node_attrs is None or np.ndim(node_attrs) != 3:
            return None
        return [f"attr {i + 1}" for i in range(np.shape(node_attrs)[2])]
    if isinstance(names, str):
        return [names]
    if isinstance(names, np.ndarray) and names.ndim == 1:
        return names.tolist()
    return list(names) if isinstance(names, tuple) else names


def _all_or_none_weighted(graphs, field_of, source):
    """Every graph weighted, or none: an unweighted one among weighted ones is more likely a
    forgotten weight than edges of weight 1, so it is not guessed."""
    for k, g in enumerate(graphs):
        if g.weighted != graphs[0].weighted:
            weighted, plain = (k, 0) if g.weighted else (0, k)
            raise InputError(source, field_of(plain), f"has no weights, but {field_of(weighted)} has",
                             "weights on every graph, or on none (give an unweighted graph weights of 1)")


def _padded(x, t, source):
    """(x, t) with a list of trajectories of different lengths padded with NaN to the longest."""
    if not isinstance(t, (list, tuple)) or not isinstance(x, (list, tuple)) or not x or np.ndim(x[0]) != 3:
        return x, t
    if len(t) != len(x):
        raise InputError(source, "t", "is not a list as long as x's",
                         "with x a list of trajectories (T_b+1, N, dx): t a list of their times (T_b+1,)")
    longest = max(len(a) for a in x)
    xs = np.full((len(x), longest) + np.shape(x[0])[1:], np.nan)
    ts = np.full((len(x), longest), np.nan)
    for b, (xb, tb) in enumerate(zip(x, t)):
        if np.shape(xb)[1:] != np.shape(x[0])[1:] or np.shape(tb) != (len(xb),):
            raise InputError(source, f"x[{b}]", f"has shape {np.shape(xb)} with times {np.shape(tb)}",
                             f"(T_b+1, N, dx) = (.., {', '.join(map(str, np.shape(x[0])[1:]))}) and times (T_b+1,)")
        xs[b, :len(xb)], ts[b, :len(xb)] = xb, tb
    return xs, ts


def _times(t, shape, source):
    """t as (B, T+1) float64 (a (T+1,) array is every trajectory's), or None."""
    if t is None:
        return None
    t = _float_array(t, "t", source)
    if t.ndim == 1 and t.shape[0] == shape[1]:
        t = np.broadcast_to(t, shape)
    return np.array(t, dtype=np.float64)


def _median_interval(t):
    """The median time between consecutive observations (the nominal dt of irregular data)."""
    if t is None:
        return None
    gaps = np.diff(t, axis=1)
    gaps = gaps[np.isfinite(gaps)]
    return float(np.median(gaps)) if gaps.size else None


def _float_array(a, name, source):
    """``a`` as an ndarray; integers (and float16) become float64, other dtypes are left to the checker."""
    try:
        a = np.asarray(a)
    except ValueError as e:  # ragged nested lists
        raise InputError(source, name, f"is not a rectangular array ({one_line(e)})",
                         "one number per entry of a regular grid") from None
    if a.dtype.kind in "iub" or (a.dtype.kind == "f" and a.dtype.itemsize < 4):
        a = a.astype(np.float64)
    return a


def _float64(a, name, source):
    """``a`` as an ndarray, float64 when it holds numbers (static attributes need no other precision)."""
    a = _float_array(a, name, source)
    return a.astype(np.float64, copy=False) if a.dtype.kind == "f" else a


def _plain_scalar(v):
    """A one-element array (e.g. loaded from a file) as its Python number; anything else unchanged."""
    if isinstance(v, np.ndarray) and v.size == 1 and v.dtype.kind in "iuf":
        return v.item()
    return v


def _graph_specs(graph, source):
    """(list of graph specs, field name of spec k): one graph, or a list of them."""
    if graph is None:
        raise InputError(source, "graph", "is missing",
                         "an edge list of (sender, receiver) pairs, an mpnode.Graph or a networkx graph")
    single = (lambda k: "graph")
    if isinstance(graph, Graph) or is_networkx(graph):
        return [graph], single
    if isinstance(graph, np.ndarray):
        return (list(graph), (lambda k: f"graph[{k}]")) if graph.ndim == 3 else ([graph], single)
    if isinstance(graph, (list, tuple)):
        if not graph:
            raise InputError(source, "graph", "is an empty list",
                             "an edge list (for a graph without edges: np.zeros((0, 2), int)) or a list of graphs")
        if not any(isinstance(g, Graph) or is_networkx(g) for g in graph):
            try:
                if np.asarray(graph).ndim == 2:  # a list of pairs: one edge list
                    return [graph], single
            except ValueError:  # ragged: a list of edge lists of different lengths
                pass
        return list(graph), (lambda k: f"graph[{k}]")
    return [graph], single
