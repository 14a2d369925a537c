"""numba's code generator, built before mpnode declares a compiled function: the vector width.

LLVM's tuning for Intel's AVX-512 cores keeps loops at 256 bits; with 512 the MP-NODE field
ran 1.2-1.35x faster (docs/evidence/speed.md#512-bit-vectors-for-the-command-line).  numba
builds one generator per process, with the CPU features in its configuration at that moment,
so the width holds for every function compiled in the process, a host program's too: the
`mpnode` command asks for it (MPNODE_WIDE_VECTORS=1, for itself and the workers it starts),
a library user opts in the same way.
"""
import os


def build_numba_codegen():
    """Build numba's code generator, unless something in the process built it before: for the
    CPU's full vector width where MPNODE_WIDE_VECTORS=1.  NUMBA_CPU_FEATURES, if set, wins;
    numba's configuration is left as it was.  Every module of mpnode that declares compiled
    functions calls this before it does."""
    import numba
    from numba.core.registry import cpu_target

    user = numba.config.CPU_FEATURES
    numba.config.CPU_FEATURES = _wide_vector_features() or user
    try:
        cpu_target.target_context  # noqa: B018  (built on first access, with numba.config's features)
    finally:
        numba.config.CPU_FEATURES = user


def _wide_vector_features():
    """The host's CPU features with LLVM's 256-bit preference lifted, or None (not asked for,
    no AVX-512, or the user chose the features)."""
    import numba

    if os.environ.get("MPNODE_WIDE_VECTORS") != "1" or numba.config.CPU_FEATURES is not None:
        return None
    import llvmlite.binding as llvm

    features = llvm.get_host_cpu_features().flatten()
    return features + ",-prefer-256-bit" if "+avx512f" in features.split(",") else None
