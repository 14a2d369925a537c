"""Model files (docs/model-format.md, version 2; 3 for a model with the linear aggregate path;
version 1 still reads): validated reader, atomic writer.

The reader returns what the file holds (spec, flat parameters, normalisation, extra
attributes) and the writer takes the same; `mpnode.model.Model` makes a model of them.
"""
import numpy as np

from mpnode import engine
from mpnode.base.atomic import atomic_path
from mpnode.base.errors import InputError
from mpnode.base.h5 import H5_DAMAGE, plain_attr
from mpnode.engine import layouts

FORMAT = "mpnode.model"
FORMAT_VERSION = 2
#: written only for a model with the linear aggregate path, so that a version-2 reader (which
#: ignores attributes it does not know) refuses it instead of dropping the path
LINEAR_PATH_VERSION = 3

_INT_ATTRS = ("state_dim", "control_dim", "message_dim", "hidden", "substeps", "zero_messages", "self_messages")
_SPEC_ATTRS = set(_INT_ATTRS) | {"format", "format_version", "activation", "dt", "integrator", "kind",
                                 "aggregation", "mean_degree", "n_nodes", "linear_aggregate",
                                 "linear_aggregation", "linear_target"}


def _is_int(v):
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


class _Attrs:
    """The root attributes of an open file, each checked as it is read."""

    def __init__(self, f, path):
        self.a = {k: plain_attr(v) for k, v in f.attrs.items()}
        self.path = path

    def need(self, name, check, expected, default=None):
        if name not in self.a:
            if default is not None:
                return default
            raise InputError(self.path, name, "root attribute is missing", expected)
        if not check(self.a[name]):
            raise InputError(self.path, name, f"is {self.a[name]!r}", expected)
        return self.a[name]

    def spec(self):
        """The FieldSpec the attributes describe (every rule of the format's root attributes)."""
        need = self.need
        need("format", lambda v: isinstance(v, str) and v == FORMAT, f"'{FORMAT}'")
        version = need("format_version", lambda v: _is_int(v) and v in (1, FORMAT_VERSION, LINEAR_PATH_VERSION),
                       f"1, {FORMAT_VERSION} or {LINEAR_PATH_VERSION} (the versions this reader knows)")
        need("activation", lambda v: isinstance(v, str) and v == "tanh", "'tanh'")
        need("integrator", lambda v: isinstance(v, str) and v == "rk4", "'rk4' (classic 4-stage)")
        known = engine.KINDS if version > 1 else ("mpnode",)
        kind = need("kind", lambda v: isinstance(v, str) and v in known,
                    " or ".join(known) + f" (the kinds format version {version} knows)", default="mpnode")
        aggs = engine.AGGREGATIONS if version > 1 else ("mean",)
        aggregation = need("aggregation", lambda v: isinstance(v, str) and v in aggs,
                           " or ".join(aggs) + " (the aggregations this version knows)",
                           default=engine.default_aggregation(kind))
        linear = self.linear_aggregation(aggs)
        mean_degree = None
        if "scaled" in (aggregation, linear):
            mean_degree = float(need("mean_degree", lambda v: _is_number(v) and v > 0,
                                     "a number > 0 (the training graphs' mean in-degree)"))
        n_nodes = None
        if kind == "node":
            n_nodes = need("n_nodes", lambda v: _is_int(v) and v >= 1, "an integer >= 1 (the system's node count)")
        dx = need("state_dim", lambda v: _is_int(v) and v >= 1, "an integer >= 1")
        du = need("control_dim", lambda v: _is_int(v) and v >= 0, "an integer >= 0")
        if kind == "mpnode":
            dm = need("message_dim", lambda v: _is_int(v) and v >= 0, "an integer >= 0")
        else:
            dm = need("message_dim", lambda v: _is_int(v) and v == 0, f"0 (a {kind} model has no messages)", default=0)
        hidden = need("hidden", lambda v: _is_int(v) and v >= 1, "an integer >= 1")
        substeps = need("substeps", lambda v: _is_int(v) and v >= 1, "an integer >= 1")
        flag = lambda v: isinstance(v, (int, float)) and v in (0, 1)  # noqa: E731
        zero = need("zero_messages", flag, "0 or 1", default=0 if kind != "mpnode" else None)
        if kind != "mpnode" and zero:
            raise InputError(self.path, "zero_messages", "is 1", f"0 (a {kind} model has no messages)")
        self_msg = need("self_messages", flag, "0 or 1", default=0 if kind == "node" else None)
        dt = need("dt", lambda v: _is_number(v) and v > 0, "a number > 0")
        on = self.linear_aggregate(kind, dm, zero)
        if (version == LINEAR_PATH_VERSION) != on:
            raise InputError(self.path, "format_version", f"is {version} with linear_aggregate {int(on)}",
                             f"{LINEAR_PATH_VERSION} exactly when the model has the linear aggregate path "
                             f"(linear_aggregate 1), {FORMAT_VERSION} otherwise")
        if linear is not None and not on:
            raise InputError(self.path, "linear_aggregation", f"is {linear!r} without linear_aggregate 1",
                             "no linear_aggregation, or linear_aggregate 1 (the path it feeds)")
        target = self.need("linear_target", lambda v: isinstance(v, str) and v in engine.LINEAR_TARGETS,
                           " or ".join(engine.LINEAR_TARGETS) + " (what the linear aggregate path adds to)",
                           default="all")
        if target != "all" and not on:
            raise InputError(self.path, "linear_target", f"is {target!r} without linear_aggregate 1",
                             "no linear_target, or linear_aggregate 1 (the path it says where to add)")
        return engine.FieldSpec(dx, du, dm, hidden, float(dt), substeps, bool(zero), bool(self_msg), kind,
                                aggregation, mean_degree, n_nodes, on, linear, target)

    def linear_aggregation(self, aggs):
        """The linear path's own aggregate, or None when absent (the path reads the MLP's)."""
        if "linear_aggregation" not in self.a:
            return None
        return self.need("linear_aggregation", lambda v: isinstance(v, str) and v in aggs,
                         " or ".join(aggs) + " (the aggregations this version knows)")

    def linear_aggregate(self, kind, dm, zero):
        """The linear aggregate path switch: 0 when absent (files before it, and every model
        without it); 1 only for an mpnode model that has messages to aggregate."""
        flag = lambda v: isinstance(v, (int, float)) and v in (0, 1)  # noqa: E731
        on = bool(self.need("linear_aggregate", flag, "0 or 1", default=0))
        if on and (kind != "mpnode" or not dm or zero):
            raise InputError(self.path, "linear_aggregate", "is 1",
                             "0 (the linear aggregate path needs an mpnode model with messages: message_dim > 0, "
                             "zero_messages 0)")
        return on


def read_model(path):
    """What ``path`` holds: {spec, theta, x_mean, x_std, u_mean, u_std, attrs} (the arguments of
    mpnode.model.Model); InputError(path, field, ...) for anything off-format."""
    import h5py

    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist", "a model file written by `mpnode train`") from None
    except H5_DAMAGE as e:
        raise InputError(path, "file", f"is not a readable HDF5 file ({e})", "an mpnode model file") from None
    try:
        with f:
            attrs = _Attrs(f, path)
            spec = attrs.spec()
            shapes = layouts.param_shapes(spec)
            params, dtype = {}, None
            for name, shape in shapes.items():
                arr = _dataset(f, path, f"params/{name}", shape)
                if dtype is None:
                    dtype = arr.dtype
                elif arr.dtype != dtype:
                    raise InputError(path, f"params/{name}", f"has dtype {arr.dtype} but the first parameter has "
                                     f"{dtype}", "one float dtype for all parameters")
                params[name] = arr
            dx, du = spec.state_dim, spec.control_dim
            norm = {"x_mean": _dataset(f, path, "norm/x_mean", (dx,)), "x_std": _dataset(f, path, "norm/x_std", (dx,))}
            if du:
                norm["u_mean"] = _dataset(f, path, "norm/u_mean", (du,))
                norm["u_std"] = _dataset(f, path, "norm/u_std", (du,))
            for key in ("x_std", "u_std"):
                if key in norm and np.any(norm[key] <= 0):
                    raise InputError(path, f"norm/{key}", "has a value <= 0", "standard deviations > 0")
            extra = {k: v for k, v in attrs.a.items() if k not in _SPEC_ATTRS}
    except InputError:
        raise
    except H5_DAMAGE as e:  # damaged bytes that h5py only notices while reading
        raise InputError(path, "file", f"cannot be read ({' '.join(str(e).split())})",
                         "an intact mpnode model file") from None
    return dict(spec=spec, theta=layouts.join(params, shapes, dtype=dtype), x_mean=norm["x_mean"],
                x_std=norm["x_std"], u_mean=norm.get("u_mean"), u_std=norm.get("u_std"), attrs=extra)


def _dataset(f, path, name, shape):
    if name not in f:
        raise InputError(path, name, "dataset is missing", f"a float dataset of shape {shape}")
    d = f[name]
    if not hasattr(d, "dtype") or d.dtype.kind != "f" or d.dtype.itemsize not in (4, 8):
        raise InputError(path, name, f"has dtype {getattr(d, 'dtype', 'group')}", "float32 or float64")
    if d.shape != shape:
        raise InputError(path, name, f"has shape {d.shape}", f"shape {shape}")
    arr = d[()].astype(d.dtype.newbyteorder("="))
    if not np.all(np.isfinite(arr)):
        raise InputError(path, name, "contains NaN or inf", "finite values")
    return arr


def spec_attrs(spec):
    """The root attributes that describe ``spec`` (format version 2, or 3 with the linear path)."""
    version = LINEAR_PATH_VERSION if spec.linear_aggregate else FORMAT_VERSION
    attrs = dict(format=FORMAT, format_version=version, kind=spec.kind, aggregation=spec.aggregation,
                 state_dim=spec.state_dim, control_dim=spec.control_dim, message_dim=spec.message_dim,
                 hidden=spec.hidden, activation="tanh", dt=float(spec.dt), substeps=spec.substeps,
                 integrator="rk4", zero_messages=int(spec.zero_messages), self_messages=int(spec.self_messages))
    if spec.mean_degree is not None:
        attrs["mean_degree"] = float(spec.mean_degree)
    if spec.n_nodes is not None:
        attrs["n_nodes"] = int(spec.n_nodes)
    if spec.linear_aggregate:  # absent means off: files without the path stay as they were
        attrs["linear_aggregate"] = 1
    if spec.linear_aggregation is not None:  # absent: the path reads the MLP's aggregate
        attrs["linear_aggregation"] = spec.linear_aggregation
    if spec.linear_target != "all":  # absent: the path adds to every output
        attrs["linear_target"] = spec.linear_target
    return attrs


def write_model(path, spec, params, norm, attrs):
    """Write a model file atomically: ``params`` {name: array} of spec's layout, ``norm``
    {x_mean, x_std, u_mean, u_std} (the u entries only when du > 0), extra ``attrs``."""
    import h5py

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for k, v in attrs.items():
            if k not in _SPEC_ATTRS and v is not None:
                f.attrs[k] = v
        f.attrs.update(spec_attrs(spec))
        for name, arr in params.items():
            f[f"params/{name}"] = arr
        for name in ("x_mean", "x_std", "u_mean", "u_std")[:4 if spec.control_dim else 2]:
            f[f"norm/{name}"] = norm[name]
