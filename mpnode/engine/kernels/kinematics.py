"""The fixed derivatives of a model with kinematics (mpnode.engine.kinematics) on a tile of
nodes, and their VJP.  The constants are the last dims[KINEMATICS] floats of ``theta`` (layout:
mpnode.engine.dims); states and derivatives are in the model's normalised units, feature-major
(XT (>= dx, n): the stage's states as the MP-NODE field's input cache holds them)."""
from numba import njit

from ..dims import HEADER, KINEMATICS, PAIR_WIDTH, QUATERNION_WIDTH
from .layers import JIT


@njit(inline="always", **JIT)
def constants(theta, dims):
    return theta[theta.shape[0] - dims[KINEMATICS]:]


@njit(**JIT)
def quaternion_and_rates(t, o, XT, q0, w0, r):
    """Node r's quaternion (w, x, y, z) and body rates in the data's units: the term at t[o:]
    holds their means (t[o + 2:o + 6], t[o + 10:o + 13]) and scales (t[o + 6:o + 10], t[o + 13:o + 16])."""
    qw, qx = t[o + 6] * XT[q0, r] + t[o + 2], t[o + 7] * XT[q0 + 1, r] + t[o + 3]
    qy, qz = t[o + 8] * XT[q0 + 2, r] + t[o + 4], t[o + 9] * XT[q0 + 3, r] + t[o + 5]
    wx, wy = t[o + 13] * XT[w0, r] + t[o + 10], t[o + 14] * XT[w0 + 1, r] + t[o + 11]
    return qw, qx, qy, qz, wx, wy, t[o + 15] * XT[w0 + 2, r] + t[o + 12]


@njit(**JIT)
def apply(theta, dims, XT, KT):
    """KT (dz, n): the fixed rows overwritten with their derivatives at the states XT."""
    t = constants(theta, dims)
    n = KT.shape[1]
    o = HEADER
    for _ in range(int(t[0])):
        d, s, a, b = int(t[o]), int(t[o + 1]), t[o + 2], t[o + 3]
        for r in range(n):
            KT[d, r] = a * XT[s, r] + b
        o += PAIR_WIDTH
    half = t.dtype.type(0.5)
    for _ in range(int(t[1])):
        q0, w0 = int(t[o]), int(t[o + 1])
        for r in range(n):
            qw, qx, qy, qz, wx, wy, wz = quaternion_and_rates(t, o, XT, q0, w0, r)
            KT[q0, r] = half * (-qx * wx - qy * wy - qz * wz) / t[o + 6]
            KT[q0 + 1, r] = half * (qw * wx + qy * wz - qz * wy) / t[o + 7]
            KT[q0 + 2, r] = half * (qw * wy + qz * wx - qx * wz) / t[o + 8]
            KT[q0 + 3, r] = half * (qw * wz + qx * wy - qy * wx) / t[o + 9]
        o += QUATERNION_WIDTH


@njit(**JIT)
def take(theta, dims, GK):
    """A copy of GK (n, dz), the cotangent of k, and GK with the fixed columns zeroed: the
    network's outputs there are not used, so they get no cotangent."""
    G = GK.copy()
    t = constants(theta, dims)
    o = HEADER
    for _ in range(int(t[0])):
        GK[:, int(t[o])] = 0
        o += PAIR_WIDTH
    for _ in range(int(t[1])):
        q0 = int(t[o])
        GK[:, q0:q0 + 4] = 0
        o += QUATERNION_WIDTH
    return G


@njit(**JIT)
def vjp(theta, dims, XT, G, gin, i0, zoff):
    """Adds into gin (rows ``i - zoff``) the cotangent of the states XT through the fixed
    derivatives, given theirs in G (n, dz) (`take`)."""
    t = constants(theta, dims)
    n = G.shape[0]
    o = HEADER
    for _ in range(int(t[0])):
        d, s, a = int(t[o]), int(t[o + 1]), t[o + 2]
        for r in range(n):
            gin[i0 + r - zoff, s] += a * G[r, d]
        o += PAIR_WIDTH
    half = t.dtype.type(0.5)
    for _ in range(int(t[1])):
        q0, w0 = int(t[o]), int(t[o + 1])
        for r in range(n):
            zi = i0 + r - zoff
            qw, qx, qy, qz, wx, wy, wz = quaternion_and_rates(t, o, XT, q0, w0, r)
            cw, cx = half * G[r, q0] / t[o + 6], half * G[r, q0 + 1] / t[o + 7]
            cy, cz = half * G[r, q0 + 2] / t[o + 8], half * G[r, q0 + 3] / t[o + 9]
            gin[zi, q0] += (cx * wx + cy * wy + cz * wz) * t[o + 6]
            gin[zi, q0 + 1] += (-cw * wx - cy * wz + cz * wy) * t[o + 7]
            gin[zi, q0 + 2] += (-cw * wy + cx * wz - cz * wx) * t[o + 8]
            gin[zi, q0 + 3] += (-cw * wz - cx * wy + cy * wx) * t[o + 9]
            gin[zi, w0] += (-cw * qx + cx * qw + cy * qz - cz * qy) * t[o + 13]
            gin[zi, w0 + 1] += (-cw * qy - cx * qz + cy * qw + cz * qx) * t[o + 14]
            gin[zi, w0 + 2] += (-cw * qz + cx * qy - cy * qx + cz * qw) * t[o + 15]
        o += QUATERNION_WIDTH
