"""Compile the engine's five drivers (rollout and VJP, block and stagewise, and the block VJP that
recomputes the stages) for one dtype and each field (MP-NODE, L2S) into numba's on-disk cache:
python tests/warm_kernels.py float32

tests/conftest.py runs this once per dtype, the two at once, the first time a test calls the
compiled kernels (see "Compiling the kernels on both cores" there).  Every model kind and size
of a field runs the same compiled driver for a dtype, so one tiny rollout and VJP per driver
and field compiles everything the suite calls.
"""
import os
import sys
import time

import numpy as np

from mpnode.engine import compiling

#: exit status when numba's cache writes cannot be serialised here: nothing was compiled, and
#: the tests compile the kernels themselves, as they would without this script
CANNOT_LOCK = 3


def warm(dtype):
    """One rollout and one VJP through each driver in ``dtype``, for each field."""
    from mpnode.base.graph import Graph
    from mpnode.engine import forward_with_vjp
    from mpnode.engine.precompile import compile_vjp
    from mpnode.model import Model

    graph = Graph.from_edges(3, [(0, 1), (1, 2)])
    for model in (Model.create(state_dim=2, message_dim=2, hidden=4, dt=0.1),
                  Model.create(state_dim=2, hidden=4, dt=0.1, kind="l2s")):
        theta = model.theta.astype(dtype)
        for driver in ("blocks", "stagewise"):
            x, vjp = forward_with_vjp(model.spec, theta, np.zeros((3, 2)), graph, None, 1, driver=driver)
            vjp(np.zeros_like(x))
        compile_vjp(dtype, "vjp_blocks_recompute", model.spec.kind)  # the block VJP that recomputes the stages


if __name__ == "__main__":
    os.environ[compiling.VARIABLE] = "0"  # the two precisions already compile at once, one process each
    if not compiling.serialise_cache_writes():  # no fcntl (Windows); else one lock for every mpnode process
        print("cannot serialise numba's cache writes here: nothing compiled", file=sys.stderr)
        sys.exit(CANNOT_LOCK)
    start = time.perf_counter()
    warm(np.dtype(sys.argv[1]))
    print(f"{sys.argv[1]} {time.perf_counter() - start:.0f} s")
