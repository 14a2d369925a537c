"""The compiled engine: fields on tiles of nodes (MP-NODE, L2S), RK4 drivers and their adjoint.

Modules: ``layers`` (dense layers, tanh, neighbour sums), ``feature_major`` (products on
(width, n) tiles, their sums unrolled per chunk width: the MP-NODE field's layers and the dense
neighbour sums), ``mpnode_field`` and ``l2s_field`` (one field each: send, update and their VJPs),
``kinematics`` (the derivatives a model's kinematics fix, and their VJP), ``rk4`` (the drivers),
``reorder`` (node rows between the user's order and the kernels').
`mpnode.engine` is the Python entry point; nothing else calls these directly.

Numba caches each compiled function under its own source file's hash, but a compiled
driver contains the code of everything it calls from the sibling modules: after an
edit to ``layers.py`` alone, numba would still serve the drivers compiled with the old
layers.  So the cache folder of this package is keyed by a digest of all its sources.  It
lives under NUMBA_CACHE_DIR when that is set, else in the user's cache folder (an installed
package's own folder may be read-only, and a new checkout would compile again).
"""
import hashlib
import os
from pathlib import Path

import numba

from ..codegen import build_numba_codegen


def cache_base():
    """NUMBA_CACHE_DIR, else the user's cache folder for mpnode (XDG_CACHE_HOME or ~/.cache;
    LOCALAPPDATA on Windows)."""
    if numba.config.CACHE_DIR:
        return numba.config.CACHE_DIR
    if os.name == "nt" and os.environ.get("LOCALAPPDATA"):
        return os.path.join(os.environ["LOCALAPPDATA"], "mpnode", "Cache")
    return os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "mpnode")


def _cache_dir():
    """<cache_base()>/mpnode-kernels-<digest of the sources>."""
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(here.glob("*.py")) + [here.parent / "dims.py"]:  # and the dims layout they read
        digest.update(path.name.encode() + path.read_bytes())
    return os.path.join(cache_base(), "mpnode-kernels-" + digest.hexdigest()[:16])


build_numba_codegen()  # before the first declaration: the vector width it compiles for
_user_cache_dir = numba.config.CACHE_DIR
numba.config.CACHE_DIR = _cache_dir()  # read when each function below is decorated
try:
    from .feature_major import dense_sum  # noqa: F401
    from .layers import (  # noqa: F401
        dense_backward,
        dense_forward,
        dense_tanh_backward,
        dense_tanh_forward,
    )
    from .reorder import rows_to_kernel_order, rows_to_user_order  # noqa: F401
    from .rk4 import (  # noqa: F401
        STAGE_TILE,
        TILE,
        caches,
        rollout_blocks,
        rollout_stagewise,
        vjp_blocks,
        vjp_stagewise,
    )
finally:
    numba.config.CACHE_DIR = _user_cache_dir

from . import feature_major, kinematics, l2s_field, layers, mpnode_field, reorder, rk4  # noqa: E402

#: the modules that declare compiled functions
MODULES = (feature_major, kinematics, l2s_field, layers, mpnode_field, reorder, rk4)
