"""What `mpnode inspect` shows of trajectory data: sizes, step, graphs, parameters, for data
as they come how regular their times are and how much of each dimension and node was observed,
and for networks as they are the range of the edge weights and of each node attribute."""
import math

import numpy as np


def summarize(traj):
    """A JSON-ready description of ``traj``: sizes, step, dtypes, graphs, parameters, attributes.

    Small arrays (<= 8 entries) in params/aux are shown with their values.
    """
    used = np.bincount(np.asarray(traj.graph_index, dtype=np.int64), minlength=len(traj.graphs))
    return {
        "system": traj.system,
        "B": traj.n_trajectories,
        "T": traj.horizon,
        "N": traj.n_nodes,
        "dx": traj.state_dim,
        "du": traj.control_dim,
        "dt": float(traj.dt),
        "duration": float(traj.dt) * traj.horizon,
        "x_dtype": str(traj.x.dtype),
        "u_dtype": None if traj.u is None else str(traj.u.dtype),
        "graphs": [{"nodes": g.n_nodes, "edges": g.n_edges, "self_loops": bool(g.self_loops),
                    "trajectories": int(used[i])} for i, g in enumerate(traj.graphs)],
        "params": {name: _describe(a) for name, a in traj.params.items()},
        "aux": {name: _describe(a) for name, a in traj.aux.items()},
        "attrs": {key: _jsonable(v) for key, v in traj.attrs.items()},
        "sampling": sampling(traj),
        "weights": weight_range(traj),
        "node_attrs": attr_ranges(traj),
    }


def weight_range(traj):
    """The edge weights of every graph: smallest, largest and the share below zero (a sign the
    user gave, e.g. repression); None for unweighted graphs."""
    if not traj.weighted:
        return None
    w = np.concatenate([g.weights for g in traj.graphs if g.weighted])
    if not w.size:  # weighted graphs without edges
        return {"min": None, "max": None, "negative": 0.0}
    return {"min": float(w.min()), "max": float(w.max()), "negative": round(float(np.mean(w < 0)), 4)}


def attr_ranges(traj):
    """Each node attribute's smallest and largest value over nodes and trajectories, by name
    ({} without attributes)."""
    if traj.node_attrs is None:
        return {}
    a = np.asarray(traj.node_attrs)
    return {name: {"min": float(a[..., k].min()), "max": float(a[..., k].max())}
            for k, name in enumerate(traj.attr_names)}


def sampling(traj):
    """How the data were observed: regular or not, the smallest / median / largest time between
    observations, the trajectories' lengths, and the fraction observed per state dimension and
    per node (1.0 everywhere for complete data)."""
    gaps = np.diff(traj.times(), axis=1)
    gaps = gaps[np.isfinite(gaps)]
    seen = traj.observed()
    inside = np.broadcast_to((np.arange(traj.horizon + 1)[None, :] < traj.lengths[:, None])[:, :, None, None],
                             seen.shape)
    count = inside.sum(axis=(0, 1, 2)).astype(float)
    lengths = traj.lengths - 1
    return {"regular": bool(traj.regular), "gap_min": float(gaps.min()), "gap_median": float(np.median(gaps)),
            "gap_max": float(gaps.max()), "steps_min": int(lengths.min()), "steps_max": int(lengths.max()),
            "observed_per_dim": (seen.sum(axis=(0, 1, 2)) / count).round(4).tolist(),
            "observed_per_node": (seen.sum(axis=(0, 1, 3)) / inside.sum(axis=(0, 1, 3))).round(4).tolist(),
            "unmeasured_dims": traj.unmeasured_dims().tolist(), "truth": traj.truth is not None}


def _describe(a):
    a = np.asarray(a)
    out = {"shape": list(a.shape), "dtype": str(a.dtype)}
    if a.size <= 8:
        out["value"] = _jsonable(a)
    return out


def _jsonable(v):
    """Plain JSON values; NaN/inf become the strings "nan"/"inf" so the output stays valid JSON."""
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, (list, tuple)):
        return [_jsonable(e) for e in v]
    if isinstance(v, np.generic):
        return _jsonable(v.item())
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if isinstance(v, bytes):
        return v.decode("utf-8", errors="replace")
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    return str(v)
