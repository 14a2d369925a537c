"""The engine: RK4 rollouts of a field over a flat (block-diagonal) graph, and their exact VJP.

`forward` integrates (`integrate` from a full state); `forward_with_vjp` (and
`integrate_with_vjp`) also returns the vector-Jacobian product of
the rollout, the *discrete adjoint*: for any cotangent gx of the output states it gives
the exact gradient, with respect to the parameters, the initial state and (on request)
the controls, of <gx, rollout> as computed (not of the ODE it approximates).  Losses, windows,
multiple shooting are the caller's business (`mpnode.training.losses`).  Outputs fall every dt, or
at each trajectory's own times (``intervals``, see `mpnode.engine.schedule`).  Cost: memory for one
state per RK4 step (sum of the steps + 1 arrays of (M, dz)), and every stage's inputs and activations
while they fit in KEEP_CACHES_BYTES (beyond, the reverse pass recomputes them, so memory does not grow
with the hidden width); time a few rollouts' worth (the forward and a VJP that costs about twice a
forward; docs/evidence/speed.md).

Arrays here are time-major and flat over nodes: x (T+1, M, dx), u (T, M, du).
`mpnode.model` turns (B, T+1, N, dx) batches into this layout.
"""
import functools
import sys
from dataclasses import replace

import numpy as np

from mpnode.base.graph import Graph

from . import compiling
from .backend import resolve_backend, run_blocks, single_threaded_blas
from .dims import KIND, L2S
from .plan import plan_for
from .schedule import time_grid
from .spec import checked_controls

# ---------------------------------------------------------------------------
# Entry points
# ---------------------------------------------------------------------------


def _whole_systems(spec, x0, u, graph):
    """A plain NODE as the kernels run it: an MP-NODE field without messages on one "node"
    per system, whose state is [x_1, ..., x_N] and control [u_1, ..., u_N] (node-major, so
    the flat rows of a system reshape to it for free), on a graph with no edges."""
    n = spec.n_nodes
    m, dx = x0.shape
    if graph.n_nodes != m:
        raise ValueError(f"graph has {graph.n_nodes} nodes but the states have {m}")
    if m % n:
        raise ValueError(f"{m} nodes are not whole systems of {n} nodes (a node model's n_nodes)")
    kin = None if spec.kinematics is None else spec.kinematics.for_systems(n, dx)
    inner = replace(spec, kind="mpnode", state_dim=n * dx, control_dim=n * spec.control_dim, attr_dim=0,
                    n_nodes=None, kinematics=kin)
    u = None if u is None else np.asarray(u).reshape(u.shape[0], m // n, n * spec.control_dim)
    return inner, np.asarray(x0).reshape(m // n, n * dx), u, _edgeless(m // n)


def _per_system(spec, intervals):
    """A node model's intervals (T, M) as its whole systems' (T, M / N): a system's nodes share them."""
    if intervals is None:
        return None
    iv = np.asarray(intervals)
    return iv.reshape(iv.shape[0], -1, spec.n_nodes)[:, :, 0]


def _kernel_theta(spec, theta):
    """The parameters as the kernels read them: followed by the kinematics' constants, if any."""
    theta = np.ascontiguousarray(theta)
    if spec.kinematics is None:
        return theta
    return np.concatenate([theta, spec.kinematics.constants(theta.dtype)])


@functools.lru_cache(maxsize=16)
def _edgeless(n):
    return Graph(np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int64))


def _field(spec):
    """The kernels' field marker for ``spec`` and the field's name for `compiling` (each field's
    drivers compile apart: `kernels.rk4`)."""
    return (1, "l2s") if spec.dims[KIND] == L2S else (None, "mpnode")


def _run(spec, theta, z0, graph, u, n_steps, driver, keep_states, ordering, intervals):
    """The forward rollout from the full state z0: (x (n_steps+1, M, dx) and z at the end in
    the user's node order, states, the kept stage caches (None for one large graph) and u,
    the time grid and the plan as the kernels saw them)."""
    from . import kernels

    theta = _kernel_theta(spec, theta)
    z0 = np.ascontiguousarray(z0, dtype=theta.dtype)
    m = z0.shape[0]
    if z0.shape != (m, spec.state_width):
        raise ValueError(f"the full state has shape {z0.shape}, expected (M, {spec.state_width}) (x, then messages)")
    u = checked_controls(spec, graph, u, n_steps, m, theta.dtype)
    plan = plan_for(graph, spec, theta.dtype, driver, ordering)
    nsub, hstep = time_grid(spec, n_steps, m, theta.dtype, intervals)
    z0, u = plan.to_kernel_order(z0), np.ascontiguousarray(plan.to_kernel_order(u, axis=1))
    if intervals is not None:  # a regular grid's step sizes are the same at every node
        hstep = np.ascontiguousarray(plan.to_kernel_order(hstep, axis=1))
    out = _touched((n_steps + 1, m, spec.state_dim), theta.dtype)
    n_states = int(nsub.sum()) + 1 if keep_states else 0
    states = _touched((n_states, m if keep_states else 0, spec.state_width), theta.dtype)
    zend = np.empty_like(z0)
    g = plan.kernel_graph()
    kept = None if plan.blocks is None else _stage_caches(spec, n_states - 1, m, theta)
    l2s, field = _field(spec)
    if keep_states:  # a VJP follows: its driver compiles on the other core while this one compiles the rollout's
        compiling.compile_vjp_ahead(theta.dtype, _vjp_driver(plan, _kept_any(kept)), field)
    elif plan.blocks is not None:  # none does: the other core compiles the neighbour sums
        compiling.compile_sums_ahead(theta.dtype, field)
    compiling.before_call("rollout_stagewise" if plan.blocks is None else "rollout_blocks", theta.dtype, field)
    with single_threaded_blas():
        if plan.blocks is None:
            kernels.rollout_stagewise(theta, spec.dims, l2s, z0, u, g, nsub, hstep, out, states, zend)
        else:
            run_blocks(lambda b0, b1: kernels.rollout_blocks(
                theta, spec.dims, l2s, b0, b1, z0, u, g, plan.blocks, plan.dense_n, plan.dense_off, plan.dense_AT,
                nsub, hstep, out, states, zend, kept), len(plan.blocks) - 1)
    return plan.to_user_order(out), states, kept, plan.to_user_order(zend[None])[0], u, (nsub, hstep), plan


#: the stage caches of a rollout's every RK4 step are kept for its VJP up to this size: the
#: reverse pass then skips recomputing the stages, a third of a training step's work
#: (docs/evidence/speed.md#kept-stage-caches); larger rollouts recompute them, so that memory
#: stays one state per step.
KEEP_CACHES_BYTES = 128 * 2**20
#: dtype -> the last buffer of kept stage caches: the next rollout reuses it once no VJP's caches
#: view it (a training step's, after the step), instead of having fresh pages mapped and faulted
#: in for every batch.  Checked by reference count when it is taken, not by a callback when a
#: VJP dies: a Ctrl-C landing in such a callback would be swallowed.
_caches_buffers = {}


def _caches_layout(spec, n_rk4_steps, m, dtype):
    """(rows, widths, padded sizes) of the five stage caches of every RK4 step, or None when there
    is nothing to keep: no VJP asked, or more than KEEP_CACHES_BYTES."""
    if n_rk4_steps <= 0:
        return None
    from . import kernels

    rows = 4 * n_rk4_steps * m
    widths = [c.shape[2] for c in kernels.caches(spec.dims, 1, 0, np.empty(0, dtype))]
    lanes = 64 // np.dtype(dtype).itemsize  # every array starts on a 64-byte boundary, as the kernels' own
    padded = [-(-rows * w // lanes) * lanes for w in widths]
    return None if sum(padded) * np.dtype(dtype).itemsize > KEEP_CACHES_BYTES else (rows, widths, padded)


def _stage_caches(spec, n_rk4_steps, m, theta):
    """The arrays rollout_blocks fills with every RK4 step's stage caches (rows per
    `kernels.rk4.block_caches`), views of one buffer; arrays without rows when there is nothing
    to keep (`_caches_layout`)."""
    layout = _caches_layout(spec, n_rk4_steps, m, theta.dtype)
    if layout is None:
        return tuple(np.empty((0, 0), theta.dtype) for _ in range(5))  # the kernels' five caches
    rows, widths, padded = layout
    lanes = 64 // theta.itemsize
    buf = _caches_buffers.pop(theta.dtype, None)  # popped: no other thread's rollout takes it meanwhile
    if buf is None or sys.getrefcount(buf) > 2 or buf.size < sum(padded) + lanes:  # 2: `buf` and the call's
        buf = np.empty(sum(padded) + lanes, theta.dtype)
    at = (-buf.ctypes.data % 64) // theta.itemsize
    kept = []
    for w, size in zip(widths, padded):
        kept.append(buf[at:at + rows * w].reshape(rows, w))
        at += size
    _caches_buffers[theta.dtype] = buf
    return tuple(kept)


def _touched(shape, dtype):
    """An array for the kernels to write, its memory touched first, here, in one pass.

    Fresh memory is mapped on first touch; taken inside the kernels' parallel loops, one output
    slice at a time, those page faults cost a million-node rollout a fifth of its time, against
    under one percent here (docs/evidence/speed.md#a-million-nodes-where-the-time-went)."""
    a = np.empty(shape, dtype=dtype)
    a.fill(0)
    return a


def initial_state(spec, x0, dtype=None):
    """The full state [x0, 0] (M, dx + dm) a rollout starts from: messages start at 0."""
    x0 = np.asarray(x0)
    z0 = np.zeros((x0.shape[0], spec.state_width), dtype=dtype or x0.dtype)
    z0[:, :spec.state_dim] = x0
    return z0


def forward(spec, theta, x0, graph, u=None, n_steps=1, driver="auto", backend="auto", ordering="auto",
            intervals=None):
    """Integrate from x0 (messages start at 0).

    x0 : ndarray, shape (M, dx); u : ndarray, shape (n_steps, M, du) or None;
    returns x : ndarray, shape (n_steps+1, M, dx), in theta's dtype.
    intervals : None (outputs every dt) or (n_steps, M): each node's time to its next output
        (mpnode.engine.schedule); u is held over each interval.
    driver, ordering : see plan_for.  For kind "node" the graph only gives M (whole systems).
    backend : see `resolve_backend` ("auto": the compiled kernels, NumPy without numba).
    """
    z0 = initial_state(spec, x0, np.asarray(theta).dtype)
    return integrate(spec, theta, z0, graph, u, n_steps, driver, backend, ordering, intervals)[0]


def integrate(spec, theta, z0, graph, u=None, n_steps=1, driver="auto", backend="auto", ordering="auto",
              intervals=None):
    """Integrate from a full state z0 = [x, m] (M, dx + dm), e.g. where an earlier call stopped.

    Returns (x, z): x (n_steps+1, M, dx) as `forward`, z (M, dx + dm) the full state at the
    end.  Calling this T times with n_steps=1, each from the last z, gives bit for bit the
    rollout of T steps (same kernels, same plan): the stepping API (mpnode.Simulator) is
    built on it.  Other arguments as `forward`.
    """
    if resolve_backend(backend) == "numpy":
        from . import numpy_path

        return numpy_path.integrate(spec, theta, z0, graph, u, n_steps, intervals=intervals)
    z_shape = np.shape(z0)
    shape = (n_steps + 1, z_shape[0], spec.state_dim)
    if spec.kind == "node":
        intervals = _per_system(spec, intervals)
        spec, z0, u, graph = _whole_systems(spec, z0, u, graph)
    x, _, _, zend, _, _, _ = _run(spec, theta, z0, graph, u, n_steps, driver, False, ordering, intervals)
    return x.reshape(shape), zend.reshape(z_shape)


def forward_with_vjp(spec, theta, x0, graph, u=None, n_steps=1, driver="auto", keep_states=True, ordering="auto",
                     intervals=None):
    """`forward`, and the vector-Jacobian product of the rollout (the discrete adjoint).

    Returns (x, vjp): x as `forward`; ``vjp(gx)`` takes the cotangent of every output
    state, gx : ndarray, shape (n_steps+1, M, dx), and returns (gtheta like theta,
    gx0 of shape (M, dx)): the gradient of sum(gx * x) with respect to theta and x0;
    ``vjp(gx, controls=True)`` returns (gtheta, gx0, gu) with gu (n_steps, M, du) the
    gradient with respect to u (model predictive control; training does not ask for it);
    ``node_attrs=True`` appends ga (M, dp), the gradient with respect to the node attributes (the
    last attr_dim control columns, held over every step, as the kernels read them);
    ``edge_weights=True`` appends gw (E,), the gradient with respect to the graph's edge weights
    in its CSR order (1 for an unweighted graph's edges; fitting a network's parameters), which
    needs the block drivers (a graph the plan splits, or driver="blocks").
    vjp may be called several times; it keeps one state per RK4 step alive
    (``keep_states=False``: no vjp, the rollout alone).  Compiled kernels only (numba):
    the NumPy path rolls out but does not train.
    """
    z0 = initial_state(spec, x0, np.asarray(theta).dtype)
    return integrate_with_vjp(spec, theta, z0, graph, u, n_steps, driver, keep_states, ordering, intervals)


def integrate_with_vjp(spec, theta, z0, graph, u=None, n_steps=1, driver="auto", keep_states=True,
                       ordering="auto", intervals=None):
    """`forward_with_vjp` from a full state z0 = [x, m] (M, dx + dm), as `integrate`.

    gx0 is then the gradient with respect to z0's x columns, its messages held at their
    values (a step's Jacobian as `mpnode.Simulator.jacobians` defines it).
    """
    resolve_backend("numba", purpose="computing gradients (training)")
    z0 = np.asarray(z0)
    shape = (n_steps + 1, z0.shape[0], spec.state_dim)
    u_shape = (n_steps, z0.shape[0], spec.control_dim)
    n_edges, attr_dim = graph.n_edges, spec.attr_dim
    if spec.kind == "node":
        intervals = _per_system(spec, intervals)
        spec, z0, u, graph = _whole_systems(spec, z0, u, graph)
    x, states, kept, _, u, grid, plan = _run(spec, theta, z0, graph, u, n_steps, driver, keep_states, ordering,
                                             intervals)
    x = x.reshape(shape)
    if not keep_states:
        return x, None
    theta = np.ascontiguousarray(theta)

    def vjp(gx, controls=False, edge_weights=False, node_attrs=False):
        if np.shape(gx) != shape:
            raise ValueError(f"the cotangent has shape {np.shape(gx)}, the rollout {shape}")
        gtheta, gx0, gu, gw = _reverse(spec, theta, plan, u, grid, states, kept, gx, controls or node_attrs,
                                       edge_weights)
        out = (gtheta, gx0.reshape(shape[1:]))
        if controls:
            out += (gu.reshape(u_shape),)
        if node_attrs:  # held over every step: the sum of their columns' cotangents
            out += (gu.reshape(u_shape)[:, :, u_shape[2] - attr_dim:].sum(axis=0),)
        if edge_weights:  # a node model never reads the graph: its edges' cotangents are 0
            out += (gw if gw.size == n_edges else np.zeros(n_edges, theta.dtype),)
        return out

    return x, vjp


def compile_vjp_ahead(spec, dtype, graph, n_steps=1, driver="auto", ordering="auto"):
    """Have the VJP driver that a rollout of ``n_steps`` on ``graph`` needs compile on the other core
    (`compiling`), if it is not compiled yet, while this process goes on (a training run's first
    validation, say)."""
    if spec.kind == "node":
        spec, _, _, graph = _whole_systems(spec, np.zeros((graph.n_nodes, spec.state_dim)), None, graph)
    plan = plan_for(graph, spec, dtype, driver, ordering)
    n_rk4_steps = int(time_grid(spec, n_steps, graph.n_nodes, dtype, None)[0].sum())
    keeps = _caches_layout(spec, n_rk4_steps, graph.n_nodes, dtype) is not None
    compiling.compile_vjp_ahead(dtype, _vjp_driver(plan, keeps), _field(spec)[1])


def _vjp_driver(plan, keeps_caches, edge_weights=False, l2s=None):
    """The reverse driver for a rollout planned so: the stagewise one for one large graph; the block
    one reading the kept stage caches, or recomputing the stages (`kernels.rk4.vjp_blocks`) where
    none were kept, or for an MP-NODE's edge weights (their cotangent needs the stages' messages)."""
    if plan.blocks is None:
        return "vjp_stagewise"
    return "vjp_blocks" if keeps_caches and not (edge_weights and l2s is None) else "vjp_blocks_recompute"


def _kept_any(kept):
    """Did the rollout keep its stage caches (`_stage_caches`; None for the stagewise driver)?"""
    return kept is not None and kept[0].shape[0] > 0


def _reverse(spec, theta, plan, u, grid, states, kept, gx, controls=False, edge_weights=False):
    """The kernels' reverse pass for the cotangent ``gx`` of every output: (gtheta, gx0 (M, dx),
    gu (T, M, du) or None, gw (E,) or None) in the user's node order."""
    from . import kernels

    if edge_weights and plan.blocks is None:
        raise ValueError("the edge weights' cotangent needs the block drivers: roll out with driver='blocks'")
    n_params = theta.size
    theta = _kernel_theta(spec, theta)
    n_steps, m = u.shape[0], states.shape[1]
    gx = np.asarray(gx, dtype=theta.dtype).reshape(-1, m, spec.state_dim)
    gx = np.ascontiguousarray(plan.to_kernel_order(gx, axis=1))
    n_parts = len(plan.blocks) - 1 if plan.blocks is not None else -(-m // kernels.STAGE_TILE)
    gthetas = np.empty((n_parts, theta.size), dtype=theta.dtype)
    gx0 = np.empty((m, spec.state_dim), dtype=theta.dtype)
    gu = np.zeros((n_steps, m if controls else 0, spec.control_dim), dtype=theta.dtype)
    gw = np.zeros(plan.csr.n_edges if edge_weights else 0, dtype=theta.dtype)
    g, gt = plan.kernel_graph(), plan.kernel_transposed()
    nsub, hstep = grid
    l2s, field = _field(spec)
    name = _vjp_driver(plan, _kept_any(kept), edge_weights, l2s)
    compiling.before_call(name, theta.dtype, field)
    with single_threaded_blas():
        if plan.blocks is None:
            kernels.vjp_stagewise(theta, spec.dims, l2s, u, g, gt, nsub, hstep, states, gx, gthetas, gx0, gu)
        else:  # the block driver takes the states or the kept caches, the other None: two drivers compiled apart
            states, kept = (states, None) if name == "vjp_blocks_recompute" else (None, kept)
            run_blocks(lambda b0, b1: kernels.vjp_blocks(
                theta, spec.dims, l2s, b0, b1, u, g, gt, plan.blocks, plan.dense_n, plan.dense_off, plan.dense_A,
                plan.dense_AT, nsub, hstep, states, kept, gx, gthetas, gx0, gu, gw), len(plan.blocks) - 1)
    if plan.order is not None:
        gx0[plan.order] = gx0.copy()
    gtheta = gthetas.sum(axis=0, dtype=theta.dtype)[:n_params]
    gw /= plan.weight_scale or 1.0  # the kernels weigh by w / weight_scale
    return gtheta, gx0, plan.to_user_order(gu) if controls else None, gw if edge_weights else None
