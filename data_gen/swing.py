"""Power grids as networks of swinging machines: the swing equation (second-order Kuramoto model),
its synchronous operating point, the inertia and damping rule, the disturbances a trajectory starts
from, and the synthetic grids a model trains on (docs/systems.md#swing).

Bus i has an angle theta_i (rad, in the frame that turns at the grid's nominal frequency) and a
frequency deviation omega_i (rad/s); lines carry power B_ij sin(theta_i - theta_j) (per unit):

    theta_i' = omega_i
    M_i omega_i' = P_i - D_i omega_i - sum_j B_ij sin(theta_i - theta_j)

A node keeps [cos theta_i, sin theta_i, omega_i]: the coupling is linear in the neighbours'
(cos, sin), so a node computes it from the weighted sum of what they send, and the state stays
bounded.  The node attributes are [M_i, D_i, P_i], the edge weights B_ij.  Nothing here knows
about files or scenes; the real cases are read in data_gen.grids.
"""
import numpy as np
import scipy.optimize
import scipy.sparse
import scipy.sparse.csgraph

from mpnode.base.errors import InputError, NumericalError
from mpnode.engine.backend import single_threaded_blas

from .graphs import symmetric_weights

#: the node attributes, in the columns of node_attrs
ATTR_NAMES = ("inertia (pu s^2)", "damping (pu s)", "power (pu)")
STATE_NAMES = ("cos angle", "sin angle", "frequency deviation (rad/s)")
#: the state dimension a grid's operator watches bus by bus: omega, the frequency deviation
FREQUENCY = 2
#: the system's scalar parameters: the inertia and damping rule, the disturbances, the synthetic family
DEFAULTS = dict(
    f_gen=0.7, f_load=1.4, gamma=1.0,                      # rule: own swing frequency (Hz), D / M (1/s)
    kick_buses=3.0, kick_angle=0.5, kick_speed=2.0, step=0.5,  # disturbances
    b_min=3.0, b_max=100.0, b_spread=1.5,                  # family: a grid's line level (pu), spread (decades)
    gen_min=0.1, gen_max=0.5, zero_max=0.3, p_spread=2.0,  # family: generator, zero-power fractions; sizes
    angle_min=0.05, angle_max=0.5,                         # family: the largest line angle at the operating point
)
#: a grid's powers balance when they add to at most this fraction of their sizes' sum
BALANCE_TOL = 1e-9
#: a synchronous state matches the powers to this fraction of the largest one
MATCH_TOL = 1e-9
#: disturbances drawn again when the powers before a step have no synchronous state
STEP_TRIES = 10


# ---- the right-hand side ------------------------------------------------------------------------
def swing_rhs(t, y, M, D, P, W):
    """The swing equation on y = [c_0, s_0, omega_0, c_1, ...] (c, s the angle's cosine and sine),
    shape (3N,) or (3N, K) (one state per column).

    sum_j B_ij sin(theta_i - theta_j) = s_i (W c)_i - c_i (W s)_i: two sparse products.
    M, D, P : (N,);  W : sparse (N, N), W[i, j] = B_ij.
    """
    c, s, omega = y[0::3], y[1::3], y[2::3]
    shape = (-1,) + (1,) * (c.ndim - 1)
    M, D, P = M.reshape(shape), D.reshape(shape), P.reshape(shape)
    dy = np.empty_like(y)
    dy[0::3] = -s * omega
    dy[1::3] = c * omega
    dy[2::3] = (P - D * omega - (s * (W @ c) - c * (W @ s))) / M
    return dy


def time_scale(p):
    """A radian of the fastest swing: the rule bounds every mode by sqrt(2) times the faster bus
    frequency (docs/systems.md#swing)."""
    fastest = np.sqrt(2) * 2 * np.pi * max(abs(p["f_gen"]), abs(p["f_load"]))
    return 1.0 / fastest if fastest else np.inf


# ---- inertia and damping ------------------------------------------------------------------------
def strength(graph):
    """sum_j B_ij of every bus (N,)."""
    return np.bincount(graph.edges()[:, 0], weights=graph.weights, minlength=graph.n_nodes)


def grid_attrs(graph, power, generator, p):
    """node_attrs (N, 3) = [M, D, P] by the rule: M_i = sum_j B_ij / (2 pi f)^2 with f = f_gen at a
    generator bus and f_load elsewhere (each bus swings against its lines at f), D_i = gamma M_i."""
    f = np.where(generator, p["f_gen"], p["f_load"])
    M = strength(graph) / (2 * np.pi * f) ** 2
    return np.stack([M, p["gamma"] * M, np.asarray(power, dtype=np.float64)], axis=1)


# ---- the operating point ------------------------------------------------------------------------
def check_grid(graph, power, source, field="power"):
    """InputError unless the grid is weighted and connected, every bus has a line, and the powers are
    finite and balance (sum P_i = 0: else the grid's frequency drifts without end and no state is
    synchronous)."""
    if not graph.weighted:
        raise InputError(source, "graph", "has no line susceptances", "a weighted graph: B_ij on every line (pu)")
    lonely = np.flatnonzero(graph.degrees() == 0)
    if len(lonely):
        raise InputError(source, "graph", f"bus {lonely[0]} has no line (an isolated bus cannot be kept in step)",
                         "a line at every bus")
    count = pieces(graph)
    if count > 1:
        raise InputError(source, "graph", f"is in {count} pieces (each would need its own balance)",
                         "one connected grid")
    power = np.asarray(power, dtype=np.float64)
    if not np.all(np.isfinite(power)):
        raise InputError(source, field, "is not finite everywhere", "finite powers (pu)")
    total, size = power.sum(), np.abs(power).sum()
    if abs(total) > BALANCE_TOL * max(size, 1.0):
        raise InputError(source, field, f"adds to {total:.6g} pu, not 0: generation and load do not balance",
                         "powers that add to 0 (sum P_i = 0)")


def pieces(graph):
    """The number of connected pieces of ``graph``."""
    lines = scipy.sparse.csr_array((np.ones(graph.n_edges), graph.indices, graph.indptr),
                                   shape=(graph.n_nodes, graph.n_nodes))
    return scipy.sparse.csgraph.connected_components(lines, directed=False)[0]


def mismatch(theta, graph, power):
    """P_i - sum_j B_ij sin(theta_i - theta_j) (N,) and its Jacobian in theta (N, N)."""
    r, s = graph.edges().T
    n = graph.n_nodes
    flow = graph.weights * np.sin(theta[r] - theta[s])
    stiff = graph.weights * np.cos(theta[r] - theta[s])
    J = np.zeros((n, n))
    np.add.at(J, (r, s), stiff)
    J[np.diag_indices(n)] = -np.bincount(r, weights=stiff, minlength=n)
    return power - np.bincount(r, weights=flow, minlength=n), J


def operating_point(graph, power, source="grid", field="power", inertia=None):
    """The stable synchronous state: angles theta* (N,) with sum_j B_ij sin(theta_i - theta_j) = P_i,
    their mean weighted by ``inertia`` (the centre of inertia; plain mean without) 0.

    Newton (scipy's hybrid method) on the N - 1 angles against bus 0, from the linearised (DC)
    solution; InputError naming ``source`` and ``field`` when the grid has none (powers beyond what
    the lines carry), or only an unstable one, or fails `check_grid`.
    """
    check_grid(graph, power, source, field)
    power = np.asarray(power, dtype=np.float64)
    with single_threaded_blas():  # the generator's processes solve side by side: BLAS threads would fight them
        theta = _solve(graph, power)
    left, J = mismatch(theta, graph, power)
    scale = max(np.abs(power).max(), 1.0)
    if not np.abs(left).max() <= MATCH_TOL * scale:
        k = int(np.argmax(np.abs(left)))
        raise InputError(source, field, f"has no synchronous state: the lines cannot carry these powers (the "
                         f"closest angles leave {abs(left[k]):.3g} pu unmatched at bus {k})",
                         "powers within the lines' capacity: smaller powers or stronger lines")
    if not _stable(graph, theta, J):
        raise InputError(source, field, "has only an unstable synchronous state (a line beyond 90 degrees)",
                         "powers within the lines' capacity: smaller powers or stronger lines")
    w = np.ones_like(theta) if inertia is None else np.asarray(inertia, dtype=np.float64)
    return theta - np.dot(w, theta) / w.sum()


def _solve(graph, power):
    """Angles (N,), bus 0 at 0, that zero the mismatch if scipy finds them: hybr, then Newton steps."""
    def reduced(x):
        left, J = mismatch(np.concatenate([[0.0], x]), graph, power)
        return left[1:], J[1:, 1:]

    _, J = mismatch(np.zeros(graph.n_nodes), graph, power)
    x = _linear_solve(-J[1:, 1:], power[1:])  # the DC angles
    x = scipy.optimize.root(reduced, x, jac=True, method="hybr").x
    for _ in range(3):  # hybr stops near 1e-9; Newton takes the last digits
        left, J = reduced(x)
        step = _linear_solve(J, -left)
        if not np.all(np.isfinite(step)):
            break
        x = x + step
    return np.concatenate([[0.0], x])


def _linear_solve(A, b):
    """A^-1 b, or the least-squares answer where A is singular."""
    try:
        return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(A, b, rcond=None)[0]


def _stable(graph, theta, J):
    """The cosine-weighted Laplacian -J at a synchronous state: positive semidefinite with one zero
    eigenvalue (the common angle) -- every disturbance but a common turn decays.  On a connected
    grid whose every line has B_ij cos(theta_i - theta_j) > 0 it is, without eigenvalues."""
    r, s = graph.edges().T
    if np.all(graph.weights * np.cos(theta[r] - theta[s]) > 0):
        return True
    ev = np.linalg.eigvalsh(-(J + J.T) / 2)
    tol = 1e-10 * max(abs(ev).max(), 1.0)
    return ev[0] > -tol and ev[1] > tol


# ---- the disturbances: the initial state --------------------------------------------------------
def disturbed(rng, system, n_nodes, graph=None, node_attrs=None, params=None):
    """The initial state (N, 3) of a grid just disturbed: the operating point of the powers before a
    step that raises bus a's power by ``step`` x mean |P| x uniform(-1, 1) and lowers bus b's by as
    much (after it the powers are the node attributes), then 1..kick_buses buses kicked by an angle uniform within
    +-kick_angle and a frequency deviation within +-kick_speed.  A step whose powers have no
    synchronous state is drawn again (NumericalError after STEP_TRIES)."""
    p = params
    M, power = node_attrs[:, 0], node_attrs[:, 2]
    theta = _before_step(rng, graph, M, power, p["step"])
    omega = np.zeros(n_nodes)
    count = min(n_nodes, int(rng.integers(1, int(p["kick_buses"]) + 1)))
    kicked = rng.choice(n_nodes, size=count, replace=False)
    theta[kicked] += rng.uniform(-p["kick_angle"], p["kick_angle"], len(kicked))
    omega[kicked] += rng.uniform(-p["kick_speed"], p["kick_speed"], len(kicked))
    return np.stack([np.cos(theta), np.sin(theta), omega], axis=1)


disturbed.needs_network = True  # data_gen.initial.draw_initial hands it the graph, attributes and parameters


def _before_step(rng, graph, M, power, step):
    """The operating point of the powers before a step between two buses (drawn again while they
    have none)."""
    size = step * np.abs(power).mean()
    for _ in range(STEP_TRIES):
        before = np.array(power, dtype=np.float64)
        a, b = rng.choice(len(power), size=2, replace=False)
        delta = size * rng.uniform(-1.0, 1.0)
        before[a] -= delta
        before[b] += delta
        try:
            return operating_point(graph, before, inertia=M)
        except InputError as e:
            problem = e
    raise NumericalError(f"no step of the powers kept a synchronous state in {STEP_TRIES} draws (last: {problem})")


# ---- the synthetic family -----------------------------------------------------------------------
def draw_grid(p, graph, rng):
    """One trajectory's (line susceptances (E,), node attributes (N, 3) = [M, D, P]) on ``graph``:
    lines at a grid level log-uniform in [b_min, b_max] times 10^u, u uniform within +-b_spread
    (one draw per line); a fraction of generator buses uniform in [gen_min, gen_max], of zero-power
    buses in [0, zero_max], the rest loads, each of a size 10^-u, u uniform in [0, p_spread];
    generation scaled to the load, then every power scaled so that the largest line angle of the
    linearised flow is uniform in [angle_min, angle_max].  Inertia and damping by `grid_attrs`."""
    spread = symmetric_weights(graph, -p["b_spread"], p["b_spread"], rng)
    level = np.exp(rng.uniform(np.log(p["b_min"]), np.log(p["b_max"])))
    weights = level * 10.0**spread
    lines = graph.reweighted(weights)
    generator, power = _draw_powers(p, graph.n_nodes, rng)
    power = power * rng.uniform(p["angle_min"], p["angle_max"]) / _largest_dc_angle(lines, power)
    return weights, grid_attrs(lines, _synchronous(lines, power), generator, p)


def _draw_powers(p, n, rng):
    """(generator buses (N,) bool, balanced powers (N,)) before scaling: see draw_grid."""
    n_gen = min(n - 1, max(1, round(rng.uniform(p["gen_min"], p["gen_max"]) * n)))
    n_zero = min(n - 1 - n_gen, round(rng.uniform(0.0, p["zero_max"]) * n))
    kind = rng.permutation(np.repeat([1, 0, -1], [n_gen, n_zero, n - n_gen - n_zero]))
    size = 10.0 ** -rng.uniform(0.0, p["p_spread"], n)
    power = kind * size
    gen = kind > 0
    power[gen] *= -power[~gen].sum() / power[gen].sum()
    return gen, power


def _synchronous(graph, power):
    """``power``, halved until the grid has a synchronous state (the linearised flow's angles can
    understate the true ones on a meshed grid; at the default angles no draw has needed it)."""
    for _ in range(STEP_TRIES):
        try:
            operating_point(graph, power)
            return power
        except InputError:
            power = power / 2
    raise NumericalError(f"a drawn grid kept no synchronous state after halving its powers {STEP_TRIES} times")


def _largest_dc_angle(graph, power):
    """The largest |theta_i - theta_j| over the lines of the linearised flow (sin x = x)."""
    _, J = mismatch(np.zeros(graph.n_nodes), graph, power)
    theta = np.concatenate([[0.0], _linear_solve(-J[1:, 1:], power[1:])])
    r, s = graph.edges().T
    return np.abs(theta[r] - theta[s]).max()
