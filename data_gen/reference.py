"""The reference simulator as a yardstick: how long it takes, and how close it gets, on a file's states.

`mpnode eval` sets the learned rollout's speed beside this (speed against error).
"""
import time

import numpy as np

from mpnode.evaluation.metrics import nmse

from .simulate import integrate
from .systems import SYSTEMS, file_rhs


def reference_timing(traj, sample):
    """Time the reference simulator on the first ``sample`` initial states of ``traj``.

    Returns {system, integrator, sample, reference_seconds_per_trajectory,
    reference_nmse_vs_file (its normalised MSE against the file, steps 1..T, variances of
    the whole file)}, or None
    when the file does not name a reference system this package can rebuild from the
    file's own parameters (predictions, controlled systems, foreign files).
    """
    if traj.system not in SYSTEMS or "predicted_by" in traj.attrs or traj.u is not None:
        return None
    system = SYSTEMS[traj.system]
    if traj.state_dim != system.state_dim:
        return None
    try:
        rhs = file_rhs(traj)
    except (KeyError, ValueError, TypeError):
        return None
    method = str(traj.attrs.get("integrator", "DOP853"))
    rtol, atol = float(traj.attrs.get("rtol", 1e-9)), float(traj.attrs.get("atol", 1e-9))
    k = min(sample, traj.n_trajectories)
    x = np.asarray(traj.x, dtype=np.float64)
    out = np.empty((k,) + x.shape[1:])
    start = time.perf_counter()
    for b in range(k):
        out[b] = integrate(rhs[int(traj.graph_index[b])], x[b, 0], traj.horizon, traj.dt, method, rtol, atol,
                           system.guard)
    seconds = time.perf_counter() - start
    return {"system": traj.system, "integrator": f"{method} rtol={rtol:g} atol={atol:g}", "sample": k,
            "reference_seconds_per_trajectory": seconds / k,
            "reference_nmse_vs_file": nmse(out[:, 1:], x[:k, 1:], spread=x)}


def speed_against_reference(model, traj, result, sample):
    """The reference's timing beside the learned model's on the same initial states.

    result : the EvalResult of ``model`` on ``traj`` (its substeps and full-batch time).
    Returns reference_timing's dict plus learned_seconds_per_trajectory (the first
    ``sample`` trajectories as one batch), ..._full_batch and speedup; None as reference_timing.
    """
    from mpnode.evaluation.evaluate import learned_seconds_per_trajectory

    ref = reference_timing(traj, sample)
    if ref is None:
        return None
    m = model.with_spec(dt=float(traj.dt), substeps=result.substeps)
    ref["learned_seconds_per_trajectory"] = learned_seconds_per_trajectory(m, traj, ref["sample"])
    ref["learned_seconds_per_trajectory_full_batch"] = result.rollout_seconds / result.n_trajectories
    ref["speedup"] = ref["reference_seconds_per_trajectory"] / ref["learned_seconds_per_trajectory"]
    return ref
