"""What a model saw in training, and the inputs that leave it.

A model answers anywhere, also where it has never been: a denser graph, more nodes, states
or neighbour aggregates larger than any in its training data.  Training records the range
of every input its networks received on the training split (`record`: the states per
dimension, the in-degree, each aggregate input per channel, the number of nodes and, for a
model that has them, each node attribute and the edge weights), and
`scan` + `off_range` tell, for new data, which of them left that range, by how much and
where, so that a user can see when not to trust a prediction.

The aggregates are those of the model's own rollout from each trajectory's first state, at
the output steps (not at every RK4 stage): the same pass on the training split and on new
data, so the two compare like with like.  The node attributes reach the networks as their last
control columns (mpnode.model.inputs) but are named by their own names here, as the states are:
a user knows a pendulum's length, not the model's fourth control.  The ranges live in
``Model.attrs[KEY]`` as plain lists, and in the model file as the optional group ``seen/``
(docs/model-format.md).
"""
import warnings

import numpy as np

from mpnode import engine
from mpnode.engine.numpy_path import aggregator, field_arrays, l2s_heard

from .file import SEEN_ATTR as KEY  # the Model.attrs entry holding the ranges (the file's group seen/)
from .model import batch_graph, node_intervals

#: an input is off the range when it lies beyond what training saw by more than this fraction of
#: the seen range's width (docs/evidence/off-range.md: in-distribution test sets stay inside it)
MARGIN = 0.25
#: quantities with one value per node, and quantities of a whole graph
_SCALARS = ("in_degree", "nodes")
#: quantities whose channels have names (the state's dimensions, the node attributes), not numbers
_NAMED = ("state", "attribute")
#: quantities that stay as they are along a rollout: reported without a step
_STATIC = _SCALARS + ("edge_weight", "attribute")
#: where each quantity's value was (the default: along a rollout)
_WHERE = {"nodes": "", "in_degree": " at node {node}", "attribute": " at node {node} (trajectory {trajectory})",
          "edge_weight": " on an edge into node {node} (trajectory {trajectory})"}
_ROLLOUT_WHERE = " at node {node} (trajectory {trajectory}, step {step})"


class OffRangeWarning(UserWarning):
    """An input of a model lies outside the range it saw in training."""


class Tally:
    """The smallest and largest value of every quantity seen so far, each with where it was:
    (trajectory, step, node) per channel; ``names``: the channels' names of a quantity that has
    them beside the state (the node attributes')."""

    def __init__(self):
        self.lo, self.hi, self.lo_at, self.hi_at, self.names = {}, {}, {}, {}, {}

    def add(self, name, values, step, first_trajectory=0):
        """values (B, N, c) at output ``step`` of trajectories first_trajectory.. (NaN ignored, and so
        is inf: a prediction that blew up is the blow-up test's to report)."""
        v = np.asarray(values, dtype=np.float64)
        v = np.where(np.isfinite(v), v, np.nan)
        b, n, c = v.shape
        flat = v.reshape(b * n, c)
        if not flat.size:
            return
        for ext, arg, better, side in ((self.lo, np.argmin, np.less, self.lo_at),
                                       (self.hi, np.argmax, np.greater, self.hi_at)):
            fill = np.inf if arg is np.argmin else -np.inf
            k = arg(np.where(np.isnan(flat), fill, flat), axis=0)
            new = flat[k, np.arange(c)]
            at = np.stack([first_trajectory + k // n, np.full(c, step), k % n], axis=1)
            if name not in ext:
                ext[name], side[name] = np.full(c, np.nan), np.zeros((c, 3), dtype=np.int64)
            take = np.isnan(ext[name]) & ~np.isnan(new) | better(new, ext[name])
            ext[name][take], side[name][take] = new[take], at[take]

    def ranges(self):
        """{name: (lo (c,), hi (c,))} of everything tallied."""
        return {k: (self.lo[k], self.hi[k]) for k in self.lo}


def network_inputs(model, x0, graph, u=None, steps=0, times=None):
    """Yield (step, states (B, N, dx) data units, {quantity: (B, N, c)}) along the model's rollout
    from x0 (B, N, dx): what its networks receive at every output step.  graph : one Graph or
    B; u : (B, T, N, du) data units or None; times : (B, T+1) or None (every dt)."""
    spec = model.spec
    b, n, dx = x0.shape
    flat = batch_graph(graph, b)
    z = engine.initial_state(spec, model.normalize_x(x0).reshape(b * n, dx), model.dtype)
    un = None if u is None else model.normalize_u(np.asarray(u)).transpose(1, 0, 2, 3).reshape(-1, b * n,
                                                                                             spec.control_dim)
    iv = None if times is None else np.repeat(node_intervals(times), n, axis=1)
    heard = aggregate_inputs(model, flat)
    for t in range(steps + 1):
        if t:
            _, z = engine.integrate(spec, model.theta, z, flat, None if un is None else un[t - 1:t], 1,
                                    intervals=None if iv is None else iv[t - 1:t])
        ut = None if un is None else un[min(t, len(un) - 1)]
        x = model.denormalize_x(z[:, :dx].astype(np.float64))
        yield t, x.reshape(b, n, dx), {k: a.reshape(b, n, -1) for k, a in heard(z, ut).items()}


def aggregate_inputs(model, flat):
    """(z, u) -> {quantity: (M, c)}: the aggregate inputs of the model's networks, in its units."""
    spec = model.spec
    dx = spec.state_dim
    if spec.kind == "node" or (spec.kind == "mpnode" and (spec.zero_messages or not spec.message_dim)):
        return lambda z, u: {}
    mlp = aggregator(spec, flat, np.float64)
    if spec.kind == "l2s":
        arrays = field_arrays(spec, model.theta.astype(np.float64), flat)

        def l2s(z, u):
            u = np.zeros((len(z), spec.control_dim)) if u is None else u
            return {"aggregate": l2s_heard(arrays, z[:, :dx].astype(np.float64), u)[1]}

        return l2s
    own = spec.aggregation.own_linear
    linear = None if own is None else aggregator(spec, flat, np.float64, own)

    def mpnode(z, u):
        m = z[:, dx:].astype(np.float64)
        return {"aggregate": mlp(m), **({"linear_aggregate": linear(m)} if linear else {})}

    return mpnode


def scan(model, x0, graphs, graph_index, u=None, steps=0, times=None, max_nodes=16384):
    """A Tally of every input along the model's rollouts from x0 (B, N, dx) on
    ``graphs[graph_index[b]]`` (chunks of about ``max_nodes`` nodes), with the in-degree
    and the number of nodes."""
    tally = Tally()
    b, n, _ = x0.shape
    gi = np.asarray(graph_index)
    size = max(1, max_nodes // max(n, 1))
    with np.errstate(all="ignore"):
        for i in range(0, b, size):
            j = min(i + size, b)
            graph = graphs[int(gi[i])] if np.all(gi[i:j] == gi[i]) else [graphs[int(k)] for k in gi[i:j]]
            for t, x, heard in network_inputs(model, x0[i:j], graph, None if u is None else u[i:j], steps,
                                              None if times is None else times[i:j]):
                tally.add("state", x, t, i)
                for name, a in heard.items():
                    tally.add(name, a, t, i)
            if u is not None and np.shape(u)[1]:  # held over every step: the first one's are all of them
                add_attributes(tally, model, np.asarray(u)[i:j, 0], i)
    add_graphs(tally, graphs, gi, n)
    return tally


def add_attributes(tally, model, u, first_trajectory=0):
    """The node attributes among the controls u (B, N, du) in the data's units (their last
    ``attr_dim`` columns), under the model's names for them; nothing for a model without."""
    dp = model.spec.attr_dim
    if dp and u is not None:
        tally.add("attribute", u[..., -dp:], 0, first_trajectory)
        tally.names["attribute"] = model.attr_names


def add_graphs(tally, graphs, graph_index, n_nodes):
    """The in-degree of every node of the graphs used, their edge weights when they have them,
    and their number of nodes."""
    for k in np.unique(graph_index):
        first = int(np.argmax(graph_index == k))
        tally.add("in_degree", graphs[int(k)].degrees().reshape(1, -1, 1), 0, first)
        add_edge_weights(tally, graphs[int(k)], first)
    tally.add("nodes", np.array([[[n_nodes]]]), 0, 0)


def add_edge_weights(tally, graph, first_trajectory=0):
    """The weights of a weighted graph's edges, each node's smallest and largest incoming one (so
    that a report names the node whose edge it is); nothing for an unweighted graph."""
    if not graph.weighted or not graph.n_edges:
        return
    rows = np.repeat(np.arange(graph.n_nodes), graph.degrees())
    for pick, start in ((np.minimum, np.inf), (np.maximum, -np.inf)):
        per_node = np.full(graph.n_nodes, start)  # a node that hears nobody stays infinite: not tallied
        pick.at(per_node, rows, graph.weights)
        tally.add("edge_weight", per_node.reshape(1, -1, 1), 0, first_trajectory)


def record(tally):
    """The model attribute (JSON-ready) of the ranges in ``tally``: {quantity_min, quantity_max}."""
    out = {}
    for name, (lo, hi) in tally.ranges().items():
        out[f"{name}_min"], out[f"{name}_max"] = lo.tolist(), hi.tolist()
    return out


def merge(a, b):
    """The union of two recorded ranges (e.g. the data's states and the rollouts')."""
    out = dict(a)
    for key, v in b.items():
        if key not in out:
            out[key] = v
            continue
        pick = np.fmin if key.endswith("_min") else np.fmax
        out[key] = pick(np.asarray(out[key], dtype=np.float64), np.asarray(v, dtype=np.float64)).tolist()
    return out


def off_range(seen, tally, state_names=None, margin=MARGIN):
    """One entry (dict, with a plain ``message``) per quantity of ``tally`` that left ``seen``
    (a recorded range) by more than ``margin`` of the seen width, worst channel first; []
    when none did."""
    out, names = [], {"state": state_names, **tally.names}
    for name, (lo, hi) in tally.ranges().items():
        if f"{name}_min" not in seen:
            continue
        s_lo, s_hi = (np.asarray(seen[f"{name}_{e}"], dtype=np.float64) for e in ("min", "max"))
        if s_lo.shape != lo.shape:
            continue
        width = np.where(s_hi > s_lo, s_hi - s_lo, 0.0)
        below, above = (s_lo - margin * width) - lo, hi - (s_hi + margin * width)
        for channel in range(len(lo)):
            entries = [_entry(name, channel, "below", lo[channel], s_lo[channel], s_hi[channel],
                              tally.lo_at[name][channel], names.get(name))] if below[channel] > 0 else []
            if above[channel] > 0:
                entries.append(_entry(name, channel, "above", hi[channel], s_lo[channel], s_hi[channel],
                                      tally.hi_at[name][channel], names.get(name)))
            out += entries
    return _worst_per_quantity(out)


def _worst_per_quantity(entries):
    """The entry that goes furthest beyond its range, of every quantity (a state dimension each)."""
    def size(e):  # a range of one value (width 0) is left by any amount
        return np.inf if e["beyond_width"] is None else e["beyond_width"]

    best = {}
    for e in entries:
        if e["quantity"] not in best or size(e) > size(best[e["quantity"]]):
            best[e["quantity"]] = e
    return sorted(best.values(), key=lambda e: -size(e))


def _entry(name, channel, side, value, s_lo, s_hi, at, names):
    """One quantity's departure; ``names``: its channels' names, if it has any."""
    bound = s_lo if side == "below" else s_hi
    width = s_hi - s_lo
    beyond = abs(value - bound)
    quantity = _quantity(name, channel, names)
    trajectory, step, node = (int(v) for v in at)
    where = _WHERE.get(name, _ROLLOUT_WHERE).format(node=node, trajectory=trajectory, step=step)
    limit = "smallest" if side == "below" else "largest"
    share = f", {beyond / width:.3g}x the range seen" if width > 0 else ""
    numbered = name not in _STATIC and name not in _NAMED  # the aggregates: a channel of a vector
    text = (f"{quantity}{f' channel {channel}' if numbered else ''} {_num(value)}{where} is {side} the {limit} "
            f"seen in training ({_num(bound)}) by {_num(beyond)}{share}")
    return {"quantity": quantity, "channel": channel if numbered else None,
            "value": float(value), "seen_min": float(s_lo), "seen_max": float(s_hi), "side": side,
            "beyond": float(beyond), "beyond_width": float(beyond / width) if width > 0 else None,
            "trajectory": None if name == "nodes" else trajectory, "step": None if name in _STATIC else step,
            "node": None if name == "nodes" else node, "message": text}


def _quantity(name, channel, names):
    if name in _NAMED:
        symbol = {"state": "x", "attribute": "p"}[name]
        named = names is not None and len(names) > channel
        return f"{name} {names[channel] if named else f'{symbol}[{channel}]'}"
    return {"in_degree": "in-degree", "nodes": "number of nodes", "aggregate": "aggregate input",
            "linear_aggregate": "linear-path aggregate input", "edge_weight": "edge weight"}[name]


def _num(v):
    return f"{int(v)}" if float(v).is_integer() and abs(v) < 1e15 else f"{v:.4g}"


def training_ranges(model, datasets, split):
    """The ranges to record for ``model`` trained on ``datasets`` (Trajectories as training heard
    them: the model's latent dimensions, node attributes as the last controls) whose training
    trajectories are ``split[i][0]``: the data's states joined with those of one rollout of the
    model from each training trajectory's start, whose aggregates, in-degrees, number of nodes,
    node attributes and edge weights come with them."""
    seen = {}
    for traj, (train, _) in zip(datasets, split):
        train, traj = np.asarray(train), model.fitted(traj)
        if not len(train):
            continue
        x = np.asarray(traj.x, dtype=np.float64)[train]
        x0 = model.initial_state(x[:, :1], None if traj.regular else traj.times()[train, :1])
        u = None if traj.u is None else np.nan_to_num(np.asarray(traj.u)[train])
        times = None if traj.regular else traj.times()[train]
        tally = scan(model, x0, traj.graphs, np.asarray(traj.graph_index)[train], u, traj.horizon, times)
        with warnings.catch_warnings():  # a dimension never measured is all NaN: its range is the rollouts'
            warnings.simplefilter("ignore", RuntimeWarning)
            data = {"state_min": np.nanmin(x, axis=(0, 1, 2)).tolist(), "state_max": np.nanmax(x, axis=(0, 1, 2)).tolist()}
        seen = merge(seen, merge(record(tally), data))
    return seen


class Watch:
    """What a stepped model (mpnode.Simulator) receives, checked step by step against its training
    ranges: each quantity that leaves them is warned of once (OffRangeWarning), its first
    departure kept in ``entries``.  Does nothing for a model without recorded ranges."""

    def __init__(self, model, graph, n_copies):
        self.model, self.seen = model, model.attrs.get(KEY)
        self.shape = (n_copies, graph.n_nodes, model.spec.state_dim)
        self.heard = aggregate_inputs(model, batch_graph(graph, n_copies)) if self.seen else None
        self.entries = {}
        if self.seen:
            tally = Tally()
            add_graphs(tally, [graph], np.zeros(1, dtype=np.int64), graph.n_nodes)
            self.warn(tally)

    def __call__(self, z, u, step):
        """Check the full state z (B*N, dx+dm) and the controls u (B*N, du) in the model's units (its
        node attributes their last columns), at output ``step``."""
        if not self.seen:
            return
        tally = Tally()
        dx = self.model.spec.state_dim
        tally.add("state", self.model.denormalize_x(np.asarray(z[:, :dx], dtype=np.float64)).reshape(self.shape), step)
        for name, a in self.heard(z, u).items():
            tally.add(name, a.reshape(self.shape[:2] + (-1,)), step)
        if u is not None:
            units = np.asarray(u, dtype=np.float64) * self.model.u_std + self.model.u_mean
            add_attributes(tally, self.model, units.reshape(self.shape[:2] + (-1,)))
        self.warn(tally)

    def warn(self, tally):
        for e in off_range(self.seen, tally):
            if e["quantity"] not in self.entries:
                self.entries[e["quantity"]] = e
                warnings.warn(f"off the training range: {e['message']}", OffRangeWarning, stacklevel=4)
