"""Where the work runs: threads (the calling thread and a pool for blocks of nodes, numba's own
pool for one large graph) with BLAS pinned to one thread, or the NumPy path when numba cannot be
imported."""
import contextlib
import threading

# ---------------------------------------------------------------------------
# Threads: blocks on the calling thread and a pool (`run_blocks`), one large graph on numba's
# pool; BLAS runs single-threaded inside either.
# ---------------------------------------------------------------------------
_blas_libs = None


@contextlib.contextmanager
def single_threaded_blas():
    """Pin BLAS to one thread while numba's threads call it (two thread pools on the same cores
    fight, and rollouts slow down many times).

    The libraries are found once (threadpoolctl's scan of the loaded libraries is slow beside a
    kernel call); each call then only sets and restores their thread counts.
    """
    global _blas_libs
    if _blas_libs is None:
        import scipy.linalg.cython_blas  # noqa: F401  (the BLAS numba calls must be loaded to be seen)
        from threadpoolctl import ThreadpoolController

        _blas_libs = ThreadpoolController().select(user_api="blas").lib_controllers
    before = [lib.num_threads for lib in _blas_libs]
    for lib in _blas_libs:
        lib.set_num_threads(1)
    try:
        yield
    finally:
        for lib, n in zip(_blas_libs, before):
            lib.set_num_threads(n)


def n_threads():
    import numba

    return numba.get_num_threads()


_pool = None  # the threads that run blocks beside the calling thread
_pool_size = 0


def run_blocks(run, n_blocks):
    """``run(b0, b1)`` for blocks 0..n_blocks on up to `n_threads` threads: the calling thread and a
    pool of threads each take the next block not yet taken until none is left (a Plan cuts a batch
    into one block per thread, more where its graphs change).  A thread with no block left sleeps
    instead of spinning at a barrier, so another process keeps its core.  ``run`` must release the
    GIL (the block drivers are compiled with nogil).  Blocks write disjoint rows and their own
    partial sums, so the results do not depend on which thread ran which block; an exception in
    any block is raised here, once every thread has stopped."""
    workers = min(n_blocks, n_threads()) - 1
    if workers <= 0:
        run(0, n_blocks)
        return
    blocks, lock, stopped = iter(range(n_blocks)), threading.Lock(), threading.Event()

    def take_blocks():
        try:
            while not stopped.is_set():
                with lock:
                    b = next(blocks, None)
                if b is None:
                    return
                run(b, b + 1)
        except BaseException:  # a failed block, or Ctrl-C: no thread takes another
            stopped.set()
            raise

    futures = []
    try:
        for _ in range(workers):
            futures.append(_threads(workers).submit(take_blocks))
        take_blocks()
    except BaseException:  # here, or while submitting: no thread takes another block
        stopped.set()
        raise
    finally:  # even on Ctrl-C: no thread may write into the caller's arrays once this returns
        _wait_all(futures)
    for f in futures:
        f.result()


def _threads(workers):
    """The pool, grown to ``workers`` threads if it has fewer."""
    global _pool, _pool_size
    if workers > _pool_size:
        from concurrent.futures import ThreadPoolExecutor

        _pool, _pool_size = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mpnode-blocks"), workers
    return _pool


def _wait_all(futures):
    """Wait for every future; a Ctrl-C meanwhile is raised once they have all ended."""
    interrupted = False
    for f in futures:
        while True:
            try:
                f.exception()
                break
            except KeyboardInterrupt:
                interrupted = True
    if interrupted:
        raise KeyboardInterrupt


# ---------------------------------------------------------------------------
# Backends: the compiled kernels, or the NumPy path where numba cannot be imported.
# ---------------------------------------------------------------------------
#: "auto" (numba when it imports, else numpy), "numba" (the compiled kernels), "numpy"
#: (mpnode.engine.numpy_path: the same rollout in plain NumPy; slow, no training)
BACKENDS = ("auto", "numba", "numpy")
_numba_problem = []  # [] untried; [None] numba imports; [reason] it does not
_warned = []  # [True] once the fallback to NumPy has been announced


def numba_problem():
    """None when the compiled kernels import, else why not (tried once, then remembered)."""
    if not _numba_problem:
        try:
            from . import kernels  # noqa: F401  (imports numba and declares the kernels; compiles nothing)
            _numba_problem.append(None)
        except Exception as e:  # a missing numba, or a broken one (llvmlite raises OSError, ...)
            _numba_problem.append(f"{type(e).__name__}: {e}")
    return _numba_problem[0]


def resolve_backend(backend="auto", purpose="the compiled backend"):
    """"numba" or "numpy" for a requested backend (BACKENDS).

    "auto" falls back to "numpy" when numba cannot be imported, with one warning per
    process; "numba" then raises ImportError saying why.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, not {backend!r}")
    if backend == "numpy":
        return backend
    problem = numba_problem()
    if problem is None:
        return "numba"
    if backend == "numba":
        raise ImportError(f"{purpose} needs numba, which cannot be imported here ({problem}); "
                          "install numba, or roll out with backend='numpy' (no training)")
    if not _warned:
        import warnings

        _warned.append(True)
        warnings.warn(f"numba cannot be imported ({problem}): using the NumPy path, which rolls out "
                      "the same models several times slower and cannot train", RuntimeWarning, stacklevel=3)
    return "numpy"

