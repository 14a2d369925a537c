"""When a rollout's outputs fall: how many RK4 steps reach each output, and each node's step size.

A regular rollout reaches every output in ``substeps`` steps of dt/substeps.  Observations at
irregular times give each trajectory (each of its nodes) its own interval to the next output:
all trajectories of a batch then take the same number of steps over output interval t, the
fewest that keeps every step at most dt/substeps long, each trajectory at its own step size
(a trajectory that has ended has intervals of 0: it stays where it is).  So a batch with
irregular times runs in the same compiled loop as a regular one.
"""
import numpy as np

#: the most RK4 steps one output interval may take (a gap of 1,000 model steps in the data)
MAX_STEPS_PER_INTERVAL = 1000


def time_grid(spec, n_steps, n_nodes, dtype, intervals=None):
    """(nsub (n_steps,) int64, hstep (n_steps, n_nodes) in ``dtype``): the RK4 steps of each
    output interval and every node's step size in it.

    intervals : None (every interval is the model's dt), or (n_steps, n_nodes) times between
    consecutive outputs, >= 0, in the model's time units (a node's column: its trajectory's).
    """
    dtype = np.dtype(dtype)
    if intervals is None:
        nsub = np.full(n_steps, spec.substeps, dtype=np.int64)
        return nsub, np.full((n_steps, n_nodes), dtype.type(spec.dt / spec.substeps), dtype=dtype)
    iv = np.asarray(intervals, dtype=np.float64)
    if iv.shape != (n_steps, n_nodes):
        raise ValueError(f"intervals have shape {iv.shape}, expected {(n_steps, n_nodes)}")
    if not np.all(np.isfinite(iv)) or np.any(iv < 0):
        raise ValueError("intervals must be finite and >= 0")
    # the fewest steps of at most dt/substeps; an interval a rounding error above a multiple is that multiple
    need = np.ceil(iv.max(axis=1, initial=0.0) * spec.substeps / spec.dt - 1e-9).astype(np.int64)
    nsub = np.maximum(need, 0)
    if nsub.max(initial=0) > MAX_STEPS_PER_INTERVAL:
        t = int(np.argmax(nsub))
        raise ValueError(f"output interval {t} needs {nsub[t]} RK4 steps of dt/substeps = "
                         f"{spec.dt / spec.substeps:g}, more than {MAX_STEPS_PER_INTERVAL}")
    hstep = (iv / np.maximum(nsub, 1)[:, None]).astype(dtype)
    return nsub, hstep
