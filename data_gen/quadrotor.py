"""quadrotor_load: n quadrotors carrying one cable-suspended load (docs/systems.md, "quadrotor_load").

The physics (``rhs``), the statics (``static_equilibrium``), the doorway scenario with
its closed-loop controller (``Reference``, ``Controller``) and the data-set driver
(``generate``, called by ``simulate.generate`` for this system).

State of one trajectory, flat, ``y`` shape ``(13 n + 6,)``: node after node
``[r (3), q = [w, x, y, z] body to world (4), v (3), omega body rates (3)]``, then the load
``[r_L (3), v_L (3)]``.  Controls ``F`` shape ``(n, 4)``: the rotor thrusts F1..F4 in N,
held constant over each saved step (zero-order hold).  Rotor layout implied by the spec's
torque ``tau = [L (F2 - F4), L (F3 - F1), k_m (F1 - F2 + F3 - F4)]``: rotor 1 on +x,
2 on +y, 3 on -x, 4 on -y (a "+" quadrotor), 1 and 3 spinning the other way from 2 and 4.

The integration runs one saved step at a time (the control changes every step) with a
stiff-capable solve_ivp method (LSODA, rtol = atol = 1e-9 in the scenes: it switches to BDF
when the stiff damped cable needs it, far cheaper than Radau for the same result: the counts are
in docs/evidence/speed.md, "The reference simulators"),
renormalises every quaternion at the step and continues from the saved state, so
``x[b, k+1]`` is exactly (to the tolerances) the integration of ``x[b, k]``, ``aux/load[b, k]``
under ``u[b, k]``: the file's controls reproduce its trajectories.
"""
import math

import numpy as np
from scipy.integrate import solve_ivp

from mpnode.base.errors import InputError, NumericalError
from mpnode.data import Trajectories
from mpnode.engine.codegen import build_numba_codegen
from mpnode.runs.executors import chunk_ranges, map_chunks, open_executor

try:
    from numba import njit
except ImportError:  # without numba the RHS runs as plain Python (same results, far slower), so that
    def njit(**_):   # importing the scenes -- which `mpnode eval` does -- still works (the NumPy path)
        return lambda f: f
else:
    build_numba_codegen()  # before the declarations below: the vector width numba compiles for

SYSTEM = "quadrotor_load"
STATE_DIM = 13
#: the node state's dimensions: position, attitude quaternion (body to world), velocity, body rates
STATE_NAMES = ("r_x (m)", "r_y (m)", "r_z (m)", "q_w", "q_x", "q_y", "q_z", "v_x (m/s)", "v_y (m/s)", "v_z (m/s)",
               "omega_x (rad/s)", "omega_y (rad/s)", "omega_z (rad/s)")
#: the group of each dimension (file attribute ``state_groups``): `mpnode eval` reports each group's error
STATE_GROUPS = ("position",) * 3 + ("attitude",) * 4 + ("velocity",) * 3 + ("body rates",) * 3
CONTROL_DIM = 4
LOAD_DIM = 6

#: scalar physics parameters under the spec's names (root attributes of every file);
#: F_max is the rotor thrust limit of the spec ("clipped to [0, 4.66]")
PARAMS = dict(m_q=1.0, L=0.175, k_m=0.0245, m_L=0.9, d=1.55, k_c=500.0, c_c=10.0, F_max=4.66)
#: inertia J = diag(J_DIAG) and gravity g (the `params/` datasets J (3x3) and g (3,))
J_DIAG = (0.0023, 0.0023, 0.004)
GRAVITY = (0.0, 0.0, -9.81)

#: the doorway scenario and controller; every entry goes to the file as attribute ``ctrl_<name>``
CONTROL = dict(
    radius=1.2,                    # formation circle about the load (m)
    fan_deg=50.0,                  # doorway formation: x-z fan, angles -fan..+fan from vertical
    start=(0.0, 0.0, 0.25),        # load start, plus uniform(-start_offset, start_offset) in x and y
    start_offset=0.3,
    doorway=(3.0, 0.0, 0.25),      # the load path passes exactly through it (path parameter 1/2)
    goal=(6.0, 0.0, 0.25),         # load goal, plus uniform(-goal_offset, goal_offset) in x and y
    goal_offset=0.5,
    transport_time=10.0,           # minimum-jerk time profile over 10 s (T = 100 at dt = 0.1)
    fan_window=(0.02, 0.3, 0.7, 0.98),  # path parameter: start/end narrowing, start/end widening
    pos_omega=2.0,                 # position loop natural frequency (rad/s) ...
    pos_zeta=0.9,                  # ... and damping, per unit of m_q + m_L / n
    att_pole=0.3,                  # attitude loop: both discrete poles of the sampled PD at z = att_pole
    tilt_max_deg=40.0,             # desired thrust direction limited to this tilt
    gain_jitter=0.15,              # per trajectory: each gain times uniform(1 - jitter, 1 + jitter)
    thrust_noise=0.03,             # per step and rotor: N(0, thrust_noise^2) N added before clipping
    thrust_excitation=0.0,         # per quadrotor and pair of steps: an N(0, thrust_excitation^2) N collective offset
    excitation_torque=0.25,        # and a torque doublet of this fraction of it: thrusts the state does not decide
    tension_reg=1e-2,              # Tikhonov term of the feed-forward tension split (N^2 units of |u|^2)
    fail_tilt_deg=75.0,            # a trajectory whose quadrotor tilts beyond this ...
    fail_error=2.0,                # ... or leaves its reference by this (m) is re-drawn
)


# ---- physics ------------------------------------------------------------------------
@njit(cache=True)
def _rhs_columns(Y, F, P, Jd, g, out):
    """dY/dt for each column of Y (shape (13 n + 6, k)); P = [m_q, L, k_m, m_L, d, k_c, c_c].
    F (n, 4, 1): the thrusts of every column, or (n, 4, k): each column's own."""
    n = F.shape[0]
    m_q, L, k_m, m_L, d, k_c, c_c = P[0], P[1], P[2], P[3], P[4], P[5], P[6]
    oL = 13 * n
    for k in range(Y.shape[1]):
        kf = k if F.shape[2] > 1 else 0
        rLx, rLy, rLz = Y[oL, k], Y[oL + 1, k], Y[oL + 2, k]
        vLx, vLy, vLz = Y[oL + 3, k], Y[oL + 4, k], Y[oL + 5, k]
        aLx, aLy, aLz = g[0], g[1], g[2]
        for i in range(n):
            o = 13 * i
            rx, ry, rz = Y[o, k], Y[o + 1, k], Y[o + 2, k]
            qw, qx, qy, qz = Y[o + 3, k], Y[o + 4, k], Y[o + 5, k], Y[o + 6, k]
            vx, vy, vz = Y[o + 7, k], Y[o + 8, k], Y[o + 9, k]
            wx, wy, wz = Y[o + 10, k], Y[o + 11, k], Y[o + 12, k]
            # cable: tension only, s = max(0, k_c (l - d) + c_c dl/dt), pulling along e = (r_L - r)/l
            dx, dy, dz = rLx - rx, rLy - ry, rLz - rz
            l = math.sqrt(dx * dx + dy * dy + dz * dz)
            ldot = (dx * (vLx - vx) + dy * (vLy - vy) + dz * (vLz - vz)) / l
            s = k_c * (l - d) + c_c * ldot
            if s < 0.0:
                s = 0.0
            ex, ey, ez = dx / l, dy / l, dz / l
            # thrust along the body z axis: R(q) e_z, exact for any nonzero q (divided by |q|^2)
            qq = qw * qw + qx * qx + qy * qy + qz * qz
            bx = 2.0 * (qx * qz + qw * qy) / qq
            by = 2.0 * (qy * qz - qw * qx) / qq
            bz = (qw * qw - qx * qx - qy * qy + qz * qz) / qq
            F1, F2, F3, F4 = F[i, 0, kf], F[i, 1, kf], F[i, 2, kf], F[i, 3, kf]
            thrust = F1 + F2 + F3 + F4
            out[o, k], out[o + 1, k], out[o + 2, k] = vx, vy, vz
            # q' = 1/2 q (x) [0, w]
            out[o + 3, k] = 0.5 * (-qx * wx - qy * wy - qz * wz)
            out[o + 4, k] = 0.5 * (qw * wx + qy * wz - qz * wy)
            out[o + 5, k] = 0.5 * (qw * wy + qz * wx - qx * wz)
            out[o + 6, k] = 0.5 * (qw * wz + qx * wy - qy * wx)
            out[o + 7, k] = g[0] + (bx * thrust + s * ex) / m_q
            out[o + 8, k] = g[1] + (by * thrust + s * ey) / m_q
            out[o + 9, k] = g[2] + (bz * thrust + s * ez) / m_q
            # w' = J^-1 (tau - w x J w)
            tx, ty, tz = L * (F2 - F4), L * (F3 - F1), k_m * (F1 - F2 + F3 - F4)
            Jx, Jy, Jz = Jd[0] * wx, Jd[1] * wy, Jd[2] * wz
            out[o + 10, k] = (tx - (wy * Jz - wz * Jy)) / Jd[0]
            out[o + 11, k] = (ty - (wz * Jx - wx * Jz)) / Jd[1]
            out[o + 12, k] = (tz - (wx * Jy - wy * Jx)) / Jd[2]
            aLx -= s * ex / m_L
            aLy -= s * ey / m_L
            aLz -= s * ez / m_L
        out[oL, k], out[oL + 1, k], out[oL + 2, k] = vLx, vLy, vLz
        out[oL + 3, k], out[oL + 4, k], out[oL + 5, k] = aLx, aLy, aLz


class Physics:
    """The parameters of one system, packed for the compiled right-hand side.

    params : mapping with the scalar parameters (PARAMS names; missing ones take the defaults)
    and optionally ``J`` (3x3 diagonal or its diagonal, 3) and ``g`` (3,).
    """

    def __init__(self, params=None):
        p = {**PARAMS, **(params or {})}
        self.params = {k: float(p[k]) for k in PARAMS}
        J = np.asarray(p.get("J", J_DIAG), dtype=np.float64)
        if J.shape == (3, 3):
            if np.any(J != np.diag(np.diag(J))):
                raise InputError("params", "J", "is not diagonal", "a diagonal inertia (body axes = principal axes)")
            J = np.diag(J)
        self.J = np.ascontiguousarray(J, dtype=np.float64)
        self.g = np.ascontiguousarray(np.asarray(p.get("g", GRAVITY), dtype=np.float64))
        self.packed = np.array([self.params[k] for k in ("m_q", "L", "k_m", "m_L", "d", "k_c", "c_c")])
        for name in ("m_q", "m_L", "d", "k_c", "L", "k_m", "F_max"):
            if not self.params[name] > 0:
                raise InputError("params", name, f"is {self.params[name]}", "a number > 0")
        self.evaluations = 0  # RHS evaluations (state columns) since the last reset

    def __getattr__(self, name):  # p.m_q, p.k_c, ...
        try:
            return self.__dict__["params"][name]
        except KeyError:
            raise AttributeError(name) from None

    def rhs(self, t, y, F):
        """dy/dt; y shape (13 n + 6,) or (13 n + 6, k) (solve_ivp's vectorized form); F shape (n, 4),
        or (n, 4, k): each column of y under its own thrusts (batched predictions, e.g. a controller's)."""
        Y = y if y.ndim == 2 else y[:, None]
        F = np.asarray(F, dtype=np.float64)
        out = np.empty(Y.shape)
        _rhs_columns(Y, np.ascontiguousarray(F if F.ndim == 3 else F[:, :, None]), self.packed, self.J, self.g, out)
        self.evaluations += Y.shape[1]
        return out if y.ndim == 2 else out[:, 0]

    def tensions(self, y, n):
        """Cable tensions s_i = max(0, k_c (l_i - d) + c_c dl_i/dt), shape (n,) (or (n, k) for y (., k))."""
        Y = y if y.ndim == 2 else y[:, None]
        quads = Y[:13 * n].reshape(n, 13, -1)
        dr = Y[13 * n:13 * n + 3][None] - quads[:, 0:3]
        dv = Y[13 * n + 3:13 * n + 6][None] - quads[:, 7:10]
        l = np.sqrt(np.sum(dr * dr, axis=1))
        s = np.maximum(0.0, self.k_c * (l - self.d) + self.c_c * np.sum(dr * dv, axis=1) / l)
        return s if y.ndim == 2 else s[:, 0]

    def momentum(self, y, n):
        """Total linear momentum m_q sum v_i + m_L v_L, shape (3,)."""
        quads = y[:13 * n].reshape(n, 13)
        return self.m_q * quads[:, 7:10].sum(axis=0) + self.m_L * y[13 * n + 3:13 * n + 6]

    def external_force(self, y, F):
        """Gravity on everything plus the rotor thrusts, sum_i R(q_i) e_z (F1+..+F4): shape (3,)."""
        n = F.shape[0]
        q = y[:13 * n].reshape(n, 13)[:, 3:7]
        total = (n * self.m_q + self.m_L) * self.g
        return total + (body_z(q) * F.sum(axis=1)[:, None]).sum(axis=0)


def body_z(q):
    """R(q) e_z for quaternions q = [w, x, y, z], shape (..., 4) -> (..., 3)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    qq = w * w + x * x + y * y + z * z
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), w * w - x * x - y * y + z * z], axis=-1) / qq[..., None]


def rotmat_to_quat(R):
    """Unit quaternion [w, x, y, z] with w >= 0 of a rotation matrix (Shepperd's method)."""
    t = np.trace(R)
    i = int(np.argmax([t, R[0, 0], R[1, 1], R[2, 2]]))
    if i == 0:
        w = 0.5 * math.sqrt(1 + t)
        q = [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]
    elif i == 1:
        x = 0.5 * math.sqrt(1 + 2 * R[0, 0] - t)
        q = [(R[2, 1] - R[1, 2]) / (4 * x), x, (R[0, 1] + R[1, 0]) / (4 * x), (R[0, 2] + R[2, 0]) / (4 * x)]
    elif i == 2:
        y = 0.5 * math.sqrt(1 + 2 * R[1, 1] - t)
        q = [(R[0, 2] - R[2, 0]) / (4 * y), (R[0, 1] + R[1, 0]) / (4 * y), y, (R[1, 2] + R[2, 1]) / (4 * y)]
    else:
        z = 0.5 * math.sqrt(1 + 2 * R[2, 2] - t)
        q = [(R[1, 0] - R[0, 1]) / (4 * z), (R[0, 2] + R[2, 0]) / (4 * z), (R[1, 2] + R[2, 1]) / (4 * z), z]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quat_mul(a, b):
    """Hamilton product a (x) b of quaternions [w, x, y, z]."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def _cross(a, b):
    """a x b for 3-vectors (np.cross's per-call overhead dominates for 3-vectors, and the controller
    makes thousands of calls: docs/evidence/speed.md)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def attitude_for_thrust(b3, yaw=0.0):
    """The attitude (unit quaternion) whose body z axis is b3 and whose heading is ``yaw``.

    Body x is the projection of [cos yaw, sin yaw, 0] onto the plane normal to b3 (the
    usual geometric-controller construction), so a quadrotor never needs to yaw.
    """
    b3 = np.asarray(b3, dtype=np.float64) / np.linalg.norm(b3)
    b2 = _cross(b3, (math.cos(yaw), math.sin(yaw), 0.0))
    b2 /= math.sqrt(b2 @ b2)
    return rotmat_to_quat(np.column_stack([_cross(b2, b3), b2, b3]))


def mixer(L, k_m):
    """M with [total thrust, tau_x, tau_y, tau_z] = M @ [F1, F2, F3, F4] (the spec's torques)."""
    return np.array([[1.0, 1.0, 1.0, 1.0], [0.0, L, 0.0, -L], [-L, 0.0, L, 0.0], [k_m, -k_m, k_m, -k_m]])


def pack(x, load):
    """Flat state y from quadrotor states x (n, 13) and the load (6,)."""
    return np.concatenate([np.asarray(x, dtype=np.float64).ravel(), np.asarray(load, dtype=np.float64)])


def unpack(y, n):
    """(x (n, 13), load (6,)) of a flat state; views of y."""
    return y[:13 * n].reshape(n, 13), y[13 * n:]


# ---- statics ------------------------------------------------------------------------
def circle_directions(n, radius, d):
    """Unit vectors load -> quadrotor of the circle formation, shape (n, 3).

    Quadrotor i at azimuth 2 pi i / n on the circle of ``radius`` about the load, at the
    height d cos(asin(radius / d)) above it (the cable at angle a = asin(radius / d) from vertical).
    """
    a = math.asin(radius / d)
    phi = 2 * np.pi * np.arange(n) / n
    return np.column_stack([math.sin(a) * np.cos(phi), math.sin(a) * np.sin(phi), np.full(n, math.cos(a))])


def fan_directions(n, radius, d, fan_deg):
    """Unit vectors load -> quadrotor of the doorway formation: the x-z fan, shape (n, 3).

    Fan slots at angles linspace(-fan, +fan, n) from vertical in the x-z plane; quadrotor i
    takes the slot of its rank when the circle formation is ordered by x (then y), so each
    moves to the nearest side of the fan and no two swap sides.
    """
    theta = np.radians(np.linspace(-fan_deg, fan_deg, n)) if n > 1 else np.zeros(1)
    c = circle_directions(n, radius, d)
    rank = np.empty(n, dtype=np.int64)
    rank[np.lexsort((c[:, 1], np.round(c[:, 0], 12)))] = np.arange(n)
    th = theta[rank]
    return np.column_stack([np.sin(th), np.zeros(n), np.cos(th)])


def split_tension(u, force, reg=0.0):
    """Cable tensions s (n,) with sum_i s_i u_i = force: the least-norm split (Tikhonov ``reg``).

    u : (n, 3) unit vectors load -> quadrotor; force : (3,) what the cables must exert on the
    load.  reg = 0 solves exactly (least squares when the directions are coplanar).
    """
    A = np.asarray(u, dtype=np.float64).T
    if reg == 0.0:
        return np.linalg.lstsq(A, force, rcond=None)[0]
    return A.T @ np.linalg.solve(A @ A.T + reg * np.eye(3), force)


def static_equilibrium(n, load_pos, physics=None, directions=None):
    """The static equilibrium of the formation with the load at rest at ``load_pos``.

    directions : (n, 3) unit vectors load -> quadrotor (default the circle formation);
    each cable carries s_i (for the circle m_L g / (n cos a)), is stretched by s_i / k_c,
    and quadrotor i is tilted (yaw-free construction, attitude_for_thrust) so that its thrust
    f_i = m_q |g| e_z + s_i u_i balances its weight and its cable's pull; every rotor gives f_i / 4.
    Returns x (n, 13), load (6,), F (n, 4), s (n,).
    """
    p = physics or Physics()
    u = circle_directions(n, CONTROL["radius"], p.d) if directions is None else np.asarray(directions, float)
    s = split_tension(u, -p.m_L * p.g)
    if np.any(s <= 0):
        raise InputError("static_equilibrium", "directions", "need a slack or pushing cable", "a formation above the load")
    load_pos = np.asarray(load_pos, dtype=np.float64)
    x = np.zeros((n, STATE_DIM))
    F = np.zeros((n, CONTROL_DIM))
    for i in range(n):
        f = -p.m_q * p.g + s[i] * u[i]
        x[i, 0:3] = load_pos + (p.d + s[i] / p.k_c) * u[i]
        x[i, 3:7] = attitude_for_thrust(f)
        F[i] = np.linalg.norm(f) / 4
    return x, np.concatenate([load_pos, np.zeros(3)]), F, s


# ---- the doorway scenario -----------------------------------------------------------
def _smooth(z):
    """Quintic smoothstep on [0, 1] (C2: zero slope and curvature at both ends)."""
    z = min(max(z, 0.0), 1.0)
    return z * z * z * (10 + z * (-15 + 6 * z))


class Reference:
    """Where the load and every quadrotor should be at time t (one trajectory).

    Load path: the parabola through start (path parameter s = 0), doorway (s = 1/2) and goal
    (s = 1), run with the minimum-jerk profile s(t) over ``transport_time`` (then held).
    Formation: directions blended from the circle to the x-z fan and back (weight alpha(s),
    1 inside the fan window) and renormalised; each cable's nominal tension is the least-norm
    split of m_L (a_L - g), and the quadrotor sits at r_L + (d + s_i / k_c) u_i.
    """

    def __init__(self, n, start, goal, physics, ctrl):
        self.n, self.p, self.c = n, physics, ctrl
        self.start, self.goal = np.asarray(start, float), np.asarray(goal, float)
        self.door = np.asarray(ctrl["doorway"], float)
        self.circle = circle_directions(n, ctrl["radius"], physics.d)
        self.fan = fan_directions(n, ctrl["radius"], physics.d, ctrl["fan_deg"])

    def progress(self, t):
        """(s, ds/dt, d2s/dt2) of the minimum-jerk profile."""
        Tt = self.c["transport_time"]
        z = min(max(t / Tt, 0.0), 1.0)
        s = z ** 3 * (10 + z * (-15 + 6 * z))
        sd = 30 * z * z * (1 - z) ** 2 / Tt
        sdd = 60 * z * (1 - z) * (1 - 2 * z) / Tt ** 2
        return s, sd, sdd

    def load(self, t):
        """Load reference position, velocity, acceleration, each (3,)."""
        s, sd, sdd = self.progress(t)
        p0, D, pG = self.start, self.door, self.goal
        P = p0 * (1 - s) * (1 - 2 * s) + D * 4 * s * (1 - s) + pG * s * (2 * s - 1)
        dP = p0 * (4 * s - 3) + D * (4 - 8 * s) + pG * (4 * s - 1)
        ddP = 4 * p0 - 8 * D + 4 * pG
        return P, dP * sd, ddP * sd * sd + dP * sdd

    def alpha(self, t):
        """Fan weight: 0 in the circle formation, 1 in the doorway fan."""
        s = self.progress(t)[0]
        a, b, c, d = self.c["fan_window"]
        return _smooth((s - a) / (b - a)) * _smooth((d - s) / (d - c))

    def formation(self, t):
        """(quadrotor positions (n, 3), directions u (n, 3), nominal tensions (n,)) at time t."""
        al = self.alpha(t)
        u = (1 - al) * self.circle + al * self.fan
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        rL, _, aL = self.load(t)
        s = split_tension(u, self.p.m_L * (aL - self.p.g), self.c["tension_reg"])
        return rL + (self.p.d + s / self.p.k_c)[:, None] * u, u, s

    def quads(self, t, h=1e-3):
        """Quadrotor reference position, velocity, acceleration (each (n, 3)), direction u and
        nominal tension s at t; the derivatives by central differences of step h."""
        r0, u, s = self.formation(t)
        rm, rp = self.formation(t - h)[0], self.formation(t + h)[0]
        return r0, (rp - rm) / (2 * h), (rp - 2 * r0 + rm) / (h * h), u, s


class Controller:
    """The cascaded controller of every quadrotor, run once per saved step (sampled data).

    Position loop (PD + feed-forward): f_des = m_q (a_ref - g) + s_nom u + m_eff (kp e_r + kd e_v),
    with m_eff = m_q + m_L / n; in the circle formation at rest the feed-forward
    m_q |g| + s_nom u has the vertical part g (m_q + m_L / n) of the spec and, in addition, the
    cable's horizontal pull (without it a PD would sag inwards by m_L g tan(a) / (n m_eff kp)).
    f_des's tilt is limited to tilt_max.  Attitude loop: quaternion PD towards the yaw-free
    attitude of f_des with gyroscopic cancellation, tau = J (-kp_att 2 q_e,vec - kd_att w) + w x J w,
    its gains designed for the SAMPLED double integrator so that both closed-loop poles sit at
    z = att_pole: kp_att = P / dt^2, kd_att = D / dt with P / 2 + D = 2 - 2 att_pole and
    D - P / 2 = 1 - att_pole^2 (att_pole = 0 would be dead-beat).  Collective thrust
    f_des . b3 (current body z).  Mixer inverted, rotors clipped to [0, F_max].
    """

    def __init__(self, n, reference, physics, ctrl, dt, gain_scale=(1.0, 1.0, 1.0, 1.0)):
        self.n, self.ref, self.p, self.c, self.dt = n, reference, physics, ctrl, dt
        w, z = ctrl["pos_omega"], ctrl["pos_zeta"]
        self.m_eff = physics.m_q + physics.m_L / n
        pole = ctrl["att_pole"]
        D = ((2 - 2 * pole) + (1 - pole * pole)) / 2
        P = 2 * ((2 - 2 * pole) - D)
        gs = np.asarray(gain_scale, dtype=np.float64)
        self.kp, self.kd = w * w * gs[0], 2 * z * w * gs[1]
        self.kp_att, self.kd_att = P / dt ** 2 * gs[2], D / dt * gs[3]
        self.Minv = np.linalg.inv(mixer(physics.L, physics.k_m))
        self.tilt_max = math.radians(ctrl["tilt_max_deg"])

    def gains(self):
        return dict(kp=self.kp, kd=self.kd, kp_att=self.kp_att, kd_att=self.kd_att)

    def __call__(self, t, x):
        """Rotor thrusts (n, 4), clipped, for quadrotor states x (n, 13) at time t; and the
        position errors |r_ref - r| (n,)."""
        p, J = self.p, self.p.J
        r_ref, v_ref, a_ref, u, s = self.ref.quads(t)
        F = np.empty((self.n, 4))
        err = np.linalg.norm(r_ref - x[:, 0:3], axis=1)
        for i in range(self.n):
            r, q, v, w = x[i, 0:3], x[i, 3:7], x[i, 7:10], x[i, 10:13]
            f = (p.m_q * (a_ref[i] - p.g) + s[i] * u[i]
                 + self.m_eff * (self.kp * (r_ref[i] - r) + self.kd * (v_ref[i] - v)))
            f = self._limit_tilt(f)
            q_d = attitude_for_thrust(f)
            q_e = quat_mul(q_d * [1, -1, -1, -1], q / np.linalg.norm(q))  # q = q_d (x) q_e
            if q_e[0] < 0:
                q_e = -q_e
            tau = J * (-self.kp_att * 2 * q_e[1:] - self.kd_att * w) + _cross(w, J * w)
            qw, qx, qy, qz = q / math.sqrt(q @ q)
            thrust = f[0] * 2 * (qx * qz + qw * qy) + f[1] * 2 * (qy * qz - qw * qx) + f[2] * (1 - 2 * (qx * qx + qy * qy))
            F[i] = self.Minv @ np.concatenate([[thrust], tau])
        return np.clip(F, 0.0, p.F_max), err

    def _limit_tilt(self, f):
        horiz = math.hypot(f[0], f[1])
        vert = max(f[2], 1e-6)
        if math.atan2(horiz, vert) <= self.tilt_max:
            return f
        scale = vert * math.tan(self.tilt_max) / horiz
        return np.array([f[0] * scale, f[1] * scale, vert])


def tilt(q):
    """Angle (rad) between body z and world z, for quaternions (..., 4)."""
    return np.arccos(np.clip(body_z(q)[..., 2], -1.0, 1.0))


# ---- integration --------------------------------------------------------------------
def step(physics, y, F, t0, dt, method="LSODA", rtol=1e-9, atol=1e-9):
    """Integrate one saved step under the held thrusts F (n, 4): y(t0) -> y(t0 + dt), quaternions
    renormalised.  Raises NumericalError when the solver fails or the state is not finite."""
    F = np.ascontiguousarray(F, dtype=np.float64)
    sol = solve_ivp(physics.rhs, (t0, t0 + dt), y, method=method, rtol=rtol, atol=atol, args=(F,),
                    vectorized=True)
    if sol.status != 0:
        raise NumericalError(f"solver stopped at t = {sol.t[-1]:g}: {sol.message}")
    y1 = sol.y[:, -1].copy()
    if not np.all(np.isfinite(y1)):
        raise NumericalError(f"non-finite state at t = {t0 + dt:g}")
    n = F.shape[0]
    x, _ = unpack(y1, n)
    x[:, 3:7] /= np.linalg.norm(x[:, 3:7], axis=1, keepdims=True)
    return y1


def open_loop(physics, x0, load0, F, dt, method="LSODA", rtol=1e-9, atol=1e-9):
    """Integrate under given thrusts F (T, n, 4) (ZOH): returns x (T+1, n, 13), load (T+1, 6)."""
    F = np.asarray(F, dtype=np.float64)
    n = F.shape[1]
    y = pack(x0, load0)
    ys = [y]
    for k in range(F.shape[0]):
        y = step(physics, y, F[k], k * dt, dt, method, rtol, atol)
        ys.append(y)
    ys = np.stack(ys)
    return ys[:, :13 * n].reshape(-1, n, 13), ys[:, 13 * n:]


def draw_scenario(rng, ctrl):
    """Per-trajectory randomness: load start (3,), load goal (3,), gain scale factors (4,)."""
    start = np.asarray(ctrl["start"], float) + np.r_[rng.uniform(-ctrl["start_offset"], ctrl["start_offset"], 2), 0]
    goal = np.asarray(ctrl["goal"], float) + np.r_[rng.uniform(-ctrl["goal_offset"], ctrl["goal_offset"], 2), 0]
    j = ctrl["gain_jitter"]
    return start, goal, rng.uniform(1 - j, 1 + j, 4)


def closed_loop(rng, n, n_steps, dt, physics, ctrl=None, method="LSODA", rtol=1e-9, atol=1e-9):
    """One doorway trajectory: the controller runs at every saved step, its (noisy, clipped)
    output held for dt.  Draws the scenario, then N(0, thrust_noise^2) per rotor and step, all
    from ``rng``.  Starts in the static equilibrium of the circle formation at the load start.
    With ``thrust_excitation`` > 0, each quadrotor's rotors also carry random offsets drawn every
    second step (before that step's noise; `excitation`), so that a model learning from the data
    sees what the thrusts do apart from what the state does; at 0 nothing more is drawn.  The
    torques come as doublets, and small: a torque held over two steps, or a doublet much above a
    tenth of a newton per rotor, tips a quadrotor over (the attitude loop has no integral action).

    Returns dict: x (T+1, n, 13), u (T, n, 4), load (T+1, 6), start, goal, gain_scale (4,),
    evaluations (RHS state evaluations), min_tension.  Raises NumericalError if the solver fails
    or the closed loop loses a quadrotor (tilt or tracking error beyond the fail limits).
    """
    c = {**CONTROL, **(ctrl or {})}
    start, goal, gain_scale = draw_scenario(rng, c)
    ref = Reference(n, start, goal, physics, c)
    control = Controller(n, ref, physics, c, dt, gain_scale)
    x0, load0, _, _ = static_equilibrium(n, start, physics)
    y = pack(x0, load0)
    ys, us = [y], []
    physics.evaluations = 0
    fail_tilt = math.radians(c["fail_tilt_deg"])
    min_tension = np.inf
    offsets = np.zeros((2, n, CONTROL_DIM))
    for k in range(n_steps):
        t = k * dt
        x, _ = unpack(y, n)
        if np.max(tilt(x[:, 3:7])) > fail_tilt:
            raise NumericalError(f"closed loop lost a quadrotor at t = {t:g} (tilt > {c['fail_tilt_deg']} deg)")
        F, err = control(t, x)
        if np.max(err) > c["fail_error"]:
            raise NumericalError(f"closed loop lost a quadrotor at t = {t:g} (tracking error {np.max(err):.2f} m)")
        F = disturbed_thrusts(rng, k, F, offsets, c["thrust_excitation"], c["excitation_torque"], c["thrust_noise"],
                              physics.F_max)
        y = step(physics, y, F, t, dt, method, rtol, atol)
        min_tension = min(min_tension, float(np.min(physics.tensions(y, n))))
        ys.append(y)
        us.append(F)
    ys = np.stack(ys)
    return dict(x=ys[:, :13 * n].reshape(-1, n, 13), u=np.stack(us), load=ys[:, 13 * n:], start=start,
                goal=goal, gain_scale=gain_scale, evaluations=physics.evaluations, min_tension=min_tension,
                gains=control.gains())


def disturbed_thrusts(rng, k, F, offsets, std, torque, noise, f_max):
    """The thrusts (n, 4) held over step k: the controller's F plus the excitation (redrawn into
    ``offsets`` (2, n, 4) every second step when ``std`` > 0) and N(0, noise^2) per rotor, clipped
    to the rotors' range.  `closed_loop` and `SceneControllers` both draw through here, so a
    learned swarm driven by the scene's controllers gets the file's draws."""
    if std > 0 and k % 2 == 0:
        offsets[:] = excitation(rng, F.shape[0], std, torque)
    return np.clip(F + offsets[k % 2] + noise * rng.standard_normal(F.shape), 0.0, f_max)


def excitation(rng, n, std, torque):
    """Thrust offsets (2, n, 4) of two steps: per quadrotor, one N(0, std^2) collective offset on
    its four rotors in both steps, plus a doublet, a zero-sum pattern across its rotors (torques)
    of N(0, (torque std)^2) draws in the first step and its negative in the second."""
    collective = np.repeat(std * rng.standard_normal((n, 1)), CONTROL_DIM, axis=1)
    d = torque * std * rng.standard_normal((n, CONTROL_DIM))
    d -= d.mean(axis=1, keepdims=True)
    return np.stack([collective + d, collective - d])


# ---- a learned model in the loop ----------------------------------------------------
class SceneControllers:
    """The controllers of a scene's B trajectories, to drive a learned model (`mpnode simulate`) as
    `generate` drives the physics: trajectory b draws its scenario (start, goal, gain factors) and
    then its thrust excitation and noise step after step from ``SeedSequence(scene.seed,
    spawn_key=(b,))``, as `closed_loop` does, and starts in the same equilibrium; so where the
    physics needed no re-draw, trajectory b of a file generated with the same scene and seed is
    the reference of the learned trajectory b.  Nothing stops a learned swarm that loses a quadrotor.

    x0 : (B, n, 13) initial states;  calling it with (k, x (B, n, 13)) gives the thrusts (B, n, 4)
    held over step k.
    """

    def __init__(self, scene):
        n, c = scene.graph.n_nodes, CONTROL
        physics = Physics({**PARAMS, **scene.params})
        self.dt, self.noise, self.f_max = scene.dt, c["thrust_noise"], physics.F_max
        self.excitation, self.torque = scene.excitation, c["excitation_torque"]
        self.offsets = np.zeros((scene.trajectories, 2, n, CONTROL_DIM))
        self.rngs = [np.random.default_rng(np.random.SeedSequence(scene.seed, spawn_key=(b,)))
                     for b in range(scene.trajectories)]
        self.controllers, x0 = [], []
        for rng in self.rngs:
            start, goal, gain_scale = draw_scenario(rng, c)
            self.controllers.append(Controller(n, Reference(n, start, goal, physics, c), physics, c, scene.dt,
                                               gain_scale))
            x0.append(static_equilibrium(n, start, physics)[0])
        self.x0 = np.stack(x0)

    def __call__(self, k, x):
        F = np.empty(np.shape(x)[:2] + (CONTROL_DIM,))
        with np.errstate(all="ignore"):  # a lost (non-finite) swarm gets non-finite thrusts, not an error
            for b, (control, rng) in enumerate(zip(self.controllers, self.rngs)):
                f, _ = control(k * self.dt, np.asarray(x[b], dtype=np.float64))
                F[b] = disturbed_thrusts(rng, k, f, self.offsets[b], self.excitation, self.torque, self.noise,
                                         self.f_max)
        return F


def controllers(scene):
    """(x0 (B, n, 13), controls(k, x) -> (B, n, 4)): the scene's closed loop around a learned model."""
    loop = SceneControllers(scene)
    return loop.x0, loop


# ---- the data set -------------------------------------------------------------------
def draw_params(p, n_nodes, rng):
    """The array parameters of the spec (nothing is random): J (3, 3) and g (3,)."""
    return {"J": np.diag(J_DIAG), "g": np.asarray(GRAVITY)}


def make_rhs(p, graph):
    """f(t, y, F) on the flat state (13 n + 6,) INCLUDING the load, thrusts F (n, 4) held."""
    return Physics(p).rhs


def generate(scene, *, workers=2, max_tries=10, progress=None, scheduler=None):
    """The trajectories of a quadrotor_load scene (Trajectories with u and aux/load).

    Trajectory b draws everything (start, goal, gain factors, thrust excitation and noise) from
    ``SeedSequence(scene.seed, spawn_key=(b,))``; a trajectory that fails is re-drawn from the
    same generator, at most ``max_tries`` times.  Root attributes: the physics (spec names),
    the controller settings (ctrl_*), seed, integrator, tolerances, controller_rate,
    redrawn, evaluations; params/: J, g; aux/: load [B, T+1, 6], load_start, load_goal
    [B, 3], gain_scale [B, 4] (kp, kd, kp_att, kd_att factors).
    """
    if scene.initial != "equilibrium":
        raise InputError(scene.name, "initial", f"is {scene.initial!r}", "'equilibrium' for quadrotor_load")
    n, B, T = scene.graph.n_nodes, scene.trajectories, scene.horizon
    graphs = scene.graph.build()
    physics_params = {**PARAMS, **scene.params}
    arrays = draw_params(physics_params, n, None)
    ctrl = {**CONTROL, "thrust_excitation": scene.excitation}
    job = dict(n=n, T=T, dt=scene.dt, params={**physics_params, **arrays}, method=scene.integrator,
               rtol=scene.rtol, atol=scene.atol, seed=scene.seed, max_tries=max_tries, ctrl=ctrl)
    out = dict(x=np.empty((B, T + 1, n, STATE_DIM)), u=np.empty((B, T, n, CONTROL_DIM)),
               load=np.empty((B, T + 1, LOAD_DIM)), start=np.empty((B, 3)), goal=np.empty((B, 3)),
               gain_scale=np.empty((B, 4)), evaluations=np.empty(B, np.int64), redraws=np.empty(B, np.int64),
               min_tension=np.empty(B))

    def keep(chunk, results):
        for b, r in zip(chunk, results):
            for key in out:
                out[key][b] = r[key]
        if progress is not None:
            progress(len(chunk))

    if workers == 1 and scheduler is None:
        map_chunks(None, _run, job, chunk_ranges(B, 1, 10), keep)
    else:
        with open_executor(scheduler, workers) as farm:
            map_chunks(farm, _run, job, chunk_ranges(B, farm.workers, 10), keep)
    probe = Controller(n, None, Physics(job["params"]), CONTROL, scene.dt)
    attrs = dict(physics_params, seed=scene.seed, system_seed=scene.system_seed, integrator=scene.integrator,
                 rtol=scene.rtol, atol=scene.atol, scene=scene.name, description=scene.description,
                 initial=scene.initial, max_tries=max_tries, redrawn=int(out["redraws"].sum()),
                 controller_rate=1.0 / scene.dt, control_hold="zero-order hold over dt; u reproduces x exactly",
                 integration="solve_ivp one saved step at a time, quaternions renormalised at every step",
                 evaluations_mean=float(out["evaluations"].mean()),
                 min_tension=float(out["min_tension"].min()), state_names=list(STATE_NAMES),
                 state_groups=list(STATE_GROUPS),
                 **{f"ctrl_{k}": (np.asarray(v, float) if isinstance(v, tuple) else v) for k, v in ctrl.items()},
                 **{f"ctrl_{k}_nominal": v for k, v in probe.gains().items()},
                 **scene.graph.describe())
    aux = dict(load=out["load"], load_start=out["start"], load_goal=out["goal"], gain_scale=out["gain_scale"],
               evaluations=out["evaluations"])
    return Trajectories(x=out["x"], u=out["u"], graphs=graphs, dt=scene.dt, system=SYSTEM, attrs=attrs,
                        params=arrays, aux=aux)


def _run(job, chunk):
    """Worker: the trajectories ``chunk`` (a range of b), each a dict as closed_loop returns + redraws."""
    physics = Physics(job["params"])
    results = []
    for b in chunk:
        rng = np.random.default_rng(np.random.SeedSequence(job["seed"], spawn_key=(b,)))
        for tries in range(job["max_tries"]):
            try:
                r = closed_loop(rng, job["n"], job["T"], job["dt"], physics, job["ctrl"], job["method"],
                                job["rtol"], job["atol"])
                break
            except NumericalError as e:
                problem = e
        else:
            raise NumericalError(f"{SYSTEM}: trajectory {b} failed {job['max_tries']} times in a row "
                                 f"(last: {problem}); check the parameters, dt and the controller gains")
        r["redraws"] = tries
        results.append(r)
    return results
