"""numba's code generator, built before mpnode declares a compiled function: the vector width.

LLVM's tuning for Intel's AVX-512 cores keeps vectorised loops at 256 bits, and the MP-NODE
field's products are faster at 512 (docs/evidence/speed.md#512-bit-vectors-for-the-command-line).
numba builds one generator per process, when the process declares its first numba function,
so the width holds for every function compiled in it, a host program's too: only mpnode's own
processes ask for it (`ask_for_wide_vectors`), and a host program opts in the same way.
"""
import functools
import os

VARIABLE = "MPNODE_WIDE_VECTORS"


def ask_for_wide_vectors():
    """Ask for the CPU's full vector width in this process and the workers it starts (they
    inherit the environment), unless the user set MPNODE_WIDE_VECTORS (0: numba's default)."""
    os.environ.setdefault(VARIABLE, "1")


@functools.cache
def build_numba_codegen():
    """Build numba's code generator, unless something in the process built it before: for the
    CPU's full vector width where MPNODE_WIDE_VECTORS=1.  NUMBA_CPU_FEATURES, if set, wins;
    numba's configuration is left as it was.  Every module of mpnode that declares compiled
    functions calls this before it does; the first call does the work."""
    import numba
    from numba.core.registry import cpu_target

    user = numba.config.CPU_FEATURES
    numba.config.CPU_FEATURES = _wide_vector_features() or user
    try:
        cpu_target.target_context  # noqa: B018  (built on first access, with numba.config's features)
    finally:
        numba.config.CPU_FEATURES = user


def _wide_vector_features():
    """numba's view of the host's CPU features (NUMBA_ENABLE_AVX=0 masks AVX) with LLVM's
    256-bit preference lifted, or None: not asked for, no AVX-512, or the user chose the features."""
    import numba
    from numba.core.codegen import get_host_cpu_features

    if os.environ.get(VARIABLE) != "1" or numba.config.CPU_FEATURES is not None:
        return None
    features = get_host_cpu_features()
    return features + ",-prefer-256-bit" if "+avx512f" in features.split(",") else None
