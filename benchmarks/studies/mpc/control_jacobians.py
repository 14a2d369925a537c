"""Does a learned quadrotor model know what the thrusts do?  Its step Jacobian with respect to the
thrusts (`Simulator.jacobians`: exact, of the model) against the true one (the true equations by
RK4 at dt / 10, one-sided differences), at states of a quad3 file, per block of the state.

The model steps from the trajectory's start under the file's thrusts up to step t (so its
messages are those it would have there; with --messages zero they are set to 0, as
`quadrotor_mpc.py --messages zero` has them at the first step of every plan), then takes the
file's true state at t; printed: the
relative error ||Ju_model - Ju_true|| / ||Ju_true|| of each block (positions, quaternions,
velocities, body rates) at each of the states, with respect to all thrusts and, apart, to each
quadrotor's collective thrust (its four rotors together) and to its three torques (the rotors'
differences, the mixer's other rows).

    python benchmarks/studies/mpc/control_jacobians.py MODEL.h5 QUAD3.h5 [--states 3,20 10,5 50,35] \
        [--messages carry|zero]
"""
import argparse

import numpy as np

from data_gen import quadrotor as quad
from mpnode import Model, Simulator, read_trajectories
from mpnode.base.graph import Graph
from true_equations import rk4_step

BLOCKS = {"positions": [0, 1, 2], "quaternions": [3, 4, 5, 6], "velocities": [7, 8, 9], "body rates": [10, 11, 12]}
#: rotor thrust changes (columns) that move one quadrotor's collective thrust, roll, pitch and yaw torque alone
COMBINATIONS = np.linalg.inv(quad.mixer(quad.PARAMS["L"], quad.PARAMS["k_m"]))


def true_ju(x, load, F, eps=1e-6, substeps=10, dt=0.1):
    """d(next quadrotor states)/d(thrusts) (3*13, 3*4) of the true equations, from the full state."""
    p, n = quad.Physics(), F.size
    Fs = np.repeat(F[..., None], n + 1, axis=-1)
    Fs.reshape(n, n + 1)[:, 1:] += eps * np.eye(n)
    Y = rk4_step(p, np.repeat(quad.pack(x, load)[:, None], n + 1, axis=1), Fs, dt, substeps)
    quads = Y[:13 * 3]
    return (quads[:, 1:] - quads[:, :1]) / eps


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--states", nargs="+", default=["3,20", "10,5", "50,35"], help="trajectory,step pairs")
    ap.add_argument("--messages", default="carry", choices=("carry", "zero"),
                    help="the model's messages at the state: those of its run from the start, or 0")
    a = ap.parse_args()
    model, data = Model.load(a.model).copy(np.float64), read_trajectories(a.data)
    errors = {(name, part): [] for name in BLOCKS for part in ("all", "collective", "torques")}
    combine = np.kron(np.eye(3), COMBINATIONS)  # Ju @ combine: columns (quadrotor, [collective, 3 torques])
    parts = {"all": slice(None), "collective": [0, 4, 8], "torques": [1, 2, 3, 5, 6, 7, 9, 10, 11]}
    for pair in a.states:
        b, t = map(int, pair.split(","))
        sim = Simulator(model, Graph.complete(3))
        sim.reset(data.x[b, :1])
        for k in range(t):
            sim.step(data.u[b, k][None])
        sim._z[:, :13] = model.normalize_x(data.x[b, t]).reshape(-1, 13)  # the true state, the model's messages
        if a.messages == "zero":
            sim._z[:, 13:] = 0
        ju = sim.jacobians(data.u[b, t][None])[1][0]
        want = true_ju(data.x[b, t], data.aux["load"][b, t], data.u[b, t])
        for name, dims in BLOCKS.items():
            rows = [i * 13 + d for i in range(3) for d in dims]
            for part, cols in parts.items():
                got, true = (j[rows] if part == "all" else (j[rows] @ combine)[:, cols] for j in (ju, want))
                nothing = np.linalg.norm(true) < 1e-6 * np.linalg.norm(want[rows])  # e.g. collective -> rates
                errors[name, part].append(np.nan if nothing else np.linalg.norm(got - true) / np.linalg.norm(true))
    for (name, part), e in errors.items():
        if not np.all(np.isnan(e)):  # "-": the true equations' response is 0
            print(f"{name:12s} {part:10s} relative error of d(next state)/d(thrusts): "
                  + ", ".join("-" if np.isnan(v) else f"{v:.2f}" for v in e))


if __name__ == "__main__":
    main()
