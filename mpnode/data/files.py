"""Trajectory files (docs/trajectory-format.md): the validating reader and the atomic writer.

Version 1 is the regular, fully observed file every mpnode reader knows; version 2 adds
observation times ``t``, NaN for values not observed, trajectories of different lengths
and the clean ``truth`` of degraded data; version 3 adds edge weights and static node
attributes to what version 2 holds.  The writer writes the lowest version the data need,
so older readers keep reading what they can.  h5py is imported inside the functions so that
`import mpnode` stays light.
"""

import numpy as np

from mpnode.base.arguments import check_path
from mpnode.base.atomic import atomic_path
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph
from mpnode.base.h5 import H5_DAMAGE, one_line, open_h5, plain_attr

from .rules import (FIELD_ATTRS, RESERVED_ATTRS, needs_version_2, required_version, storable_text,
                    validate_trajectories)
from .trajectories import Trajectories, shared_attrs

FORMAT_NAME = "mpnode.trajectories"
#: the newest version this reader knows (it reads every earlier one; the writer picks the lowest the data need)
FORMAT_VERSION = 3
VERSIONS = (1, 2, 3)
#: the datasets version 2 adds
VERSION_2_DATASETS = ("t", "truth")


# ---- reading --------------------------------------------------------------

def read_trajectories(path):
    """Read and validate a trajectory file; raise InputError naming the file and the field.

    x and u keep their stored precision (float32 or float64, native byte order);
    graph_index is int64 and is all zeros when the file has one graph and omits it.
    """
    source = check_path(path, "read_trajectories")
    f = open_h5(source, "trajectory file")
    try:
        with f:
            traj, version = _read_open_file(f, source)
    except InputError:
        raise
    except H5_DAMAGE as e:  # damage that only shows once data is read
        raise InputError(source, "file", f"cannot be read ({one_line(e)})", "an intact HDF5 file") from None
    validate_trajectories(traj, source)
    if version == 1 and needs_version_2(traj):
        idx = [int(i) for i in np.argwhere(np.isnan(traj.x))[0]]
        raise InputError(source, "x", f"contains nan at {idx} in a format_version 1 file",
                         "finite values (a file with values not observed is format_version 2)")
    traj.dt = float(traj.dt)
    traj.graph_index = traj.graph_index.astype(np.int64)
    return traj


def _read_open_file(f, source):
    """(Trajectories of an open file, its format version), checking what only the file can get wrong."""
    fmt = plain_attr(f.attrs.get("format"))
    if not isinstance(fmt, str) or fmt != FORMAT_NAME:  # an array attribute compares element-wise
        what = "is missing" if fmt is None else f"is {fmt!r}"
        raise InputError(source, "format", what,
                         f"the root attribute format = {FORMAT_NAME!r}, as mpnode trajectory files have")
    version = plain_attr(f.attrs.get("format_version"))
    if isinstance(version, bool) or not isinstance(version, int) or version not in VERSIONS:
        what = "is missing" if version is None else f"is {version!r}"
        raise InputError(source, "format_version", what, "1, 2 or 3, the versions this reader knows")
    for name, meaning in (("dt", "the time step, a finite number > 0"), ("system", "a string naming the system")):
        if name not in f.attrs:
            raise InputError(source, name, "is missing", f"a root attribute {name}: {meaning}")
    attrs = {k: plain_attr(v) for k, v in f.attrs.items() if k not in RESERVED_ATTRS + FIELD_ATTRS}
    x = _read_array(f, "x", source)
    u = _read_array(f, "u", source) if "u" in f else None
    graphs = _read_graphs(f, version, source)
    if "graph_index" in f:
        graph_index = _read_array(f, "graph_index", source)
    elif len(graphs) == 1:
        graph_index = np.zeros(x.shape[:1], dtype=np.int64)
    else:
        raise InputError(source, "graph_index", f"is missing, but the file has {len(graphs)} graphs",
                         "a dataset graph_index [B] naming the graph of each trajectory "
                         "(it may be omitted only when there is one graph)")
    extra = {}
    for name in VERSION_2_DATASETS:
        if name in f:
            if version == 1:
                raise InputError(source, name, "is a dataset of format version 2 in a version 1 file",
                                 "format_version 2 (or no such dataset)")
            extra[name] = _read_array(f, name, source)
    if "x_std" in f:
        extra["x_std"] = _read_array(f, "x_std", source)
    extra.update(_read_node_attrs(f, version, x.shape, source))
    traj = Trajectories(x=x, graphs=graphs, dt=plain_attr(f.attrs["dt"]), system=plain_attr(f.attrs["system"]),
                        u=u, graph_index=graph_index, attrs=attrs, params=_read_group(f, "params", source),
                        aux=_read_group(f, "aux", source), **extra)
    return traj, version


def _read_node_attrs(f, version, shape, source):
    """{node_attrs: (B, N, dp), attr_names: list} of a version-3 file (float64 when stored as float32
    or float64; the shared [N, dp] form broadcast to every trajectory); {} when it has none."""
    has_attrs, has_names = "node_attrs" in f, "attr_names" in f.attrs
    if not (has_attrs or has_names):
        return {}
    if version < 3:
        _too_new("node_attrs" if has_attrs else "attr_names", version, source)
    names = plain_attr(f.attrs.get("attr_names"))
    out = {"attr_names": [names] if isinstance(names, str) else names}  # one name may be stored as a string
    if "node_attrs" in f:
        a = _read_array(f, "node_attrs", source)
        if a.dtype.kind == "f" and a.dtype.itemsize in (4, 8):  # other dtypes stay, for the rules to name
            a = a.astype(np.float64, copy=False)
        out["node_attrs"] = shared_attrs(a, shape, source)
    return out


def _too_new(name, version, source):
    raise InputError(source, name, f"belongs to format version 3 but the file is format_version {version}",
                     "format_version 3 (or no such dataset or attribute)")


def _read_graphs(f, version, source):
    """The graphs/ group as a list of Graph; names must be 0..G-1, arrays integer, weights (version 3) float."""
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
        graphs.append(Graph(indptr, indices, self_loops=flag == 1, weights=_read_weights(f, where, version, source)))
    return graphs


def _read_weights(f, where, version, source):
    """graphs/<g>/weights (float64), or None when the graph has none."""
    name = f"{where}/weights"
    if name not in f:
        return None
    if version < 3:
        _too_new(name, version, source)
    w = _read_array(f, name, source)
    if w.dtype.kind != "f":  # checked before Graph casts to float64
        raise InputError(source, name, f"has dtype {w.dtype}", "float32 or float64 weights, one per edge")
    return w


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
                       directed=False, attrs=None, params=None, aux=None, t=None, truth=None, node_attrs=None,
                       attr_names=None):
    """Validate and write trajectories to ``path`` atomically: the complete file or nothing.

    Either a `Trajectories` (``write_trajectories(path, traj)``) or plain arrays, e.g.
    ``write_trajectories(path, x=x, graph=edges, dt=0.05, system="springs")`` or, for data
    observed at their own times with gaps, ``write_trajectories(path, x=x, t=t, graph=edges,
    system="springs")`` (NaN in x: a value not observed): the keywords are those of
    `Trajectories.from_arrays`.  Every problem is an InputError naming ``path`` and the field.
    Data that need neither times, missing values nor a truth are written as format version 1;
    weighted graphs or node attributes (``node_attrs``, ``attr_names``) make it version 3.
    """
    import h5py

    path = check_path(path, "write_trajectories")
    traj = _as_trajectories(path, traj, dict(x=x, u=u, graph=graph, graph_index=graph_index, dt=dt, system=system,
                                             attrs=attrs, params=params, aux=aux, t=t, truth=truth,
                                             node_attrs=node_attrs, attr_names=attr_names), directed)
    version = required_version(traj)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs.update(format=FORMAT_NAME, format_version=version, dt=float(traj.dt), system=traj.system)
        f["x"] = np.asarray(traj.x)
        for name, value in (("u", traj.u), ("t", traj.t), ("truth", traj.truth), ("x_std", traj.x_std)):
            if value is not None:
                f[name] = np.asarray(value)
        if len(traj.graphs) > 1:
            f["graph_index"] = np.asarray(traj.graph_index, dtype=np.int64)
        _write_graphs(f, traj.graphs)
        _write_node_attrs(f, traj)
        _write_extras(path, f, traj)


def _as_trajectories(path, traj, arrays, directed):
    """The validated Trajectories to write: ``traj`` itself, or one built from the arrays."""
    if isinstance(traj, Trajectories):
        given = [k for k, v in arrays.items() if v is not None]
        if given or directed:
            raise TypeError(f"write_trajectories: give a Trajectories or arrays, not both ({given or ['directed']})")
        return validate_trajectories(traj, path)
    if traj is not None:  # write_trajectories(path, x_array, graph=..., ...)
        if arrays["x"] is not None:
            raise TypeError("write_trajectories: x given twice (positionally and as x=)")
        arrays["x"] = traj
    if arrays["x"] is None:
        raise TypeError("write_trajectories needs a Trajectories or the array x=")
    return Trajectories.from_arrays(**arrays, directed=directed, source=path)


def _write_graphs(f, graphs):
    for g, graph in enumerate(graphs):
        group = f.create_group(f"graphs/{g}")
        group["indptr"] = graph.indptr
        group["indices"] = graph.indices
        if graph.self_loops:
            group.attrs["self_loops"] = 1
        if graph.weighted:
            group["weights"] = np.asarray(graph.weights, dtype=np.float64)


def _write_node_attrs(f, traj):
    """node_attrs as [N, dp] when every trajectory has the same, else [B, N, dp]; their names."""
    if traj.node_attrs is None:
        return
    a = np.asarray(traj.node_attrs, dtype=np.float64)
    f["node_attrs"] = a[0] if (a == a[:1]).all() else a
    f.attrs["attr_names"] = list(traj.attr_names)


def _write_extras(path, f, traj):
    extras = [(f.attrs, key, value) for key, value in traj.attrs.items()]
    extras += [(f, f"{group}/{name}", value) for group in ("params", "aux")
               for name, value in getattr(traj, group).items()]
    for target, key, value in extras:
        if not storable_text(key):
            raise InputError(path, repr(key), "is not a name HDF5 can store", "a UTF-8 name without NUL")
        try:
            target[key] = value
        except (TypeError, ValueError) as e:
            raise InputError(path, key, f"cannot be stored in HDF5 ({one_line(e)})",
                             "numbers, strings or arrays of them") from None
