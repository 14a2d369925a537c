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
from mpnode.base.graph import Graph, block_diagonal

from . import forced_pendulum, quadrotor, swing
from .grids import bus_names
from .graphs import symmetric_weights

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


def spring_pendulums_het_rhs(t, y, m, l, g, S, stiffness):
    """Pendulums of their own length l_i and mass m_i, joined by springs of their own stiffness
    k_ij; y = [theta_0, omega_0, ...], shape (2N,) or (2N, K) (then one state per column).

    In the bobs' horizontal positions X_i = l_i sin(theta_i), m_i X_i'' = -m_i g sin(theta_i)
    + sum_{j in N(i)} k_ij (X_j - X_i), hence
    theta_i'' = (m_i l_i om_i^2 s_i - m_i g s_i + sum_j k_ij (X_j - X_i)) / (m_i l_i cos(th_i)):
    with equal l, m and k exactly `spring_pendulums_rhs`.  m, l : (N,);  S : sparse (N, N),
    S[i, j] = k_ij;  stiffness : (N,) its row sums.
    """
    theta, omega = y[0::2], y[1::2]
    shape = (-1,) + (1,) * (theta.ndim - 1)  # node values against one column per state
    m, l, stiffness = m.reshape(shape), l.reshape(shape), stiffness.reshape(shape)
    s = np.sin(theta)
    X = l * s
    dy = np.empty_like(y)
    dy[0::2] = omega
    dy[1::2] = (m * l * omega**2 * s - m * g * s + S @ X - stiffness * X) / (m * l * np.cos(theta))
    return dy


def kuramoto_het_rhs(t, y, omega, K, W, inv_degree):
    """Kuramoto oscillators of their own natural frequencies, coupled along weighted edges, each
    hearing the weighted mean of its neighbours; y = [cos th_0, sin th_0, cos th_1, ...], shape
    (2N,) or (2N, K) (then one state per column).

    theta_i' = omega_i + K / deg_i sum_{j in N(i)} w_ij sin(theta_j - theta_i), deg_i the number of
    neighbours, and (cos, sin)' = theta' (-sin, cos).  sin(th_j - th_i) = s_j c_i - c_j s_i is
    linear in the neighbours' (c_j, s_j): the coupling is two sparse products.  omega,
    inv_degree : (N,) (1/deg_i, 0 for a node that hears nobody);  W : sparse (N, N), W[i, j] = w_ij.
    """
    c, s = y[0::2], y[1::2]
    shape = (-1,) + (1,) * (c.ndim - 1)
    rate = omega.reshape(shape) + K * inv_degree.reshape(shape) * (c * (W @ s) - s * (W @ c))
    dy = np.empty_like(y)
    dy[0::2] = -s * rate
    dy[1::2] = c * rate
    return dy


def adjacency(graph):
    """The CSR graph as a scipy sparse matrix (N, N) of ones; sparse graphs stay sparse."""
    n = graph.n_nodes
    return scipy.sparse.csr_array((np.ones(graph.n_edges), graph.indices, graph.indptr), shape=(n, n))


def weighted_adjacency(graph):
    """The CSR graph as a sparse matrix (N, N) of its edge weights (ones where it has none)."""
    n = graph.n_nodes
    w = np.ones(graph.n_edges) if graph.weights is None else np.asarray(graph.weights, dtype=np.float64)
    return scipy.sparse.csr_array((w, graph.indices, graph.indptr), shape=(n, n))


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


def draw_kuramoto_het(p, graph, rng):
    """One trajectory's (edge weights (E,), node attributes (N, 1)): w_ij uniform in [w_min, w_max],
    the same both ways; omega_i uniform in [omega_min, omega_max]."""
    weights = symmetric_weights(graph, p["w_min"], p["w_max"], rng)
    return weights, rng.uniform(p["omega_min"], p["omega_max"], size=(graph.n_nodes, 1))


def draw_spring_pendulums_het(p, graph, rng):
    """One trajectory's (spring stiffnesses (E,), node attributes (N, 2) = [length, mass]):
    k_ij uniform in [k_min, k_max], the same both ways; l_i, m_i uniform in their ranges."""
    stiffness = symmetric_weights(graph, p["k_min"], p["k_max"], rng)
    n = graph.n_nodes
    lengths, masses = rng.uniform(p["l_min"], p["l_max"], n), rng.uniform(p["m_min"], p["m_max"], n)
    return stiffness, np.stack([lengths, masses], axis=1)


def cos_sin(phase):
    """The state of phases (N, 1): their cosines and sines (N, 2), a point on the circle per node."""
    return np.concatenate([np.cos(phase), np.sin(phase)], axis=1)


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
    controllers : closed-loop systems: controllers(scene) -> (x0 (B, N, dx), controls), where
        controls(k, x (B, N, dx)) -> u (B, N, du) closes the scene's loop around a learned model
    control_dim : du, the controls per node (0: none)
    state_names : one name (with its unit where there is one) per state dimension; files
        carry them as the attribute ``state_names`` and the figures label their axes with them
    state_groups : the group each state dimension belongs to (e.g. position, attitude), or () when
        the state is one group; files carry them as ``state_groups`` and `mpnode eval` reports each
        group's error
    node_dims : the state dimensions a user watches node by node (the swing equation's frequency
        deviation): `mpnode eval` ranks the nodes by their error on them and draws the worst and
        the median node's; () for the whole state
    time_scale : (scalar parameters) -> the time over which a trajectory changes appreciably
        (docs/systems.md#time-scales); saved steps longer than MAX_DT_TIME_SCALES of it are refused
    attr_names : systems whose nodes differ: one name (with its unit) per node attribute; files carry
        the attributes as node_attrs (B, N, dp) and these names as attr_names.  () when nodes are alike
    draw_trajectory : systems whose nodes or edges differ: (scalars, graph, rng) -> (edge weights (E,),
        node attributes (N, dp)), drawn afresh for each trajectory; their rhs takes the node
        attributes as a third argument and reads the weights from the graph
    state_of : the state made of the uniform sampler's draw, (N, len(low)) -> (N, dx) (kuramoto_het
        draws a phase and keeps its cosine and sine); None: the draw is the state
    ranges : ((low, high, floor), ...): scalar parameters bounding a draw, refused unless low <= high
        and (floor not None) low > floor
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
    controllers: Callable = None
    control_dim: int = 0
    state_names: tuple = ()
    state_groups: tuple = ()
    node_dims: tuple = ()
    time_scale: Callable = lambda p: 1.0
    attr_names: tuple = ()
    draw_trajectory: Callable = None
    state_of: Callable = None
    ranges: tuple = ()

    def check_graph(self, graph, source, field):
        """Raise InputError unless ``graph`` is one this system's physics is defined on."""
        n = graph.n_nodes
        if self.n_nodes is not None and n != self.n_nodes:
            raise InputError(source, field, f"{self.name} has {n} nodes", f"exactly {self.n_nodes} nodes")
        if self.complete:
            if not graph.equals(Graph.complete(n)):
                raise InputError(source, field, f"{self.name} needs every node coupled to every other",
                                 "a complete graph without self-loops")

    def check_ranges(self, params, source):
        """InputError unless each range a trajectory draws from (``ranges``) is low <= high above its floor."""
        p = {**self.defaults, **params}
        for low, high, floor in self.ranges:
            if not p[low] <= p[high]:
                raise InputError(source, f"params.{low}", f"is {p[low]:g}, above {high} = {p[high]:g}",
                                 f"{low} <= {high}")
            if floor is not None and not p[low] > floor:
                raise InputError(source, f"params.{low}", f"is {p[low]:g}", f"a number > {floor:g}")

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


def _spring_pendulums_het(p, graph, attrs):
    attrs = np.asarray(attrs, dtype=np.float64)
    S = weighted_adjacency(graph)
    return partial(spring_pendulums_het_rhs, m=attrs[:, 1].copy(), l=attrs[:, 0].copy(), g=p["g"], S=S,
                   stiffness=np.asarray(S.sum(axis=1)).ravel())


def _kuramoto_het(p, graph, attrs):
    degree = graph.degrees().astype(np.float64)
    return partial(kuramoto_het_rhs, omega=np.asarray(attrs, dtype=np.float64)[:, 0].copy(), K=p["K"],
                   W=weighted_adjacency(graph),
                   inv_degree=np.divide(1.0, degree, out=np.zeros_like(degree), where=degree > 0))


def _swing(p, graph, attrs):
    attrs = np.asarray(attrs, dtype=np.float64)
    return partial(swing.swing_rhs, M=attrs[:, 0].copy(), D=attrs[:, 1].copy(), P=attrs[:, 2].copy(),
                   W=weighted_adjacency(graph))


def _pendulum_period(length):
    """The small-oscillation period of a pendulum of ``length`` (the pendulums' time scale)."""
    return lambda p: 2 * np.pi * np.sqrt(abs(p[length] / p["g"])) if p["g"] else np.inf


def _kuramoto_het_time(p):
    """The time a phase takes to move one radian at the fastest frequency or coupling."""
    rate = max(abs(p["omega_min"]), abs(p["omega_max"]), abs(p["K"]) * p["w_max"])
    return 1.0 / rate if rate else np.inf


def _nothing_drawn(p, n_nodes, rng):
    return {}


SYSTEMS = {
    s.name: s
    for s in [
        System("coupled_pendulum", 2, dict(m=1.0, l=1.5, k=2.0, g=9.81),
               low=(-np.pi / 4, -0.5), high=(np.pi / 4, 0.5), draw=_nothing_drawn, rhs=_pendulum,
               guard=pendulum_guard, n_nodes=2, complete=True,
               state_names=("angle (rad)", "angular velocity (rad/s)"),
               time_scale=_pendulum_period("l")),
        System("spring_pendulums", 2, dict(m=1.0, l=1.5, k=2.0, g=9.81),
               low=(-np.pi / 4, -0.5), high=(np.pi / 4, 0.5), draw=_nothing_drawn, rhs=_spring_pendulums,
               guard=pendulum_guard, state_names=("angle (rad)", "angular velocity (rad/s)"),
               time_scale=_pendulum_period("l")),
        # rhs: f(t, y, u) with the horizontal forces u (2,) on the bobs, held (see forced_pendulum.py)
        System(forced_pendulum.SYSTEM, 2, dict(forced_pendulum.PARAMS), low=(-np.pi / 4, -0.5),
               high=(np.pi / 4, 0.5), draw=_nothing_drawn, rhs=_forced_pendulum, guard=pendulum_guard, n_nodes=2,
               complete=True, generator=forced_pendulum.generate,
               state_names=("angle (rad)", "angular velocity (rad/s)"),
               time_scale=_pendulum_period("l")),
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
        System("spring_pendulums_het", 2,
               dict(g=9.81, l_min=1.0, l_max=2.0, m_min=0.5, m_max=2.0, k_min=1.0, k_max=4.0),
               low=(-np.pi / 6, -0.5), high=(np.pi / 6, 0.5), draw=_nothing_drawn, rhs=_spring_pendulums_het,
               guard=pendulum_guard, state_names=("angle (rad)", "angular velocity (rad/s)"),
               time_scale=_pendulum_period("l_min"), attr_names=("length (m)", "mass (kg)"),
               draw_trajectory=draw_spring_pendulums_het,
               ranges=(("l_min", "l_max", 0.0), ("m_min", "m_max", 0.0), ("k_min", "k_max", 0.0))),
        System("kuramoto_het", 2, dict(K=1.0, omega_min=0.0, omega_max=2.0, w_min=0.5, w_max=1.5),
               low=(-np.pi,), high=(np.pi,), draw=_nothing_drawn, rhs=_kuramoto_het, state_of=cos_sin,
               state_names=("cos phase", "sin phase"), time_scale=_kuramoto_het_time,
               attr_names=("natural frequency (rad/s)",), draw_trajectory=draw_kuramoto_het,
               ranges=(("omega_min", "omega_max", None), ("w_min", "w_max", 0.0))),
        System("swing", 3, dict(swing.DEFAULTS), low=(), high=(), draw=_nothing_drawn, rhs=_swing,
               samplers=("disturbed",), state_names=swing.STATE_NAMES, node_dims=(swing.FREQUENCY,),
               time_scale=swing.time_scale,
               attr_names=swing.ATTR_NAMES, draw_trajectory=swing.draw_grid,
               ranges=(("b_min", "b_max", 0.0), ("gen_min", "gen_max", 0.0), ("angle_min", "angle_max", 0.0))),
        # rhs: f(t, y, F) on the state INCLUDING the load, thrusts F held (see quadrotor.py)
        System(quadrotor.SYSTEM, quadrotor.STATE_DIM, dict(quadrotor.PARAMS), low=(), high=(),
               draw=quadrotor.draw_params, rhs=quadrotor.make_rhs, complete=True,
               samplers=("equilibrium",), generator=quadrotor.generate, controllers=quadrotor.controllers,
               control_dim=quadrotor.CONTROL_DIM, state_names=quadrotor.STATE_NAMES,
               state_groups=quadrotor.STATE_GROUPS),
    ]
}


def get_system(name, source="system", field="system"):
    """The System called ``name``; InputError listing the known ones otherwise."""
    try:
        return SYSTEMS[name]
    except (KeyError, TypeError):
        raise InputError(source, field, f"unknown system {name!r}", "one of " + ", ".join(SYSTEMS)) from None


def node_view(traj):
    """(dims, names) of `mpnode eval`'s error per node of a file: the state dimensions its system's
    users watch node by node (System.node_dims; None for the whole state, also for a file of no
    system here or of other dimensions) and what to call its nodes (a grid case's buses by their
    numbers; None: by index)."""
    system = SYSTEMS.get(traj.system)
    known = system is not None and system.state_dim == traj.state_dim and system.node_dims
    return (list(system.node_dims) if known else None), bus_names(traj.attrs, traj.n_nodes)


def make_rhs(system, params, graph, node_attrs=None):
    """f(t, y) for one trajectory of ``system`` on ``graph``; for coupled_pendulum_force f(t, y, u) with its
    forces u (2,) held; for the controlled quadrotor_load,
    f(t, y, F) with the thrusts F (n, 4) held over the step (its state includes the load).

    params : mapping holding at least the system's scalar parameters and drawn arrays
    (e.g. a file's root attributes merged with its `params/` group); extra keys are ignored.
    node_attrs : (N, dp), the trajectory's node attributes, for a system whose nodes differ (its
    edge weights are the graph's).
    """
    s = get_system(system)
    return s.rhs(params, graph) if node_attrs is None else s.rhs(params, graph, node_attrs)


def file_rhs(traj):
    """f(t, y) for each graph of a trajectory file, rebuilt from what the file records.

    traj : Trajectories of a reference system (root attributes + `params/` hold its parameters).
    Raises KeyError/ValueError/TypeError when the file lacks or garbles a parameter.
    """
    if traj.node_attrs is not None:
        raise ValueError(f"{traj.system}: its nodes differ from trajectory to trajectory; trajectory_rhs gives "
                         "each trajectory's right-hand side")
    params = {**traj.attrs, **traj.params}
    return [make_rhs(traj.system, params, g) for g in traj.graphs]


def trajectory_rhs(traj, b):
    """f(t, y) of trajectory ``b`` of a file, its node attributes and weighted graph included.

    Raises ValueError when the file's attribute names are not its system's (the rhs reads them
    by position), KeyError/TypeError as file_rhs.
    """
    if traj.node_attrs is None:
        return make_rhs(traj.system, {**traj.attrs, **traj.params}, traj.graph_of(b))
    return make_rhs(traj.system, {**traj.attrs, **traj.params}, traj.graph_of(b), _node_attrs(traj)[b])


def union_rhs(traj, k):
    """f(t, y) of the first k trajectories of a file whose nodes differ, side by side as one network:
    their graphs block-diagonal, their node attributes stacked; y holds trajectory 0's nodes, then
    trajectory 1's, ...  (every such system's nodes hear only their neighbours, so the networks stay
    apart).  Raises as trajectory_rhs."""
    graph = block_diagonal([traj.graph_of(b) for b in range(k)])
    return make_rhs(traj.system, {**traj.attrs, **traj.params}, graph, np.concatenate(_node_attrs(traj)[:k]))


def _node_attrs(traj):
    """The file's node attributes (B, N, dp); ValueError unless they are its system's, by name (an rhs
    reads them by position)."""
    expected = list(get_system(traj.system).attr_names)
    if list(traj.attr_names or ()) != expected:
        raise ValueError(f"{traj.system}: node attributes {traj.attr_names}, expected {expected}")
    return np.asarray(traj.node_attrs)
