"""coupled_pendulum_force: the two spring-coupled pendulums with a horizontal force on each bob
as the control (docs/systems.md, "coupled_pendulum_force"), and its data-set driver.

The pendulum's equation is that of the bob's horizontal position, m d2(l sin th)/dt2 =
-m g sin th - k l (sin th - sin th_j); a horizontal force u on the bob adds u to its right-hand
side: th'' = (...) / (m l cos th) + u / (m l cos th).  The data excite the controls: every
trajectory starts uniform in the pendulum's ranges and draws, at every saved step and for each
bob, a force uniform in [-u_max, u_max], held over the step (zero-order hold), so a model sees
what a force does independently of the state (a controller's output would not show it).
"""
import numpy as np
from scipy.integrate import solve_ivp

from mpnode.base.errors import NumericalError
from mpnode.data import Trajectories
from mpnode.runs.executors import chunk_ranges, map_chunks, open_executor

SYSTEM = "coupled_pendulum_force"
CONTROL_DIM = 1
#: the pendulum's parameters, and the largest force (N) the data draw
PARAMS = dict(m=1.0, l=1.5, k=2.0, g=9.81, u_max=3.0)


def rhs(t, y, u, m, l, k, g):
    """dy/dt for y = [theta_0, omega_0, theta_1, omega_1] under the horizontal forces u (2,) held."""
    theta, omega = y[0::2], y[1::2]
    dy = np.empty_like(y)
    dy[0::2] = omega
    dy[1::2] = (np.sin(theta) * (m * (l * omega**2 - g) - k * l) + k * l * np.sin(theta[::-1])
                + np.ravel(u)) / (m * l * np.cos(theta))
    return dy


def step(y, u, dt, p, method="DOP853", rtol=1e-9, atol=1e-9):
    """y after dt under the held forces u (2,); NumericalError if the solver fails or |cos th| gets near 0."""
    args = (np.asarray(u, dtype=np.float64), p["m"], p["l"], p["k"], p["g"])
    sol = solve_ivp(rhs, (0.0, dt), y, method=method, rtol=rtol, atol=atol, args=args)
    if sol.status != 0 or not np.all(np.isfinite(sol.y[:, -1])) or np.min(np.abs(np.cos(sol.y[0::2, -1]))) < 1e-6:
        raise NumericalError(f"{SYSTEM}: the step failed ({sol.message})")
    return sol.y[:, -1]


def _run(job, chunk):
    """Worker: trajectories ``chunk``, each re-drawn from its own generator until it stays defined."""
    from .initial import trajectory_rng

    out = []
    for b in chunk:
        rng = trajectory_rng(job["seed"], b)
        for tries in range(job["max_tries"]):
            x = np.empty((job["T"] + 1, 2, 2))
            x[0] = rng.uniform(job["low"], job["high"], size=(2, 2))
            u = rng.uniform(-job["params"]["u_max"], job["params"]["u_max"], size=(job["T"], 2, 1))
            try:
                for t in range(job["T"]):
                    x[t + 1] = step(x[t].ravel(), u[t], job["dt"], job["params"], job["method"], job["rtol"],
                                    job["atol"]).reshape(2, 2)
                break
            except NumericalError:
                continue
        else:
            raise NumericalError(f"{SYSTEM}: trajectory {b} failed {job['max_tries']} times in a row")
        out.append((x, u, tries))
    return out


def generate(scene, *, workers=2, max_tries=10, progress=None, scheduler=None):
    """The trajectories of a coupled_pendulum_force scene: x, and the forces u (B, T, 2, 1)."""
    from .systems import SYSTEMS

    system = SYSTEMS[SYSTEM]
    params = {**PARAMS, **scene.params}
    job = dict(seed=scene.seed, T=scene.horizon, dt=scene.dt, params=params, low=system.low, high=system.high,
               method=scene.integrator, rtol=scene.rtol, atol=scene.atol, max_tries=max_tries)
    B = scene.trajectories
    x, u = np.empty((B, scene.horizon + 1, 2, 2)), np.empty((B, scene.horizon, 2, 1))
    redraws = np.zeros(B, dtype=np.int64)

    def keep(chunk, results):
        for b, (xb, ub, tries) in zip(chunk, results):
            x[b], u[b], redraws[b] = xb, ub, tries
        if progress is not None:
            progress(len(chunk))

    if workers == 1 and scheduler is None:
        map_chunks(None, _run, job, chunk_ranges(B, 1, 50), keep)
    else:
        with open_executor(scheduler, workers) as farm:
            map_chunks(farm, _run, job, chunk_ranges(B, farm.workers, 50), keep)
    attrs = dict(params, seed=scene.seed, integrator=scene.integrator, rtol=scene.rtol, atol=scene.atol,
                 scene=scene.name, description=scene.description, initial=scene.initial, max_tries=max_tries,
                 redrawn=int(redraws.sum()), control_hold="zero-order hold over dt; u reproduces x exactly",
                 state_names=list(system.state_names), **scene.graph.describe())
    return Trajectories(x=x, u=u, graphs=scene.graph.build(), dt=scene.dt, system=SYSTEM, attrs=attrs)
