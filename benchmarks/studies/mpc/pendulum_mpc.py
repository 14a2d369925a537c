"""The coupled pendulums driven to a target configuration by horizontal forces on the bobs
(scene pendulum_force), in closed loop on the reference simulator (DOP853 at 1e-9), under:

- ``pd``: a PD law around the target's static force, u = u_eq + kp (th* - th) - kd omega;
- ``true``: shooting MPC through the true equations (RK4 at dt / 10; gradient by one-sided
  finite differences of all forces at once, each perturbation a column of one batched run);
- ``learned``: shooting MPC through a learned model (mpnode.control.ShootingMPC, the engine's
  exact gradient with respect to the forces).

Every run starts from a state drawn as the scene draws them (seeds the training data never
used) and must reach a target drawn uniform in [-0.15, 0.15] rad per bob, at rest, and hold it.
Reported: the angle error (rad, both bobs) averaged over the last second of a 4 s run, and
the wall time per control step.  Forces within [-3, 3] N (the data's range).

    python benchmarks/studies/mpc/pendulum_mpc.py MODEL.h5 [--runs 20] [--horizon 20] [--out DIR]
"""
import argparse
import json
import os
import time

import numpy as np

from data_gen import forced_pendulum as fp
from mpnode import Model
from mpnode.base.graph import Graph
from mpnode.control import ShootingMPC, optimise_controls, tracking_cost

DT, STEPS, U_MAX = 0.05, 80, 3.0
P = {k: fp.PARAMS[k] for k in ("m", "l", "k", "g")}
Q, R = np.array([10.0, 1.0]), np.array([0.01])


def static_force(target):
    """The forces (2,) that hold the bobs at rest at angles ``target``."""
    s = np.sin(target)
    return P["m"] * P["g"] * s + P["k"] * P["l"] * (s - s[::-1])


def true_predictor(y, U, substeps=10, eps=1e-6):
    """(X (1, H+1, 2, 2), vjp) of the true equations by RK4 from y (4,), U (1, H, 2, 1)."""
    n = U[0].size
    F = np.repeat(U[0].reshape(-1, 2)[..., None], n + 1, axis=-1)  # (H, 2, n+1)
    F.reshape(n, n + 1)[:, 1:] += eps * np.eye(n)
    h = DT / substeps
    Y = np.repeat(y[:, None], n + 1, axis=1)
    out = [Y]

    def f(Y, u):
        th, om = Y[0::2], Y[1::2]
        dy = np.empty_like(Y)
        dy[0::2] = om
        dy[1::2] = (np.sin(th) * (P["m"] * (P["l"] * om ** 2 - P["g"]) - P["k"] * P["l"])
                    + P["k"] * P["l"] * np.sin(th[::-1]) + u) / (P["m"] * P["l"] * np.cos(th))
        return dy

    for t in range(F.shape[0]):
        for _ in range(substeps):
            k1 = f(Y, F[t])
            k2 = f(Y + h / 2 * k1, F[t])
            k3 = f(Y + h / 2 * k2, F[t])
            k4 = f(Y + h * k3, F[t])
            Y = Y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(Y)
    Y = np.stack(out).reshape(len(out), 2, 2, n + 1)

    def vjp(dX):
        return np.tensordot(dX[0], (Y[..., 1:] - Y[..., :1]) / eps, axes=3).reshape(U.shape)

    return Y[None, ..., 0], vjp


def pd(target):
    u_eq = static_force(target)
    return lambda y: u_eq + 15.0 * (target - y[0::2]) - 6.0 * y[1::2]


def true_mpc(target, horizon, iterations):
    x_ref = np.stack([target, np.zeros(2)], axis=1)
    cost = tracking_cost(x_ref, Q, R, static_force(target)[:, None])
    plan = np.repeat(static_force(target)[None, None, :, None], horizon, axis=1)

    def control(y):
        nonlocal plan
        plan, _ = optimise_controls(lambda U: true_predictor(y, U), cost, plan, (-U_MAX, U_MAX), iterations)
        u = plan[0, 0, :, 0].copy()
        plan = np.concatenate([plan[:, 1:], plan[:, -1:]], axis=1)
        return u

    return control


def learned_mpc(model, target, horizon, iterations, messages):
    x_ref = np.stack([target, np.zeros(2)], axis=1)
    cost = tracking_cost(x_ref, Q, R, static_force(target)[:, None])
    mpc = ShootingMPC(model, Graph.complete(2), horizon, bounds=(-U_MAX, U_MAX), iterations=iterations,
                      messages=messages)
    started = []

    def control(y):
        x = y.reshape(1, 2, 2)
        if not started:
            mpc.reset(x, static_force(target)[None, :, None])
            started.append(True)
        return mpc.control(x, cost)[0, :, 0]

    return control


def closed_loop(controller, y0):
    """Angles (STEPS+1, 2), forces (STEPS, 2) and seconds per control step on the truth."""
    y, ys, us, secs = y0.copy(), [y0[0::2]], [], []
    for _ in range(STEPS):
        t0 = time.perf_counter()
        u = np.clip(controller(y), -U_MAX, U_MAX)
        secs.append(time.perf_counter() - t0)
        y = fp.step(y, u, DT, P)
        ys.append(y[0::2])
        us.append(u)
    return np.array(ys), np.array(us), secs


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=10_000)
    ap.add_argument("--horizon", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--messages", default="zero", choices=("zero", "carry"),
                    help="the learned model's messages at the start of each plan (ShootingMPC)")
    ap.add_argument("--out", default=os.path.dirname(os.path.abspath(__file__)))
    a = ap.parse_args()
    model = Model.load(a.model)
    low, high = np.array([-np.pi / 4, -0.5]), np.array([np.pi / 4, 0.5])
    results = {"model": os.path.basename(a.model), "horizon": a.horizon, "iterations": a.iterations,
               "messages": a.messages, "runs": []}
    for r in range(a.runs):
        rng = np.random.default_rng(np.random.SeedSequence(a.first_seed + r))
        y0, target = rng.uniform(low, high, size=(2, 2)).ravel(), rng.uniform(-0.15, 0.15, size=2)
        row = {"seed": a.first_seed + r, "y0": y0.tolist(), "target": target.tolist()}
        for name, ctrl in (("pd", pd(target)), ("true", true_mpc(target, a.horizon, a.iterations)),
                           ("learned", learned_mpc(model, target, a.horizon, a.iterations, a.messages))):
            th, u, secs = closed_loop(ctrl, y0)
            err = np.abs(th - target).mean(axis=1)
            row[name] = dict(final_error=float(err[-20:].mean()), ms_per_step=1e3 * float(np.mean(secs)),
                             angles=np.round(th, 6).tolist(), forces=np.round(u, 6).tolist())  # 1e-6: the file's size
            print(f"run {r} {name:8s} error over the last second {err[-20:].mean():.4f} rad, "
                  f"{1e3 * np.mean(secs):.1f} ms/step", flush=True)
        results["runs"].append(row)
    with open(os.path.join(a.out, "pendulum_results.json"), "w") as f:
        json.dump(results, f)
    for name in ("pd", "true", "learned"):
        rows = [r[name] for r in results["runs"]]
        print(f"{name:8s} mean error over the last second {np.mean([r['final_error'] for r in rows]):.4f} rad "
              f"(worst {np.max([r['final_error'] for r in rows]):.4f}), "
              f"{np.mean([r['ms_per_step'] for r in rows]):.1f} ms per control step")


if __name__ == "__main__":
    main()
