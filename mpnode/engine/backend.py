"""Where the work runs: numba's thread pool with BLAS pinned to one thread inside it, or the
NumPy path when numba cannot be imported."""
import contextlib

# ---------------------------------------------------------------------------
# Threads: numba's pool does the parallel work; BLAS runs single-threaded inside it.
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

