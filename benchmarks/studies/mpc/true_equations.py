"""The quadrotor swarm's true equations (`data_gen.quadrotor.Physics.rhs`) stepped by fixed-step
RK4, every column of Y a separate state: what the studies here difference to get the truth's
Jacobians and gradients, many perturbations in one batched run."""


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
