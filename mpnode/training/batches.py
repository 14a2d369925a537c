"""Training data made ready for the engine: checks, the split, normalisation, noise, windows, batches.

Everything is decided once per run and depends only on the data and the seed, so that a
resumed run sees exactly the data of an uninterrupted one.  Batches: every batch comes
from one file (one node count N per file, so one block-diagonal graph per batch); each
epoch shuffles every file's training trajectories, cuts them into batches and shuffles
the order of all batches together, so several files are interleaved in proportion to
their size.  The shuffle of epoch e depends only on (seed, e).

Horizon windows (the curriculum of `mpnode.training`): every training trajectory of T steps
is cut into consecutive windows of w steps, each starting from its own (noisy) true
state: starts 0, w, 2w, ... and, when w does not divide T, one last window ending at T
(overlapping the one before), so every transition is trained on and the epoch is
deterministic; random windows would add sampling noise for no gain in coverage.
"""
import functools
import json
import math
import zlib
from typing import NamedTuple

import numpy as np

from mpnode.base.errors import InputError
from mpnode.model import batch_graph
from mpnode.model.inputs import attr_names_of, attrs_as_controls, weight_scale, without_attrs
from mpnode.model.renormalise import renormalised

from .learnable import check_learnable


def check_same_kind(datasets, sources):
    """Several training files must agree on dx, du and dt (graphs and N may differ)."""
    first, src0 = datasets[0], sources[0]
    for traj, src in zip(datasets[1:], sources[1:]):
        for what, a, b in (("x", traj.state_dim, first.state_dim), ("u", traj.control_dim, first.control_dim)):
            if a != b:
                raise InputError(src, what, f"has {a} dimensions per node but {src0} has {b}",
                                 "files of one system (same dx and du)")
        if not math.isclose(traj.dt, first.dt, rel_tol=1e-9, abs_tol=0.0):
            raise InputError(src, "dt", f"is {traj.dt:g} but {src0} has dt = {first.dt:g}", "the same dt in every file")


def split_indices(n, val_split, seed, file_index=0):
    """A random (train, val) split of range(n), the same for the same (n, val_split, seed, file).

    round(val_split * n) trajectories go to validation, but at least one trajectory stays
    in training.  Returns two sorted int64 arrays.
    """
    rng = np.random.default_rng([seed, 2, file_index])
    perm = rng.permutation(n)
    n_val = min(int(round(val_split * n)), n - 1)
    return np.sort(perm[n_val:]).astype(np.int64), np.sort(perm[:n_val]).astype(np.int64)


def split_by_graphs(graph_index, n_graphs, val_graphs, seed, file_index=0):
    """A (train, val) split that holds out ``val_graphs`` whole graphs (chosen from the seed):
    the validation trajectories are those that ran on them, so the best model is the one
    that generalises to graphs it has not seen.  Returns (train idx, val idx, held graphs)."""
    rng = np.random.default_rng([seed, 4, file_index])
    held = np.sort(rng.permutation(n_graphs)[:val_graphs])
    on_held = np.isin(np.asarray(graph_index), held)
    return (np.flatnonzero(~on_held).astype(np.int64), np.flatnonzero(on_held).astype(np.int64),
            [int(g) for g in held])


def split_settings(config):
    """What decides the split, the noise, the resample and the shuffles: two configurations that
    agree on it see the same data."""
    return (config.seed, config.split_by, config.val_split, config.val_graphs, config.noise, config.bootstrap)


def make_split(datasets, config):
    """Every file's (train idx, val idx): whole graphs held out (config.val_graphs) in files
    with more graphs than that, a random fraction (config.val_split) otherwise."""
    out = []
    for f, traj in enumerate(datasets):
        if config.val_graphs and len(traj.graphs) > config.val_graphs:
            out.append(split_by_graphs(traj.graph_index, len(traj.graphs), config.val_graphs, config.split_by, f)[:2])
        else:
            out.append(split_indices(traj.n_trajectories, config.val_split, config.split_by, f))
    return out


def bootstrap_sample(train, seed, file_index=0):
    """As many of the training trajectories ``train`` as there are, drawn with replacement (an
    ensemble member's resample: members that see different data disagree where data are thin)."""
    rng = np.random.default_rng([seed, 6, file_index])
    return np.sort(rng.choice(train, size=len(train), replace=True)).astype(np.int64)


def fit_normalization(arrays):
    """Per-dimension mean and std over the observed entries of ``arrays`` (each (..., d); NaN: not
    observed).  A dimension with zero spread gets std 1, one observed nowhere mean 0 and std 1
    (a hidden state: the model chooses its scale).  Returns (mean, std), float64 shape (d,)."""
    flat = [a.reshape(-1, a.shape[-1]) for a in arrays]
    seen = [~np.isnan(a) for a in flat]
    count = sum(s.sum(axis=0) for s in seen)
    total = sum(np.where(s, a, 0).sum(axis=0, dtype=np.float64) for a, s in zip(flat, seen))
    mean = total / np.maximum(count, 1)
    sq = sum(np.where(s, (a - mean) ** 2, 0).sum(axis=0) for a, s in zip(flat, seen))
    std = np.sqrt(sq / np.maximum(count, 1))
    std[~(std > 1e-12 * np.maximum(1.0, np.abs(mean)))] = 1.0
    return mean, std


def fingerprint(datasets):
    """A JSON string identifying the training data (shapes, dt, checksums), for resume."""
    out = []
    for traj in datasets:
        x = np.ascontiguousarray(traj.x)
        out.append({"shape": list(x.shape), "du": traj.control_dim, "dt": float(traj.dt),
                    "x_crc": zlib.crc32(x.view(np.uint8)),
                    "graphs": [zlib.crc32(np.ascontiguousarray(g.indices).view(np.uint8)) for g in traj.graphs]})
    return json.dumps(out, sort_keys=True)


class Batch(NamedTuple):
    """What the engine trains on: x (T+1, M, dx) normalised, NaN where not observed; u (T, M, du)
    or None; the block-diagonal graph; intervals (T, M) between observations, or None (every dt)."""

    x: np.ndarray
    u: np.ndarray
    graph: object
    intervals: np.ndarray


class Part:
    """Trajectories of one file on one side of the split, normalised and time-major for the engine.

    x : ndarray, shape (T+1, B, N, dx), model dtype, NaN where not observed;  u : (T, B, N, du) or None
    iv : (T, B) time between consecutive observations (0 after a trajectory's end), or None when
        the file is regular (every dt)
    gi : ndarray, shape (B,), each trajectory's graph;  graphs : the file's graphs
    index : ndarray, shape (B,), each trajectory's number in its file
    source : the file's name (validation figures are reported per file)
    """

    def __init__(self, x, u, gi, graphs, index, source=None, iv=None):
        self.x, self.u, self.gi, self.graphs, self.index, self.source = x, u, gi, graphs, index, source
        self.iv = iv
        self.n = x.shape[1]
        self.n_nodes = x.shape[2]
        self.single_graph = len(graphs) == 1 or len(np.unique(gi)) <= 1

    @classmethod
    def of_file(cls, traj, idx, model, noise_std=0.0, rng=None, source=None):
        """Trajectories ``idx`` of ``traj``, normalised with ``model``'s constants, plus Gaussian noise."""
        x = model.normalize_x(np.asarray(traj.x)[idx])
        if noise_std > 0 and len(idx):
            x = (x + rng.standard_normal(x.shape) * noise_std).astype(model.dtype)
        u = None
        if traj.u is not None:
            u = np.nan_to_num(model.normalize_u(np.asarray(traj.u)[idx]), nan=0.0)  # past a trajectory's end
            u = np.ascontiguousarray(u.transpose(1, 0, 2, 3))
        iv = None if traj.regular else np.ascontiguousarray(traj.intervals()[idx].T)
        return cls(np.ascontiguousarray(x.transpose(1, 0, 2, 3)), u, np.asarray(traj.graph_index)[idx],
                   traj.graphs, idx, source, iv)

    def windows(self, window):
        """The windows of ``window`` steps of every trajectory (module docstring) as a new Part:
        window j of trajectory b becomes trajectory b * n_windows + j."""
        t1, b, n, dx = self.x.shape
        starts = window_starts(t1 - 1, window)
        w, nw = min(window, t1 - 1), len(starts)

        def cut(a, steps):  # (steps of each window, b * nw, ...)
            return np.ascontiguousarray(np.stack([a[s:s + steps] for s in starts], axis=2)).reshape(
                (steps, b * nw) + a.shape[2:])

        return Part(cut(self.x, w + 1), None if self.u is None else cut(self.u, w), np.repeat(self.gi, nw),
                    self.graphs, np.repeat(self.index, nw), self.source, None if self.iv is None else cut(self.iv, w))

    def batch(self, sel):
        """The Batch of local trajectory numbers ``sel``.

        Trajectories are grouped by graph inside the batch (the loss is a sum, so order is
        free): runs of copies of one small graph let the kernels aggregate densely.
        """
        if not self.single_graph:
            sel = sel[np.argsort(self.gi[sel], kind="stable")]
        b = len(sel)
        t1, _, n, dx = self.x.shape
        x = np.take(self.x, sel, axis=1).reshape(t1, b * n, dx)
        u = None if self.u is None else np.take(self.u, sel, axis=1).reshape(t1 - 1, b * n, -1)
        iv = None if self.iv is None else np.repeat(self.iv[:, sel], n, axis=1)
        return Batch(x, u, self.graph(sel), iv)

    def graph(self, sel):
        """The batch's block-diagonal graph (copies of one graph come from batch_graph's cache)."""
        if self.single_graph:
            return batch_graph(self.graphs[int(self.gi[0])] if len(self.gi) else self.graphs[0], len(sel))
        return batch_graph([self.graphs[int(i)] for i in self.gi[sel]], len(sel))


class TrainingData:
    """The training files made ready once: checked, split, fingerprinted, with the statistics a
    new model takes from its training split (normalisation, mean in-degree).

    datasets : list of Trajectories, node attributes as their last controls (mpnode.model.inputs)
    sources : their names (for messages)
    split : list of (train idx, val idx) per file (`make_split`)
    attr_names : the node attributes' names;  weight_scale : the edge weights' mean size, or None
    """

    def __init__(self, datasets, config, sources=None):
        datasets = list(datasets)
        if not datasets:
            raise InputError("training data", "files", "none given", "at least one trajectory file")
        self.sources = list(sources or [f"data[{i}]" for i in range(len(datasets))])
        if config.ignore_attrs:
            datasets = [without_attrs(traj) for traj in datasets]
        self.attr_names = attr_names_of(datasets, self.sources)
        self.weight_scale = weight_scale(datasets)
        self.datasets = [attrs_as_controls(traj) for traj in datasets]
        check_same_kind(self.datasets, self.sources)
        self.seed, self.noise, self.bootstrap = config.seed, config.noise, config.bootstrap
        self.split_settings = split_settings(config)
        self.split = make_split(self.datasets, config)
        self.fingerprint = fingerprint(self.datasets)
        check_learnable(self, config)

    def training(self, field):
        """Every file's training trajectories of ``field`` ("x" or "u"), NaN where not observed."""
        out = []
        for traj, (tr, _) in zip(self.datasets, self.split):
            a = np.asarray(getattr(traj, field))[tr]
            if not traj.regular:  # past a trajectory's end nothing counts
                inside = np.arange(a.shape[1])[None, :] < (traj.lengths[tr] - (field == "u"))[:, None]
                a = np.where(inside[:, :, None, None], a, np.nan)
            out.append(a)
        return out

    @functools.cached_property
    def _normalization(self):
        x_mean, x_std = fit_normalization(self.training("x"))
        if not self.datasets[0].control_dim:
            return x_mean, x_std, None, None
        return (x_mean, x_std) + fit_normalization(self.training("u"))

    def normalization(self):
        """(x_mean, x_std, u_mean, u_std) of the training split (u's None without controls), copies."""
        return tuple(None if a is None else a.copy() for a in self._normalization)

    def unmeasured_dims(self):
        """The state dimensions the training split observes nowhere (hidden states of the model)."""
        return np.flatnonzero(np.all([np.isnan(a).all(axis=(0, 1, 2)) for a in self.training("x")], axis=0))

    def mean_in_degree(self, self_messages):
        """The mean in-degree over every node of every training trajectory (+1 when nodes hear
        themselves): the ``scaled`` aggregation's divisor."""
        total = count = 0
        for traj, (tr, _) in zip(self.datasets, self.split):
            used = np.bincount(np.asarray(traj.graph_index)[tr], minlength=len(traj.graphs))
            for g, times in zip(traj.graphs, used):
                total += times * (g.n_edges + (g.n_nodes if self_messages else 0))
                count += times * g.n_nodes
        return total / count

    def parts(self, model, norm):
        """(train parts, val parts) of every file, normalised with ``model``'s constants after
        ``norm`` set them: "fit" (the training split's), "refit" (the same, the weights changed
        so that the model computes what it did: mpnode.model.renormalise) or "keep".
        Modifies ``model`` unless "keep"; files without validation trajectories have no val part.
        With ``bootstrap``, each file's training part is a resample of its training trajectories
        (the normalisation stays the whole training split's)."""
        if norm in ("fit", "refit"):
            x_mean, x_std, u_mean, u_std = self.normalization()
            if u_mean is None:
                u_mean, u_std = model.u_mean, model.u_std
            if norm == "refit":
                model.theta[:] = renormalised(model, x_mean, x_std, u_mean, u_std).theta
            model.x_mean, model.x_std, model.u_mean, model.u_std = x_mean, x_std, u_mean, u_std
        train, val = [], []
        for f, (traj, (tr, va)) in enumerate(zip(self.datasets, self.split)):
            rng = np.random.default_rng([self.seed, 3, f])
            drawn = bootstrap_sample(tr, self.seed, f) if self.bootstrap and len(tr) else tr
            train.append(Part.of_file(traj, drawn, model, self.noise, rng, self.sources[f]))
            if len(va):
                val.append(Part.of_file(traj, va, model, source=self.sources[f]))
        return train, val


def window_starts(horizon, window):
    """Start steps of the windows of ``window`` steps covering 0..horizon (module docstring).

    Consecutive windows 0, w, 2w, ...; when w does not divide T a last window ends at T.
    ``window >= horizon`` gives the whole trajectory: [0].
    """
    if window >= horizon:
        return np.zeros(1, dtype=np.int64)
    starts = list(range(0, horizon - window + 1, window))
    if starts[-1] + window < horizon:
        starts.append(horizon - window)
    return np.asarray(starts, dtype=np.int64)


def epoch_batches(parts, batch_size, seed, epoch):
    """The batches of one epoch: list of (part number, local indices), shuffled."""
    rng = np.random.default_rng([seed, 1, epoch])
    out = []
    for p, part in enumerate(parts):
        perm = rng.permutation(part.n)
        out += [(p, perm[i:i + batch_size]) for i in range(0, part.n, batch_size)]
    order = rng.permutation(len(out))
    return [out[i] for i in order]
