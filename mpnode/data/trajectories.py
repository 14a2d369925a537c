"""Trajectory files (docs/trajectory-format.md, version 1).

`Trajectories` is the in-memory form every part of mpnode passes around; the
reader validates every rule of the format and raises `InputError` naming the
file and the field; the writer validates too and writes atomically.  Both use
the one checker `validate_trajectories`.  h5py is imported inside the functions
so that `import mpnode` stays light.
"""
import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from mpnode.base.arguments import check_bool, check_mapping, check_path
from mpnode.base.atomic import atomic_path
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph, as_graph, check_csr, is_networkx
from mpnode.base.h5 import H5_DAMAGE, one_line, plain_attr
from mpnode.base.oserrors import file_error, refused


@dataclass
class Trajectories:
    """A set of trajectories of one homogeneous networked system.

    x : ndarray, shape (B, T+1, N, dx) -- node states, x[b, 0] the initial state
    u : ndarray, shape (B, T, N, du), or None when du = 0 -- controls held over t -> t+1
    graphs : list of Graph, each on N nodes
    graph_index : ndarray, shape (B,), int -- graph of each trajectory
    dt : float -- time between saved states
    system : str -- the generating system, e.g. "lorenz"
    attrs : dict -- further root attributes (parameters, seed, solver, tolerances)
    params : dict name -> ndarray -- the `params/` group (system parameters)
    aux : dict name -> ndarray -- the `aux/` group (e.g. the quadrotor load)
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

    def __post_init__(self):
        if self.graph_index is None:
            self.graph_index = np.zeros(self.x.shape[0], dtype=np.int64)

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

    def graph_of(self, b):
        """The Graph trajectory ``b`` ran on."""
        return self.graphs[int(self.graph_index[b])]

    @classmethod
    def from_arrays(cls, x, graph, dt, system, u=None, graph_index=None, directed=False, attrs=None,
                    params=None, aux=None, source="arrays"):
        """Trajectories from plain arrays (your own simulator's or experiment's), validated.

        x : (B, T+1, N, dx) states, x[:, :, i] node i;  u : (B, T, N, du) controls or None;
        graph : one graph for every trajectory -- an mpnode.Graph, a networkx graph or an
        edge list of (sender, receiver) pairs (E, 2), undirected unless ``directed`` -- or a
        list of them with ``graph_index`` (B,) naming each trajectory's;  dt : time between
        saved states;  system : a name for the system;  attrs : further root attributes
        (``state_names``: one name per state dimension, used by the figures).
        Integer arrays become float64.  Raises InputError naming ``source`` and the field.
        """
        directed = check_bool(directed, source, "directed")
        attrs, params, aux = (check_mapping(v, source, k) for k, v in (("attrs", attrs), ("params", params), ("aux", aux)))
        x, u = _float_array(x, "x", source), None if u is None else _float_array(u, "u", source)
        if x.ndim != 4:
            raise InputError(source, "x", f"has shape {x.shape}",
                             "a 4-D array [B, T+1, N, dx] (one trajectory: x[None])")
        specs, field = _graph_specs(graph, source)
        graphs = [as_graph(g, x.shape[2], directed, source, field(k)) for k, g in enumerate(specs)]
        if graph_index is None and len(graphs) > 1:
            raise InputError(source, "graph_index", f"is missing, but there are {len(graphs)} graphs",
                             f"an integer array of shape ({x.shape[0]},) naming the graph of each trajectory")
        if graph_index is not None:
            graph_index = np.asarray(graph_index)
            if graph_index.dtype.kind == "f" and np.all(graph_index == np.round(graph_index)):
                graph_index = graph_index.astype(np.int64)
        traj = cls(x=x, graphs=graphs, dt=_plain_scalar(dt), system=system, u=u, graph_index=graph_index,
                   attrs=attrs, params=params, aux=aux)
        return validate_trajectories(traj, source)


def _float_array(a, name, source):
    """``a`` as an ndarray; integers (and float16) become float64, other dtypes are left to the checker."""
    try:
        a = np.asarray(a)
    except ValueError as e:  # ragged nested lists
        raise InputError(source, name, f"is not a rectangular array ({one_line(e)})",
                         "one number per entry of a regular grid") from None
    if a.dtype.kind in "iu" or (a.dtype.kind == "f" and a.dtype.itemsize < 4):
        a = a.astype(np.float64)
    return a


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


# ---- validation (shared by reader and writer) -----------------------------

RESERVED_ATTRS = ("format", "format_version", "dt", "system")
FORMAT_NAME = "mpnode.trajectories"
FORMAT_VERSION = 1


def validate_trajectories(traj, source):
    """Raise InputError (naming ``source`` and the field) unless ``traj`` obeys the format.

    The one checker behind both `read_trajectories` and `write_trajectories`, so a
    file mpnode writes is always a file mpnode (and any careful reader) accepts.
    Returns ``traj``.
    """
    dt = traj.dt
    is_number = isinstance(dt, numbers.Real) and not isinstance(dt, (bool, np.bool_))
    if not (is_number and math.isfinite(dt) and dt > 0):
        raise InputError(source, "dt", f"is {dt!r}", "a finite number > 0")
    if not _storable_text(traj.system) or not traj.system.strip():
        raise InputError(source, "system", f"is {traj.system!r}",
                         "a non-empty string naming the system, e.g. 'lorenz' (no NUL character)")

    x = np.asarray(traj.x)
    if x.ndim != 4:
        raise InputError(source, "x", f"has shape {x.shape}", "a 4-D array [B, T+1, N, dx]")
    minimum = (("B", 1, "one trajectory"), ("T+1", 2, "one step"), ("N", 1, "one node"),
               ("dx", 1, "one state dimension"))
    for size, (name, least, meaning) in zip(x.shape, minimum):
        if size < least:
            raise InputError(source, "x", f"has shape {x.shape}, so {name} = {size}",
                             f"{name} >= {least}: at least {meaning}")
    _check_float_values(x, "x", source)
    B, T, N = x.shape[0], x.shape[1] - 1, x.shape[2]

    if traj.u is not None:
        u = np.asarray(traj.u)
        if u.ndim != 4 or u.shape[:3] != (B, T, N) or u.shape[3] < 1:
            raise InputError(source, "u", f"has shape {u.shape}",
                             f"[B, T, N, du] = [{B}, {T}, {N}, du >= 1] to match x; omit u when there are no controls")
        _check_float_values(u, "u", source)

    graphs = traj.graphs
    if not isinstance(graphs, (list, tuple)) or not graphs:
        raise InputError(source, "graphs", f"is {graphs!r}", "a non-empty list of graphs (graphs/0, graphs/1, ...)")
    for g, graph in enumerate(graphs):
        if not isinstance(graph, Graph):
            raise InputError(source, f"graphs/{g}", f"is a {type(graph).__name__}", "an mpnode.Graph")
        check_csr(graph.indptr, graph.indices, N, graph.self_loops, source, f"graphs/{g}")

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

    for key in traj.attrs:
        if key in RESERVED_ATTRS:
            raise InputError(source, key, "is set in attrs, but it is a format attribute",
                             "dt and system as Trajectories fields; format and format_version are written by mpnode")
    _check_names(traj.attrs.get("state_names"), "state_names", x.shape[3], source)
    if traj.u is not None:
        _check_names(traj.attrs.get("control_names"), "control_names", np.shape(traj.u)[3], source)
    return traj


def _storable_text(text):
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
        and all(_storable_text(n) and n.strip() for n in names)
    if not ok:
        raise InputError(source, key, f"is {names!r}", f"a list of {size} non-empty strings, one per dimension")


def _check_float_values(a, name, source):
    """float32/float64 and finite; a violation names the first bad index."""
    if a.dtype.kind != "f" or a.dtype.itemsize not in (4, 8):
        raise InputError(source, name, f"has dtype {a.dtype}", "float32 or float64")
    finite = np.isfinite(a)
    if not finite.all():
        idx = tuple(int(i) for i in np.argwhere(~finite)[0])
        raise InputError(source, name, f"contains {a[idx]} at {list(idx)}", "finite values only (no NaN / inf)")


# ---- reading --------------------------------------------------------------

def read_trajectories(path):
    """Read and validate a trajectory file; raise InputError naming the file and the field.

    x and u keep their stored precision (float32 or float64, native byte order);
    graph_index is int64 and is all zeros when the file has one graph and omits it.
    """
    import h5py

    source = check_path(path, "read_trajectories")
    try:
        f = h5py.File(source, "r")
    except FileNotFoundError:
        raise InputError(source, "file", "does not exist", "an existing trajectory file") from None
    except H5_DAMAGE as e:
        if refused(e):
            raise file_error(e, source, "read") from None
        raise InputError(source, "file", f"cannot be opened as HDF5 ({one_line(e)})",
                         "an HDF5 trajectory file (not truncated, not another format)") from None
    try:
        with f:
            traj = _read_open_file(f, source)
    except InputError:
        raise
    except H5_DAMAGE as e:  # damage that only shows once data is read
        raise InputError(source, "file", f"cannot be read ({one_line(e)})", "an intact HDF5 file") from None
    validate_trajectories(traj, source)
    traj.dt = float(traj.dt)
    traj.graph_index = traj.graph_index.astype(np.int64)
    return traj


def _read_open_file(f, source):
    """Build a Trajectories from an open file, checking what only the file can get wrong."""
    fmt = plain_attr(f.attrs.get("format"))
    if not isinstance(fmt, str) or fmt != FORMAT_NAME:  # an array attribute compares element-wise
        what = "is missing" if fmt is None else f"is {fmt!r}"
        raise InputError(source, "format", what,
                         f"the root attribute format = {FORMAT_NAME!r}, as mpnode trajectory files have")
    version = plain_attr(f.attrs.get("format_version"))
    if isinstance(version, bool) or not isinstance(version, int) or version != FORMAT_VERSION:
        what = "is missing" if version is None else f"is {version!r}"
        raise InputError(source, "format_version", what, f"the integer {FORMAT_VERSION}, the version this reader knows")
    for name, meaning in (("dt", "the time step, a finite number > 0"), ("system", "a string naming the system")):
        if name not in f.attrs:
            raise InputError(source, name, "is missing", f"a root attribute {name}: {meaning}")
    attrs = {k: plain_attr(v) for k, v in f.attrs.items() if k not in RESERVED_ATTRS}

    x = _read_array(f, "x", source)
    u = _read_array(f, "u", source) if "u" in f else None
    graphs = _read_graphs(f, source)
    if "graph_index" in f:
        graph_index = _read_array(f, "graph_index", source)
    elif len(graphs) == 1:
        graph_index = np.zeros(x.shape[:1], dtype=np.int64)
    else:
        raise InputError(source, "graph_index", f"is missing, but the file has {len(graphs)} graphs",
                         "a dataset graph_index [B] naming the graph of each trajectory "
                         "(it may be omitted only when there is one graph)")
    return Trajectories(x=x, graphs=graphs, dt=plain_attr(f.attrs["dt"]), system=plain_attr(f.attrs["system"]),
                        u=u, graph_index=graph_index, attrs=attrs,
                        params=_read_group(f, "params", source), aux=_read_group(f, "aux", source))


def _read_graphs(f, source):
    """The graphs/ group as a list of Graph; names must be 0..G-1 and arrays integer."""
    group = _member(f, "graphs", "group", source)
    names = list(group)
    if not names:
        raise InputError(source, "graphs", "has no graphs", "at least one group graphs/0 with indptr and indices")
    if sorted(names) != sorted(str(g) for g in range(len(names))):
        raise InputError(source, "graphs", f"has members {sorted(names, key=lambda s: (len(s), s))}",
                         f"groups named 0..{len(names) - 1} with no gaps")
    graphs = []
    for g in range(len(names)):
        where = f"graphs/{g}"
        attrs = _member(f, where, "group", source).attrs
        indptr = _read_array(f, f"{where}/indptr", source)
        indices = _read_array(f, f"{where}/indices", source)
        for name, a in ((f"{where}/indptr", indptr), (f"{where}/indices", indices)):
            if a.size and a.dtype.kind not in "iu":  # checked before Graph casts to int64
                raise InputError(source, name, f"has dtype {a.dtype}", "an integer dtype")
        flag = plain_attr(attrs.get("self_loops", 0))
        if not isinstance(flag, int) or flag not in (0, 1):  # bool is an int: True/False accepted
            raise InputError(source, where, f"has attribute self_loops = {flag!r}",
                             "self_loops = 1 (self-loops allowed), 0 or absent")
        graphs.append(Graph(indptr, indices, self_loops=flag == 1))
    return graphs


def _read_group(f, name, source):
    """Every dataset under group ``name`` (absent: empty), keyed by path relative to it."""
    import h5py

    if name not in f:
        return {}
    group = _member(f, name, "group", source)
    out = {}

    def visit(rel, obj):
        if isinstance(obj, h5py.Dataset):
            out[rel] = _values(obj)

    group.visititems(visit)
    return out


def _member(f, name, kind, source):
    """f[name], which must exist and be a 'group' or a 'dataset'."""
    import h5py

    if name not in f:
        raise InputError(source, name, "is missing", f"a {kind} {name}")
    try:
        obj = f[name]
    except KeyError:  # a soft or external link to nothing
        raise InputError(source, name, "is a link to an object that does not exist", f"a {kind} {name}") from None
    if not isinstance(obj, h5py.Group if kind == "group" else h5py.Dataset):
        raise InputError(source, name, f"is not a {kind}", f"a {kind} {name}")
    return obj


def _read_array(f, name, source):
    """The dataset f[name] (which must exist) as an ndarray."""
    return _values(_member(f, name, "dataset", source))


def _values(ds):
    """A dataset's contents as an ndarray: strings decoded, numbers in native byte order."""
    import h5py

    if h5py.check_string_dtype(ds.dtype) is not None:
        return np.asarray(ds.asstr()[()])
    a = np.asarray(ds[()])
    if a.dtype.kind in "iuf" and not a.dtype.isnative:
        a = a.astype(a.dtype.newbyteorder("="))
    return a


# ---- writing --------------------------------------------------------------

def write_trajectories(path, traj=None, *, x=None, u=None, graph=None, graph_index=None, dt=None, system=None,
                       directed=False, attrs=None, params=None, aux=None):
    """Validate and write trajectories to ``path`` atomically: the complete file or nothing.

    Either a `Trajectories` (``write_trajectories(path, traj)``) or plain arrays, e.g.
    ``write_trajectories(path, x=x, graph=edges, dt=0.05, system="springs")``: the keywords
    are those of `Trajectories.from_arrays` (x (B, T+1, N, dx); u (B, T, N, du); graph an
    mpnode.Graph, a networkx graph, an edge list of (sender, receiver) pairs -- undirected
    unless ``directed`` -- or a list of them with graph_index (B,)).  Every problem is an
    InputError naming ``path`` and the field.  graph_index is stored only when there are
    several graphs (the format omits it for one); graphs whose ``self_loops`` is True get the
    attribute ``self_loops = 1``.
    """
    import h5py

    path = check_path(path, "write_trajectories")
    arrays = dict(x=x, u=u, graph=graph, graph_index=graph_index, dt=dt, system=system, attrs=attrs,
                  params=params, aux=aux)
    if isinstance(traj, Trajectories):
        given = [k for k, v in arrays.items() if v is not None]
        if given or directed:
            raise TypeError(f"write_trajectories: give a Trajectories or arrays, not both ({given or ['directed']})")
        validate_trajectories(traj, path)
    else:
        if traj is not None:  # write_trajectories(path, x_array, graph=..., ...)
            if x is not None:
                raise TypeError("write_trajectories: x given twice (positionally and as x=)")
            arrays["x"] = traj
        if arrays["x"] is None:
            raise TypeError("write_trajectories needs a Trajectories or the array x=")
        traj = Trajectories.from_arrays(**arrays, directed=directed, source=path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs.update(format=FORMAT_NAME, format_version=FORMAT_VERSION, dt=float(traj.dt), system=traj.system)
        f["x"] = np.asarray(traj.x)
        if traj.u is not None:
            f["u"] = np.asarray(traj.u)
        if len(traj.graphs) > 1:
            f["graph_index"] = np.asarray(traj.graph_index, dtype=np.int64)
        for g, graph in enumerate(traj.graphs):
            group = f.create_group(f"graphs/{g}")
            group["indptr"] = graph.indptr
            group["indices"] = graph.indices
            if graph.self_loops:
                group.attrs["self_loops"] = 1
        extras = [(f.attrs, key, value) for key, value in traj.attrs.items()]
        extras += [(f, f"{group}/{name}", value) for group in ("params", "aux")
                   for name, value in getattr(traj, group).items()]
        for target, key, value in extras:
            if not _storable_text(key):
                raise InputError(path, repr(key), "is not a name HDF5 can store", "a UTF-8 name without NUL")
            try:
                target[key] = value
            except (TypeError, ValueError) as e:
                raise InputError(path, key, f"cannot be stored in HDF5 ({one_line(e)})",
                                 "numbers, strings or arrays of them") from None


# ---- summary --------------------------------------------------------------

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
    }


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
