"""Trajectories from a NumPy .npz archive: the layout `mpnode convert` reads.

Arrays saved with ``np.savez(path, x=x, edges=edges, dt=0.05, system="springs")`` are the
most common way data leave another simulator or an experiment.  The keys (KEYS below, also
in `mpnode convert --help` and the README) map onto the trajectory format one to one; the
graph may be an edge list or CSR arrays, one graph or several.  Every problem is an
InputError naming the archive and the key.  Nothing is guessed: a key that is not part of
the layout is kept (a scalar as a root attribute, an array under ``aux/``), never dropped.
"""
import os
import re
import zipfile
import zlib

import numpy as np

from mpnode.base.errors import InputError
from mpnode.base.graph import Graph, as_graph, check_csr
from mpnode.base.h5 import one_line

from .trajectories import Trajectories

#: key -> what it holds (the documentation of the layout, in one place)
KEYS = {
    "x": "(B, T+1, N, dx) float: node states (node i is x[:,:,i]; x[b,0] the first observation); NaN where a "
         "value was not observed (required)",
    "u": "(B, T, N, du) float: controls held from one saved state to the next (optional)",
    "dt": "number: time between saved states; with uneven times t the model's step (default: their median gap)",
    "t": "(T+1,) or (B, T+1) float: times of the saved states, shared or per trajectory, strictly increasing; "
         "NaN at the end of a shorter trajectory (optional; evenly spaced times give dt)",
    "system": "string: a name for the system (required unless --system gives it)",
    "edges": "(E, 2) int: the graph as (sender, receiver) pairs, node ids 0..N-1: the receiver hears the sender",
    "directed": "0/1: the edge lists are one-way (default 0: each pair joins both ways)",
    "n_nodes": "int: N, checked against x (optional)",
    "indptr, indices": "(N+1,), (E,) int: the graph as CSR instead: node i hears indices[indptr[i]:indptr[i+1]]",
    "edges_0, edges_1, ... (or indptr_0 + indices_0, ...)": "several graphs, with graph_index",
    "graph_index": "(B,) int: the graph of each trajectory (required with several graphs)",
    "state_names, control_names": "(dx,), (du,) strings: names of the dimensions, used by the figures (optional)",
    "anything else": "kept: a scalar as a root attribute, an array under aux/",
}
_NUMBERED = re.compile(r"^(edges|indptr|indices)_(\d+)$")
_GRAPH = ("edges", "indptr", "indices", "directed", "n_nodes")


def read_npz(path, dt=None, system=None):
    """The Trajectories held by the .npz archive ``path`` (layout: KEYS), validated.

    dt, system : used when the archive has no ``dt`` (nor ``t``) or no ``system`` key; an
    archive whose key disagrees with them is an error.  Raises InputError naming ``path``
    and the key.
    """
    source = os.fspath(path)
    arrays = _load(source)
    if "x" not in arrays:
        raise InputError(source, "x", f"is missing (keys: {', '.join(sorted(arrays)) or 'none'})",
                         "the states as key x, shape (B, T+1, N, dx)")
    x = arrays.pop("x")
    if x.ndim != 4:
        raise InputError(source, "x", f"has shape {x.shape}", "a 4-D array (B, T+1, N, dx) (one trajectory: x[None])")
    attrs = {}
    step, times = _dt(arrays, dt, x.shape, attrs, source)
    name = _system(arrays, system, source)
    graphs = _graphs(arrays, x.shape[2], source)
    for key in ("state_names", "control_names"):
        if key in arrays:
            names = arrays.pop(key)
            attrs[key] = names.tolist() if names.dtype.kind in "US" and names.ndim == 1 else names
    u, graph_index = arrays.pop("u", None), arrays.pop("graph_index", None)
    aux = {}
    for key, a in arrays.items():  # the rest is kept, never dropped
        if a.ndim == 0:
            attrs[key] = a.item() if a.dtype.kind != "S" else a.item().decode("utf-8", "replace")
        else:
            aux[key] = a
    return Trajectories.from_arrays(x, graphs, step, name, u=u, graph_index=graph_index, attrs=attrs, aux=aux,
                                    t=times, source=source)


def _load(source):
    """Every array of the archive, read now (a damaged member is named by its key)."""
    try:
        with open(source, "rb") as f:
            magic = f.read(6)
        z = np.load(source, allow_pickle=False) if magic[:2] in (b"PK", b"\x93N") else None
    except FileNotFoundError:
        raise InputError(source, "file", "does not exist", "an existing .npz file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(source, "file", f"cannot be read as .npz ({one_line(e)})",
                         "a NumPy archive written by np.savez or np.savez_compressed") from None
    if z is None:
        raise InputError(source, "file", "is not a NumPy archive (it does not start like a zip file)",
                         "a .npz file written by np.savez or np.savez_compressed")
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(source, "file", "holds a single array (.npy), not named arrays",
                         "an .npz archive: np.savez(path, x=x, edges=edges, dt=dt, system=name)")
    arrays = {}
    with z:
        for key in z.files:
            try:
                arrays[key] = z[key]
            except ValueError as e:
                if "allow_pickle" not in str(e):
                    raise InputError(source, key, f"cannot be read ({one_line(e)})",
                                     "an intact .npz archive") from None
                raise InputError(source, key, "holds Python objects (an object array, stored with pickle)",
                                 "numbers or strings, e.g. np.asarray(value, dtype=float)") from None
            except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as e:
                raise InputError(source, key, f"cannot be read ({one_line(e)})", "an intact .npz archive") from None
    return arrays


def _scalar(arrays, key, kinds, source, meaning):
    """arrays[key] (removed) as one Python value of a dtype kind in ``kinds``; None when absent."""
    if key not in arrays:
        return None
    a = arrays.pop(key)
    if a.size != 1 or a.dtype.kind not in kinds:
        raise InputError(source, key, f"is a {a.dtype} array of shape {a.shape}", meaning)
    v = a.reshape(()).item()
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else v


def _agree(key, value, option, source):
    """The archive's ``value`` or the option's; when both are given they must agree."""
    if value is None or option is None:
        return option if value is None else value
    same = np.isclose(value, option, rtol=1e-9, atol=0) if key == "dt" else value == option
    if not same:
        raise InputError(source, key, f"is {value!r} in the archive but --{key} says {option!r}",
                         f"no --{key}, or the same value")
    return value


def _dt(arrays, option, shape, attrs, source):
    """(dt, t): dt from the key dt, the times t or the --dt option; t the times when they are not
    evenly spaced (None when they are: the file is then regular)."""
    dt = _scalar(arrays, "dt", "iuf", source, "one number > 0: the time between saved states")
    dt = None if dt is None else float(dt)
    times = None
    if "t" in arrays:
        times = _times(arrays.pop("t"), shape, source)
        steps = shape[1] - 1
        step = (times[:, -1] - times[:, 0]) / steps
        # within 0.1 % of one step: float32 times are that uneven, a real change of rate is not
        even = (np.isfinite(times).all() and np.all(step > 0) and np.allclose(step, step[0], rtol=1e-3, atol=0)
                and np.all(np.abs(np.diff(times, axis=1) - step[:, None]) <= 1e-3 * step[:, None])
                and np.all(times[:, 0] == times[0, 0]))
        if even:
            if dt is not None and not np.isclose(dt, step[0], rtol=1e-3, atol=0):
                raise InputError(source, "dt", f"is {dt:g} but the times t are {step[0]:g} apart", "dt and t to agree")
            dt = float(dt if dt is not None else step[0])
            if times[0, 0] != 0:
                attrs["t0"] = float(times[0, 0])
            times = None
    dt = _agree("dt", dt, option, source)
    if dt is None and times is None:
        raise InputError(source, "dt", "is missing", "a key dt (the time between saved states), a key t, or --dt")
    return dt, times


def _times(t, shape, source):
    """The key t as (B, T+1) float64: the times of x's saved states, shared (T+1,) or per trajectory."""
    if t.dtype.kind not in "iuf" or t.shape not in ((shape[1],), tuple(shape[:2])):
        raise InputError(source, "t", f"is a {t.dtype} array of shape {t.shape}",
                         f"the times of x's {shape[1]} saved states, shape ({shape[1]},) or ({shape[0]}, {shape[1]})")
    return np.array(np.broadcast_to(t.astype(np.float64), tuple(shape[:2])))


def _system(arrays, option, source):
    name = _scalar(arrays, "system", "US", source, "one string naming the system, e.g. np.str_('springs')")
    name = _agree("system", name, option, source)
    if name is None:
        raise InputError(source, "system", "is missing", "a string key system naming the system, or --system")
    return name


def _graphs(arrays, n, source):
    """The archive's graph(s) as a list of Graph (keys edges / indptr+indices, or numbered)."""
    directed = _scalar(arrays, "directed", "biu", source, "0 or 1 (true or false)")
    if directed not in (None, 0, 1):
        raise InputError(source, "directed", f"is {directed!r}", "0 or 1 (true or false)")
    given_n = _scalar(arrays, "n_nodes", "iu", source, "one integer: the number of nodes N")
    if given_n is not None and given_n != n:
        raise InputError(source, "n_nodes", f"is {given_n} but x has N = {n} nodes (its third axis)",
                         "n_nodes equal to x.shape[2], or no n_nodes")
    numbered = sorted({int(m.group(2)) for m in map(_NUMBERED.match, arrays) if m})
    single = [k for k in ("edges", "indptr", "indices") if k in arrays]
    if numbered and single:
        raise InputError(source, single[0], "is given together with numbered graphs (edges_0, ...)",
                         "one graph as edges (or indptr/indices), or several as edges_0, edges_1, ...")
    if numbered:
        if numbered != list(range(len(numbered))):
            raise InputError(source, "edges_0", f"the numbered graphs are {numbered}",
                             f"graphs numbered 0..{len(numbered) - 1} with no gaps")
        return [_one_graph(arrays, f"_{g}", n, bool(directed), source) for g in numbered]
    if not single:
        raise InputError(source, "edges", "is missing: the archive has no graph (no edges, no indptr and indices)",
                         "edges (E, 2) of (sender, receiver) pairs, or CSR indptr and indices")
    return [_one_graph(arrays, "", n, bool(directed), source)]


def _one_graph(arrays, suffix, n, directed, source):
    """edges{suffix} or indptr{suffix} + indices{suffix} (removed from ``arrays``) as a Graph."""
    e, ip, ix = (f"edges{suffix}", f"indptr{suffix}", f"indices{suffix}")
    if e in arrays:
        if ip in arrays or ix in arrays:
            raise InputError(source, e, f"is given together with {ip if ip in arrays else ix}",
                             "each graph either as an edge list or as CSR, not both")
        return as_graph(arrays.pop(e), n, directed, source, e)
    for key in (ip, ix):
        if key not in arrays:
            raise InputError(source, key, "is missing", f"CSR graphs need both {ip} and {ix} (or give {e})")
    indptr, indices = arrays.pop(ip), arrays.pop(ix)
    for key, a in ((ip, indptr), (ix, indices)):
        if a.size and a.dtype.kind not in "iu":
            raise InputError(source, key, f"has dtype {a.dtype}", "integer node ids / offsets")
    try:
        check_csr(indptr, indices, n, True, source, "csr")
    except InputError as err:  # name the archive's key, not the format's
        key = ip if err.field.endswith("indptr") else ix
        raise InputError(source, key, err.problem, err.expected) from None
    rows = np.repeat(np.arange(n), np.diff(indptr))
    return Graph(indptr, indices, self_loops=bool(np.any(rows == indices)))
