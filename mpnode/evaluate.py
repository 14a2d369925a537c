"""Evaluating a model on a trajectory file: roll out from every initial state, measure error and speed.

Error is the normalised MSE of the seed paper: the squared error of every state
coordinate divided by the variance of that state dimension over the file's true
states (all trajectories, steps and nodes), averaged over trajectories, nodes and
dimensions -- per step, and over steps 1..T.  A value of 1 means "no better than
predicting the file's mean"; 0 is perfect.

A prediction that becomes non-finite, or leaves a box ten times as wide as the data
(per dimension: [mid - 5 r, mid + 5 r] with mid and r the midpoint and range of the
true states), counts as blown up; its error from that step on is infinite.

Averages hide where a chaotic prediction (Lorenz) parts from the truth, so the
*predictable horizon* is reported too: per trajectory, the first step t >= 1 at which
its own normalised MSE (mean over nodes and dimensions, same variances as above)
exceeds a threshold (0.1 and 1.0 by default; a blown-up step exceeds every threshold),
and per file the lower median of that step over trajectories (in steps and in time,
step * dt).  A trajectory that never exceeds the threshold counts as "beyond T"; if at
least half do, the median is reported as None ("beyond the horizon").

With ``substeps="auto"`` the number of RK4 substeps is chosen by step doubling
(`mpnode.stepsize.choose_substeps`); after the rollout `mpnode.stepsize.stability_check`
says whether a blow-up was caused by too large an RK4 step (``step_too_large``).
This module knows nothing of any particular system.
"""
import math
import time
from dataclasses import dataclass

import numpy as np

from . import stepsize
from .data import Trajectories
from .errors import NumericalError
from .train import check_data

HORIZON_THRESHOLDS = (0.1, 1.0)


@dataclass
class EvalResult:
    """nmse_per_step : ndarray, shape (T+1,) (step 0 is the initial state, 0 by construction)
    nmse : mean over steps 1..T;  nmse_last : step T
    first_bad_step : first step where any prediction blew up (None if none did)
    n_bad : number of trajectories that blew up
    rollout_seconds : wall time of the learned rollouts of all B trajectories
    node_steps_per_second : B*N*T / rollout_seconds
    predictions : ndarray, shape (B, T+1, N, dx), data units
    substeps : RK4 substeps per dt used;  substeps_report : `choose_substeps` report (auto) or None
    stability : `stepsize.stability_check` dict (step_too_large, suggested_substeps, ...) or None
    horizons : `predictable_horizon` dict (threshold -> median step/time, per trajectory)
    """

    nmse_per_step: np.ndarray
    nmse: float
    nmse_last: float
    first_bad_step: int
    n_bad: int
    rollout_seconds: float
    node_steps_per_second: float
    predictions: np.ndarray
    n_trajectories: int
    horizon: int
    n_nodes: int
    substeps: int = 1
    substeps_report: dict = None
    stability: dict = None
    horizons: dict = None

    def summary(self):
        """A JSON-ready dict (no predictions; inf/NaN as strings)."""
        def num(v):
            return v if v is None or math.isfinite(v) else str(v)

        return {"trajectories": self.n_trajectories, "horizon": self.horizon, "nodes": self.n_nodes,
                "nmse": num(self.nmse), "nmse_last": num(self.nmse_last),
                "nmse_per_step": [num(float(v)) for v in self.nmse_per_step],
                "first_bad_step": self.first_bad_step, "blown_up_trajectories": self.n_bad,
                "rollout_seconds": self.rollout_seconds, "node_steps_per_second": self.node_steps_per_second,
                "substeps": self.substeps, "substeps_auto": self.substeps_report,
                "step_too_large": bool(self.stability and self.stability["step_too_large"]),
                "suggested_substeps": self.stability and self.stability["suggested_substeps"],
                "stability": self.stability, "predictable_horizon": self.horizons}


def rollout_all(model, x0, graphs, graph_index, steps, u=None, max_nodes=16384):
    """Roll the model out from every initial state, in chunks of about ``max_nodes`` nodes.

    x0 : ndarray, shape (B, N, dx) data units;  graphs : list of Graph;  graph_index : (B,)
    u : (B, T, N, du) or None.  Returns x : (B, steps+1, N, dx) in the model's dtype.
    """
    b, n, _ = x0.shape
    graph_index = np.asarray(graph_index)
    size = max(1, max_nodes // max(n, 1))
    out = np.empty((b, steps + 1, n, model.spec.state_dim), dtype=model.dtype)
    with np.errstate(all="ignore"):
        for i in range(0, b, size):
            j = min(i + size, b)
            gi = graph_index[i:j]
            graph = graphs[int(gi[0])] if np.all(gi == gi[0]) else [graphs[int(k)] for k in gi]
            out[i:j] = model.rollout(x0[i:j], graph, None if u is None else u[i:j], steps)
    return out


def data_box(truth):
    """(mid, r): per-dimension midpoint and range of ``truth`` (..., dx), r floored above 0."""
    d = truth.shape[-1]
    flat = truth.reshape(-1, d)
    lo, hi = flat.min(axis=0), flat.max(axis=0)
    mid, r = (lo + hi) / 2, hi - lo
    return mid, np.maximum(r, np.maximum(1e-12, 1e-6 * np.abs(mid)))


def blow_up_mask(pred, truth=None, box=None):
    """Boolean (B, T+1): prediction non-finite or outside ten times the data's box at that step.

    The box is ``data_box(truth)`` unless ``box`` = (mid, r) is given.
    """
    mid, r = data_box(truth) if box is None else box
    with np.errstate(invalid="ignore", over="ignore"):
        outside = ~(np.abs(pred - mid) <= 5 * r)  # NaN compares False -> outside
    bad = outside.any(axis=(2, 3))
    return np.logical_or.accumulate(bad, axis=1)  # once blown up, stays blown up


def nmse_per_step(pred, truth, bad=None):
    """Normalised MSE per step, shape (T+1,): squared error / per-dimension variance of ``truth``.

    Steps where some trajectory has blown up (``bad``) are infinite.
    """
    d = truth.shape[-1]
    var = truth.reshape(-1, d).var(axis=0)
    var = np.where(var > 0, var, 1.0)
    with np.errstate(all="ignore"):
        err = ((pred.astype(np.float64) - truth) ** 2 / var).mean(axis=(0, 2, 3))
    if bad is not None:
        err[bad.any(axis=0)] = np.inf
    err[~np.isfinite(err)] = np.inf
    return err


def predictable_horizon(pred, truth, dt, thresholds=HORIZON_THRESHOLDS, bad=None):
    """Where predictions part from the truth: per threshold, the first step each exceeds it.

    pred, truth : ndarray, shape (B, T+1, N, dx);  bad : (B, T+1) blow-up mask or None.
    The error of trajectory b at step t is its normalised MSE (squared error / the
    per-dimension variance of ``truth``, mean over nodes and dimensions); blown-up or
    non-finite steps are infinite.  Returns {str(threshold): {"median_step", "median_time",
    "beyond_horizon" (trajectories never above it), "first_step" (per trajectory, None if
    never)}}; the median is the lower median with "never" counted as beyond T, None when
    that falls beyond T.
    """
    d = truth.shape[-1]
    var = truth.reshape(-1, d).var(axis=0)
    var = np.where(var > 0, var, 1.0)
    with np.errstate(all="ignore"):
        err = ((pred.astype(np.float64) - truth) ** 2 / var).mean(axis=(2, 3))  # (B, T+1)
    err[~np.isfinite(err)] = np.inf
    if bad is not None:
        err[bad] = np.inf
    b, t1 = err.shape
    out = {}
    for thr in thresholds:
        above = err[:, 1:] > thr
        first = np.where(above.any(axis=1), above.argmax(axis=1) + 1, t1)  # t1 = "beyond T"
        med = int(np.sort(first)[(b - 1) // 2]) if b else t1
        out[f"{thr:g}"] = {"median_step": med if med < t1 else None,
                           "median_time": med * float(dt) if med < t1 else None,
                           "beyond_horizon": int((first >= t1).sum()),
                           "first_step": [int(f) if f < t1 else None for f in first]}
    return out


def evaluate(model, traj, source="data", allow_dt_mismatch=False, max_nodes=16384, substeps=None,
             substeps_tol=stepsize.DEFAULT_TOL, max_substeps=stepsize.DEFAULT_MAX_SUBSTEPS,
             horizon_thresholds=HORIZON_THRESHOLDS, check_stability=True):
    """Roll ``model`` out on every trajectory of ``traj`` and measure error and speed (EvalResult).

    Raises InputError (naming ``source``) when dx/du differ, or dt differs and is not allowed.
    With ``allow_dt_mismatch`` the model is rolled out with the file's dt.
    substeps : None (the model's own), an int, or "auto" (`stepsize.choose_substeps` with
        ``substeps_tol`` and ``max_substeps`` on the file's initial states).
    check_stability : run `stepsize.stability_check` after the rollout (result.stability).
    """
    check_data(model, [traj], [source], allow_dt_mismatch=allow_dt_mismatch)
    if not math.isclose(traj.dt, model.spec.dt, rel_tol=1e-9, abs_tol=0.0):
        model = model.with_spec(dt=float(traj.dt))
    model.check_finite()
    x = np.asarray(traj.x, dtype=np.float64)
    b, t1, n, dx = x.shape
    u = None if traj.u is None else np.asarray(traj.u)
    graph_arg = traj.graphs[0] if len(traj.graphs) == 1 else [traj.graphs[int(i)] for i in traj.graph_index]
    auto_report = None
    if substeps == "auto":
        chosen, auto_report = stepsize.choose_substeps(model, x[:, 0], graph_arg, u, substeps_tol,
                                                       max_substeps=max_substeps, horizon=t1 - 1)
        model = model.with_spec(substeps=chosen)
    elif substeps is not None:
        model = model.with_spec(substeps=int(substeps))
    # warm-up: load the compiled kernels before timing
    rollout_all(model, x[:1, 0], traj.graphs, traj.graph_index[:1], 1, None if u is None else u[:1, :1])
    start = time.perf_counter()
    pred = rollout_all(model, x[:, 0], traj.graphs, traj.graph_index, t1 - 1, u, max_nodes)
    seconds = time.perf_counter() - start
    box = data_box(x)
    bad = blow_up_mask(pred, box=box)
    err = nmse_per_step(pred, x, bad)
    blown = bad.any(axis=0)
    first_bad = int(np.argmax(blown)) if blown.any() else None
    stability = None
    if check_stability:
        stability = stepsize.stability_check(model, x[:, 0], graph_arg, u, pred, bad, substeps_tol,
                                             max_substeps=max_substeps, box=box)
    horizons = predictable_horizon(pred, x, traj.dt, horizon_thresholds, bad)
    return EvalResult(err, float(err[1:].mean()), float(err[-1]), first_bad, int(bad[:, -1].sum()), seconds,
                      b * n * (t1 - 1) / max(seconds, 1e-12), pred, b, t1 - 1, n, model.spec.substeps,
                      auto_report, stability, horizons)


def prediction_file(traj, pred, model_name, extra_attrs=None):
    """Trajectories holding ``pred`` (B, T+1, N, dx) on ``traj``'s graphs and controls.

    attrs say they are predictions (``predicted_by`` = model_name); raises NumericalError
    when a prediction is non-finite (the trajectory format forbids it).
    """
    if not np.all(np.isfinite(pred)):
        b = int(np.argmax(~np.isfinite(pred).all(axis=(1, 2, 3))))
        raise NumericalError(f"the prediction of trajectory {b} (and maybe others) became non-finite; "
                             "predictions not written (the trajectory format forbids NaN/inf)")
    attrs = {"predicted_by": str(model_name), "prediction": 1, **(extra_attrs or {})}
    return Trajectories(x=pred, graphs=traj.graphs, dt=traj.dt, system=traj.system, u=traj.u,
                        graph_index=np.asarray(traj.graph_index) if len(traj.graphs) > 1 else None,
                        attrs=attrs)


def subset(traj, idx):
    """The trajectories ``idx`` of ``traj`` (same graphs, attrs and parameters)."""
    idx = np.asarray(idx, dtype=np.int64)
    return Trajectories(x=np.asarray(traj.x)[idx], graphs=traj.graphs, dt=traj.dt, system=traj.system,
                        u=None if traj.u is None else np.asarray(traj.u)[idx],
                        graph_index=np.asarray(traj.graph_index)[idx], attrs=dict(traj.attrs),
                        params=dict(traj.params), aux=dict(traj.aux))
