"""Compiling the kernels: once per machine, said aloud, and the VJP on the other core.

numba compiles a driver (`kernels.rk4`) the first time it is called for a precision, then keeps
the machine code in its on-disk cache (`kernels._cache_dir`), so a second run starts at once.
A first compile takes a minute on a small machine, and training needs two drivers, the rollout
and its VJP, which numba would compile one after the other.  So `integrate_with_vjp` calls
`compile_vjp_ahead`: a process of its own compiles the VJP driver into the cache while this one
compiles the rollout, and the VJP's first call (`before_call`) waits for it and loads what it
wrote.  The two drivers share callees (the neighbour sums, the products): each is compiled by
whichever process reaches it first, the other waits and loads it (`_OneCompileEach`).  numba
rewrites a function's cache index with no lock, so two processes saving overloads of one
function at once can lose an entry or leave one naming the other's code: both processes'
cache writes take turns (`serialise_cache_writes`), and where that cannot be
done (no fcntl) everything compiles here, in turn.

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
DEFAULT_SECONDS = 60.0
_TIMES_FILE = "mpnode-compile-seconds.json"
#: the drivers by name -> (the function of `kernels.rk4`, whether its ``states`` is None, or None where
#: that does not tell drivers apart): the block VJP is compiled apart for kept stage caches (its
#: ``states`` None) and for recomputed stages (its ``kept`` None)
DRIVERS = {"rollout_blocks": ("rollout_blocks", None), "rollout_stagewise": ("rollout_stagewise", None),
           "vjp_blocks": ("vjp_blocks", True), "vjp_blocks_recompute": ("vjp_blocks", False),
           "vjp_stagewise": ("vjp_stagewise", None)}
_VJP_STATES = 15  # the position of vjp_blocks's ``states``
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


def compile_vjp_ahead(dtype, name, field="mpnode"):
    """Start compiling VJP driver ``name`` (`DRIVERS`) for ``dtype`` and ``field`` in another process
    unless it is compiled (or ahead-compiling is switched off): the caller goes on to compile the
    rollout."""
    _start_ahead(name, dtype, field, name)


def compile_sums_ahead(dtype, field="mpnode"):
    """Before a rollout that no VJP follows (`mpnode eval`, say) compiles on one core: have another
    process compile the MP-NODE field's neighbour sums (`precompile.compile_sums`), which the
    rollout then loads, unless the rollout is compiled."""
    if field == "mpnode":
        _start_ahead("sums", dtype, field, "rollout_blocks")


def _start_ahead(what, dtype, field, driver):
    """Start ``python -m mpnode.engine.precompile DTYPE WHAT FIELD`` unless ``driver`` is compiled."""
    key = (what, np.dtype(dtype).name, field)
    if key in _known or key in _pending or os.environ.get(VARIABLE, "1") == "0":
        return
    if is_compiled(driver, dtype, field):
        _known.add(key)
        return
    if not serialise_cache_writes():
        return
    try:  # a failure there only means this process compiles it all itself: nothing to show
        proc = subprocess.Popen([sys.executable, "-m", "mpnode.engine.precompile", key[1], what, field],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:  # no interpreter to start (an embedded Python): compile here, in turn
        return
    _pending[key] = (proc, time.perf_counter())


def serialise_cache_writes():
    """Make each of this process's numba cache writes hold an exclusive lock on one file in the
    cache folder, shared by every mpnode process, and each kernel compile a lock of its own
    (`_OneCompileEach`); False where file locks are not to be had (no fcntl)."""
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
        _OneCompileEach.install()
    return True


class _OneCompileEach:
    """A kernel's numba cache whose miss waits for the lock of that function and signature,
    then looks again: of two processes compiling drivers with callees in common (the rollout
    here, the VJP ahead), the second to reach a callee loads what the first compiled instead
    of compiling it too.  The lock is held from the miss until numba saves the compile (or the
    compile fails).  Locks are taken callers first, and the call graph has no cycles, so two
    processes cannot wait for each other."""

    def __init__(self, cache):
        self.cache, self.held = cache, {}
        self.prefix = os.path.join(cache.cache_path, "locks", cache._impl.filename_base)

    def __getattr__(self, name):
        return getattr(self.cache, name)

    @classmethod
    def install(cls):
        """Wrap the cache of every kernel compiled apart (its inlined helpers compile in their callers)."""
        from numba.core import event
        from numba.core.registry import CPUDispatcher

        from . import kernels

        class ReleaseOnFailure(event.Listener):
            """Releases a failed compile's lock (one that succeeded added its overload before this event)."""

            def on_start(self, ev):
                pass

            def on_end(self, ev):
                disp, args = ev.data["dispatcher"], tuple(ev.data["args"])
                if isinstance(getattr(disp, "_cache", None), cls) and args not in disp.overloads:
                    disp._cache.release(_signature_key(args))

        for module in kernels.MODULES:
            for disp in vars(module).values():
                if isinstance(disp, CPUDispatcher) and disp._cache.__class__ is not cls:
                    disp._cache = cls(disp._cache)
        event.register("numba:compile", ReleaseOnFailure())

    def load_overload(self, sig, target_context):
        import fcntl

        cres = self.cache.load_overload(sig, target_context)
        if cres is not None:
            return cres
        key = _signature_key(sig)
        try:
            os.makedirs(os.path.dirname(self.prefix), exist_ok=True)
            lock = open(f"{self.prefix}-{key}.lock", "a")
        except OSError:  # a folder it cannot write: compile without waiting for anyone
            return None
        fcntl.flock(lock, fcntl.LOCK_EX)
        cres = self.cache.load_overload(sig, target_context)
        if cres is not None:
            lock.close()
        else:
            self.held[key] = lock  # until save_overload, or the compile's failure
        return cres

    def save_overload(self, sig, data):
        try:
            self.cache.save_overload(sig, data)
        finally:
            self.release(_signature_key(sig))

    def release(self, key):
        lock = self.held.pop(key, None)
        if lock is not None:
            lock.close()


def _signature_key(sig):
    import hashlib

    from numba.core import sigutils

    args, _ = sigutils.normalize_signature(sig)
    return hashlib.sha256(str(tuple(args)).encode()).hexdigest()[:16]


def _wait(key):
    if key not in _pending:
        return
    proc, t0 = _pending.pop(key)
    if proc.wait() == 0:
        _record(key[0], time.perf_counter() - t0)


def is_compiled(name, dtype, field="mpnode"):
    """Is driver ``name`` (`DRIVERS`) compiled for ``dtype`` and ``field`` in this process or in
    numba's on-disk cache?"""
    from numba import types

    from .kernels import rk4

    function, states_none = DRIVERS[name]
    disp = getattr(rk4, function)
    want = types.float32 if np.dtype(dtype) == np.float32 else types.float64

    def match(sig):  # (theta, dims, l2s, ...): l2s is None for the MP-NODE field, an int64 for L2S
        return (sig[0].dtype == want and isinstance(sig[2], types.NoneType) == (field == "mpnode")
                and (states_none is None or isinstance(sig[_VJP_STATES], types.NoneType) == states_none))

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
