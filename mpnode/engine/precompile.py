"""The process `compiling.compile_vjp_ahead` starts: ``python -m mpnode.engine.precompile float32 vjp_blocks
mpnode`` compiles one VJP driver (`compiling.DRIVERS`), for one field ("mpnode" or "l2s"), into numba's
on-disk cache and exits; ``... float32 sums mpnode``, which `compiling.compile_sums_ahead` starts, the
neighbour sums alone (`compile_sums`)."""
import sys

import numpy as np

from mpnode.base.graph import Graph

from .compiling import serialise_cache_writes
from .layouts import n_params
from .plan import plan_for
from .rollout import _reverse, _stage_caches
from .schedule import time_grid
from .spec import FieldSpec, checked_controls


def compile_vjp(dtype, name, field="mpnode"):
    """One tiny VJP of ``field`` through driver ``name`` ("vjp_blocks", "vjp_blocks_recompute" or
    "vjp_stagewise") in ``dtype``, from stand-in states (the reverse pass's types are all that
    matter here): numba compiles the VJP driver and its callees into the on-disk cache, and the
    rollout driver is never called."""
    spec, graph = _tiny(field)
    theta = np.zeros(n_params(spec), dtype)
    plan = plan_for(graph, spec, theta.dtype, "stagewise" if name == "vjp_stagewise" else "blocks")
    grid = time_grid(spec, 1, 3, theta.dtype, None)
    u = checked_controls(spec, graph, None, 1, 3, theta.dtype)
    n_states = int(grid[0].sum()) + 1
    states = np.zeros((n_states, 3, spec.state_width), dtype)
    kept_steps = n_states - 1 if name == "vjp_blocks" else 0  # no caches kept: the stages are recomputed
    kept = None if name == "vjp_stagewise" else _stage_caches(spec, kept_steps, 3, theta)
    _reverse(spec, theta, plan, u, grid, states, kept, np.zeros((2, 3, spec.state_dim), dtype))


def compile_sums(dtype):
    """The MP-NODE field's neighbour sums (`kernels.layers.aggregate_tile`, the largest function a
    rollout compiles), through the reverse pass's transpose of them, which calls them with the
    types the rollout does: a rollout compiling meanwhile in another process loads them instead
    of compiling them (`compiling._OneCompileEach`)."""
    from .dims import DX, SELF_MSG
    from .kernels import layers

    spec, graph = _tiny("mpnode")
    plan = plan_for(graph, spec, np.dtype(dtype), "blocks")
    sums, target = np.zeros((3, spec.message_dim), dtype), np.zeros((3, spec.state_width), dtype)
    layers.transpose_tile(sums, *plan.kernel_transposed(), spec.dims[SELF_MSG], 0, 3, 0, target, spec.dims[DX])


def _tiny(field):
    """A tiny model of ``field`` and a 3-node path: only the kernels' argument types matter here."""
    spec = FieldSpec(kind=field, state_dim=2, message_dim=2 if field == "mpnode" else 0, hidden=4, dt=0.1)
    return spec, Graph.from_edges(3, [(0, 1), (1, 2)])


if __name__ == "__main__":
    serialise_cache_writes()
    if sys.argv[2] == "sums":
        compile_sums(np.dtype(sys.argv[1]))
    else:
        compile_vjp(np.dtype(sys.argv[1]), sys.argv[2], sys.argv[3])
