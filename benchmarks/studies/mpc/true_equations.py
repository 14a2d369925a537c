"""The quadrotor swarm's true equations (`data_gen.quadrotor.Physics.rhs`) stepped by fixed-step
RK4, every column of Y a separate state: what the studies here difference to get the truth's
Jacobians and gradients, many perturbations in one batched run."""
import numpy as np


def rk4_step(physics, Y, F, dt, substeps=10):
    """Y (13 N + 6, k) after dt under the thrusts F (N, 4, k) held, by RK4 at dt / substeps."""
    h = dt / substeps
    for _ in range(substeps):
        k1 = physics.rhs(0, Y, F)
        k2 = physics.rhs(0, Y + h / 2 * k1, F)
        k3 = physics.rhs(0, Y + h / 2 * k2, F)
        k4 = physics.rhs(0, Y + h * k3, F)
        Y = Y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return Y


def rk4_rollout(physics, y, F, dt, substeps=10):
    """States (H+1, 13 N + 6, k) from y (13 N + 6,) under thrusts F (H, N, 4, k), each held for a step."""
    Y = np.repeat(y[:, None], F.shape[-1], axis=1)
    out = [Y]
    for t in range(F.shape[0]):
        Y = rk4_step(physics, Y, F[t], dt, substeps)
        out.append(Y)
    return np.stack(out)
