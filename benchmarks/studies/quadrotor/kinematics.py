"""Would exact kinematics help a swarm model's attitude?  A model's predictions (`mpnode eval
MODEL DATA --predictions PRED.h5`) against the truth, per state group, as they are and with the
quaternions (and positions) replaced by the exact kinematics, q' = q (x) (0, omega) / 2 and
r' = v, integrated from each trajectory's true first state with the model's own body rates and
velocities (and, as a check of the integration, with the true ones).  Body rates interpolated
linearly between samples, RK4 at dt / 10; nMSE per dimension over the data's variance, steps 1..T.

    python benchmarks/studies/quadrotor/kinematics.py DATA.h5 PRED.h5
"""
import argparse

import numpy as np

from data_gen import quadrotor as quad
from mpnode import read_trajectories

SUBSTEPS = 10


def quaternion_rate(q, w):
    """q' = q (x) (0, w) / 2 for quaternions [w, x, y, z] (..., 4) and body rates (..., 3)."""
    wx, wy, wz = np.moveaxis(w, -1, 0)
    product = quad.quat_mul(np.moveaxis(q, -1, 0), (np.zeros_like(wx), wx, wy, wz))
    return 0.5 * np.moveaxis(product, 0, -1)


def rate_at(rates, k, a):
    """The body rates a fraction a of the way from sample k to k + 1 (linear)."""
    return (1 - a) * rates[:, k] + a * rates[:, k + 1]


def integrate_attitude(q0, rates, dt):
    """Quaternions (B, T+1, N, 4) from q0 (B, N, 4) under the body rates (B, T+1, N, 3)."""
    qs, q, h = [q0], q0.copy(), dt / SUBSTEPS
    for k in range(rates.shape[1] - 1):
        for s in range(SUBSTEPS):
            w0, w1, w2 = (rate_at(rates, k, (s + f) / SUBSTEPS) for f in (0.0, 0.5, 1.0))
            k1 = quaternion_rate(q, w0)
            k2 = quaternion_rate(q + h / 2 * k1, w1)
            k3 = quaternion_rate(q + h / 2 * k2, w1)
            k4 = quaternion_rate(q + h * k3, w2)
            q = q + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        qs.append(q.copy())
    return np.stack(qs, axis=1)


def integrate_positions(r0, v, dt):
    """Positions (B, T+1, N, 3) from r0 under the velocities v, by the trapezoid rule."""
    steps = np.cumsum(dt * (v[:, 1:] + v[:, :-1]) / 2, axis=1)
    return np.concatenate([r0[:, None], r0[:, None] + steps], axis=1)


def groups(pred, truth):
    """nMSE over steps 1..T: all, position, attitude, velocity, body rates, q_w, q_z."""
    var = truth.reshape(-1, truth.shape[-1]).var(axis=0)
    e = ((pred[:, 1:] - truth[:, 1:]) ** 2).reshape(-1, truth.shape[-1]).mean(axis=0) / var
    return e.mean(), e[0:3].mean(), e[3:7].mean(), e[7:10].mean(), e[10:13].mean(), e[3], e[6]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="the quadrotor file the predictions are of")
    ap.add_argument("predictions", help="`mpnode eval --predictions` of a model on it")
    a = ap.parse_args()
    d = read_trajectories(a.data)
    truth, pred = d.x, read_trajectories(a.predictions).x
    print("nMSE: all, position, attitude, velocity, body rates, q_w, q_z")
    print("the model           ", " ".join(f"{v:.4f}" for v in groups(pred, truth)))
    for name, src in (("true rates, v", truth), ("the model's rates, v", pred)):
        p = pred.copy()
        p[..., 3:7] = integrate_attitude(truth[:, 0, :, 3:7], src[..., 10:13], d.dt)
        print(f"{name:20s} q", " ".join(f"{v:.4f}" for v in groups(p, truth)))
        p[..., 0:3] = integrate_positions(truth[:, 0, :, 0:3], src[..., 7:10], d.dt)
        print(f"{name:20s} q, r", " ".join(f"{v:.4f}" for v in groups(p, truth)))


if __name__ == "__main__":
    main()
