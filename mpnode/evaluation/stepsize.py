"""How many RK4 substeps a rollout needs: step doubling, and the "step too large" diagnosis.

A model's rollout advances every output step dt with ``substeps`` classic RK4 steps of
h = dt / substeps.  RK4's global error is O(h^4), so halving h divides it by about 16:
if x_s is the rollout with s substeps and x the exact solution of the learned ODE,
``x_s - x_2s = (x_s - x) - (x_2s - x) ~ (1 - 1/16) (x_s - x)``.  The difference between
the s- and the 2s-rollout is therefore an estimate (15/16 of it) of the error of the
s-rollout.  This is the *step-doubling* estimate used here.

The rule of `choose_substeps` (``mpnode eval/simulate --substeps auto``):

- probe: the first ``probe_steps`` output steps (default min(T, 20)) of up to
  ``sample`` trajectories (default 32, spread evenly over the batch; fewer for large
  graphs, at most ~MAX_PROBE_NODES = 4096 nodes in all), rolled out in
  float64 on the NumPy path (so the estimate measures truncation error, not float32
  round-off, and no float64 kernels are compiled for it);
- error measure: ``max |x_s - x_2s| / x_std`` over the probed trajectories, steps,
  nodes and state dimensions, i.e. in the model's normalised units (x_std is the
  training data's per-dimension standard deviation, stored in the model), so
  ``tol = 1e-4`` (the default) means "one ten-thousandth of the data's spread";
- s = 1, 2, 4, ... up to ``max_substeps`` (default 64): the first s whose estimate is
  <= tol is chosen.  If none is, the report says so (``reached: false``) and s is the
  largest power of two <= max_substeps.

A float32 model's own rollout carries round-off of ~1e-6 of the state's size per step
on top of the truncation error the float64 probe measures: tolerances much below 1e-5
buy nothing for float32 models.

The estimate is for the probed stretch only: over a long horizon a (non-chaotic)
rollout's error grows roughly in proportion to the number of steps, and a chaotic
one's exponentially -- so the tolerance is about the integration error per stretch,
not a bound on the error at step T.  Note also that a model trained with s substeps
learned the *discrete* map of its RK4 step; more substeps converge to its continuous
ODE, which agrees with that map to about the step-doubling estimate at s.

`stability_check` is what `mpnode eval` and `mpnode simulate` run after a rollout: it
reports the step-doubling estimate of the substeps used and, when predictions blew up,
whether more substeps stop the blow-up -- if so, the RK4 step was too large for this
model on this data (``step_too_large``) and a substep count is suggested.
This module knows nothing of any particular system.
"""
import math

import numpy as np

from .metrics import blow_up_mask

DEFAULT_TOL = 1e-4
DEFAULT_MAX_SUBSTEPS = 64
DEFAULT_PROBE_STEPS = 20
DEFAULT_SAMPLE = 32
#: the probes roll out at most about this many nodes (fewer trajectories of large graphs)
MAX_PROBE_NODES = 4096
#: a step-doubling estimate above this (normalised units: the data's spread) means the
#: rollout's first stretch is numerically meaningless -- the step is too large
HUGE_ESTIMATE = 1.0


def sample_indices(n, sample, n_nodes=1):
    """Up to ``sample`` indices spread evenly over range(n) (all of them when n <= sample),
    fewer when trajectories of ``n_nodes`` nodes would exceed MAX_PROBE_NODES (at least 1)."""
    sample = max(1, min(sample, MAX_PROBE_NODES // max(1, n_nodes)))
    if n <= sample:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, sample).round().astype(np.int64))


def _pick(graph, idx):
    """The graph argument of Model.rollout for the trajectories ``idx``."""
    if isinstance(graph, (list, tuple)):
        return [graph[int(i)] for i in idx]
    return graph


def _rollout(model, substeps, x0, graph, u, steps):
    """The probe's rollout, on the NumPy path: a few trajectories in float64, which would
    otherwise compile the float64 kernels (minutes on a cold cache) for a float32 model."""
    m = model.with_spec(substeps=int(substeps))
    with np.errstate(all="ignore"):
        return m.rollout(x0, graph, u, steps, backend="numpy").astype(np.float64)


def doubling_estimate(pred_s, pred_2s, x_std):
    """max |pred_s - pred_2s| / x_std (normalised units); inf when either is non-finite.

    pred_s, pred_2s : ndarray, shape (B, T+1, N, dx);  x_std : (dx,)
    """
    with np.errstate(all="ignore"):
        d = np.abs(pred_s - pred_2s) / np.asarray(x_std)
    if d.size == 0:
        return 0.0
    m = float(np.max(d))
    return m if math.isfinite(m) else math.inf


def choose_substeps(model, x0, graph, u=None, tol=DEFAULT_TOL, probe_steps=DEFAULT_PROBE_STEPS,
                    max_substeps=DEFAULT_MAX_SUBSTEPS, sample=DEFAULT_SAMPLE, horizon=None):
    """The smallest s in 1, 2, 4, ... max_substeps whose step-doubling estimate is <= tol.

    x0 : ndarray, shape (B, N, dx), data units;  graph : one Graph or a list of B Graphs
    u : (B, T, N, du) or None;  horizon : T (probe at most min(T, probe_steps) steps).
    Returns (substeps, report) with report a JSON-ready dict: substeps, tol, reached
    (False when even max_substeps missed tol), estimate (of the chosen s), estimates
    ({s: estimate} for every s tried), probe_steps, probe_trajectories, rule (one line).
    See the module docstring for the rule.
    """
    if not (tol > 0):
        raise ValueError(f"tol must be > 0, not {tol}")
    if max_substeps < 1:
        raise ValueError(f"max_substeps must be >= 1, not {max_substeps}")
    x0 = np.asarray(x0)
    k = probe_steps
    if horizon is not None:
        k = min(k, horizon)
    if u is not None:
        k = min(k, np.asarray(u).shape[1])
    k = max(1, int(k))
    idx = sample_indices(x0.shape[0], sample, x0.shape[1])
    fine = model.copy(dtype=np.float64)
    xs, g = x0[idx], _pick(graph, idx)
    us = None if u is None else np.asarray(u)[idx, :k]
    estimates = {}
    s = 1
    pred = _rollout(fine, s, xs, g, us, k)
    while True:
        finer = _rollout(fine, 2 * s, xs, g, us, k)
        estimates[s] = doubling_estimate(pred, finer, model.x_std)
        if estimates[s] <= tol or 2 * s > max_substeps:
            break
        s, pred = 2 * s, finer
    reached = estimates[s] <= tol
    report = {"substeps": s, "tol": tol, "reached": bool(reached), "estimate": _num(estimates[s]),
              "estimates": {str(a): _num(e) for a, e in estimates.items()}, "probe_steps": k,
              "probe_trajectories": int(len(idx)), "max_substeps": max_substeps,
              "rule": (f"smallest s in 1, 2, 4, ..., {max_substeps} with max |x_s - x_2s| / x_std <= {tol:g} over "
                       f"the first {k} steps of {len(idx)} trajectories (step doubling; float64 probe)")}
    if not reached:
        report["message"] = (f"no substep count up to {max_substeps} reached the tolerance {tol:g} (estimate at "
                             f"{s}: {estimates[s]:.3g}); using {s}")
    return s, report


def _num(v):
    return v if math.isfinite(v) else str(v)


def stability_check(model, x0, graph, u, pred, bad, tol=DEFAULT_TOL, probe_steps=DEFAULT_PROBE_STEPS,
                    max_substeps=DEFAULT_MAX_SUBSTEPS, sample=16, box=None):
    """Was the RK4 step too large?  A JSON-ready dict for the report of a finished rollout.

    model : the Model as rolled out (its spec.substeps is the s used)
    x0 : (B, N, dx);  graph : Graph or list of B Graphs;  u : (B, T, N, du) or None
    pred : (B, T+1, N, dx) the rollout;  bad : (B, T+1) its blow-up mask (metrics.blow_up_mask)
    box : (mid, r) of the blow-up test for re-rolled trajectories (outside mid +- 5 r per
        dimension, or non-finite, is a blow-up)

    Keys: substeps (s used), h (dt / s), estimate (step-doubling estimate of s on the
    first stretch), blew_up (trajectories), stable_substeps (smallest 2^j s <= max_substeps
    under which a sample of the blown-up trajectories stays finite and inside the box;
    None if none or nothing blew up), step_too_large (more substeps cure the blow-up, or
    the estimate exceeds HUGE_ESTIMATE), suggested_substeps (then: the larger of
    stable_substeps and auto_substeps, the `choose_substeps` choice), message (None when
    all is well).
    """
    s = model.spec.substeps
    horizon = pred.shape[1] - 1
    h = model.spec.dt / s
    k = max(1, min(probe_steps, horizon))
    idx = sample_indices(x0.shape[0], sample, x0.shape[1])
    fine = model.copy(dtype=np.float64)
    us = None if u is None else np.asarray(u)[idx, :k]
    a = _rollout(fine, s, x0[idx], _pick(graph, idx), us, k)
    b = _rollout(fine, 2 * s, x0[idx], _pick(graph, idx), us, k)
    estimate = doubling_estimate(a, b, model.x_std)
    blown = np.flatnonzero(bad.any(axis=1))
    stable = None
    if len(blown) and box is not None:
        sel = blown[sample_indices(len(blown), sample, x0.shape[1])]
        gsel = _pick(graph, sel)
        usel = None if u is None else np.asarray(u)[sel]
        t = 2 * s
        while t <= max_substeps:
            if not blow_up_mask(_rollout(model, t, x0[sel], gsel, usel, horizon), box=box).any():
                stable = t
                break
            t *= 2
    too_large = stable is not None or estimate > HUGE_ESTIMATE
    out = {"substeps": s, "h": h, "estimate": _num(estimate), "blew_up": int(len(blown)),
           "stable_substeps": stable, "step_too_large": bool(too_large), "suggested_substeps": None,
           "auto_substeps": None, "message": None}
    if too_large:
        auto, auto_report = choose_substeps(model, x0, graph, u, tol, probe_steps, max_substeps, sample, horizon)
        suggested = max(stable or 1, auto, 2 * s if stable is None else 1)
        out["suggested_substeps"] = suggested
        why = (f"{len(blown)} predictions blew up with {s} substeps but not with {stable}" if stable is not None
               else f"the step-doubling error estimate on the first {k} steps is {estimate:.3g} (normalised units)")
        out["auto_substeps"] = auto
        out["message"] = (f"the RK4 step h = {h:.4g} (dt {model.spec.dt:g} / {s} substeps) is too large for this "
                          f"model on this data ({why}); try --substeps {suggested} ("
                          + (f"step-doubling estimate <= {tol:g} from {auto} substeps" if auto_report["reached"]
                             else f"no count up to {max_substeps} reaches the tolerance {tol:g}")
                          + "), or --substeps auto")
    elif len(blown):
        out["message"] = (f"{len(blown)} predictions blew up, and still do with up to {max_substeps} substeps: not "
                          f"a step-size problem -- the learned field itself diverges from these states")
    return out
