"""What every HDF5 reader of mpnode shares: the errors damaged bytes raise, attribute values as
plain Python, and a file's declared format.  h5py is imported inside the functions."""
import os

import numpy as np

from .errors import InputError

#: what h5py raises for damaged bytes: OSError (unreadable blocks), RuntimeError (corrupt headers,
#: e.g. "wrong version number in dataspace message"), KeyError (an object that cannot be opened),
#: TypeError/ValueError (damaged datatype messages)
H5_DAMAGE = (OSError, RuntimeError, KeyError, TypeError, ValueError)  # + "Unknown string encoding", ...


def plain_attr(v):
    """An HDF5 attribute value as plain Python: numpy scalars -> int/float/bool, bytes -> str
    (undecodable bytes stay bytes), string arrays -> lists; shared by the file readers."""
    if isinstance(v, str):
        return str(v)
    if isinstance(v, bytes):
        try:
            return v.decode("utf-8")
        except UnicodeDecodeError:
            return bytes(v)
    if isinstance(v, np.ndarray):
        return [plain_attr(e) for e in v.tolist()] if v.dtype.kind in "SOU" else v
    if isinstance(v, np.generic):
        return v.item()
    return v


def one_line(e):
    """An exception's message on one line (for messages that quote it)."""
    return " ".join(str(e).split())


def open_h5(path, kind="mpnode file"):
    """``path`` opened for reading (an h5py.File); InputError naming the file when it is missing or
    not HDF5, and the system's refusal (permission, ...) as its FileSystemError.
    kind : what the file should be, for the fix ("trajectory file", "model file", ...)."""
    import h5py

    from .oserrors import file_error, refused

    source = os.fspath(path)
    try:
        return h5py.File(source, "r")
    except FileNotFoundError:
        raise InputError(source, "file", "does not exist", f"an existing {kind}") from None
    except H5_DAMAGE as e:
        if refused(e):
            raise file_error(e, source, "read") from None
        raise InputError(source, "file", f"cannot be opened as HDF5 ({one_line(e)})",
                         f"an HDF5 {kind} (not truncated, not another format)") from None


def file_format(path):
    """The root attribute ``format`` of an HDF5 file ("mpnode.trajectories", "mpnode.model", ...),
    or None when it has none; InputError when the file cannot be opened."""
    with open_h5(path) as f:
        fmt = plain_attr(f.attrs.get("format"))
    return fmt if isinstance(fmt, str) else None
