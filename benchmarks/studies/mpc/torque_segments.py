"""Short quad3 flights whose torques the state does not decide: segments of --steps steps started
from states of a scene file's flights (trajectory and step drawn at random), each flown by that
trajectory's own controller (its start, goal and gain factors from the file's aux/) with the
scene's excitation (`data_gen.quadrotor.excitation`: per quadrotor and pair of steps a collective
offset N(0, --collective^2) and a zero-sum torque doublet) but torques larger than a whole flight
survives, --torque N per rotor, plus the scene's 0.03 N noise.  Short segments let the torques be
large: the attitude loop is weak at dt = 0.1 s, and such torques over a whole flight tilt a
quadrotor far beyond the scene's tilts (docs/evidence/control.md).  A segment that tilts a quadrotor beyond --max-tilt degrees (or whose
solver fails) is re-drawn from its own generator.

With --nominal there is no controller either: the flight's own recorded thrusts are replayed from
its state at the segment's start, plus fresh offsets every step.  That is what an MPC plan is, a
thrust sequence near a flyable one that no feedback corrects within the plan, and it shows what
thrusts do over several steps without a controller's reaction mixed in.  The swarm is so
unstable open loop that fresh offsets of 0.05 N over five steps already tilt it by tens of degrees.

With --draws K, K segments start from each drawn state, each with its own thrusts: only the
thrusts explain their differences (a re-drawn segment keeps its start).  The group of segments
j*K .. j*K+K-1 draws everything from SeedSequence(--seed, spawn_key=(j,)) (K = 1: segment j).  Train on it beside the
scene's file, so that the model still predicts the scene's flights:

    python benchmarks/studies/mpc/torque_segments.py quad3.h5 OUT.h5 [-B 4000] [--steps 10] \\
        [--torque 0.3] [--collective 0.3] [--open-loop | --open-steps K | --nominal]
"""
import argparse
import math

import numpy as np

from data_gen import quadrotor as quad
from mpnode import read_trajectories, write_trajectories
from mpnode.base.errors import NumericalError
from mpnode.data import Trajectories

#: thrust draws from one start state (--draws > 1) before giving up on it
MAX_TRIES = 1000


def offsets(rng, n, a):
    """(n, 4) thrust offsets of one step: a collective N(0, --collective^2) and a torque pattern of --torque."""
    return quad.excitation(rng, n, a.collective, a.torque / a.collective)[0]


def start(rng, data, a):
    """A segment's trajectory and first step; --nominal needs the flight's thrusts for every step."""
    last = data.horizon - a.steps + 1 if a.nominal else data.horizon - 1
    return rng.integers(data.n_trajectories), rng.integers(last)


def segment(rng, data, a, physics, b, k0):
    """One segment from step k0 of trajectory b: dict x (T+1, n, 13), u (T, n, 4), load (T+1, 6),
    or None when it tipped over."""
    n, dt = data.n_nodes, data.dt
    aux = data.aux
    ref = quad.Reference(n, aux["load_start"][b], aux["load_goal"][b], physics, quad.CONTROL)
    control = quad.Controller(n, ref, physics, quad.CONTROL, dt, aux["gain_scale"][b])
    y = quad.pack(data.x[b, k0], aux["load"][b, k0])
    ys, us, extra = [y], [], np.zeros((2, n, quad.CONTROL_DIM))
    hold = np.repeat(data.u[b, k0].mean(axis=1, keepdims=True), quad.CONTROL_DIM, axis=1)
    for s in range(a.steps):
        t = (k0 + s) * dt
        if a.nominal:  # the flight's own thrusts replayed without feedback, plus fresh offsets
            F = np.clip(data.u[b, k0 + s] + offsets(rng, n, a), 0.0, physics.F_max)
        elif a.open_loop or s < a.open_steps:  # the start's collective thrusts without torques, held, plus fresh offsets
            F = np.clip(hold + offsets(rng, n, a), 0.0, physics.F_max)
        else:
            F, _ = control(t, quad.unpack(y, n)[0])
            F = quad.disturbed_thrusts(rng, s, F, extra, a.collective, a.torque / a.collective,
                                       quad.CONTROL["thrust_noise"], physics.F_max)
        try:
            y = quad.step(physics, y, F, t, dt)
        except NumericalError:
            return None
        if np.max(quad.tilt(quad.unpack(y, n)[0][:, 3:7])) > math.radians(a.max_tilt):
            return None
        ys.append(y)
        us.append(F)
    ys = np.stack(ys)
    return dict(x=ys[:, :13 * n].reshape(-1, n, 13), u=np.stack(us), load=ys[:, 13 * n:])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_file", help="a quad3 file of `mpnode generate` (its flights' states and aux/)")
    ap.add_argument("output")
    ap.add_argument("-B", "--segments", type=int, default=4000)
    ap.add_argument("--steps", type=int, default=10, help="steps per segment")
    ap.add_argument("--torque", type=float, default=0.3, help="std (N) of the per-rotor torque doublet's draws")
    ap.add_argument("--collective", type=float, default=0.3, help="std (N) of the collective offset (> 0)")
    ap.add_argument("--open-loop", action="store_true",
                    help="no controller: the start's collective thrusts held without torques, a fresh collective offset "
                         "and torque pattern every step (thrusts no state decides, not even through the controller)")
    ap.add_argument("--open-steps", type=int, default=0,
                    help="the first K steps open loop as --open-loop has them, the rest under the controller: what the "
                         "first steps' thrusts do over the steps after them, as a plan's first thrusts in MPC")
    ap.add_argument("--nominal", action="store_true",
                    help="no controller: the flight's own recorded thrusts replayed from its state, plus fresh offsets "
                         "every step (a plan's thrust sequence near a flyable one, which no feedback corrects)")
    ap.add_argument("--max-tilt", type=float, default=50.0, help="re-draw a segment tilting beyond this (deg)")
    ap.add_argument("--draws", type=int, default=1, help="segments (thrust draws) per drawn start state")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    data, physics = read_trajectories(a.scene_file), quad.Physics()
    runs, redrawn = [], 0
    for j in range(-(-a.segments // a.draws)):
        rng = np.random.default_rng(np.random.SeedSequence(a.seed, spawn_key=(j,)))
        b, k0 = start(rng, data, a)
        for _ in range(min(a.draws, a.segments - j * a.draws)):
            tries = 0
            while (r := segment(rng, data, a, physics, b, k0)) is None:
                redrawn, tries = redrawn + 1, tries + 1
                if a.draws == 1:  # a lone segment is re-drawn whole, start included
                    b, k0 = start(rng, data, a)
                elif tries == MAX_TRIES:
                    raise SystemExit(f"no segment of {a.steps} steps from trajectory {b}, step {k0} stays within "
                                     f"{a.max_tilt} degrees in {MAX_TRIES} draws: lower --torque or --steps, or raise --max-tilt")
            runs.append(r)
    traj = Trajectories(x=np.stack([r["x"] for r in runs]), u=np.stack([r["u"] for r in runs]),
                        graphs=data.graphs[:1], dt=data.dt, system=quad.SYSTEM,
                        attrs={**quad.PARAMS, "scene": "quad3", "seed": a.seed, "redrawn": redrawn,
                               "segment_torque": a.torque, "segment_collective": a.collective,
                               "segment_draws": a.draws,
                               "segment_open_steps": a.steps if a.open_loop or a.nominal else a.open_steps,
                               "segment_nominal": int(a.nominal),
                               "segment_source": a.scene_file,
                               "description": "quad3 segments with torque offsets "
                                              "(benchmarks/studies/mpc/torque_segments.py)"},
                        params=quad.draw_params(None, data.n_nodes, None),
                        aux={"load": np.stack([r["load"] for r in runs])})
    write_trajectories(a.output, traj)
    print(f"wrote {a.output}: {a.segments} segments of {a.steps} steps, {redrawn} re-drawn")


if __name__ == "__main__":
    main()
