"""Compiling the kernels: once per machine, said aloud, and the VJP on the other core.

numba compiles a driver (`kernels.rk4`) the first time it is called for a precision, then keeps
the machine code in its on-disk cache (`kernels._cache_dir`), so a second run starts at once.
A first compile takes minutes on a small machine, and training needs two drivers, the rollout
and its VJP, which numba would compile one after the other.  So `integrate_with_vjp` calls
`compile_vjp_ahead`: a process of its own compiles the VJP driver into the cache while this one
compiles the rollout, and the VJP's first call (`before_call`) waits for it and loads what it
wrote.  numba rewrites a function's cache index with no lock, so two processes saving overloads
of one function at once can lose an entry or leave one naming the other's code (numba issue
4807): both processes' cache writes take turns (`serialise_cache_writes`), and where that cannot
be done (no fcntl) everything compiles here, in turn.

`set_announcer` lets the command line say what is happening ("compiling the MP-NODE kernels for
float32, once: ~N s"); the library itself prints nothing.  MPNODE_COMPILE_AHEAD=0 keeps every
compile in this process.
"""
import json
import os
import subprocess
import sys
import time

import numpy as np

from mpnode.base.atomic import atomic_path

VARIABLE = "MPNODE_COMPILE_AHEAD"
#: seconds a first run waits for its compile on a 2-core machine (docs/evidence/cold-start.md), until this
#: machine has its own figure
DEFAULT_SECONDS = 80.0
_TIMES_FILE = "mpnode-compile-seconds.json"
_FIELD_NAMES = {"mpnode": "MP-NODE", "l2s": "L2S"}

_announce = None
_announced = set()  # the (dtype, field) whose compile was announced in this process
_known = set()  # (driver, dtype, field) compiled or loaded in this process
_pending = {}  # (driver, dtype, field) -> (process, start time)
_lock_path = None  # the file every cache write of this process locks, once `serialise_cache_writes` ran


def set_announcer(fn):
    """``fn(message)`` is told, once per precision and field, that the kernels are being compiled
    (None: silence)."""
    global _announce
    _announce = fn


def before_call(name, dtype, field="mpnode"):
    """Called before each call of driver ``name`` in ``dtype`` for ``field`` ("mpnode" or "l2s",
    compiled apart: `kernels.rk4`): wait for its compile in the other process if one runs, and
    announce a compile here the first time it has to happen."""
    key = (name, np.dtype(dtype).name, field)
    if key in _known:
        return
    _wait(key)
    if not is_compiled(name, dtype, field) and _announce is not None and key[1:] not in _announced:
        _announced.add(key[1:])
        _announce(f"compiling the {_FIELD_NAMES[field]} kernels for {key[1]}, once: ~{estimate():.0f} s")
    _known.add(key)


def compile_vjp_ahead(dtype, stagewise, field="mpnode"):
    """Start compiling the VJP driver for ``dtype`` and ``field`` in another process unless it is
    compiled (or ahead-compiling is switched off): the caller goes on to compile the rollout."""
    name = "vjp_stagewise" if stagewise else "vjp_blocks"
    key = (name, np.dtype(dtype).name, field)
    if key in _known or key in _pending or os.environ.get(VARIABLE, "1") == "0":
        return
    if is_compiled(name, dtype, field):
        _known.add(key)
        return
    if not serialise_cache_writes():
        return
    try:  # a failure there only means this process compiles the VJP itself: nothing to show
        proc = subprocess.Popen([sys.executable, "-m", "mpnode.engine.precompile", key[1],
                                 "stagewise" if stagewise else "blocks", field],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:  # no interpreter to start (an embedded Python): compile here, in turn
        return
    _pending[key] = (proc, time.perf_counter())


def serialise_cache_writes():
    """Make each of this process's numba cache writes hold an exclusive lock on one file in the
    cache folder, shared by every mpnode process; False where file locks are not to be had
    (no fcntl)."""
    global _lock_path
    try:
        import fcntl

        from numba.core.caching import IndexDataCacheFile
    except ImportError:
        return False
    if _lock_path is None:
        from .kernels import cache_base

        os.makedirs(cache_base(), exist_ok=True)
        _lock_path = os.path.join(cache_base(), "mpnode-cache-writes.lock")
        save = IndexDataCacheFile.save

        def locked_save(self, key, data):
            with open(_lock_path, "a") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                return save(self, key, data)  # closing the file releases the lock

        IndexDataCacheFile.save = locked_save
    return True


def _wait(key):
    if key not in _pending:
        return
    proc, t0 = _pending.pop(key)
    if proc.wait() == 0:
        _record(key[0], time.perf_counter() - t0)


def is_compiled(name, dtype, field="mpnode"):
    """Is driver ``name`` compiled for ``dtype`` and ``field`` in this process or in numba's
    on-disk cache?"""
    from numba import types

    from .kernels import rk4

    disp = getattr(rk4, name)
    want = types.float32 if np.dtype(dtype) == np.float32 else types.float64

    def match(sig):  # (theta, dims, l2s, ...): l2s is None for the MP-NODE field, an int64 for L2S
        return sig[0].dtype == want and isinstance(sig[2], types.NoneType) == (field == "mpnode")

    if any(match(sig) for sig in disp.signatures):
        return True
    try:
        magic = disp.targetctx.codegen().magic_tuple()
        index = disp._cache._cache_file._load_index()
        return any(key[1] == magic and match(key[0]) for key in index)
    except Exception:  # numba's cache layout is private: when it cannot be read, assume a compile
        return False


def estimate():
    """Seconds a first compile of a driver took on this machine: the longest recorded (each VJP
    compiled ahead is timed), else DEFAULT_SECONDS."""
    return max(_times().values(), default=DEFAULT_SECONDS)


def _times():
    try:
        with open(_times_path()) as f:
            return {k: float(v) for k, v in json.load(f).items()}
    except (OSError, ValueError, AttributeError, TypeError):
        return {}


def _record(name, seconds):
    """Remember how long ``name`` took to compile, for the next estimate (best effort: a
    read-only cache folder just keeps the default)."""
    times = _times()
    times[name] = round(seconds, 1)
    try:
        os.makedirs(os.path.dirname(_times_path()), exist_ok=True)
        with atomic_path(_times_path()) as tmp, open(tmp, "w") as f:
            json.dump(times, f)
    except OSError:
        pass


def _times_path():
    from .kernels import cache_base

    return os.path.join(cache_base(), _TIMES_FILE)
