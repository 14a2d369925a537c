"""The reference physics of docs/systems.md: right-hand sides and parameters.

Every right-hand side ``f(t, y, ...)`` takes the flat state of ONE trajectory,
``y : ndarray, shape (N*dx,)`` laid out node after node (``y.reshape(N, dx)``), and
returns ``dy/dt`` of the same shape, so it plugs into ``scipy.integrate.solve_ivp``
as is; the uncontrolled ones also take K states at once as the columns of ``y`` (N*dx, K)
(the batched reference of data_gen.reference).  Each system has a time scale (`System.time_scale`,
docs/systems.md#time-scales) that saved steps are checked against (`check_dt`).  Nothing here
knows about learning, files or scenes.
"""
from dataclasses import dataclass
from functools import partial
from typing import Callable

import numpy as np
import scipy.sparse

from mpnode.base.errors import InputError
from mpnode.base.graph import Graph

from . import forced_pendulum, quadrotor

#: the pendulum is refused where |cos(theta)| falls below this (the RHS divides by it)
PENDULUM_COS_MIN = 1e-6


# ---- right-hand sides ---------------------------------------------------------------
def pendulum_rhs(t, y, m, l, k, g):
    """Two spring-coupled pendulums; y = [theta_0, omega_0, theta_1, omega_1], shape (4,).

    theta_i'' = (sin(th_i) (m (l om_i^2 - g) - k l) + k l sin(th_j)) / (m l cos(th_i)),
    j the other node.
    """
    theta, omega = y[0::2], y[1::2]
    other = theta[::-1]
    dy = np.empty_like(y)
    dy[0::2] = omega
    dy[1::2] = (np.sin(theta) * (m * (l * omega**2 - g) - k * l) + k * l * np.sin(other)) / (m * l * np.cos(theta))
    return dy


def spring_pendulums_rhs(t, y, m, l, k, g, A, degree):
    """Pendulums joined by a spring along every edge of the graph; y = [theta_0, omega_0, ...],
    shape (2N,) or (2N, K) (then one state per column).

    theta_i'' = (sin(th_i) m (l om_i^2 - g) + k l sum_{j in N(i)} (sin(th_j) - sin(th_i))) / (m l cos(th_i)):
    on the 2-node graph exactly `pendulum_rhs`.  A : sparse (N, N); degree : (N,) its row sums.
    """
    theta, omega = y[0::2], y[1::2]
    s = np.sin(theta)
    spring = A @ s - degree.reshape((-1,) + (1,) * (s.ndim - 1)) * s
    dy = np.empty_like(y)
    dy[0::2] = omega
    dy[1::2] = (s * m * (l * omega**2 - g) + k * l * spring) / (m * l * np.cos(theta))
    return dy


def pendulum_guard(t, y):
    """min_i |cos(theta_i)| - PENDULUM_COS_MIN: positive while the pendulum RHS is defined.

    y : shape (4,) or (4, T) (then one value per column).
    """
    return np.min(np.abs(np.cos(y[0::2])), axis=0) - PENDULUM_COS_MIN


def lorenz_rhs(t, y, sigma, rho, beta, H):
    """k Lorenz oscillators coupled linearly: X' = F(X) + H X; y shape (3k,), H shape (3k, 3k)."""
    x, yy, z = y[0::3], y[1::3], y[2::3]
    dy = H @ y
    dy[0::3] += sigma * (yy - x)
    dy[1::3] += x * (rho - z) - yy
    dy[2::3] += x * yy - beta * z
    return dy


def gene_rhs(t, y, b, f, h, A):
    """Michaelis-Menten gene regulation: x_i' = -b x_i^f + sum_{j in N(i)} x_j^h / (1 + x_j^h).

    y : shape (N,);  A : sparse (N, N), A[i, j] = 1 when i hears j (the CSR graph).
    """
    xh = y**h
    return -b * y**f + A @ (xh / (1 + xh))


def kuramoto_rhs(t, y, omega, K, A):
    """Kuramoto oscillators with three phases per node, element-wise on the phases.

    theta_i' = omega + K sum_{j in N(i)} sin(theta_j - theta_i), computed as
    cos(theta_i) (A sin theta)_i - sin(theta_i) (A cos theta)_i (sin(a-b) expanded), so the
    neighbour sum is two sparse products.  y : shape (3N,), omega : shape (3,), A : sparse (N, N).
    """
    columns = 1 if y.ndim == 1 else y.shape[1]
    theta = y.reshape(-1, 3 * columns)  # row i: node i's phases (of every column)
    s, c = np.sin(theta), np.cos(theta)
    coupling = c * (A @ s) - s * (A @ c)
    return (np.repeat(omega, columns) + K * coupling).reshape(y.shape)


def adjacency(graph):
    """The CSR graph as a scipy sparse matrix (N, N) of ones; sparse graphs stay sparse."""
    n = graph.n_nodes
    return scipy.sparse.csr_array((np.ones(graph.n_edges), graph.indices, graph.indptr), shape=(n, n))


# ---- parameters that are drawn, not given -------------------------------------------
def lorenz_coupling(n_nodes, coupling, rng):
    """H, shape (3k, 3k): uniform(0, 1), 3x3 diagonal blocks zeroed, scaled to ||H||_F = coupling (k > 1)."""
    H = rng.uniform(0.0, 1.0, size=(3 * n_nodes, 3 * n_nodes))
    for i in range(n_nodes):
        H[3 * i:3 * i + 3, 3 * i:3 * i + 3] = 0.0
    if n_nodes > 1:
        H *= coupling / np.linalg.norm(H)
    return H


def kuramoto_frequencies(rng):
    """omega, shape (3,): one standard normal draw, shared by every node."""
    return rng.standard_normal(3)


# ---- the registry -------------------------------------------------------------------
@dataclass(frozen=True)
class System:
    """One reference system: its state layout, parameters and the physics wiring.

    defaults : scalar parameters under the spec's names (root attributes of a file)
    low, high : per-dimension bounds of the spec's uniform initial state, shape (dx,)
    draw : (scalars, n_nodes, rng) -> dict of drawn array parameters (the `params/` group)
    rhs : (scalars + arrays, graph) -> f(t, y) for solve_ivp (a picklable partial)
    guard : solve_ivp terminal event, positive while the state is valid; None if always valid
    n_nodes : the only node count the system is defined for, or None
    complete : the physics couples every pair (the graph must be complete)
    samplers : initial-state samplers that make sense for it (see initial.py)
    generator : systems with controls only (quadrotor_load, coupled_pendulum_force): generator(scene, workers=, max_tries=,
        progress=) -> Trajectories, which then owns initial states, controls and aux data
    state_names : one name (with its unit where there is one) per state dimension; files
        carry them as the attribute ``state_names`` and the figures label their axes with them
    time_scale : (scalar parameters) -> the time over which a trajectory changes appreciably
        (docs/systems.md#time-scales); saved steps longer than MAX_DT_TIME_SCALES of it are refused
    """

    name: str
    state_dim: int
    defaults: dict
    low: tuple
    high: tuple
    draw: Callable
    rhs: Callable
    guard: Callable = None
    n_nodes: int = None
    complete: bool = False
    samplers: tuple = ("uniform",)
    generator: Callable = None
    state_names: tuple = ()
    time_scale: Callable = lambda p: 1.0

    def check_graph(self, graph, source, field):
        """Raise InputError unless ``graph`` is one this system's physics is defined on."""
        n = graph.n_nodes
        if self.n_nodes is not None and n != self.n_nodes:
            raise InputError(source, field, f"{self.name} has {n} nodes", f"exactly {self.n_nodes} nodes")
        if self.complete:
            if not graph.equals(Graph.complete(n)):
                raise InputError(source, field, f"{self.name} needs every node coupled to every other",
                                 "a complete graph without self-loops")


    def check_dt(self, params, dt, source, field="dt"):
        """InputError unless saved states ``dt`` apart can be integrated and learned: at most
        MAX_DT_TIME_SCALES time scales (a larger dt makes the integrator take ever more steps per
        saved state -- 1e300 never ends -- and leaves nothing of one state in the next)."""
        scale = self.time_scale({**self.defaults, **params})
        if dt > MAX_DT_TIME_SCALES * scale:
            raise InputError(source, field, f"is {dt:g}, {dt / scale:.3g} times the time scale of {self.name} "
                             f"({scale:.3g}: docs/systems.md#time-scales); states that far apart cannot be "
                             "integrated in reasonable time, nor learned from", f"dt <= {MAX_DT_TIME_SCALES * scale:.3g}")


#: the longest saved step, in time scales of the system (System.check_dt)
MAX_DT_TIME_SCALES = 10


def _pendulum(p, graph):
    return partial(pendulum_rhs, m=p["m"], l=p["l"], k=p["k"], g=p["g"])


def _spring_pendulums(p, graph):
    A = adjacency(graph)
    return partial(spring_pendulums_rhs, m=p["m"], l=p["l"], k=p["k"], g=p["g"], A=A,
                   degree=np.asarray(A.sum(axis=1)).ravel())


def _forced_pendulum(p, graph):
    return partial(forced_pendulum.rhs, m=p["m"], l=p["l"], k=p["k"], g=p["g"])


def _lorenz(p, graph):
    return partial(lorenz_rhs, sigma=p["sigma"], rho=p["rho"], beta=p["beta"], H=np.asarray(p["H"]))


def _gene(p, graph):
    return partial(gene_rhs, b=p["b"], f=p["f"], h=p["h"], A=adjacency(graph))


def _kuramoto(p, graph):
    return partial(kuramoto_rhs, omega=np.asarray(p["omega"]), K=p["K"], A=adjacency(graph))


def _nothing_drawn(p, n_nodes, rng):
    return {}


SYSTEMS = {
    s.name: s
    for s in [
        System("coupled_pendulum", 2, dict(m=1.0, l=1.5, k=2.0, g=9.81),
               low=(-np.pi / 4, -0.5), high=(np.pi / 4, 0.5), draw=_nothing_drawn, rhs=_pendulum,
               guard=pendulum_guard, n_nodes=2, complete=True,
               state_names=("angle (rad)", "angular velocity (rad/s)"),
               time_scale=lambda p: 2 * np.pi * np.sqrt(abs(p["l"] / p["g"])) if p["g"] else np.inf),
        System("spring_pendulums", 2, dict(m=1.0, l=1.5, k=2.0, g=9.81),
               low=(-np.pi / 4, -0.5), high=(np.pi / 4, 0.5), draw=_nothing_drawn, rhs=_spring_pendulums,
               guard=pendulum_guard, state_names=("angle (rad)", "angular velocity (rad/s)"),
               time_scale=lambda p: 2 * np.pi * np.sqrt(abs(p["l"] / p["g"])) if p["g"] else np.inf),
        # rhs: f(t, y, u) with the horizontal forces u (2,) on the bobs, held (see forced_pendulum.py)
        System(forced_pendulum.SYSTEM, 2, dict(forced_pendulum.PARAMS), low=(-np.pi / 4, -0.5),
               high=(np.pi / 4, 0.5), draw=_nothing_drawn, rhs=_forced_pendulum, guard=pendulum_guard, n_nodes=2,
               complete=True, generator=forced_pendulum.generate,
               state_names=("angle (rad)", "angular velocity (rad/s)"),
               time_scale=lambda p: 2 * np.pi * np.sqrt(abs(p["l"] / p["g"])) if p["g"] else np.inf),
        System("lorenz", 3, dict(sigma=10.0, rho=28.0, beta=8.0 / 3.0, coupling=0.01),
               low=(-1.0,) * 3, high=(1.0,) * 3,
               draw=lambda p, n, rng: {"H": lorenz_coupling(n, p["coupling"], rng)}, rhs=_lorenz,
               complete=True, state_names=("x", "y", "z")),
        System("gene", 1, dict(b=1.0, f=1.0, h=2.0),
               low=(0.0,), high=(50.0,), draw=_nothing_drawn, rhs=_gene,
               samplers=("uniform", "hotspots"), state_names=("expression level",),
               time_scale=lambda p: 1.0 / min(1.0, abs(p["b"])) if p["b"] else np.inf),
        System("kuramoto", 3, dict(K=1.0 / 3.0),
               low=(-1.0,) * 3, high=(1.0,) * 3,
               draw=lambda p, n, rng: {"omega": kuramoto_frequencies(rng)}, rhs=_kuramoto,
               state_names=("phase 1 (rad)", "phase 2 (rad)", "phase 3 (rad)")),
        # rhs: f(t, y, F) on the state INCLUDING the load, thrusts F held (see quadrotor.py)
        System(quadrotor.SYSTEM, quadrotor.STATE_DIM, dict(quadrotor.PARAMS), low=(), high=(),
               draw=quadrotor.draw_params, rhs=quadrotor.make_rhs, complete=True,
               samplers=("equilibrium",), generator=quadrotor.generate, state_names=quadrotor.STATE_NAMES),
    ]
}


def get_system(name, source="system", field="system"):
    """The System called ``name``; InputError listing the known ones otherwise."""
    try:
        return SYSTEMS[name]
    except (KeyError, TypeError):
        raise InputError(source, field, f"unknown system {name!r}", "one of " + ", ".join(SYSTEMS)) from None


def make_rhs(system, params, graph):
    """f(t, y) for one trajectory of ``system`` on ``graph``; for coupled_pendulum_force f(t, y, u) with its
    forces u (2,) held; for the controlled quadrotor_load,
    f(t, y, F) with the thrusts F (n, 4) held over the step (its state includes the load).

    params : mapping holding at least the system's scalar parameters and drawn arrays
    (e.g. a file's root attributes merged with its `params/` group); extra keys are ignored.
    """
    return get_system(system).rhs(params, graph)


def file_rhs(traj):
    """f(t, y) for each graph of a trajectory file, rebuilt from what the file records.

    traj : Trajectories of a reference system (root attributes + `params/` hold its parameters).
    Raises KeyError/ValueError/TypeError when the file lacks or garbles a parameter.
    """
    params = {**traj.attrs, **traj.params}
    return [make_rhs(traj.system, params, g) for g in traj.graphs]
