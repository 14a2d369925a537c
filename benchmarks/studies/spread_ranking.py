"""Does an ensemble's spread rank its errors across test trajectories, and if not, why not?

Evaluates an ensemble file on a test file (`mpnode.evaluation.evaluate`, as `mpnode eval` does) and
takes its per-trajectory spread and error apart: how much they differ between trajectories, the
share of the squared error common to every trajectory, the Spearman correlation per state group
(the file's `state_groups`) and per dimension, under other readings of the spread (the training
data's units, a geometric mean or median over dimensions, absolute instead of squared, early steps
only), against how far each trajectory's truth lies from the average one, how high it lies (its
mean level) and how much it moves over the horizon.  With --step-scale-from OTHER.h5 the spread is
also rescaled per step by the ratio of error to spread that the ensemble shows on OTHER (a
calibration per step instead of one per dimension) and ranked again.  Prints one JSON object; the
tables in docs/evidence/ensembles.md ("quad3 -> quad6", "gene16 -> gene64") come from it.

    python benchmarks/studies/spread_ranking.py ENSEMBLE.h5 TEST.h5 [--step-scale-from OTHER.h5]
"""
import argparse
import json
import sys

import numpy as np

from mpnode.data import read_trajectories
from mpnode.evaluation.evaluate import evaluate
from mpnode.evaluation.metrics import variance
from mpnode.evaluation.spread import spearman
from mpnode.model import Model


def per_trajectory(a, dims=slice(None), steps=slice(None)):
    """(B,) the mean of a (B, T, N, dx) array over steps, nodes and the dimensions ``dims``."""
    return a[:, steps][..., dims].mean(axis=(1, 2, 3))


def readings(err, sp, mean, truth, s, var, x_std):
    """Spearman(spread, error) across trajectories under readings other than mpnode's."""
    train_var = np.asarray(x_std, dtype=np.float64) ** 2
    per_dim_err, per_dim_sp = err.mean(axis=(1, 2)), sp.mean(axis=(1, 2))
    flat = len(err), -1
    out = {"training_data_units": spearman(per_trajectory(s ** 2 / train_var), per_trajectory((mean - truth) ** 2 / train_var)),
           "geometric_mean_over_dims": spearman(np.log(per_dim_sp).mean(1), np.log(per_dim_err).mean(1)),
           "median_entry": spearman(np.median(sp.reshape(flat), 1), np.median(err.reshape(flat), 1)),
           "mean_abs_vs_mean_spread": spearman(per_trajectory(s / np.sqrt(var)),
                                               per_trajectory(np.abs(mean - truth) / np.sqrt(var)))}
    for t in (1, 5, 10, 25):
        out[f"steps_1_to_{t}"] = spearman(per_trajectory(sp, steps=slice(0, t)), per_trajectory(err, steps=slice(0, t)))
    return out


def step_scale(model, data_path, steps):
    """(steps,) per step, the root of the mean squared error over the mean squared spread on another file."""
    r = evaluate(model, read_trajectories(data_path))
    err, s = (r.predictions - r.scored)[:, 1:steps + 1], r.spread[:, 1:steps + 1]
    if err.shape[1] < steps:
        sys.exit(f"{data_path} has {err.shape[1]} steps, fewer than the test file's {steps}")
    return np.sqrt(np.nanmean(err ** 2, axis=(0, 2, 3)) / np.mean(s ** 2, axis=(0, 2, 3)))


def main(model_path, data_path, other=None):
    model = Model.load(model_path)
    r = evaluate(model, read_trajectories(data_path))
    if r.spread is None:
        sys.exit(f"{model_path} is one model, not an ensemble: it has no spread")
    truth, mean, s = r.scored[:, 1:], r.predictions[:, 1:], r.spread[:, 1:]
    var = variance(r.scored)
    err, sp = (mean - truth) ** 2 / var, s ** 2 / var
    e, q = per_trajectory(err), per_trajectory(sp)
    shared = (mean - truth).mean(axis=0, keepdims=True)  # the error every trajectory has in common
    unusual = per_trajectory((truth - truth.mean(axis=0)) ** 2 / var)  # how far each truth is from the average one
    out = {"nmse": r.nmse, "spread_error_spearman": r.ensemble["spread_error_spearman"],
           "error_p10_p50_p90": np.percentile(e, [10, 50, 90]).tolist(), "error_std_over_mean": e.std() / e.mean(),
           "spread_p10_p50_p90": np.percentile(q, [10, 50, 90]).tolist(), "spread_std_over_mean": q.std() / q.mean(),
           "common_error_share": 1 - ((mean - truth - shared) ** 2 / var).mean() / err.mean(),
           "spearman_error_vs_unusual_truth": spearman(unusual, e), "spearman_spread_vs_unusual_truth": spearman(unusual, q),
           "per_group": {g: spearman(per_trajectory(sp, dims), per_trajectory(err, dims)) for g, dims in (r.groups or {}).items()},
           "per_dim": [spearman(per_trajectory(sp, [d]), per_trajectory(err, [d])) for d in range(err.shape[-1])],
           "readings": readings(err, sp, mean, truth, s, var, model.x_std)}
    level = per_trajectory(truth / np.sqrt(var))  # the truth's mean, in the test file's standard deviations
    moves = per_trajectory(np.broadcast_to(truth.var(axis=1, keepdims=True) / var, truth.shape))
    out["spearman_error_vs_level"], out["spearman_spread_vs_level"] = spearman(level, e), spearman(level, q)
    out["spearman_error_vs_movement"], out["spearman_spread_vs_movement"] = spearman(moves, e), spearman(moves, q)
    if other is not None:
        scale = step_scale(model, other, truth.shape[1])
        out["step_scale"] = scale.tolist()
        out["spearman_step_scaled"] = spearman(per_trajectory((s * scale[None, :, None, None]) ** 2 / var), e)
    print(json.dumps(out, default=float))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ensemble")
    ap.add_argument("test")
    ap.add_argument("--step-scale-from", metavar="OTHER.h5", help="fit a spread scale per step on this file")
    a = ap.parse_args()
    main(a.ensemble, a.test, a.step_scale_from)
