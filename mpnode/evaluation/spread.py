"""How far to trust an ensemble's prediction: its spread against its error.

The spread is the members' standard deviation times the calibrated scale (in the data's
units, per trajectory, step, node and dimension).  A useful spread does two things, both
measured here over steps 1..T of what is scored: its bands cover what they claim (the
fraction of true values inside mean +- z spread for the central 50% and 90% bands), and it
ranks errors (the Spearman correlation, across trajectories, of each trajectory's spread with
its error; both as normalised mean squares, so that the spread reads as the error the
ensemble expects).
"""
import numpy as np

from mpnode.model.ensemble import coverage

from .metrics import _mean, variance


def spearman(a, b):
    """Spearman's rank correlation of two sequences (NaN when fewer than 3 pairs are finite or
    one of them is constant)."""
    from scipy.stats import spearmanr

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:
        return float("nan")
    return float(spearmanr(a[ok], b[ok]).statistic)


def spread_figures(mean, spread, scored, clean):
    """The ensemble's figures (a JSON-ready dict) of predictions ``mean`` and ``spread`` (B, T+1, N, dx)
    against ``scored`` (the truth, NaN where not scored), normalised by the variances of ``clean``."""
    var = variance(clean)
    truth, m, s = scored[:, 1:], mean[:, 1:], spread[:, 1:]
    seen = np.isfinite(truth)
    with np.errstate(all="ignore"):
        err = np.where(seen, (m - truth) ** 2 / var, np.nan)
        expected = np.where(seen, s ** 2 / var, np.nan)
    per_traj_err, per_traj_spread = _mean(err, axis=(1, 2, 3)), _mean(expected, axis=(1, 2, 3))
    shown = np.where(seen, s, np.nan)
    return {"coverage_50": _num(coverage(truth, m, s, 50)), "coverage_90": _num(coverage(truth, m, s, 90)),
            "spread_nmse": _num(_mean(expected)),
            "spread_per_dim": [_num(v) for v in _mean(shown, axis=(0, 1, 2))],
            "spread_per_node": [[_num(v) for v in row] for row in _mean(shown, axis=(0, 1))],
            "spread_per_trajectory": [_num(v) for v in per_traj_spread],
            "nmse_per_trajectory": [_num(v) for v in per_traj_err],
            "spread_error_spearman": _num(spearman(per_traj_spread, per_traj_err))}


def _num(v):
    """A float for JSON: NaN and inf as strings."""
    v = float(v)
    return v if np.isfinite(v) else str(v)
