"""Using a model: evaluate it on a trajectory file, or simulate new initial states.

`evaluate` rolls a model out from every initial state of a file and measures the error
(mpnode.evaluation.metrics: normalised MSE per step and overall, blow-ups, predictable horizon) and
the speed; `simulate` rolls it out where there is no truth, with a blow-up test against
the training data's range.  Both take ``substeps="auto"`` (the RK4 substeps chosen by
step doubling, mpnode.evaluation.stepsize) and report afterwards whether a blow-up was caused by
too large an RK4 step (``stepsize.stability_check``).  This module knows nothing of any
particular system; timing the reference simulator is `data_gen.reference`'s job.
"""
import math
import time
from dataclasses import dataclass

import numpy as np

from mpnode.base.errors import InputError, NumericalError
from mpnode import engine
from mpnode.data import Trajectories
from mpnode.model import batch_graph, check_data, ranges
from mpnode.model.inputs import for_model
from mpnode.model.ensemble import Ensemble, models_of
from mpnode.model.start import fit_initial_state

from . import stepsize
from .nodes import NodeErrors, node_errors
from .metrics import (
    HORIZON_THRESHOLDS,
    _mean,
    blow_up_mask,
    by_block,
    data_box,
    hold_nmse_per_step_and_dim,
    invariant_drift,
    nmse_per_dimension,
    nmse_per_step,
    nmse_per_step_and_dim,
    over_dims,
    predictable_horizon,
    state_groups,
)
from .spread import spread_figures


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
    warmup : the observations each rollout's start was estimated from (scored from step max(1, warmup))
    nmse_per_dim : the normalised MSE of each state dimension (NaN: not scored)
    hidden_dims : the dimensions the model never saw measured in training: not scored
    off_range : the inputs that left what the model saw in training (mpnode.model.ranges.off_range;
        [] when none did), or None when its file records no training ranges
    invariant_drift : (prediction's, truth's) relative drift per step (T+1,) of the quantity
        ``evaluate(invariant=...)`` was given (metrics.invariant_drift), or None
    scored : (B, T+1, N, dx) what the predictions were scored against (NaN: not scored)
    member_std, spread : of an ensemble (predictions are its mean): the members' standard
        deviation and the calibrated spread (data units, the shape of predictions); else None
    ensemble : of an ensemble, mpnode.evaluation.spread.spread_figures (coverage, spread); else None
    per_dim, hold_per_dim : (T+1, dx) normalised MSE per step and state dimension, of the model and
        of holding the initial state;  groups : {group: [dimensions]} of the file's state_groups
    nodes : mpnode.evaluation.nodes.NodeErrors, each node's error on the graph most trajectories run on
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
    warmup: int = 0
    nmse_per_dim: list = None
    hidden_dims: list = None
    off_range: list = None
    invariant_drift: tuple = None
    scored: np.ndarray = None
    member_std: np.ndarray = None
    spread: np.ndarray = None
    ensemble: dict = None
    per_dim: np.ndarray = None
    hold_per_dim: np.ndarray = None
    groups: dict = None
    nodes: NodeErrors = None

    @property
    def hold_per_step(self):
        """(T+1,) normalised MSE of holding the initial state."""
        return over_dims(self.hold_per_dim)

    def first_step_not_below_hold(self, dims=slice(None)):
        """The first step >= 1 at which the model's error (over ``dims``) is not below holding the
        initial state's, or None when it is below at every step."""
        first = max(self.warmup, 1)
        worse = over_dims(self.per_dim[first:], dims) >= over_dims(self.hold_per_dim[first:], dims)
        return int(np.argmax(worse)) + first if worse.any() else None

    def summary(self):
        """A JSON-ready dict (no predictions; inf/NaN as strings)."""
        first = max(self.warmup, 1)
        hold = {**_errors(self.hold_per_step, first), "first_step_not_below": self.first_step_not_below_hold()}
        groups = {name: {"dims": dims, **_errors(over_dims(self.per_dim, dims), first),
                         **{f"hold_{k}": v for k, v in _errors(over_dims(self.hold_per_dim, dims), first).items()},
                         "first_step_not_below_hold": self.first_step_not_below_hold(dims)}
                  for name, dims in (self.groups or {}).items()}
        return {"trajectories": self.n_trajectories, "horizon": self.horizon, "nodes": self.n_nodes,
                **_errors(self.nmse_per_step, first), "hold": hold, "groups": groups,
                "first_bad_step": self.first_bad_step, "blown_up_trajectories": self.n_bad,
                "rollout_seconds": self.rollout_seconds, "node_steps_per_second": self.node_steps_per_second,
                "substeps": self.substeps, "substeps_auto": self.substeps_report,
                "step_too_large": bool(self.stability and self.stability["step_too_large"]),
                "suggested_substeps": self.stability and self.stability["suggested_substeps"],
                "stability": self.stability, "predictable_horizon": self.horizons, "warmup": self.warmup,
                "nmse_per_dim": [_num(float(v)) for v in self.nmse_per_dim or []], "hidden_dims": self.hidden_dims or [],
                "per_node": self.nodes and self.nodes.summary(self.n_trajectories),
                **self.trust(), "coverage_50": None, "coverage_90": None, **(self.ensemble or {})}

    def trust(self):
        """The summary's entries that say how far to trust the error: nMSE by block of steps
        (error against horizon), the inputs off the training range, the invariant's drift."""
        def blocks(per_step):  # a blown-up block's inf as a string, as the summary's other numbers
            return [dict(b, value=b["value"] if b["value"] is None or math.isfinite(b["value"]) else str(b["value"]))
                    for b in by_block(per_step, max(self.warmup, 1))]

        out = {"nmse_by_block": blocks(self.nmse_per_step), "off_range": self.off_range or [],
               "training_ranges_recorded": self.off_range is not None}
        if self.invariant_drift is not None:
            pred, truth = (blocks(d) for d in self.invariant_drift)
            out["invariant_drift_by_block"] = [dict(p, truth=t["value"]) for p, t in zip(pred, truth)]
        return out


def _num(v):
    """A JSON number, or inf/NaN as a string."""
    return v if v is None or math.isfinite(v) else str(v)


def _errors(per_step, first=1):
    """The summary's error entries of a (T+1,) normalised MSE per step, scored from step ``first``."""
    return {"nmse": _num(float(_mean(per_step[first:]))), "nmse_last": _num(_last(per_step)),
            "nmse_per_step": [_num(float(v)) for v in per_step]}


@dataclass
class SimulationResult:
    """predictions : ndarray, shape (B, T+1, N, dx), data units;  seconds : rollout wall time;
    substeps, substeps_report, stability, off_range : as in EvalResult;  spread : an ensemble's
    calibrated spread (the shape of predictions, data units), else None;  u : (B, T, N, du) the
    controls (given, or chosen by a closed loop), or None."""

    predictions: np.ndarray
    seconds: float
    substeps: int
    substeps_report: dict
    stability: dict
    off_range: list = None
    spread: np.ndarray = None
    u: np.ndarray = None


def rollout_all(model, x0, graphs, graph_index, steps, u=None, max_nodes=16384, times=None):
    """Roll the model out from every initial state, in chunks of about ``max_nodes`` nodes.

    x0 : ndarray, shape (B, N, dx) data units;  graphs : list of Graph;  graph_index : (B,)
    u : (B, T, N, du) or None;  times : (B, steps+1) the outputs' times, or None (every dt).
    Returns x : (B, steps+1, N, dx) in the model's dtype.
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
            out[i:j] = model.rollout(x0[i:j], graph, None if u is None else u[i:j], steps,
                                     times=None if times is None else times[i:j])
    return out


def _per_trajectory(graphs, graph_index):
    """The graph argument of Model.rollout for all B trajectories: one Graph or a list of B."""
    return graphs[0] if len(graphs) == 1 else [graphs[int(i)] for i in graph_index]


def with_substeps(model, substeps, x0, graphs, graph_index, u, horizon, tol, max_substeps):
    """The model with the substeps asked for: None (its own), an int, or "auto" (step doubling
    on these initial states).  Returns (model, the auto report or None)."""
    if substeps == "auto":
        chosen, report = stepsize.choose_substeps(model, x0, _per_trajectory(graphs, graph_index), u, tol,
                                                  max_substeps=max_substeps, horizon=horizon)
        return model.with_spec(substeps=chosen), report
    if substeps is not None:
        return model.with_spec(substeps=int(substeps)), None
    return model, None


def evaluate(model, traj, source="data", allow_dt_mismatch=False, max_nodes=16384, substeps=None,
             substeps_tol=stepsize.DEFAULT_TOL, max_substeps=stepsize.DEFAULT_MAX_SUBSTEPS,
             horizon_thresholds=HORIZON_THRESHOLDS, check_stability=True, warmup=0, truth=None, start="encoder",
             invariant=None, state_names=None, ignore_attrs=False, node_dims=None, node_names=None):
    """Roll ``model`` out on every trajectory of ``traj`` and measure error and speed (EvalResult).

    Predictions fall at the file's observation times.  warmup : K, the first K observations
    of each trajectory are the model's to estimate where it starts from (with an initial-state
    encoder; without, the first); the error counts the observations after them (steps
    max(K, 1)..T).  truth : the clean states (like traj.x) to score against, when the data are
    noisy; default the file's own truth, else its observations (what was observed only).
    start : how the warm-up gives the start: "encoder" (the model's estimate, `Model.initial_state`)
    or "fit" (from there, fitted to the warm-up's observations through the engine: mpnode.model.start).
    Raises InputError (naming ``source``) when dx/du (or a node model's N) differ, or a regular
    file's dt differs and is not allowed; with ``allow_dt_mismatch`` the model runs at the file's dt.
    substeps : None (the model's own), an int, or "auto" (module docstring).
    check_stability : run `stepsize.stability_check` after the rollout (result.stability).
    invariant : x (B, T+1, N, dx) -> (B, T+1), a quantity the true dynamics conserve, whose drift
    along the predictions is measured (result.invariant_drift); the physics stays with the caller.
    state_names : what to call the state dimensions in the off-range entries.
    ignore_attrs : leave out node attributes and edge weights the model was not trained with
    (mpnode.model.inputs.for_model).
    node_dims, node_names : the state dimensions each node's error is ranked by (default all) and
    what to call the nodes (default by index): result.nodes (mpnode.evaluation.nodes).
    """
    groups = file_groups(traj, source)
    traj = for_model(model, model.fitted(traj), source, ignore_attrs)  # latent dimensions' room; attributes as controls
    truth = None if truth is None else _with_latent(np.asarray(truth, dtype=np.float64), traj.state_dim)
    check_data(model, [traj], [source], allow_dt_mismatch=allow_dt_mismatch or not traj.regular)
    if traj.regular and not math.isclose(traj.dt, model.spec.dt, rel_tol=1e-9, abs_tol=0.0):
        model = model.with_spec(dt=float(traj.dt))
    model.check_finite()
    x = np.asarray(traj.x, dtype=np.float64)
    b, t1, n, dx = x.shape
    u = None if traj.u is None else np.nan_to_num(np.asarray(traj.u))
    times = None if traj.regular else traj.times()
    x0 = start_states(model, traj, warmup, start)
    model, auto_report = with_substeps(model, substeps, x0, traj.graphs, traj.graph_index, u, t1 - 1,
                                       substeps_tol, max_substeps)
    seconds, pred, member_std = _timed_rollout(model, x0, traj, u, times, max_nodes)
    clean = _truth_of(traj, truth, source)
    score = _scored(clean, traj, max(warmup, 1), truth is None and traj.truth is None)
    hidden = [int(k) for k in np.atleast_1d(model.attrs.get("unmeasured_dims", [])) if 0 <= int(k) < dx]
    score[..., hidden] = np.nan  # a state the model never saw measured has no units to compare in
    box = data_box(score)
    bad = blow_up_mask(pred, box=box)
    err = nmse_per_step(pred, score, bad, spread=clean)
    per_dim = nmse_per_step_and_dim(pred, score, bad, spread=clean)
    blown = bad.any(axis=0)
    stability = None
    if check_stability:
        stability = stepsize.stability_check(model, x0, _per_trajectory(traj.graphs, traj.graph_index), u,
                                             pred, bad, substeps_tol, max_substeps=max_substeps, box=box)
    first = max(warmup, 1)
    spread = None if member_std is None else member_std * model.spread_scale
    figures = None if spread is None else spread_figures(pred, spread, score, clean)
    return EvalResult(err, float(_mean(err[first:])), _last(err), int(np.argmax(blown)) if blown.any() else None,
                      int(bad[:, -1].sum()), seconds, b * n * (t1 - 1) / max(seconds, 1e-12), pred, b, t1 - 1, n,
                      model.spec.substeps, auto_report, stability,
                      predictable_horizon(pred, score, traj.dt, horizon_thresholds, bad), warmup,
                      nmse_per_dimension(pred, score, clean).tolist(), hidden,
                      inputs_off_range(model, x0, traj.graphs, traj.graph_index, u, traj.horizon, times, state_names),
                      None if invariant is None else invariant_drift(invariant, pred, clean), per_dim=per_dim,
                      hold_per_dim=hold_nmse_per_step_and_dim(score, spread=clean), groups=groups,
                      scored=score, member_std=member_std, spread=spread, ensemble=figures,
                      nodes=node_errors(pred, score, clean, traj.graph_index, node_dims, node_names))


def inputs_off_range(model, x0, graphs, graph_index, u, horizon, times=None, state_names=None):
    """The inputs of the model's rollouts from x0 that leave what it saw in training
    (mpnode.model.ranges; [] when none do), or None when the model records no training ranges."""
    seen = model.attrs.get(ranges.KEY)
    if not seen:
        return None
    model = models_of(model)[0]  # an ensemble: its first member's inputs
    return ranges.off_range(seen, ranges.scan(model, x0, graphs, graph_index, u, horizon, times), state_names)


def start_states(model, traj, warmup, start="encoder"):
    """(B, N, dx) where the rollouts of ``traj`` start: the model's estimate from each
    trajectory's first max(warmup, 1) observations (mpnode.model.Model.initial_state), fitted
    to them through the engine when ``start`` is "fit" (mpnode.model.start)."""
    if start not in STARTS:
        raise InputError("--start", "start", f"is {start!r}", " or ".join(STARTS))
    if start == "fit" and isinstance(model, Ensemble):
        raise InputError("--start", "start", "is fit for an ensemble", "--start encoder (each member's start is "
                         "the members' mean estimate)")
    k = max(int(warmup), 1)
    times = None if traj.regular else traj.times()[:, :k]
    obs = np.asarray(traj.x)[:, :k]
    x0 = model.initial_state(obs, times)
    if start == "fit" and k > 1:
        u = None if traj.u is None else np.nan_to_num(np.asarray(traj.u)[:, :k - 1])
        x0 = fit_initial_state(model, obs, batch_graph(_per_trajectory(traj.graphs, traj.graph_index), len(obs)),
                               times, u, start=x0)
    return x0


def continue_from(model, traj, warmup=1, start="encoder", source="data", ignore_attrs=False):
    """(x0 (B, N, dx), steps): where simulations of ``traj``'s trajectories start -- the state at
    each one's first observation time, estimated from its first ``warmup`` observations
    (`start_states`) -- and the steps of the model's dt that reach the last observation of the
    longest, so that a simulation covers the observed span and goes on from there."""
    traj = for_model(model, model.fitted(traj), source, ignore_attrs)
    check_data(model, [traj], [source], allow_dt_mismatch=True)
    if warmup > traj.horizon + 1:
        raise InputError(source, "x", f"has {traj.horizon + 1} observations per trajectory, fewer than the "
                         f"warm-up of {warmup}", f"--warmup {traj.horizon + 1} or less")
    times = traj.times()
    span = float(np.nanmax(np.nanmax(times, axis=1) - times[:, 0]))
    steps = max(1, math.ceil(span / model.spec.dt - 1e-9))
    return start_states(model, traj, warmup, start), steps


#: how a warm-up gives a rollout its start
STARTS = ("encoder", "fit")


def _timed_rollout(model, x0, traj, u, times, max_nodes):
    """(seconds, predictions, the members' std or None): every trajectory rolled out (an
    ensemble's members each: the predictions are their mean), the compiled kernels loaded first."""
    first = models_of(model)[0]
    rollout_all(first, x0[:1], traj.graphs, traj.graph_index[:1], 1, None if u is None else u[:1, :1],
                times=None if times is None else times[:1, :2])
    start = time.perf_counter()
    pred, member_std = rollout_spread(model, x0, traj.graphs, traj.graph_index, traj.horizon, u, max_nodes, times)
    return time.perf_counter() - start, pred, member_std


def rollout_spread(model, x0, graphs, graph_index, steps, u=None, max_nodes=16384, times=None):
    """(predictions, None) of a Model (`rollout_all`); of an ensemble (its members each rolled
    out), (the members' mean, their standard deviation (ddof 1, float64))."""
    if not isinstance(model, Ensemble):
        return rollout_all(model, x0, graphs, graph_index, steps, u, max_nodes, times), None
    stacked = np.stack([rollout_all(m, x0, graphs, graph_index, steps, u, max_nodes, times) for m in model.members])
    with np.errstate(all="ignore"):
        return stacked.mean(axis=0), np.std(stacked.astype(np.float64), axis=0, ddof=1)


def _truth_of(traj, truth, source):
    """What predictions are scored against: ``truth`` given, the file's own truth, or its observations."""
    if truth is None:
        truth = traj.truth if traj.truth is not None else traj.x
    truth = np.asarray(truth, dtype=np.float64)
    if truth.shape != traj.x.shape:
        raise InputError(source, "truth", f"has shape {truth.shape} but the data have {traj.x.shape}",
                         "the clean states of the same trajectories (the same B, T+1, N, dx)")
    return truth


def _with_latent(truth, dx):
    """``truth`` (..., d) with NaN columns up to dx: a model's latent dimensions have no truth."""
    missing = dx - truth.shape[-1]
    return truth if missing <= 0 else np.concatenate([truth, np.full(truth.shape[:-1] + (missing,), np.nan)], -1)


def _scored(truth, traj, first, observations):
    """``truth`` with what is not scored made NaN: the warm-up (steps before ``first``; step 0
    stays, the start), what lies past each trajectory's end, and, scoring the observations
    themselves, what nobody observed."""
    inside = (np.arange(traj.horizon + 1)[None, :] < traj.lengths[:, None])[:, :, None, None]
    out = np.where(traj.observed() if observations else inside, truth, np.nan)
    out[:, 1:first] = np.nan
    return out


def _last(err):
    """The error at the last step that has one."""
    finite = err[~np.isnan(err)]
    return float(finite[-1]) if finite.size else float("nan")


def file_groups(traj, source="data"):
    """{group: [dimensions]} of the file's ``state_groups`` attribute ({} without one)."""
    try:
        return state_groups(traj.attrs.get("state_groups"), traj.state_dim)
    except ValueError as e:
        raise InputError(source, "state_groups", str(e), "one group name per state dimension") from None


def simulation_box(model, x0):
    """(mid, r) of the blow-up test without true states: ten times this box is the training
    data's mean +- 20 std (the model's normalisation), widened to hold the initial states x0."""
    flat = x0.reshape(-1, x0.shape[-1])
    lo = np.minimum(model.x_mean - 2 * model.x_std, flat.min(axis=0))
    hi = np.maximum(model.x_mean + 2 * model.x_std, flat.max(axis=0))
    return (lo + hi) / 2, hi - lo


def simulate(model, x0, graphs, graph_index, horizon, u=None, substeps=None, substeps_tol=stepsize.DEFAULT_TOL,
             max_substeps=stepsize.DEFAULT_MAX_SUBSTEPS, state_names=None, controls=None):
    """Roll ``model`` out from x0 (B, N, dx) on ``graphs[graph_index[b]]`` for ``horizon`` steps.

    controls : a closed loop instead of given controls ``u``: controls(k, x (B, N, dx)) -> the
    controls (B, N, du) held over step k, chosen from the model's own state (`closed_loop_rollout`);
    the result's ``u`` holds what they chose, which "auto" substeps and the stability check
    replay (auto chooses on the controls of a first pass at the model's own substeps).
    A prediction blows up when it is non-finite or leaves ten times `simulation_box`; the
    stability check says whether more substeps avoid that.  Returns a SimulationResult.
    """
    model.check_finite()
    if controls is not None and substeps == "auto":
        u = closed_loop_rollout(model, x0, graphs, graph_index, horizon, controls)[1]
    model, auto_report = with_substeps(model, substeps, x0, graphs, graph_index, u, horizon, substeps_tol,
                                       max_substeps)
    start = time.perf_counter()
    if controls is None:
        pred, member_std = rollout_spread(model, x0, graphs, graph_index, horizon, u)
    else:
        (pred, u), member_std = closed_loop_rollout(model, x0, graphs, graph_index, horizon, controls), None
    seconds = time.perf_counter() - start
    box = simulation_box(model, x0)
    stability = stepsize.stability_check(model, x0, _per_trajectory(graphs, graph_index), u, pred,
                                         blow_up_mask(pred, box=box), substeps_tol, max_substeps=max_substeps,
                                         box=box)
    spread = None if member_std is None else member_std * model.spread_scale
    return SimulationResult(pred, seconds, model.spec.substeps, auto_report, stability,
                            inputs_off_range(model, x0, graphs, graph_index, u, horizon, state_names=state_names),
                            spread=spread, u=u)


def closed_loop_rollout(model, x0, graphs, graph_index, horizon, controls):
    """Roll out one step at a time, each step's controls chosen from the model's state by
    ``controls(k, x (B, N, dx)) -> u (B, N, du)`` (a controller closing the loop around the
    model).  Messages carry over between steps, so given the same controls this is bit for bit
    `Model.rollout`.  Returns (x (B, horizon+1, N, dx) in the model's dtype, u (B, horizon, N, du))."""
    b, n, dx = x0.shape
    spec = model.spec
    flat = batch_graph(_per_trajectory(graphs, graph_index), b)
    z = engine.initial_state(spec, model.normalize_x(x0).reshape(b * n, dx), model.dtype)
    xs, us = [model.denormalize_x(z[:, :dx].reshape(b, n, dx)).astype(model.dtype)], []
    for k in range(horizon):
        u = np.asarray(controls(k, xs[-1]), dtype=np.float64)
        if u.shape != (b, n, spec.control_dim):
            raise ValueError(f"the controls of step {k} have shape {u.shape}, the model needs {(b, n, spec.control_dim)}")
        with np.errstate(all="ignore"):
            _, z = engine.integrate(spec, model.theta, z, flat, model.normalize_u(u).reshape(1, b * n, -1), 1)
        xs.append(model.denormalize_x(z[:, :dx].reshape(b, n, dx)).astype(model.dtype))
        us.append(u)
    return np.stack(xs, axis=1), np.stack(us, axis=1)


def learned_seconds_per_trajectory(model, traj, k, repeats=3):
    """Seconds per trajectory of the learned rollout of ``traj``'s first k trajectories as one
    batch (best of ``repeats``): the number to set beside the reference simulator's."""
    x0 = np.asarray(traj.x)[:k, 0]
    u = None if traj.u is None else np.asarray(traj.u)[:k]
    if model.spec.attr_dim:  # held over the horizon, as evaluation rolls them out
        u = model.controls_of(u, np.asarray(traj.node_attrs)[:k], k, traj.n_nodes, traj.horizon)
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        rollout_all(model, x0, traj.graphs, traj.graph_index[:k], traj.horizon, u)
        best = min(best, time.perf_counter() - start)
    return best / k


def predictions_file(pred, graphs, graph_index, dt, system, model_name, u=None, attrs=None, t=None, spread=None,
                     node_attrs=None, attr_names=None):
    """Trajectories holding ``pred`` (B, T+1, N, dx) on ``graphs`` (and controls ``u``), at the
    observation times ``t`` (B, T+1) when the data had their own; an ensemble's calibrated
    ``spread`` (like pred) as ``x_std``; the nodes' ``node_attrs`` (B, N, dp) named ``attr_names``
    as the data held them (the graphs keep their weights), so that the file describes the same
    network as the data it predicts and a model reads it as it read them.

    attrs say they are predictions (``predicted_by`` = model_name); raises NumericalError
    when a prediction is non-finite (the trajectory format forbids it).
    """
    if not np.all(np.isfinite(pred)):
        b = int(np.argmax(~np.isfinite(pred).all(axis=(1, 2, 3))))
        raise NumericalError(f"the prediction of trajectory {b} (and maybe others) became non-finite; "
                             "predictions not written (the trajectory format forbids NaN/inf)")
    attrs = {"predicted_by": str(model_name), "prediction": 1, **(attrs or {})}
    return Trajectories(x=pred, graphs=list(graphs), dt=dt, system=system, u=u,
                        graph_index=np.asarray(graph_index) if len(graphs) > 1 else None, attrs=attrs, t=t,
                        x_std=None if spread is None else np.asarray(spread, dtype=np.asarray(pred).dtype),
                        node_attrs=node_attrs, attr_names=None if node_attrs is None else list(attr_names))


def substeps_attrs(substeps, auto_report):
    """Attributes naming the substeps of a predictions file (and auto's rule and estimate)."""
    attrs = {"substeps": int(substeps)}
    if auto_report is not None:
        attrs.update(substeps_auto=1, substeps_tol=float(auto_report["tol"]),
                     substeps_tol_reached=int(auto_report["reached"]), substeps_rule=auto_report["rule"])
        if isinstance(auto_report["estimate"], float):
            attrs["substeps_estimate"] = auto_report["estimate"]
    return attrs


def subset(traj, idx):
    """The trajectories ``idx`` of ``traj`` (same graphs, attrs and parameters)."""
    idx = np.asarray(idx, dtype=np.int64)
    return Trajectories(x=np.asarray(traj.x)[idx], graphs=traj.graphs, dt=traj.dt, system=traj.system,
                        u=None if traj.u is None else np.asarray(traj.u)[idx],
                        graph_index=np.asarray(traj.graph_index)[idx], attrs=dict(traj.attrs),
                        params=dict(traj.params), aux=dict(traj.aux),
                        t=None if traj.t is None else np.asarray(traj.t)[idx],
                        truth=None if traj.truth is None else np.asarray(traj.truth)[idx],
                        node_attrs=None if traj.node_attrs is None else np.asarray(traj.node_attrs)[idx],
                        attr_names=traj.attr_names)
