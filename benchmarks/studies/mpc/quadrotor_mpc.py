"""The quadrotor swarm carrying its load through a doorway, in closed loop on the reference
simulator (the truth: data_gen's LSODA integration at 1e-9), under three controllers:

- ``scene``: the scene's own cascaded controller (data_gen.quadrotor.Controller, nominal gains);
- ``true``: shooting MPC through the true equations (the same right-hand side, integrated by RK4
  at dt / 10, the load included), its gradient by one-sided finite differences of all controls
  at once (one batched integration: every perturbed control sequence is a column);
- ``learned``: shooting MPC through a learned model (mpnode.control.ShootingMPC: the engine's
  exact gradient with respect to the thrusts), which sees the quadrotors only, never the load.

Both MPCs minimise the same cost of the quadrotors' states over H steps: distance to the
reference formation (positions, velocities, the attitude of the nominal thrust, no body rates)
and thrusts away from the nominal ones.  With --anchor W > 0 (a regularised MPC, for both
MPCs alike) the first step's thrusts are also charged W (F - F_scene)^2, F_scene the scene
controller's thrusts at the observed state: the plan may depart from a controller known to
fly only as far as the model's predicted gain pays for.  With --offset-free the learned MPC
adds to each plan's predictions its model's last one-step error, once per step
(ShootingMPC(offset_free=True)): the true equations' own error is that of RK4 at dt / 10.
--anchor-torques WT charges the anchor's torque part (the departure summing to zero over a
quadrotor's rotors) WT instead of W; --load-unseen has the true-model MPC plan without the
load's swing, as a model of the quadrotors alone must; --linearised has the learned MPC plan
through the model's linearisation about the warm-started plan (`LinearisedMPC`).  --record FILE writes the flights of one
controller as a trajectory file to learn from, --explore S adding N(0, S^2) to every thrust.
The paths are new: start and goal drawn as the scene draws them but from other seeds, and the
doorway moved (sideways by up to 0.4 m, up by up to 0.3 m), where the training data's doorway
never moves.  Reported per controller: the load's tracking error (its distance to the reference
path, mean and max over the run), the time per control step (mean, median and p95 of the wall
time, and the mean CPU time of this process, which a shared or paused machine does not inflate)
and the mean |F - F_scene| of the thrusts applied.  No thrust noise unless --explore, nominal gains.

    python benchmarks/studies/mpc/quadrotor_mpc.py MODEL.h5 [--paths 20] [--horizon 10] [--anchor W] \
        [--anchor-torques WT] [--offset-free] [--load-unseen] [--linearised] [--record FILE [--explore S]] [--out DIR]
"""
import argparse
import json
import math
import os
import time

import numpy as np

from data_gen import quadrotor as quad
from mpnode import Model, engine, write_trajectories
from mpnode.base.graph import Graph
from mpnode.control import ShootingMPC, optimise_controls, tracking_cost
from mpnode.data import Trajectories
from mpnode.model.model import batch_graph, to_time_major
from true_equations import rk4_rollout

N, DT, STEPS = 3, 0.1, 50
#: cost weights per state dimension: position, quaternion, velocity, body rates; per thrust
Q = np.array([10.0] * 3 + [1.0] * 4 + [1.0] * 3 + [0.0] * 3)
R = np.full(4, 0.5)


def new_path(seed):
    """start, goal, doorway of one path the training data never flew."""
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    start, goal, _ = quad.draw_scenario(rng, quad.CONTROL)
    door = np.asarray(quad.CONTROL["doorway"]) + [0.0, rng.uniform(-0.4, 0.4), rng.uniform(0.0, 0.3)]
    return start, goal, door


def references(ref, physics, t, horizon):
    """The formation's states (horizon+1, N, 13) at t, t+dt, ... and the nominal thrusts (horizon, N, 4)."""
    x = np.zeros((horizon + 1, N, 13))
    f = np.zeros((horizon, N, 4))
    for k in range(horizon + 1):
        r, v, a, u, s = ref.quads(t + k * DT)
        force = physics.m_q * (a - physics.g) + s[:, None] * u
        x[k, :, 0:3], x[k, :, 7:10] = r, v
        x[k, :, 3:7] = [quad.attitude_for_thrust(fi) for fi in force]
        if k < horizon:
            f[k] = np.linalg.norm(force, axis=1)[:, None] / 4
    return x, f


def plan_cost(x_ref, f_ref, anchor=0.0, f_scene=None, anchor_torques=None):
    """The MPC's cost of one plan (tracking_cost): states towards x_ref (H+1, N, 13), thrusts
    towards f_ref (H, N, 4) with weight R; with anchor > 0 the first step's thrusts also towards
    f_scene (N, 4) with weight anchor (the two quadratics of step 0 summed into one).  With
    anchor_torques, the part of that departure that sums to zero over a quadrotor's four rotors
    (its torques) is charged anchor_torques instead: a model may know what the collective thrust
    does better than what the torques do."""
    if not anchor:
        return tracking_cost(x_ref[None], Q, R, f_ref[None])
    u_ref, r = f_ref.copy(), np.broadcast_to(R, f_ref.shape).copy()
    u_ref[0], r[0] = (R * f_ref[0] + anchor * f_scene) / (R + anchor), R + anchor
    cost = tracking_cost(x_ref[None], Q, r[None], u_ref[None])
    if anchor_torques is None or anchor_torques == anchor:
        return cost
    extra = anchor_torques - anchor

    def with_torques(X, U):
        value, gx, gu = cost(X, U)
        d = U[:, 0] - f_scene
        d = d - d.mean(axis=-1, keepdims=True)  # the zero-sum part: torques
        gu[:, 0] += 2 * extra * d
        return value + extra * float(np.sum(d * d)), gx, gu

    return with_torques


class TruePredictor:
    """Predictions of the true equations by RK4 at DT / substeps from the full state y (with the
    load), and their gradient by one-sided differences, every perturbation a column of one run."""

    def __init__(self, physics, substeps=10, eps=1e-6):
        self.p, self.substeps, self.eps = physics, substeps, eps

    def __call__(self, y, U):
        """(X (1, H+1, N, 13), vjp) for U (1, H, N, 4)."""
        n = U[0].size
        F = np.repeat(U[0][..., None], n + 1, axis=-1)
        F.reshape(n, n + 1)[:, 1:] += self.eps * np.eye(n)
        Y = rk4_rollout(self.p, y, F, DT, self.substeps)
        quads = Y[:, :13 * N].reshape(len(Y), N, 13, n + 1)
        X = quads[..., 0][None]

        def vjp(dX):
            diff = (quads[..., 1:] - quads[..., :1]) / self.eps  # (H+1, N, 13, n): d X / d U_j
            return np.tensordot(dX[0], diff, axes=3).reshape(U.shape)

        return X, vjp


def scene_controller(ref, physics):
    control = quad.Controller(N, ref, physics, quad.CONTROL, DT)
    return lambda t, y: control(t, quad.unpack(y, N)[0])[0]


def load_unseen(ref, t, y):
    """y with the load's state replaced by what the quadrotors alone suggest: where the reference
    hangs it below its formation, moved with the quadrotors' centroid, at their mean velocity (the
    swing the plan cannot see, as a model of the quadrotors alone cannot)."""
    quads = quad.unpack(y, N)[0]
    y = y.copy()
    y[13 * N:13 * N + 3] = quads[:, 0:3].mean(axis=0) + ref.load(t)[0] - ref.quads(t)[0].mean(axis=0)
    y[13 * N + 3:13 * N + 6] = quads[:, 7:10].mean(axis=0)
    return y


def true_mpc(ref, physics, horizon, iterations, anchor, anchor_torques=None, hide_load=False):
    predict, plan, scene = TruePredictor(physics), None, scene_controller(ref, physics)

    def control(t, y):
        nonlocal plan
        y_plan = load_unseen(ref, t, y) if hide_load else y
        x_ref, f_ref = references(ref, physics, t, horizon)
        plan = f_ref[None] if plan is None else np.concatenate([plan[:, 1:], plan[:, -1:]], axis=1)
        cost = plan_cost(x_ref, f_ref, anchor, scene(t, y) if anchor else None, anchor_torques)
        plan, _ = optimise_controls(lambda U: predict(y_plan, U), cost, plan, (0.0, physics.F_max), iterations)
        return plan[0, 0]

    return control


class LinearisedMPC(ShootingMPC):
    """Plans through the model's linearisation about the warm-started plan U0: X(U) = X(U0) + J (U - U0),
    J by one-sided differences of every control at once (one batched rollout of K + 1 copies, K the
    plan's controls), so that a plan cannot exploit how the model bends away from its response at U0.
    One model, not an ensemble."""

    EPS = 1e-4  # N: float64 rollouts, thrusts of about 1 N
    _at = None  # the full states of the control step the linearisation is of

    def __init__(self, model, *args, **kwargs):
        super().__init__(model, *args, **kwargs)
        if len(self.members) > 1:
            raise ValueError("LinearisedMPC plans through one model, not an ensemble")

    def _predict(self, z0, U):
        if self._at is not z0:  # a control step's first evaluation is at its warm start
            self._at = z0
            self._X0, self._J, self._U0 = self._linearise(z0[0], U)
        J = self._J
        X = self._X0 + (J @ (U - self._U0).ravel()).reshape(self._X0.shape)
        return X, lambda dX: (J.T @ dX.ravel()).reshape(U.shape)

    def _linearise(self, z0, U0):
        m, (_, n, dx), horizon, k = self.model, self._shape, U0.shape[1], U0.size
        UB = np.repeat(U0, k + 1, axis=0)
        UB.reshape(k + 1, k)[1 + np.arange(k), np.arange(k)] += self.EPS
        un = to_time_major(m.normalize_u(UB))
        xs, _ = engine.integrate(m.spec, m.theta, np.tile(z0, (k + 1, 1)), batch_graph(self.graph, k + 1), un,
                                 horizon)
        X = m.denormalize_x(xs.reshape(horizon + 1, k + 1, n, dx).transpose(1, 0, 2, 3))
        return X[:1] + self._offset, (X[1:] - X[:1]).reshape(k, -1).T / self.EPS, U0.copy()


def learned_mpc(model, ref, physics, horizon, iterations, messages, anchor, offset_free=False, anchor_torques=None,
                linearised=False):
    mpc = (LinearisedMPC if linearised else ShootingMPC)(model, Graph.complete(N), horizon,
                                                          bounds=(0.0, physics.F_max), iterations=iterations,
                                                          messages=messages, offset_free=offset_free)
    started, scene = [], scene_controller(ref, physics)

    def control(t, y):
        x = quad.unpack(y, N)[0]
        x_ref, f_ref = references(ref, physics, t, horizon)
        if not started:
            mpc.reset(x[None], f_ref[0][None])
            started.append(True)
        cost = plan_cost(x_ref, f_ref, anchor, scene(t, y) if anchor else None, anchor_torques)
        return mpc.control(x[None], cost)[0]

    return control


def closed_loop(make_controller, path, explore=None):
    """Run one path on the truth: load error (STEPS+1,), (wall, CPU) seconds per control step, the load's path, failure,
    the mean |F - F_scene| (N) of the thrusts applied against the scene controller's at the same states, and the
    flight (the plant's states (k+1, 13 N + 6) and the thrusts applied (k, N, 4)).  With explore = (rng, S) every
    applied thrust gets N(0, S^2) added, which the controller did not choose (data to learn from)."""
    physics = quad.Physics()
    start, goal, door = path
    ref = quad.Reference(N, start, goal, physics, {**quad.CONTROL, "doorway": tuple(door)})
    controller, scene = make_controller(ref, physics), scene_controller(ref, physics)
    x0, load0, _, _ = quad.static_equilibrium(N, start, physics)
    y = quad.pack(x0, load0)
    loads, seconds, departures, failure, ys, thrusts = [y[13 * N:13 * N + 3]], [], [], None, [y], []
    for k in range(STEPS):
        t0, c0 = time.perf_counter(), time.process_time()
        F = controller(k * DT, y)
        seconds.append((time.perf_counter() - t0, time.process_time() - c0))
        if explore is not None:
            F = F + explore[0].normal(0.0, explore[1], F.shape)
        F = np.clip(F, 0.0, physics.F_max)
        thrusts.append(F)
        departures.append(float(np.mean(np.abs(F - scene(k * DT, y)))))
        try:
            y = quad.step(physics, y, F, k * DT, DT)
        except Exception as e:  # the solver gives up: the swarm was lost
            failure = f"step {k}: {e}"
            break
        loads.append(y[13 * N:13 * N + 3])
        ys.append(y)
        if np.max(quad.tilt(quad.unpack(y, N)[0][:, 3:7])) > math.radians(quad.CONTROL["fail_tilt_deg"]):
            failure = f"step {k}: tilt beyond {quad.CONTROL['fail_tilt_deg']} deg"
            break
    loads = np.array(loads)
    wanted = np.array([ref.load(k * DT)[0] for k in range(len(loads))])
    return (np.linalg.norm(loads - wanted, axis=1), seconds, loads, wanted, failure, float(np.mean(departures)),
            (np.array(ys), np.array(thrusts[:len(ys) - 1])))


def write_flights(path, flights, seeds, explore):
    """The closed-loop flights that did not fail, as a quad3 trajectory file (states, thrusts, the load in aux/)."""
    if not flights:
        raise SystemExit(f"{path} not written: every flight failed")
    ys, us = np.stack([f[0] for f in flights]), np.stack([f[1] for f in flights])
    attrs = {**quad.PARAMS, "scene": "quad3", "path_seeds": np.array(seeds), "thrust_exploration": explore,
             "description": "closed-loop flights (benchmarks/studies/mpc/quadrotor_mpc.py --record)"}
    traj = Trajectories(x=ys[:, :, :13 * N].reshape(len(ys), STEPS + 1, N, 13), u=us, graphs=[Graph.complete(N)],
                        dt=DT, system=quad.SYSTEM, params=quad.draw_params(None, N, None),
                        aux={"load": ys[:, :, 13 * N:]}, attrs=attrs)
    write_trajectories(path, traj)
    print(f"wrote {path}: {len(ys)} flights")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--paths", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=10_000, help="path p draws from SeedSequence(first_seed + p)")
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=30, help="L-BFGS-B iterations per control step")
    ap.add_argument("--controllers", default="scene,true,learned")
    ap.add_argument("--messages", default="carry", choices=("carry", "zero"),
                    help="the learned model's messages at the start of each plan (ShootingMPC)")
    ap.add_argument("--anchor", type=float, default=0.0,
                    help="weight of the first thrusts' distance to the scene controller's, both MPCs (0: none)")
    ap.add_argument("--anchor-torques", type=float,
                    help="the anchor's weight on the torques (the departure summing to zero over a quadrotor's "
                         "rotors), both MPCs; default: --anchor's")
    ap.add_argument("--load-unseen", action="store_true",
                    help="the true-model MPC plans from the load's state as the quadrotors alone suggest it "
                         "(no swing), as a learned model of the quadrotors must")
    ap.add_argument("--offset-free", action="store_true",
                    help="the learned MPC adds its model's last one-step error, once per step, to every plan's predictions")
    ap.add_argument("--linearised", action="store_true",
                    help="the learned MPC plans through the model's linearisation about its warm start")
    ap.add_argument("--record", metavar="FILE",
                    help="write the flights of the one controller given (--controllers) as a trajectory file")
    ap.add_argument("--explore", type=float, default=0.0,
                    help="std (N) of noise added to every applied thrust, per rotor (data to learn from)")
    ap.add_argument("--out", default=os.path.dirname(os.path.abspath(__file__)))
    a = ap.parse_args()
    if a.record and "," in a.controllers:
        ap.error("--record writes one controller's flights: give one with --controllers")
    model = Model.load(a.model)
    makers = {"scene": scene_controller,
              "true": lambda ref, p: true_mpc(ref, p, a.horizon, a.iterations, a.anchor, a.anchor_torques,
                                              a.load_unseen),
              "learned": lambda ref, p: learned_mpc(model, ref, p, a.horizon, a.iterations, a.messages, a.anchor,
                                                     a.offset_free, a.anchor_torques, a.linearised)}
    results = {"model": os.path.basename(a.model), "horizon": a.horizon, "iterations": a.iterations,
               "messages": a.messages, "anchor": a.anchor, "anchor_torques": a.anchor_torques,
               "load_unseen": a.load_unseen, "offset_free": a.offset_free, "linearised": a.linearised,
               "explore": a.explore, "paths": []}
    flights, seeds = [], []
    for p in range(a.paths):
        path = new_path(a.first_seed + p)
        row = {"seed": a.first_seed + p, "start": path[0].tolist(), "goal": path[1].tolist(), "door": path[2].tolist()}
        for name in a.controllers.split(","):  # every controller of a path meets the same thrust noise
            explore = (np.random.default_rng(np.random.SeedSequence(a.first_seed + p, spawn_key=(1,))), a.explore) \
                if a.explore else None
            err, times, loads, wanted, failure, departure, flight = closed_loop(makers[name], path, explore)
            if failure is None:
                flights.append(flight)
                seeds.append(a.first_seed + p)
            secs, cpu = np.array(times).T
            row[name] = dict(mean_error=float(err.mean()), max_error=float(err.max()), failure=failure,
                             departure=departure, ms_median=1e3 * float(np.median(secs)),
                             cpu_ms_per_step=1e3 * float(np.mean(cpu)),
                             ms_per_step=1e3 * float(np.mean(secs)), ms_p95=1e3 * float(np.percentile(secs, 95)),
                             load=np.round(loads, 6).tolist(), reference=np.round(wanted, 6).tolist())
            print(f"path {p} {name:8s} load error mean {err.mean():.3f} m max {err.max():.3f} m, "
                  f"{1e3 * np.mean(secs):.1f} ms/step (median {1e3 * np.median(secs):.1f}, "
                  f"CPU {1e3 * np.mean(cpu):.1f}), "
                  f"|F - F_scene| {departure:.3f} N"
                  + (f"  FAILED {failure}" if failure else ""), flush=True)
        results["paths"].append(row)
    with open(os.path.join(a.out, "quadrotor_results.json"), "w") as f:
        json.dump(results, f)
    if a.record:
        write_flights(a.record, flights, seeds, a.explore)
    summarise(results, a.controllers.split(","))


def summarise(results, names):
    for name in names:
        rows = [r[name] for r in results["paths"]]
        print(f"{name:8s} mean load error {np.mean([r['mean_error'] for r in rows]):.3f} m, "
              f"max {np.max([r['max_error'] for r in rows]):.3f} m, "
              f"{np.mean([r['ms_per_step'] for r in rows]):.1f} ms per control step "
              f"(median {np.mean([r.get('ms_median', np.nan) for r in rows]):.1f}, "
              f"CPU {np.mean([r.get('cpu_ms_per_step', np.nan) for r in rows]):.1f}), "
              f"{sum(r['failure'] is not None for r in rows)} failed, "
              f"|F - F_scene| {np.mean([r.get('departure', np.nan) for r in rows]):.3f} N")
    if {"learned", "true"} <= set(names):
        learned, true = ([r[name]["mean_error"] for r in results["paths"]] for name in ("learned", "true"))
        print(f"load error learned / true: {np.mean(learned) / np.mean(true):.2f} (means of the paths' means), "
              f"worst path {np.max(np.divide(learned, true)):.2f}")


if __name__ == "__main__":
    main()
