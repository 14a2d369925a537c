"""The rules of the trajectory format (docs/trajectory-format.md), checked in one place.

`validate_trajectories` is the one checker behind the reader, the writer and
`Trajectories.from_arrays`, so a file mpnode writes is always a file mpnode (and any careful
reader) accepts; every violation is an InputError naming the source, the field and the fix.
"""
import math
import numbers

import numpy as np

from mpnode.base.errors import InputError
from mpnode.base.graph import Graph, check_csr

RESERVED_ATTRS = ("format", "format_version", "dt", "system")
#: root attributes that hold a Trajectories field of their own (stored as attributes in the file)
FIELD_ATTRS = ("attr_names",)
#: the most model steps (dt) between two observations: a longer gap would need more RK4 steps than
#: mpnode.engine.schedule allows in one interval
MAX_GAP_STEPS = 1000


def validate_trajectories(traj, source):
    """Raise InputError (naming ``source`` and the field) unless ``traj`` obeys the format.
    Returns ``traj``."""
    _check_dt_and_system(traj, source)
    x = np.asarray(traj.x)
    if x.ndim != 4:
        raise InputError(source, "x", f"has shape {x.shape}", "a 4-D array [B, T+1, N, dx]")
    minimum = (("B", 1, "one trajectory"), ("T+1", 2, "one step"), ("N", 1, "one node"),
               ("dx", 1, "one state dimension"))
    for size, (name, least, meaning) in zip(x.shape, minimum):
        if size < least:
            raise InputError(source, "x", f"has shape {x.shape}, so {name} = {size}",
                             f"{name} >= {least}: at least {meaning}")
    lengths = _check_times(traj, x.shape, source)
    within = np.arange(x.shape[1])[None, :] < lengths[:, None]  # (B, T+1): inside each trajectory
    _check_float_values(x, "x", source, missing_ok=True)
    _check_starts(x, lengths, source)
    if traj.truth is not None:
        truth = np.asarray(traj.truth)
        if truth.shape != x.shape:
            raise InputError(source, "truth", f"has shape {truth.shape}", f"x's shape {x.shape}")
        _check_float_values(truth if within.all() else _inside(truth, within), "truth", source)
    if traj.x_std is not None:
        spread = np.asarray(traj.x_std)
        if spread.shape != x.shape:
            raise InputError(source, "x_std", f"has shape {spread.shape}", f"x's shape {x.shape}")
        _check_float_values(spread if within.all() else _inside(spread, within), "x_std", source)
        if np.any(spread < 0):
            raise InputError(source, "x_std", "has a value < 0", "spreads >= 0 (standard deviations)")
    _check_controls(traj, x.shape, within, source)
    _check_graphs(traj, x.shape, source)
    _check_node_attrs(traj, x.shape, source)
    for key in traj.attrs:
        if key in RESERVED_ATTRS:
            raise InputError(source, key, "is set in attrs, but it is a format attribute",
                             "dt and system as Trajectories fields; format and format_version are written by mpnode")
        if key in FIELD_ATTRS:
            raise InputError(source, key, "is set in attrs, but it names the node attributes",
                             f"{key}= beside node_attrs=, not in attrs")
    _check_names(traj.attrs.get("state_names"), "state_names", x.shape[3], source)
    _check_names(traj.attrs.get("state_groups"), "state_groups", x.shape[3], source)
    if traj.u is not None:
        _check_names(traj.attrs.get("control_names"), "control_names", np.shape(traj.u)[3], source)
    return traj


def needs_version_2(traj):
    """Whether ``traj`` needs format version 2 (observation times, missing values or a truth);
    anything else is written as version 1, which every reader knows."""
    return traj.t is not None or traj.truth is not None or bool(np.isnan(np.asarray(traj.x)).any())


def needs_version_3(traj):
    """Whether ``traj`` needs format version 3 (edge weights or node attributes)."""
    return traj.node_attrs is not None or any(g.weighted for g in traj.graphs)


def required_version(traj):
    """The lowest format version that holds ``traj``: 1, 2 or 3.  Writing no newer version than
    the data need keeps every file readable by as many (older) readers as possible."""
    return 3 if needs_version_3(traj) else 2 if needs_version_2(traj) else 1


def _check_dt_and_system(traj, source):
    dt = traj.dt
    is_number = isinstance(dt, numbers.Real) and not isinstance(dt, (bool, np.bool_))
    if not (is_number and math.isfinite(dt) and dt > 0):
        raise InputError(source, "dt", f"is {dt!r}", "a finite number > 0")
    if not storable_text(traj.system) or not traj.system.strip():
        raise InputError(source, "system", f"is {traj.system!r}",
                         "a non-empty string naming the system, e.g. 'lorenz' (no NUL character)")


def _check_times(traj, shape, source):
    """The observation times' rules; returns each trajectory's number of observations."""
    B, T1 = shape[:2]
    if traj.t is None:
        return np.full(B, T1, dtype=np.int64)
    t = np.asarray(traj.t)
    if t.shape != (B, T1) or t.dtype.kind != "f":
        raise InputError(source, "t", f"has shape {t.shape} and dtype {t.dtype}",
                         f"float observation times of shape [B, T+1] = [{B}, {T1}]")
    if np.isinf(t).any():
        b, k = (int(i) for i in np.argwhere(np.isinf(t))[0])
        raise InputError(source, "t", f"is {t[b, k]} at [{b}, {k}]", "finite times (NaN only to end a shorter trajectory)")
    finite = np.isfinite(t)
    lengths = finite.sum(axis=1)
    ragged = finite != (np.arange(T1)[None, :] < lengths[:, None])
    if ragged.any():
        b = int(np.argmax(ragged.any(axis=1)))
        raise InputError(source, "t", f"trajectory {b} has a NaN time before a finite one",
                         "finite times, then NaN only after the trajectory's last observation")
    if (lengths < 2).any():
        b = int(np.argmax(lengths < 2))
        raise InputError(source, "t", f"trajectory {b} has {lengths[b]} observation time(s)",
                         "at least two observation times per trajectory")
    gaps = np.diff(t, axis=1)
    if (gaps[np.isfinite(gaps)] <= 0).any():
        b, k = (int(i) for i in np.argwhere(np.isfinite(gaps) & (gaps <= 0))[0])
        raise InputError(source, "t", f"trajectory {b} goes from {t[b, k]:g} to {t[b, k + 1]:g} at step {k}",
                         "strictly increasing times (sort the observations; merge repeated ones)")
    longest = np.nanmax(gaps) if np.isfinite(gaps).any() else 0.0
    if longest > MAX_GAP_STEPS * traj.dt * (1 + 1e-9):
        b, k = (int(i) for i in np.argwhere(gaps == longest)[0])
        raise InputError(source, "t", f"trajectory {b} has a gap of {longest:g} after step {k}, "
                         f"{longest / traj.dt:.0f} times dt = {traj.dt:g}",
                         f"gaps of at most {MAX_GAP_STEPS} dt: split the trajectory at the gap, or a larger dt")
    return lengths.astype(np.int64)


def _check_starts(x, lengths, source):
    """Every trajectory observed at its start (something to start a prediction from)."""
    blank = ~np.isfinite(x[:, 0]).any(axis=(1, 2))
    if blank.any():
        b = int(np.argmax(blank))
        raise InputError(source, "x", f"trajectory {b} has nothing observed at its first time",
                         "at least one observed value at each trajectory's first observation time")


def _check_controls(traj, shape, within, source):
    if traj.u is None:
        return
    B, T1, N = shape[:3]
    u = np.asarray(traj.u)
    if u.ndim != 4 or u.shape[:3] != (B, T1 - 1, N) or u.shape[3] < 1:
        raise InputError(source, "u", f"has shape {u.shape}",
                         f"[B, T, N, du] = [{B}, {T1 - 1}, {N}, du >= 1] to match x; omit u when there are no controls")
    held = within[:, 1:]  # u[b, k] is held from observation k to k+1: both inside the trajectory
    _check_float_values(u if held.all() else _inside(u, held), "u", source)


def _check_graphs(traj, shape, source):
    B, N = shape[0], shape[2]
    graphs = traj.graphs
    if not isinstance(graphs, (list, tuple)) or not graphs:
        raise InputError(source, "graphs", f"is {graphs!r}", "a non-empty list of graphs (graphs/0, graphs/1, ...)")
    for g, graph in enumerate(graphs):
        if not isinstance(graph, Graph):
            raise InputError(source, f"graphs/{g}", f"is a {type(graph).__name__}", "an mpnode.Graph")
        check_csr(graph.indptr, graph.indices, N, graph.self_loops, source, f"graphs/{g}", graph.weights)
        if graph.weighted != graphs[0].weighted:
            weighted, plain = (g, 0) if graph.weighted else (0, g)
            raise InputError(source, f"graphs/{plain}", f"has no weights, but graphs/{weighted} has",
                             "weights on every graph of a set, or on none (give an unweighted graph weights of 1)")
    gi = np.asarray(traj.graph_index)
    if gi.shape != (B,):
        raise InputError(source, "graph_index", f"has shape {gi.shape}",
                         f"shape ({B},): one graph number per trajectory")
    if gi.dtype.kind not in "iu":
        raise InputError(source, "graph_index", f"has dtype {gi.dtype}", "an integer dtype")
    bad = (gi < 0) | (gi >= len(graphs))
    if np.any(bad):
        b = int(np.argmax(bad))
        raise InputError(source, "graph_index",
                         f"trajectory {b} names graph {gi[b]}, but there are {len(graphs)} graph(s)",
                         f"values in 0..{len(graphs) - 1}")


def _check_node_attrs(traj, shape, source):
    """Static attributes: (B, N, dp) finite floats with dp distinct names."""
    B, N = shape[0], shape[2]
    if traj.node_attrs is None:
        if traj.attr_names is not None:
            raise InputError(source, "attr_names", "is given, but there are no node_attrs",
                             "node_attrs (B, N, dp) beside the names, or no attr_names")
        return
    a = np.asarray(traj.node_attrs)
    if a.ndim == 4:
        raise InputError(source, "node_attrs", f"has shape {a.shape}, 4-D as if it changed in time, but node "
                         "attributes are static", f"one row per trajectory and node, [B, N, dp] = [{B}, {N}, dp] "
                         "(what changes in time belongs in x, or in the controls u)")
    if a.ndim != 3 or a.shape[:2] != (B, N) or a.shape[2] < 1:
        raise InputError(source, "node_attrs", f"has shape {a.shape}",
                         f"[B, N, dp] = [{B}, {N}, dp >= 1] to match x (or [N, dp] shared by every trajectory)")
    _check_float_values(a, "node_attrs", source)
    if traj.attr_names is None:
        raise InputError(source, "attr_names", "is missing", f"a list of {a.shape[2]} names, one per attribute")
    _check_names(traj.attr_names, "attr_names", a.shape[2], source)
    names = [traj.attr_names] if isinstance(traj.attr_names, str) else list(traj.attr_names)
    twice = [n for k, n in enumerate(names) if n in names[:k]]
    if twice:
        raise InputError(source, "attr_names", f"names {twice[0]!r} twice", "a different name for each attribute")


def _inside(a, inside):
    """``a`` with what lies past each trajectory's end set to 0 (the rules do not apply there)."""
    if a.dtype.kind != "f":
        return a  # the dtype check names it
    return np.where(inside[:, :, None, None], a, a.dtype.type(0))


def storable_text(text):
    """Whether ``text`` is a string HDF5 can store: UTF-8, without NUL characters."""
    if not isinstance(text, str) or "\x00" in text:
        return False
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:  # an unpaired surrogate
        return False
    return True


def _check_names(names, key, size, source):
    """Optional attribute ``key``: one non-empty string per state (control) dimension."""
    if names is None:
        return
    names = [names] if isinstance(names, str) else names
    ok = isinstance(names, (list, tuple, np.ndarray)) and len(names) == size \
        and all(storable_text(n) and n.strip() for n in names)
    if not ok:
        raise InputError(source, key, f"is {names!r}", f"a list of {size} non-empty strings, one per dimension")


def _check_float_values(a, name, source, missing_ok=False):
    """float32/float64 and finite (NaN allowed for a value not observed when ``missing_ok``);
    a violation names the first bad index."""
    if a.dtype.kind != "f" or a.dtype.itemsize not in (4, 8):
        raise InputError(source, name, f"has dtype {a.dtype}", "float32 or float64")
    bad = np.isinf(a) if missing_ok else ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        expected = ("finite values, or NaN for a value that was not observed" if missing_ok
                    else "finite values only (no NaN / inf)")
        raise InputError(source, name, f"contains {a[idx]} at {list(idx)}", expected)
