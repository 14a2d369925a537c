"""What a learned quad3 model says a plan's first thrusts do over the next H steps, against the
true equations: from states of a quad3 file, messages at 0 (as `quadrotor_mpc.py --messages
zero` starts every plan), the file's thrusts for steps 1..H-1, one-sided differences of the first
step's per-quadrotor collective thrust and torques (the mixer's rows, as `control_jacobians.py`).
Printed per model, for the positions and velocities h = 1, 2, 3, 5 and H steps on: the relative
error ||J_model - J_true|| / ||J_true|| (median and range over the states), the cosine between
the two and the ratio of their sizes.  The true response is the open-loop one (later thrusts do
not answer the perturbation), as it is inside a plan.

    python benchmarks/studies/mpc/horizon_jacobians.py MODEL.h5 [MODEL2.h5 ...] --data QUAD3.h5 \\
        [--states 3,20 10,5 50,35 7,12 100,25 200,30] [--horizon 10]
"""
import argparse

import numpy as np

import control_jacobians as cj
from data_gen import quadrotor as quad
from mpnode import Model, Simulator, read_trajectories
from mpnode.base.graph import Graph
from true_equations import rk4_rollout

N = 3
BLOCKS = {"pos": [0, 1, 2], "vel": [7, 8, 9]}
PARTS = {"torques": [c for c in range(4 * N) if c % 4], "collective": [0, 4, 8]}


def perturbations(eps):
    """(4 N, N, 4): column 4 i + c moves quadrotor i's collective thrust (c = 0) or torque c by eps."""
    d = np.zeros((4 * N, N, 4))
    for i in range(N):
        d[4 * i:4 * i + 4, i] = eps * cj.COMBINATIONS.T
    return d


def true_states(x, load, U, dF, substeps=10, dt=0.1):
    """(H, 1 + columns, N, 13): the true equations by RK4 at dt / substeps, dF added to U[0]."""
    ncol = dF.shape[0] + 1
    F = np.repeat(U[..., None], ncol, axis=-1)
    F[0, ..., 1:] += np.moveaxis(dF, 0, -1)
    Y = rk4_rollout(quad.Physics(), quad.pack(x, load), F, dt, substeps)[1:]
    return np.ascontiguousarray(Y[:, :13 * N].transpose(0, 2, 1)).reshape(len(Y), ncol, N, 13)


def model_states(model, x, U, dF):
    """(H, 1 + columns, N, 13): the model from x with messages at 0, dF added to U[0]."""
    sim = Simulator(model, Graph.complete(N))
    sim.reset(np.repeat(x[None], dF.shape[0] + 1, axis=0))
    out = []
    for k in range(U.shape[0]):
        u = np.repeat(U[k][None], dF.shape[0] + 1, axis=0)
        u[1:] += dF if k == 0 else 0.0
        out.append(sim.step(u).copy())
    return np.stack(out)


def jacobian(states, eps):
    return (states[:, 1:] - states[:, :1]) / eps


def compare(truths, model, steps):
    """{(block, part, h): [(relative error, cosine, size ratio) per state]}."""
    rows = {}
    for J_true, U, x in truths:
        J_model = jacobian(model_states(model, x, U, perturbations(1e-4)), 1e-4)
        for h in steps:
            for part, cols in PARTS.items():
                for blk, dims in BLOCKS.items():
                    t, m = (J[h - 1][cols][:, :, dims].ravel() for J in (J_true, J_model))
                    nt, nm = np.linalg.norm(t), np.linalg.norm(m)
                    rows.setdefault((blk, part, h), []).append((np.linalg.norm(m - t) / nt, m @ t / (nm * nt), nm / nt))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("models", nargs="+")
    ap.add_argument("--data", required=True, help="a quad3 file of `mpnode generate` (states, thrusts, aux/load)")
    ap.add_argument("--states", nargs="+", default=["3,20", "10,5", "50,35", "7,12", "100,25", "200,30"],
                    help="trajectory,step pairs (step + horizon within the file)")
    ap.add_argument("--horizon", type=int, default=10)
    a = ap.parse_args()
    data, H = read_trajectories(a.data), a.horizon
    truths = []
    for pair in a.states:
        b, t = map(int, pair.split(","))
        U = data.u[b, t:t + H]
        truths.append((jacobian(true_states(data.x[b, t], data.aux["load"][b, t], U, perturbations(1e-6)), 1e-6),
                       U, data.x[b, t]))
    for path in a.models:
        rows = compare(truths, Model.load(path).copy(np.float64), sorted({1, 2, 3, 5, H}))
        print(f"{path}: relative error, median [range] over the states; cosine; |model| / |true| (medians)")
        for (blk, part, h), v in rows.items():
            e, c, r = np.array(v).T
            print(f"  {blk} h={h:2d} / {part:10s}: {np.median(e):6.2f} [{e.min():.2f}-{e.max():.2f}]  "
                  f"cos {np.median(c):+.2f}  size {np.median(r):.2f}")


if __name__ == "__main__":
    main()
