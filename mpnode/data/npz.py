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
from mpnode.base.graph import Graph, as_graph, check_csr, check_weights
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
    "edges": "(E, 2) int: the graph as (sender, receiver) pairs, node ids 0..N-1: the receiver hears the sender; "
             "or (E, 3): (sender, receiver, weight) triples, a weighted graph",
    "directed": "0/1: the edge lists are one-way (default 0: each pair joins both ways)",
    "n_nodes": "int: N, checked against x (optional)",
    "indptr, indices": "(N+1,), (E,) int: the graph as CSR instead: node i hears indices[indptr[i]:indptr[i+1]]",
    "weights": "(E,) float: edge weights, one per pair of edges (both directions get it unless directed) or per "
               "entry of indices; finite, negative allowed; duplicate pairs add their weights (optional)",
    "edges_0, edges_1, ... (or indptr_0 + indices_0, ...; weights_0, ...)": "several graphs, with graph_index; "
                                                                          "weighted all, or none",
    "graph_index": "(B,) int: the graph of each trajectory (required with several graphs)",
    "node_attrs": "(B, N, dp) or (N, dp) float: static attributes of each node, per trajectory or shared by all "
                  "(optional)",
    "attr_names": "(dp,) strings: the attributes' names (optional; default attr 1, attr 2, ...)",
    "state_names, control_names": "(dx,), (du,) strings: names of the dimensions, used by the figures (optional)",
    "state_groups": "(dx,) strings: the group of each state dimension; mpnode eval reports each group's error "
                    "(optional)",
    "anything else": "kept: a scalar as a root attribute, an array under aux/",
}
_NUMBERED = re.compile(r"^(edges|indptr|indices)_(\d+)$")
_WEIGHTS = re.compile(r"^weights(_\d+)?$")


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
    for key in ("state_names", "state_groups", "control_names"):
        if key in arrays:
            attrs[key] = _names(arrays.pop(key))
    u, graph_index = arrays.pop("u", None), arrays.pop("graph_index", None)
    node_attrs, attr_names = arrays.pop("node_attrs", None), arrays.pop("attr_names", None)
    aux = {}
    for key, a in arrays.items():  # the rest is kept, never dropped
        if a.ndim == 0:
            attrs[key] = a.item() if a.dtype.kind != "S" else a.item().decode("utf-8", "replace")
        else:
            aux[key] = a
    return Trajectories.from_arrays(x, graphs, step, name, u=u, graph_index=graph_index, attrs=attrs, aux=aux,
                                    t=times, node_attrs=node_attrs,
                                    attr_names=None if attr_names is None else _names(attr_names), source=source)


def _names(a):
    """A 1-D string array as a list of str (anything else as it is, for the rules to name)."""
    return a.tolist() if a.dtype.kind in "US" and a.ndim == 1 else a


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
        graphs = [_one_graph(arrays, f"_{g}", n, bool(directed), source) for g in numbered]
    elif not single:
        raise InputError(source, "edges", "is missing: the archive has no graph (no edges, no indptr and indices)",
                         "edges (E, 2) of (sender, receiver) pairs, or CSR indptr and indices")
    else:
        graphs = [_one_graph(arrays, "", n, bool(directed), source)]
    _check_weighted(arrays, graphs, bool(numbered), source)
    return graphs


def _check_weighted(arrays, graphs, numbered, source):
    """No weights left without their graph, and every graph weighted or none (named by its key)."""
    for key in arrays:
        if _WEIGHTS.match(key):
            raise InputError(source, key, "has no graph of its own in the archive",
                             "weights_k beside edges_k (or indptr_k and indices_k) of each graph k"
                             if numbered else "weights beside edges (or indptr and indices)")
    for g, graph in enumerate(graphs):
        if graph.weighted != graphs[0].weighted:
            weighted, plain = (g, 0) if graph.weighted else (0, g)
            raise InputError(source, f"weights_{plain}", f"is missing, but graph {weighted} is weighted",
                             "weights for every graph, or for none (weights of 1 for a graph of equal edges)")


def _one_graph(arrays, suffix, n, directed, source):
    """edges{suffix} or indptr{suffix} + indices{suffix} (removed from ``arrays``) as a Graph."""
    e, ip, ix, wk = (f"edges{suffix}", f"indptr{suffix}", f"indices{suffix}", f"weights{suffix}")
    w = arrays.pop(wk, None)
    if e in arrays:
        if ip in arrays or ix in arrays:
            raise InputError(source, e, f"is given together with {ip if ip in arrays else ix}",
                             "each graph either as an edge list or as CSR, not both")
        return _edge_graph(arrays.pop(e), w, n, directed, (e, wk), source)
    for key in (ip, ix):
        if key not in arrays:
            raise InputError(source, key, "is missing", f"CSR graphs need both {ip} and {ix} (or give {e})")
    indptr, indices = arrays.pop(ip), arrays.pop(ix)
    for key, a in ((ip, indptr), (ix, indices)):
        if a.size and a.dtype.kind not in "iu":
            raise InputError(source, key, f"has dtype {a.dtype}", "integer node ids / offsets")
    try:
        check_csr(indptr, indices, n, True, source, "csr", w)
    except InputError as err:  # name the archive's key, not the format's
        key = {"indptr": ip, "weights": wk}.get(err.field.rsplit("/", 1)[-1], ix)
        raise InputError(source, key, err.problem, err.expected) from None
    rows = np.repeat(np.arange(n), np.diff(indptr))
    return Graph(indptr, indices, self_loops=bool(np.any(rows == indices)), weights=w)


def _edge_graph(edges, w, n, directed, keys, source):
    """The graph of an edge list (pairs, or triples with their weights), with the weights ``w``
    of the key keys[1] (one per pair) when the archive has them."""
    e, wk = keys
    if w is None:
        return as_graph(edges, n, directed, source, e)
    if edges.ndim == 2 and edges.shape[1] == 3:
        raise InputError(source, wk, f"is given, but {e} already holds (sender, receiver, weight) triples",
                         f"the weights once: {e} (E, 3), or {e} (E, 2) and {wk} (E,)")
    if edges.ndim == 2 and edges.shape[1] == 2 and edges.dtype.kind in "iuf":
        w = check_weights(w, len(edges), source, wk)
        return as_graph(np.column_stack([edges, w]), n, directed, source, e)
    graph = as_graph(edges, n, directed, source, e)  # names what is wrong with the edges, unless they are empty
    return graph.reweighted(check_weights(w, 0, source, wk))
