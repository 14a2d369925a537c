"""Model files (../shared/spec/model-format.md, version 1): validated reader, atomic writer."""
import numpy as np

from . import integrate, mlp
from .atomic import atomic_path
from .data import plain_attr
from .errors import InputError
from .model import FORMAT, FORMAT_VERSION, Model

_INT_ATTRS = ("state_dim", "control_dim", "message_dim", "hidden", "substeps", "zero_messages", "self_messages")
#: what h5py raises for damaged bytes: OSError, RuntimeError (corrupt headers), KeyError (unopenable objects)
_H5_DAMAGE = (OSError, RuntimeError, KeyError, TypeError, ValueError)  # + "Unknown string encoding", ...
_SPEC_ATTRS = set(_INT_ATTRS) | {"format", "format_version", "activation", "dt", "integrator"}


def read_model(path):
    """The Model stored in ``path``; InputError(path, field, ...) for anything off-spec."""
    import h5py

    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist", "a model file written by `mpnode train`") from None
    except _H5_DAMAGE as e:
        raise InputError(path, "file", f"is not a readable HDF5 file ({e})", "an mpnode model file") from None
    try:
        with f:
            a = {k: plain_attr(v) for k, v in f.attrs.items()}

            def need(name, check, expected):
                if name not in a:
                    raise InputError(path, name, "root attribute is missing", expected)
                if not check(a[name]):
                    raise InputError(path, name, f"is {a[name]!r}", expected)
                return a[name]

            need("format", lambda v: isinstance(v, str) and v == FORMAT, f"'{FORMAT}'")
            need("format_version", lambda v: isinstance(v, int) and v == FORMAT_VERSION, str(FORMAT_VERSION))
            need("activation", lambda v: isinstance(v, str) and v == "tanh", "'tanh'")
            need("integrator", lambda v: isinstance(v, str) and v == "rk4", "'rk4' (classic 4-stage)")
            is_int = lambda v: isinstance(v, int) and not isinstance(v, bool)  # noqa: E731
            dx = need("state_dim", lambda v: is_int(v) and v >= 1, "an integer >= 1")
            du = need("control_dim", lambda v: is_int(v) and v >= 0, "an integer >= 0")
            dm = need("message_dim", lambda v: is_int(v) and v >= 0, "an integer >= 0")
            hidden = need("hidden", lambda v: is_int(v) and v >= 1, "an integer >= 1")
            substeps = need("substeps", lambda v: is_int(v) and v >= 1, "an integer >= 1")
            zero = need("zero_messages", lambda v: isinstance(v, (int, float)) and v in (0, 1), "0 or 1")
            self_msg = need("self_messages", lambda v: isinstance(v, (int, float)) and v in (0, 1), "0 or 1")
            dt = need("dt", lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0,
                      "a number > 0")

            shapes = mlp.param_shapes(dx, du, dm, hidden)
            params, dtype = {}, None
            for name in mlp.PARAM_NAMES:
                arr = _dataset(f, path, f"params/{name}", shapes[name])
                if dtype is None:
                    dtype = arr.dtype
                elif arr.dtype != dtype:
                    raise InputError(path, f"params/{name}", f"has dtype {arr.dtype} but params/W1 has {dtype}",
                                     "one float dtype for all parameters")
                params[name] = arr
            norm = {"x_mean": _dataset(f, path, "norm/x_mean", (dx,)), "x_std": _dataset(f, path, "norm/x_std", (dx,))}
            if du:
                norm["u_mean"] = _dataset(f, path, "norm/u_mean", (du,))
                norm["u_std"] = _dataset(f, path, "norm/u_std", (du,))
            for key in ("x_std", "u_std"):
                if key in norm and np.any(norm[key] <= 0):
                    raise InputError(path, f"norm/{key}", "has a value <= 0", "standard deviations > 0")
            extra = {k: v for k, v in a.items() if k not in _SPEC_ATTRS}

    except InputError:
        raise
    except _H5_DAMAGE as e:  # damaged bytes that h5py only notices while reading
        raise InputError(path, "file", f"cannot be read ({' '.join(str(e).split())})",
                         "an intact mpnode model file") from None

    spec = integrate.FieldSpec(dx, du, dm, hidden, float(dt), substeps, bool(zero), bool(self_msg))
    return Model(mlp.join(params, dtype=dtype), spec, norm["x_mean"], norm["x_std"],
                 norm.get("u_mean"), norm.get("u_std"), attrs=extra)


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


def write_model(path, model, extra_attrs=None):
    """Write ``model`` per the model format, atomically; NumericalError if anything is non-finite."""
    import h5py

    model.check_finite()
    s = model.spec
    attrs = {**model.attrs, **(extra_attrs or {})}
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for k, v in attrs.items():
            if k not in _SPEC_ATTRS and v is not None:
                f.attrs[k] = v
        f.attrs.update(format=FORMAT, format_version=FORMAT_VERSION, state_dim=s.state_dim,
                       control_dim=s.control_dim, message_dim=s.message_dim, hidden=s.hidden,
                       activation="tanh", dt=float(s.dt), substeps=s.substeps, integrator="rk4",
                       zero_messages=int(s.zero_messages), self_messages=int(s.self_messages))
        for name, arr in model.params.items():
            f[f"params/{name}"] = arr
        f["norm/x_mean"] = model.x_mean
        f["norm/x_std"] = model.x_std
        if s.control_dim:
            f["norm/u_mean"] = model.u_mean
            f["norm/u_std"] = model.u_std
