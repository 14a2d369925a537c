"""A quad3 model on quad3 and on quad6: the cable's pull it implies, and when its error passes holding x0.

    python benchmarks/studies/quadrotor/first_step.py MODEL.h5 Q3_TEST.h5 Q6_TEST.h5 [...]

Why does zero-shot 3 -> 6 fail?  One guess is the load: with n quadrotors each cable pulls
m_L g / n, and a model trained on quad3 alone has only seen n = 3 (every node of the complete
graph has in-degree 2).  The first table tests it.  A quadrotor's vertical acceleration is
gravity, its thrust and its cable (spec: v' = g + (R(q) [0, 0, sum F] + s e) / m_q), so
subtracting gravity and thrust from the first-step acceleration leaves the cable's vertical
pull: the data's, and the one the model's first step implies (the step where its messages start
at 0, as in training).  The second table follows the whole rollout: nMSE per state block (r, q,
v, w) at a few steps, and the step-wise nMSE of holding the initial state, which a useful model
must beat.
"""
import argparse

import numpy as np

from mpnode.data import read_trajectories
from mpnode.evaluation.metrics import normalised_sq_error
from mpnode.model import Model

M_Q, M_L = 1.0, 0.9  # kg, spec quadrotor.md
BLOCKS = {"r": slice(0, 3), "q": slice(3, 7), "v": slice(7, 10), "w": slice(10, 13)}
STEPS = (1, 5, 10, 20, 50)


def thrust_z(x, u):
    """Vertical acceleration from the rotors: (R(q) [0, 0, sum F])_z / m_q, q = [w, x, y, z]."""
    qx, qy = x[..., 4], x[..., 5]
    return (1 - 2 * (qx ** 2 + qy ** 2)) * u.sum(-1) / M_Q


def vertical_pull(x0, x1, u0, dt, g_z):
    """Per quadrotor: the vertical force (N) that gravity and thrust leave unexplained over one step."""
    a_z = (x1[..., 9] - x0[..., 9]) / dt
    return M_Q * (a_z - g_z - thrust_z(x0, u0))


def nmse_by_step(pred, x):
    """[T+1, dx]: `mpnode eval`'s normalised squared error, averaged over trajectories and nodes."""
    return normalised_sq_error(pred, x).mean(axis=(0, 2))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("model")
    p.add_argument("data", nargs="+")
    args = p.parse_args()
    model = Model.load(args.model)
    pulls, errors = [], []
    for path in args.data:
        traj = read_trajectories(path)
        x, u, g_z = np.asarray(traj.x, float), np.asarray(traj.u, float), float(traj.params["g"][2])
        pred = model.rollout(x[:, 0], traj.graphs[0], u=u).astype(float)
        n, name = x.shape[2], path.split("/")[-1]
        true = vertical_pull(x[:, 0], x[:, 1], u[:, 0], traj.dt, g_z)
        ours = vertical_pull(x[:, 0], pred[:, 1], u[:, 0], traj.dt, g_z)
        pulls.append(f"| {name} | {n} | {M_L * g_z / n:.2f} | {true.mean():.2f} +- {true.std():.2f} | "
                     f"{ours.mean():.2f} +- {ours.std():.2f} |")
        e, hold = nmse_by_step(pred, x), nmse_by_step(np.broadcast_to(x[:, :1], x.shape), x)
        for label, rows in [("all", e), *((b, e[:, s]) for b, s in BLOCKS.items()), ("hold x0", hold)]:
            errors.append(f"| {name} | {label} | " + " | ".join(f"{rows[k].mean():.3g}" for k in STEPS) + " |")
    print("| data | n | -m_L g / n (N) | data's pull (N) | model's pull (N) |\n| --- | --- | --- | --- | --- |")
    print("\n".join(pulls))
    print("\n| data | nMSE of | " + " | ".join(f"step {k}" for k in STEPS) + " |\n| --- | --- |" + " --- |" * len(STEPS))
    print("\n".join(errors))


if __name__ == "__main__":
    main()
