"""coupled_pendulum_force (data_gen/forced_pendulum.py): the file's forces reproduce its states, the
forces are drawn as documented, and without forces it is the coupled pendulum."""
from dataclasses import replace

import numpy as np

from data_gen import BUILTIN, generate
from data_gen.forced_pendulum import step
from data_gen.simulate import integrate
from data_gen.systems import make_rhs
from mpnode.base.graph import Graph


def test_the_files_forces_reproduce_its_trajectories():
    traj = generate(replace(BUILTIN["pendulum_force"], trajectories=3, horizon=6), workers=1)
    assert traj.x.shape == (3, 7, 2, 2) and traj.u.shape == (3, 6, 2, 1)
    assert np.abs(traj.u).max() <= traj.attrs["u_max"] and traj.u.std() > 1.0  # uniform in [-3, 3]
    for b in range(3):
        for t in range(6):
            np.testing.assert_allclose(step(traj.x[b, t].ravel(), traj.u[b, t], traj.dt, traj.attrs),
                                       traj.x[b, t + 1].ravel(), rtol=1e-7, atol=1e-9)
    again = generate(replace(BUILTIN["pendulum_force"], trajectories=2, horizon=6), workers=1)
    np.testing.assert_array_equal(again.x, traj.x[:2])  # trajectory b depends on the seed and b alone


def test_without_forces_it_is_the_coupled_pendulum():
    p = BUILTIN["pendulum_force"]
    params = {"m": 1.0, "l": 1.5, "k": 2.0, "g": 9.81, "u_max": 3.0}
    y = np.array([0.3, -0.1, -0.2, 0.4])
    free = make_rhs("coupled_pendulum", params, Graph.complete(2))
    want = integrate(free, y.reshape(2, 2), 1, p.dt)[1].ravel()
    np.testing.assert_allclose(step(y, np.zeros(2), p.dt, params), want, rtol=1e-7, atol=1e-9)
    forced = make_rhs("coupled_pendulum_force", params, Graph.complete(2))
    push = forced(0.0, y, np.array([1.0, 0.0])) - forced(0.0, y, np.zeros(2))
    np.testing.assert_allclose(push, [0, 1 / (1.5 * np.cos(0.3)), 0, 0])  # u / (m l cos theta)
