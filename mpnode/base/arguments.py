"""The Python API's arguments checked as the command line checks its flags.

click refuses ``--val-split abc`` before any work; a Python caller deserves the same: a
value of the wrong type or out of range is an InputError naming the function (or object)
and the argument, never a TypeError from deep inside NumPy, and never silently taken for
something else (``directed="no"`` is not True).
"""
import math
import numbers
import os
from collections.abc import Mapping

import numpy as np

from .errors import InputError


def check_bool(value, source, field):
    """``value`` if it is True or False (NumPy's too)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise InputError(source, field, f"is {value!r}", "True or False")


def check_int(value, source, field, least=None):
    """``value`` as an int if it is an integer (not a bool) >= ``least``."""
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool) and (least is None or value >= least)
    if not ok:
        raise InputError(source, field, f"is {value!r}", "an integer" + (f" >= {least}" if least is not None else ""))
    return int(value)


def check_number(value, source, field, positive=False, least=None):
    """``value`` as a float if it is a finite real number (> 0 when ``positive``, >= ``least``)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (not positive or value > 0) and (least is None or value >= least)
    if not ok:
        bound = " > 0" if positive else (f" >= {least:g}" if least is not None else "")
        raise InputError(source, field, f"is {value!r}", f"a finite number{bound}")
    return float(value)


def check_mapping(value, source, field):
    """``value`` as a dict if it is a mapping, {} for None."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise InputError(source, field, f"is a {type(value).__name__}", "a dict (or None)")
    return dict(value)


def check_path(value, source, field="path"):
    """``value`` as a str if it is a file path (a non-empty str, bytes or os.PathLike)."""
    try:
        path = os.fsdecode(os.fspath(value))
    except TypeError:
        path = ""
    if not path:
        raise InputError(source, field, f"is {value!r}", "a file path (str or pathlib.Path)")
    return path


def check_paths(value, source, field="paths"):
    """``value`` as a list of str if it is a list or tuple of file paths (one str is not a list)."""
    if not isinstance(value, (list, tuple)) or not value:
        raise InputError(source, field, f"is {value!r}", "a non-empty list of file paths")
    return [check_path(v, source, f"{field}[{i}]") for i, v in enumerate(value)]
