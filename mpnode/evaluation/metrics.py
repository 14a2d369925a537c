"""Error measures of predictions against the truth: normalised MSE, blow-ups, predictable horizon.

Normalised MSE (the paper's error): the squared error of every state coordinate divided
by the variance of that state dimension over the true states (all trajectories, steps
and nodes), averaged over trajectories, nodes and dimensions.  1 means "no better than
predicting the mean"; 0 is perfect.  Only what was observed counts: a NaN in the truth (a
value nobody measured) is left out of every mean, and of the variances.

A prediction that becomes non-finite, or leaves a box ten times as wide as the data (per
dimension: [mid - 5 r, mid + 5 r] with mid and r the midpoint and range of the true
states), counts as blown up; its error from that step on is infinite.

Averages hide where a chaotic prediction parts from the truth, so the *predictable
horizon* is reported too: per trajectory, the first step t >= 1 at which its own
normalised MSE exceeds a threshold (0.1 and 1.0 by default; a blown-up step exceeds
every threshold), and the lower median of that step over trajectories.
"""
import numpy as np

HORIZON_THRESHOLDS = (0.1, 1.0)


def variance(x):
    """The per-dimension variance of the observed entries of ``x`` (..., d) over every other
    axis, float64; a dimension that does not vary, or was not observed, counts with variance 1."""
    x = np.asarray(x, dtype=np.float64)
    flat = x.reshape(-1, x.shape[-1])
    seen = ~np.isnan(flat)
    count = seen.sum(axis=0)
    mean = np.where(seen, flat, 0).sum(axis=0) / np.maximum(count, 1)
    var = np.where(seen, (flat - mean) ** 2, 0).sum(axis=0) / np.maximum(count, 1)
    return np.where(var > 0, var, 1.0)


def normalised_sq_error(pred, truth, spread=None, var=None):
    """(pred - truth)^2 / the per-dimension variance of ``spread`` (default: ``truth``; or the
    ``var`` given), float64, shape of ``pred``: NaN where the truth was not observed, inf where
    a prediction is non-finite."""
    var = variance(truth if spread is None else spread) if var is None else var
    with np.errstate(all="ignore"):
        err = (np.asarray(pred, dtype=np.float64) - truth) ** 2 / var
    err[~np.isfinite(err) & ~np.isnan(np.asarray(truth, dtype=np.float64))] = np.inf
    return err


def nmse(pred, truth, spread=None):
    """Normalised MSE over every observed entry (steps 1..T: pass pred[:, 1:], truth[:, 1:]); the
    variances come from ``spread`` (e.g. a whole file when ``truth`` is a sample of it)."""
    return float(_mean(normalised_sq_error(pred, truth, spread)))


def _mean(err, axis=None):
    """The mean over the observed (non-NaN) entries: NaN where there are none."""
    seen = ~np.isnan(err)
    with np.errstate(invalid="ignore"):
        return np.where(seen, err, 0).sum(axis=axis) / seen.sum(axis=axis)


def data_box(truth):
    """(mid, r): per-dimension midpoint and range of the observed ``truth`` (..., dx), r floored
    above 0; a dimension observed nowhere has no bounds (r = inf)."""
    flat = np.asarray(truth).reshape(-1, truth.shape[-1])
    seen = ~np.isnan(flat)
    lo = np.where(seen, flat, np.inf).min(axis=0)
    hi = np.where(seen, flat, -np.inf).max(axis=0)
    none = ~seen.any(axis=0)
    lo[none], hi[none] = 0.0, 0.0
    mid, r = (lo + hi) / 2, hi - lo
    r = np.maximum(r, np.maximum(1e-12, 1e-6 * np.abs(mid)))
    r[none] = np.inf
    return mid, r


def blow_up_mask(pred, truth=None, box=None):
    """Boolean (B, T+1): prediction non-finite or outside ten times the box at that step, and
    every step after it.  The box is ``data_box(truth)`` unless ``box`` = (mid, r) is given."""
    mid, r = data_box(truth) if box is None else box
    with np.errstate(invalid="ignore", over="ignore"):
        outside = ~(np.abs(pred - mid) <= 5 * r)  # NaN compares False -> outside
    bad = outside.any(axis=(2, 3))
    return np.logical_or.accumulate(bad, axis=1)


def nmse_per_step(pred, truth, bad=None, spread=None):
    """Normalised MSE per step, shape (T+1,); steps where some trajectory blew up (``bad``) are
    inf, steps where nothing was observed NaN.  spread: whose variances (default: truth's)."""
    err = _mean(normalised_sq_error(pred, truth, spread), axis=(0, 2, 3))
    if bad is not None:
        err[bad.any(axis=0)] = np.inf
    return err


def nmse_per_dimension(pred, truth, spread=None):
    """Normalised MSE of each state dimension over its observed entries of steps 1..T, (dx,)."""
    return _mean(normalised_sq_error(pred[:, 1:], truth[:, 1:], truth if spread is None else spread), axis=(0, 1, 2))


def predictable_horizon(pred, truth, dt, thresholds=HORIZON_THRESHOLDS, bad=None):
    """Where predictions part from the truth: per threshold, the first step each exceeds it.

    pred, truth : ndarray, shape (B, T+1, N, dx);  bad : (B, T+1) blow-up mask or None.
    Returns {str(threshold): {"median_step", "median_time", "beyond_horizon" (trajectories
    never above it), "first_step" (per trajectory, None if never)}}; the median is the lower
    median with "never" counted as beyond T, None when that falls beyond T.
    """
    err = np.nan_to_num(_mean(normalised_sq_error(pred, truth), axis=(2, 3)), nan=0.0)  # (B, T+1)
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


#: how many blocks of steps `by_block` splits a horizon into
HORIZON_BLOCKS = 5


def by_block(per_step, first=1, blocks=HORIZON_BLOCKS):
    """The mean of ``per_step`` (T+1,) over up to ``blocks`` equal blocks of steps first..T:
    [{"steps": [a, b], "value": mean over a..b}] (NaN steps ignored; None where all are NaN)."""
    per_step = np.asarray(per_step, dtype=np.float64)
    steps = np.arange(first, len(per_step))
    out = []
    for part in np.array_split(steps, min(blocks, len(steps))) if len(steps) else []:
        v = per_step[part]
        v = v[~np.isnan(v)]
        out.append({"steps": [int(part[0]), int(part[-1])], "value": float(v.mean()) if v.size else None})
    return out


def invariant_drift(invariant, pred, truth):
    """How far a quantity the true dynamics conserve drifts along the predictions: per step, the
    mean over trajectories of |I(pred_t) - I(truth_0)| / |I(truth_0)|, beside the same of the
    true states (the reference integrator's own drift, or a sign that the quantity is not
    conserved).  invariant : x (B, T+1, N, dx) -> (B, T+1).  Returns (pred's (T+1,), truth's)."""
    with np.errstate(all="ignore"):
        i_true = np.asarray(invariant(truth), dtype=np.float64)
        i_pred = np.asarray(invariant(pred), dtype=np.float64)
        scale = np.abs(i_true[:, :1])
        rel = lambda i: np.nanmean(np.abs(i - i_true[:, :1]) / scale, axis=0)
        return rel(i_pred), rel(i_true)
