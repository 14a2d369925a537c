"""The reference simulator as a yardstick: how fast the true equations reach a learned model's error.

`mpnode eval` sets the learned rollout's speed beside the reference's, like with like: the
reference at the cheapest setting whose error against the file, on the same sampled initial
states, is no larger than the model's.  Two families are searched, each from its cheapest
setting up, stopping at the first that reaches the model's normalised MSE:

* the file's own scipy integrator at looser tolerances, rtol = atol = 1e-3, 1e-4, ...,
  down to the file's own (which rebuilds the file), one trajectory per call;
* classic RK4 of the true equations with 1, 2, 4, ... steps per dt, all the sampled
  trajectories of a graph as one batch (the right-hand sides take states as columns:
  data_gen.systems); of a system whose nodes differ, all of them side by side as one network
  (their graphs block-diagonal, as the learned model batches them: data_gen.systems.union_rhs),
  which is how a fast reference would be written.

The faster of the two wins.  The search stops early once it has spent SEARCH_SECONDS, so
`mpnode eval` stays affordable; what it tried is reported.
"""
import math
import time

import numpy as np

from mpnode.base.errors import NumericalError
from mpnode.evaluation.metrics import nmse

from .simulate import integrate
from .systems import SYSTEMS, file_rhs, trajectory_rhs, union_rhs

#: the loosest tolerance tried first; each next is ten times tighter, down to the file's own
LOOSEST_TOL = 1e-3
#: RK4 steps per dt tried, cheapest first
RK4_STEPS = (1, 2, 4, 8, 16, 32, 64)
#: the search stops trying tighter settings once it has spent this long (seconds)
SEARCH_SECONDS = 5.0
#: a setting faster than this (seconds for the sample) is timed again, best of 3: one short run is noisy
RETIME_BELOW = 0.5


def rk4_columns(rhs, y0, n_steps, dt, steps):
    """Classic RK4 of ``rhs`` on states as columns: y0 (N*dx, K) -> (n_steps+1, N*dx, K)."""
    y = np.array(y0, dtype=np.float64)
    h = dt / steps
    out = np.empty((n_steps + 1,) + y.shape)
    out[0] = y
    with np.errstate(all="ignore"):  # a step too long for the field blows up: its error says so
        for t in range(n_steps):
            for s in range(steps):
                tt = (t * steps + s) * h
                k1 = rhs(tt, y)
                k2 = rhs(tt + h / 2, y + h / 2 * k1)
                k3 = rhs(tt + h / 2, y + h / 2 * k2)
                k4 = rhs(tt + h, y + h * k3)
                y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            out[t + 1] = y
    return out


class _Sample:
    """The first k trajectories of a file and the true right-hand side of each of its graphs (of each
    trajectory, when its nodes differ; the batched RK4 then runs them side by side as one network)."""

    def __init__(self, traj, k):
        self.system = SYSTEMS[traj.system]
        self.k, self.horizon, self.dt = k, traj.horizon, float(traj.dt)
        self.x = np.asarray(traj.x, dtype=np.float64)
        self.union = None
        if traj.node_attrs is None:
            self.rhs, self.gi = file_rhs(traj), np.asarray(traj.graph_index[:k])
        else:
            self.rhs, self.gi = [trajectory_rhs(traj, b) for b in range(k)], np.arange(k)
            self.union = union_rhs(traj, k)
        self.method = str(traj.attrs.get("integrator", "DOP853"))
        self.rtol, self.atol = float(traj.attrs.get("rtol", 1e-9)), float(traj.attrs.get("atol", 1e-9))

    def error(self, out):
        """Normalised MSE of ``out`` (k, T+1, N, dx) against the file (steps 1..T, the whole file's variances)."""
        if not np.all(np.isfinite(out)):
            return math.inf
        return nmse(out[:, 1:], self.x[:self.k, 1:], spread=self.x)

    def scipy(self, rtol, atol):
        out = np.empty((self.k,) + self.x.shape[1:])
        for b in range(self.k):
            out[b] = integrate(self.rhs[int(self.gi[b])], self.x[b, 0], self.horizon, self.dt, self.method, rtol,
                               atol, self.system.guard)
        return out

    def rk4(self, steps):
        if self.union is not None:  # one state vector: trajectory 0's nodes, then 1's, ...
            ys = rk4_columns(self.union, self.x[:self.k, 0].reshape(-1, 1), self.horizon, self.dt, steps)
            return ys[..., 0].reshape((self.horizon + 1, self.k) + self.x.shape[2:]).swapaxes(0, 1)
        out = np.empty((self.k,) + self.x.shape[1:])
        for g in np.unique(self.gi):
            idx = np.flatnonzero(self.gi == g)
            y0 = self.x[idx, 0].reshape(len(idx), -1).T
            ys = rk4_columns(self.rhs[int(g)], y0, self.horizon, self.dt, steps)
            out[idx] = np.moveaxis(ys, -1, 0).reshape((len(idx),) + self.x.shape[1:])
        return out

    def settings(self):
        """(family, setting, run) of both families, cheapest first in each."""
        tols = []
        tol = LOOSEST_TOL
        while tol > self.rtol * 1.0001:
            tols.append((tol, tol))
            tol /= 10
        tols.append((self.rtol, self.atol))
        scipy = [("scipy", f"scipy {self.method} rtol={r:g} atol={a:g}", lambda r=r, a=a: self.scipy(r, a))
                 for r, a in tols]
        rk4 = [("rk4", f"batched RK4, {s} step{'s' if s > 1 else ''} per dt", lambda s=s: self.rk4(s))
               for s in RK4_STEPS]
        return scipy, rk4


def _timed(run):
    """(run()'s output or None when the integration failed, seconds)."""
    start = time.perf_counter()
    try:
        out = run()
    except NumericalError:
        out = None
    return out, time.perf_counter() - start


def _run(setting, sample):
    """{family, setting, seconds_per_trajectory, nmse} of one setting (a run that fails: nmse inf)."""
    family, name, run = setting
    out, seconds = _timed(run)
    error = math.inf if out is None else sample.error(out)
    if math.isfinite(error) and seconds < RETIME_BELOW:
        seconds = min(seconds, *(_timed(run)[1] for _ in range(2)))
    return {"family": family, "setting": name, "seconds_per_trajectory": seconds / sample.k, "nmse": error}


def _search(family, sample, target, deadline):
    """The settings of one family tried cheapest first, up to the first whose error reaches ``target``."""
    tried = []
    for setting in family:
        tried.append(_run(setting, sample))
        if tried[-1]["nmse"] <= target or time.perf_counter() > deadline:
            break
    return tried


def reference_timing(traj, sample, target):
    """The cheapest reference setting whose normalised MSE against ``traj`` on its first
    ``sample`` trajectories is at most ``target`` (module docstring).

    Returns {system, sample, target_nmse, reached (bool), integrator (the chosen setting),
    reference_seconds_per_trajectory, reference_nmse_vs_file, tried (every setting tried:
    family, setting, seconds_per_trajectory, nmse)}; when nothing reached ``target``, the
    chosen setting is the most accurate one tried.  None when the file does not name a
    reference system this package can rebuild from its own parameters (predictions,
    controlled systems, foreign files), or its dt is beyond what the system's integrator
    can finish (data_gen.systems.System.check_dt).
    """
    if traj.system not in SYSTEMS or "predicted_by" in traj.attrs or traj.u is not None:
        return None
    system = SYSTEMS[traj.system]
    if traj.state_dim != system.state_dim:
        return None
    try:
        system.check_dt({k: traj.attrs[k] for k in system.defaults if k in traj.attrs}, traj.dt, "data")
        ref = _Sample(traj, min(sample, traj.n_trajectories))
    except (KeyError, ValueError, TypeError):  # InputError (a dt the integrator would never finish) is a ValueError
        return None
    deadline = time.perf_counter() + SEARCH_SECONDS
    tried = [row for family in ref.settings() for row in _search(family, ref, target, deadline)]
    reaching = [row for row in tried if row["nmse"] <= target]
    chosen = (min(reaching, key=lambda r: r["seconds_per_trajectory"]) if reaching
              else min(tried, key=lambda r: r["nmse"]))
    return {"system": traj.system, "sample": ref.k, "target_nmse": _number(target), "reached": bool(reaching),
            "integrator": chosen["setting"], "reference_seconds_per_trajectory": chosen["seconds_per_trajectory"],
            "reference_nmse_vs_file": _number(chosen["nmse"]),
            "tried": [{**row, "nmse": _number(row["nmse"])} for row in tried]}


def _number(v):
    """A float for JSON: inf (a run that blew up or failed) as the string "inf"."""
    return v if math.isfinite(v) else str(v)


def speed_against_reference(model, traj, result, sample):
    """The cheapest reference that reaches the model's error, timed beside the learned model on
    the same initial states.

    result : the EvalResult of ``model`` on ``traj`` (its predictions, substeps and full-batch time).
    Returns reference_timing's dict (its target: the model's normalised MSE on the sample) plus
    learned_nmse, learned_seconds_per_trajectory (the sample as one batch), ..._full_batch and
    speedup (reference time over learned time: below 1, the learned model is slower); None as
    reference_timing.
    """
    from mpnode.evaluation.evaluate import learned_seconds_per_trajectory

    k = min(sample, traj.n_trajectories)
    x = np.asarray(traj.x, dtype=np.float64)
    pred = np.asarray(result.predictions[:k], dtype=np.float64)
    learned = nmse(pred[:, 1:], x[:k, 1:], spread=x) if np.all(np.isfinite(pred)) else math.inf
    ref = reference_timing(traj, sample, learned)
    if ref is None:
        return None
    m = model.with_spec(dt=float(traj.dt), substeps=result.substeps)
    ref["learned_nmse"] = _number(learned)
    ref["learned_seconds_per_trajectory"] = learned_seconds_per_trajectory(m, traj, ref["sample"])
    ref["learned_seconds_per_trajectory_full_batch"] = result.rollout_seconds / result.n_trajectories
    ref["speedup"] = ref["reference_seconds_per_trajectory"] / ref["learned_seconds_per_trajectory"]
    return ref
