"""Would an ensemble's spread rank its errors, and its bands cover, if it widened off the training range?

Evaluates an ensemble file on a test file (`mpnode.evaluation.evaluate`, as `mpnode eval` does) and
measures, per trajectory and step, how far the inputs of its first member's rollout lie beyond the
ranges recorded in training (`mpnode.model.ranges`: the states per dimension and each aggregate
input per channel; the largest excess over nodes and channels, in widths of the seen range, 0
inside; the most so far along the trajectory).  It then widens the calibrated spread to
spread * (1 + c * excess) for a few c and reports, for each, the Spearman correlation of the
per-trajectory spread with the per-trajectory error (both as normalised mean squares, as
`spread_error_spearman`) and the bands' coverage, beside how well the excess alone ranks the
errors.  Prints one JSON object; the table in docs/evidence/ensembles.md ("Spreads widened off
the range") comes from it.

    python benchmarks/studies/spread_off_range.py ENSEMBLE.h5 TEST.h5 [--widths 0,0.25,1,4]
"""
import argparse
import json

import numpy as np

from mpnode.data import read_trajectories
from mpnode.evaluation.evaluate import evaluate, start_states
from mpnode.evaluation.spread import spearman, spread_figures
from mpnode.model import Model, ranges


def excess_along(model, x0, traj, u, only=None):
    """(B, T+1) the most any input has left the seen range by step t (seen widths; 0 inside);
    ``only``: one quantity ("state", "aggregate", ...) instead of all."""
    seen = model.attrs[ranges.KEY]
    out = np.zeros((len(x0), traj.horizon + 1))
    gi = np.asarray(traj.graph_index)
    for k in np.unique(gi):
        idx = np.flatnonzero(gi == k)
        inputs = ranges.network_inputs(model.members[0], x0[idx], traj.graphs[int(k)],
                                       None if u is None else u[idx], traj.horizon)
        for t, x, heard in inputs:
            for name, v in {"state": x, **heard}.items():
                if only not in (None, name):
                    continue
                lo, hi = (np.asarray(seen[f"{name}_{e}"], dtype=np.float64) for e in ("min", "max"))
                wide = hi > lo
                beyond = np.maximum(np.maximum(v - hi, lo - v), 0)[..., wide] / (hi - lo)[wide]
                if beyond.size:
                    out[idx, t] = np.maximum(out[idx, t], np.nanmax(beyond, axis=(1, 2)))
    return np.maximum.accumulate(out, axis=1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ensemble")
    ap.add_argument("test")
    ap.add_argument("--widths", default="0,0.25,1,4", help="the factors c of the excess to widen by")
    a = ap.parse_args()
    model, traj = Model.load(a.ensemble), read_trajectories(a.test)
    res = evaluate(model, traj, source=a.test, check_stability=False)
    u = None if traj.u is None else np.nan_to_num(np.asarray(traj.u))
    x0 = start_states(model, traj, 0)  # where evaluate's rollouts started
    err = np.asarray(res.ensemble["nmse_per_trajectory"], dtype=np.float64)
    excess = excess_along(model, x0, traj, u)
    out = {"ensemble": a.ensemble, "test": a.test, "nmse": res.nmse,
           "excess_at_end": {"median": float(np.median(excess[:, -1])), "max": float(excess.max())},
           "spearman_excess_error": {"all": spearman(excess[:, -1], err),
                                     **{q: spearman(excess_along(model, x0, traj, u, q)[:, -1], err)
                                        for q in ("state", "aggregate", "linear_aggregate")}},
           "widened": []}
    clean = np.asarray(traj.x if traj.truth is None else traj.truth, dtype=np.float64)
    for c in (float(v) for v in a.widths.split(",")):
        figures = spread_figures(res.predictions, res.spread * (1 + c * excess[:, :, None, None]), res.scored, clean)
        out["widened"].append({"c": c, **{k: figures[k] for k in ("spread_error_spearman", "spread_nmse",
                                                                   "coverage_50", "coverage_90")}})
    print(json.dumps(out, indent=1, default=str).replace("NaN", "null"))


if __name__ == "__main__":
    main()
