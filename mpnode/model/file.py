"""Model files (docs/model-format.md, version 2; 3 for a model with the linear aggregate path;
4 with an initial-state encoder; 5 for an ensemble; 6 with kinematics; 7 hearing node attributes
or edge weights; version 1 still reads):
validated reader, atomic writer.

The reader returns what the file holds (spec, flat parameters, normalisation, extra
attributes) and the writer takes the same; `mpnode.model.Model` makes a model of them.
"""
import numpy as np

from mpnode.base.atomic import atomic_path
from mpnode.base.errors import InputError
from mpnode.base.h5 import H5_DAMAGE, open_h5, plain_attr
from mpnode.engine import layouts
from mpnode.engine.spec import AGGREGATIONS, KINDS, LINEAR_TARGETS, FieldSpec, default_aggregation

FORMAT = "mpnode.model"
FORMAT_VERSION = 2
#: written only for a model with the linear aggregate path, so that a version-2 reader (which
#: ignores attributes it does not know) refuses it instead of dropping the path
LINEAR_PATH_VERSION = 3
#: written only for a model with an initial-state encoder (with or without the linear path)
ENCODER_VERSION = 4
#: written only for an ensemble (K members' parameters stacked, their calibrated spread), so that
#: an older reader refuses it instead of misreading the stacked arrays
ENSEMBLE_VERSION = 5
#: written only for a model (or an ensemble) with kinematics, which an older reader would drop
KINEMATICS_VERSION = 6
#: written only for a model (or an ensemble) that hears node attributes or edge weights, which an
#: older reader would run without them
NETWORK_VERSION = 7
VERSIONS = (1, FORMAT_VERSION, LINEAR_PATH_VERSION, ENCODER_VERSION, ENSEMBLE_VERSION, KINEMATICS_VERSION,
            NETWORK_VERSION)
#: the datasets under ensemble/ of an ensemble file: the spread's scale (dx,), then per member (K,)
ENSEMBLE_ARRAYS = ("spread_scale", "member_seed", "member_epoch", "member_val_loss")
#: the optional group of what the model saw in training (mpnode.model.ranges), and its key in attrs;
#: any version may hold it, and a reader that does not know it ignores it
SEEN, SEEN_ATTR = "seen", "seen_ranges"


def version_of(spec, ensemble=False):
    """The oldest format version that holds ``spec`` (of an ensemble's members when ``ensemble``):
    an older reader then refuses what it would misread."""
    if spec.attr_dim or spec.aggregation.weight_scale is not None:
        return NETWORK_VERSION
    if spec.kinematics is not None:
        return KINEMATICS_VERSION
    if ensemble:
        return ENSEMBLE_VERSION
    if spec.encoder_window:
        return ENCODER_VERSION
    return LINEAR_PATH_VERSION if spec.linear_path else FORMAT_VERSION

def _is_int(v):
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


def _flag(v):
    return isinstance(v, (int, float)) and v in (0, 1)


#: the spec's attributes: how each must look (the rules between them are FieldSpec's)
_TYPES = {
    "state_dim": (lambda v: _is_int(v) and v >= 1, "an integer >= 1"),
    "control_dim": (lambda v: _is_int(v) and v >= 0, "an integer >= 0"),
    "message_dim": (lambda v: _is_int(v) and v >= 0, "an integer >= 0"),
    "hidden": (lambda v: _is_int(v) and v >= 1, "an integer >= 1"),
    "substeps": (lambda v: _is_int(v) and v >= 1, "an integer >= 1"),
    "dt": (lambda v: _is_number(v) and v > 0, "a number > 0"),
    "zero_messages": (_flag, "0 or 1"),
    "self_messages": (_flag, "0 or 1"),
    "n_nodes": (lambda v: _is_int(v) and v >= 1, "an integer >= 1 (the system's node count)"),
    "mean_degree": (lambda v: _is_number(v) and v > 0, "a number > 0 (the training graphs' mean in-degree)"),
    "linear_aggregate": (_flag, "0 or 1"),
    "linear_aggregation": (lambda v: isinstance(v, str) and v in AGGREGATIONS, " or ".join(AGGREGATIONS)),
    "linear_target": (lambda v: isinstance(v, str) and v in LINEAR_TARGETS,
                      " or ".join(LINEAR_TARGETS) + " (what the linear aggregate path adds to)"),
    "encoder_window": (lambda v: _is_int(v) and v >= 1, "an integer >= 1 (the initial-state encoder's observations)"),
    "kinematics": (lambda v: isinstance(v, str), "text: terms D:S or qD:S separated by commas (model-format.md)"),
    "attr_dim": (lambda v: _is_int(v) and v >= 1, "an integer >= 1 (the last control columns that are node attributes)"),
    "weight_scale": (lambda v: _is_number(v) and v > 0, "a number > 0 (the training graphs' mean edge weight size)"),
}
_SPEC_ATTRS = set(_TYPES) | {"format", "format_version", "activation", "integrator", "kind", "aggregation",
                             "ensemble_size"}


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
        version = self.version()
        kinds, aggs = (KINDS, AGGREGATIONS) if version > 1 else (("mpnode",), ("mean",))
        kind = self.need("kind", lambda v: isinstance(v, str) and v in kinds,
                         " or ".join(kinds) + f" (the kinds format version {version} knows)", default="mpnode")
        values = {"kind": kind, "aggregation": self.need(
            "aggregation", lambda v: isinstance(v, str) and v in aggs,
            " or ".join(aggs) + " (the aggregations this version knows)", default=default_aggregation(kind))}
        required = {"state_dim", "control_dim", "hidden", "substeps", "dt"}
        required |= {"message_dim", "zero_messages"} if kind == "mpnode" else set()
        required |= {"self_messages"} if kind != "node" else set()
        for name, (check, expected) in _TYPES.items():
            if name in self.a or name in required:
                values[name] = self.need(name, check, expected)
        for name in ("linear_aggregation", "linear_target"):
            if name in values and not values.get("linear_aggregate"):
                raise InputError(self.path, name, f"is {values[name]!r} without linear_aggregate 1",
                                 f"no {name}, or linear_aggregate 1 (the linear aggregate path it describes)")
        try:
            spec = FieldSpec.from_attrs(values)
        except InputError as e:
            raise InputError(self.path, e.field, e.problem, e.expected) from None
        featured = version > 1 or "ensemble_size" in self.a or spec.kinematics is not None
        if featured and version != version_of(spec, "ensemble_size" in self.a):
            raise InputError(self.path, "format_version", f"is {version} with linear_aggregate {int(spec.linear_path)}, "
                             f"encoder_window {spec.encoder_window}, ensemble_size {self.a.get('ensemble_size')}, "
                             f"kinematics {self.a.get('kinematics')!r}, attr_dim {spec.attr_dim} and weight_scale "
                             f"{spec.aggregation.weight_scale}",
                             f"{NETWORK_VERSION} exactly for a model with node attributes or edge weights, else "
                             f"{KINEMATICS_VERSION} exactly for a model with kinematics, else {ENSEMBLE_VERSION} "
                             f"exactly for an ensemble (ensemble_size), else {ENCODER_VERSION} "
                             f"exactly when the model has an initial-state encoder, else {LINEAR_PATH_VERSION} "
                             f"exactly when it has the linear aggregate path, else {FORMAT_VERSION}")
        return spec

    def members(self):
        """K, the members of an ensemble file (its ``ensemble_size``), or None for one model."""
        if "ensemble_size" not in self.a:
            return None
        return self.need("ensemble_size", lambda v: _is_int(v) and v >= 1, "an integer >= 1 (the ensemble's members)")

    def version(self):
        """The format version, after the attributes every version has."""
        self.need("format", lambda v: isinstance(v, str) and v == FORMAT, f"'{FORMAT}'")
        version = self.need("format_version", lambda v: _is_int(v) and v in VERSIONS,
                            ", ".join(map(str, VERSIONS)) + " (the versions this reader knows)")
        self.need("activation", lambda v: isinstance(v, str) and v == "tanh", "'tanh'")
        self.need("integrator", lambda v: isinstance(v, str) and v == "rk4", "'rk4' (classic 4-stage)")
        return version


def read_model(path):
    """What ``path`` holds: {spec, theta, x_mean, x_std, u_mean, u_std, attrs} (the arguments of
    mpnode.model.Model); for an ensemble theta is (K, P) and ``ensemble`` holds its arrays
    (ENSEMBLE_ARRAYS).  InputError(path, field, ...) for anything off-format."""
    f = open_h5(path, "model file (written by `mpnode train`)")
    try:
        with f:
            attrs = _Attrs(f, path)
            spec = attrs.spec()
            k = attrs.members()
            shapes = layouts.param_shapes(spec)
            params, dtype = {}, None
            for name, shape in shapes.items():
                arr = _dataset(f, path, f"params/{name}", shape if k is None else (k,) + tuple(shape))
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
            ensemble = None if k is None else _ensemble_arrays(f, path, k, dx)
            extra = {name: v for name, v in attrs.a.items() if name not in _SPEC_ATTRS}
            _check_attr_names(extra.get("attr_names"), spec.attr_dim, path)
            if SEEN in f:
                extra[SEEN_ATTR] = _seen(f, path)
    except InputError:
        raise
    except H5_DAMAGE as e:  # damaged bytes that h5py only notices while reading
        raise InputError(path, "file", f"cannot be read ({' '.join(str(e).split())})",
                         "an intact mpnode model file") from None
    if k is None:
        theta = layouts.join(params, shapes, dtype=dtype)
    else:
        theta = np.stack([layouts.join({n: a[i] for n, a in params.items()}, shapes, dtype=dtype) for i in range(k)])
    out = dict(spec=spec, theta=theta, x_mean=norm["x_mean"], x_std=norm["x_std"], u_mean=norm.get("u_mean"),
               u_std=norm.get("u_std"), attrs=extra)
    if ensemble is not None:
        out["ensemble"] = ensemble
    return out


def _check_attr_names(names, attr_dim, path):
    """A model of node attributes names each one: the data it runs on must name them alike."""
    if not attr_dim:
        return
    if not (isinstance(names, (list, tuple)) and len(names) == attr_dim and all(isinstance(n, str) for n in names)):
        raise InputError(path, "attr_names", f"is {names!r}", f"a list of {attr_dim} names (one per node attribute)")


def _ensemble_arrays(f, path, k, dx):
    """The ``ensemble/`` datasets of a K-member file: the spread's scale (dx,) > 0 and each
    member's seed, epoch and validation loss (K,)."""
    out = {"spread_scale": _dataset(f, path, "ensemble/spread_scale", (dx,))}
    if np.any(out["spread_scale"] <= 0):
        raise InputError(path, "ensemble/spread_scale", "has a value <= 0", "scales > 0 (1: not calibrated)")
    for name in ENSEMBLE_ARRAYS[1:]:
        full = f"ensemble/{name}"
        if full in f:
            d = f[full]
            if getattr(d, "shape", None) != (k,):
                raise InputError(path, full, f"has shape {getattr(d, 'shape', None)}", f"shape ({k},): one per member")
            out[name] = d[()]
    return out


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


def _seen(f, path):
    """The training ranges of the optional group ``seen/``: {quantity_min, quantity_max: list}."""
    out = {}
    for name in f[SEEN]:
        d = f[f"{SEEN}/{name}"]
        if not hasattr(d, "dtype") or d.dtype.kind != "f" or d.ndim != 1:
            raise InputError(path, f"{SEEN}/{name}", f"is {getattr(d, 'dtype', 'a group')}",
                             "a 1-D float dataset (the range seen in training), or no seen/ group")
        out[name] = d[()].astype(np.float64).tolist()
    return out


def spec_attrs(spec, members=None):
    """The root attributes that describe ``spec`` (format version `version_of`), and an
    ensemble's size when ``members`` (K) is given."""
    version = version_of(spec, members is not None)
    more = {} if members is None else {"ensemble_size": int(members)}
    return dict(format=FORMAT, format_version=version, activation="tanh", integrator="rk4", **spec.attrs(), **more)


def write_model(path, spec, params, norm, attrs, ensemble=None):
    """Write a model file atomically: ``params`` {name: array} of spec's layout, ``norm``
    {x_mean, x_std, u_mean, u_std} (the u entries only when du > 0), extra ``attrs``.
    An ensemble (version 5): ``params`` arrays have a leading axis of K members and ``ensemble``
    holds {spread_scale (dx,), member_seed, member_epoch, member_val_loss (K,)}."""
    import h5py

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for k, v in attrs.items():
            if k not in _SPEC_ATTRS and k != SEEN_ATTR and v is not None:
                f.attrs[k] = v
        for name, values in (attrs.get(SEEN_ATTR) or {}).items():
            f[f"{SEEN}/{name}"] = np.asarray(values, dtype=np.float64)
        f.attrs.update(spec_attrs(spec, None if ensemble is None else len(next(iter(params.values())))))
        for name, arr in (ensemble or {}).items():
            f[f"ensemble/{name}"] = arr
        for name, arr in params.items():
            f[f"params/{name}"] = arr
        for name in ("x_mean", "x_std", "u_mean", "u_std")[:4 if spec.control_dim else 2]:
            f[f"norm/{name}"] = norm[name]
