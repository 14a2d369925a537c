"""Compile the engine's drivers that the default tier calls into numba's on-disk cache, a list of
jobs at a time: python tests/warm_kernels.py float32:mpnode:blocks float64:l2s:recompute ...

A job is DTYPE:FIELD:DRIVERS, where DRIVERS is ``blocks`` (the block rollout and its VJP from kept
stage caches), ``stagewise`` (the stagewise rollout and its VJP) or ``recompute`` (the block VJP
that recomputes the stages).  Every model kind and size of a field runs the same compiled driver
for a dtype, so one tiny rollout and VJP per job compiles everything the tests call through it.

tests/conftest.py runs this in two processes at once, the first time a test calls the compiled
kernels (see "Compiling the kernels on both cores" there), the jobs split between them so that
both take about as long.
"""
import os
import sys
import time

import numpy as np

from mpnode.engine import compiling

#: exit status when numba's cache writes cannot be serialised here: nothing was compiled, and
#: the tests compile the kernels themselves, as they would without this script
CANNOT_LOCK = 3
DRIVERS = ("blocks", "stagewise", "recompute")


def warm(job):
    """Compile what job DTYPE:FIELD:DRIVERS names, through one tiny rollout and VJP."""
    from mpnode.base.graph import Graph
    from mpnode.engine import forward_with_vjp
    from mpnode.engine.precompile import compile_vjp
    from mpnode.model import Model

    dtype, field, drivers = job.split(":")
    if drivers not in DRIVERS:
        raise SystemExit(f"warm_kernels: unknown drivers {drivers!r} in {job!r}: one of {', '.join(DRIVERS)}")
    if drivers == "recompute":
        compile_vjp(np.dtype(dtype), "vjp_blocks_recompute", field)
        return
    graph = Graph.from_edges(3, [(0, 1), (1, 2)])
    messages = {"message_dim": 2} if field == "mpnode" else {}
    model = Model.create(state_dim=2, hidden=4, dt=0.1, kind=field, **messages)
    x, vjp = forward_with_vjp(model.spec, model.theta.astype(dtype), np.zeros((3, 2)), graph, None, 1,
                              driver=drivers)
    vjp(np.zeros_like(x))


if __name__ == "__main__":
    os.environ[compiling.VARIABLE] = "0"  # the two processes already compile at once
    if not compiling.serialise_cache_writes():  # no fcntl (Windows); else one lock for every mpnode process
        print("cannot serialise numba's cache writes here: nothing compiled", file=sys.stderr)
        sys.exit(CANNOT_LOCK)
    start = time.perf_counter()
    for job in sys.argv[1:]:
        warm(job)
    print(f"{len(sys.argv) - 1} jobs in {time.perf_counter() - start:.0f} s")
