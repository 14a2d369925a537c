"""Kinematics: state derivatives the physics fixes, so the network learns only the rest.

A position's derivative is its velocity, and a unit quaternion's is 1/2 q (x) [0, w] with w the
body rates; no data are needed to learn that.  A model with kinematics computes those
derivatives exactly and takes the network's outputs for the other dimensions alone: a rotation
then reaches the attitude, and a torque the velocity, only through what the network learned of
the body rates and the accelerations (docs/design.md, kinematics).

Written as text (model files, ``--kinematics``): terms separated by commas,
``D:S`` for x_D' = x_S, and ``qD:S`` for the quaternion x_D..x_D+3 ([w, x, y, z], body to world)
turned by the body rates x_S..x_S+2.  The quadrotor: ``0:7,1:8,2:9,q3:10``.

The kernels work in the model's normalised units, so a `Kinematics` also carries the state's
normalisation (`scaled`); `constants` packs both into the floats the kernels read
(mpnode.engine.kernels.kinematics), appended to the parameters for the call.
"""
import functools
from dataclasses import dataclass

import numpy as np

from mpnode.base.errors import InputError

from .dims import HEADER, PAIR_WIDTH, QUATERNION_WIDTH


@dataclass(frozen=True)
class Kinematics:
    """pairs ((d, s), ...): x_d' = x_s;  quaternions ((q0, w0), ...): q = x_q0..x_q0+3 turned by
    w = x_w0..x_w0+2;  mean, std: the state's normalisation (None: the data's own units)."""

    pairs: tuple = ()
    quaternions: tuple = ()
    mean: tuple = None
    std: tuple = None

    @classmethod
    def parse(cls, text, source="model", field="kinematics"):
        """The kinematics ``text`` describes (module docstring); None for "" or "none"."""
        if text is None or str(text).strip().lower() in ("", "none"):
            return None
        pairs, quaternions = [], []
        for term in str(text).replace(" ", "").split(","):
            quaternion = term[:1].lower() == "q"
            parts = (term[1:] if quaternion else term).split(":")
            if len(parts) != 2 or not all(p.isdecimal() and p.isascii() for p in parts):
                raise InputError(source, field, f"has the term {term!r}",
                                 "terms D:S (x_D' = x_S) or qD:S (quaternion at D, body rates at S), "
                                 "separated by commas, e.g. 0:7,1:8,2:9,q3:10")
            (quaternions if quaternion else pairs).append((int(parts[0]), int(parts[1])))
        return cls(tuple(pairs), tuple(quaternions))

    def text(self):
        return ",".join([f"{d}:{s}" for d, s in self.pairs] + [f"q{q}:{w}" for q, w in self.quaternions])

    @property
    def fixed(self):
        """The state dimensions whose derivatives the kinematics give, in order."""
        return tuple(d for d, _ in self.pairs) + tuple(q + k for q, _ in self.quaternions for k in range(4))

    def check(self, state_dim, source="model", field="kinematics"):
        """InputError unless every index is a state dimension and no derivative is fixed twice."""
        read = [s for _, s in self.pairs] + [w + k for _, w in self.quaternions for k in range(3)]
        bad = [i for i in self.fixed + tuple(read) if not 0 <= i < state_dim]
        if bad:
            raise InputError(source, field, f"{self.text()!r} names state dimension {bad[0]}",
                             f"indices below the state's {state_dim} dimensions")
        if len(set(self.fixed)) != len(self.fixed):
            raise InputError(source, field, f"{self.text()!r} fixes a derivative twice",
                             "each state dimension in at most one term")

    def scaled(self, mean, std):
        """The same kinematics for a model that works on (x - mean) / std."""
        return Kinematics(self.pairs, self.quaternions, tuple(map(float, mean)), tuple(map(float, std)))

    @functools.lru_cache(maxsize=32)
    def for_systems(self, n_nodes, state_dim):
        """The kinematics of a whole system of ``n_nodes`` nodes whose states are laid end to end
        (a plain NODE as the kernels run it).  Cached: a node model asks at every engine call,
        and the same instance keeps its constants packed."""
        def tile(terms):
            return tuple((a + i * state_dim, b + i * state_dim) for i in range(n_nodes) for a, b in terms)

        mean = None if self.mean is None else self.mean * n_nodes
        std = None if self.std is None else self.std * n_nodes
        return Kinematics(tile(self.pairs), tile(self.quaternions), mean, std)

    def constants(self, dtype):
        """The floats the kernels read (mpnode.engine.kernels.kinematics), in ``dtype``: per pair
        (d, s, a, b), x_d' = a xn_s + b; per quaternion (q0, w0, q's 4 means, 4 stds, w's 3 means,
        3 stds)."""
        return self._packed.astype(dtype)

    @functools.cached_property
    def _packed(self):
        """`constants` in float64, packed once: every rollout and VJP call reads them."""
        read = tuple(s for _, s in self.pairs) + tuple(w + 2 for _, w in self.quaternions)
        n = max(self.fixed + read, default=-1) + 1
        mean = np.zeros(n) if self.mean is None else np.asarray(self.mean, dtype=np.float64)
        std = np.ones(n) if self.std is None else np.asarray(self.std, dtype=np.float64)
        out = [len(self.pairs), len(self.quaternions)]
        for d, s in self.pairs:  # x_d' = s_s xn_s + m_s, in d's units: a xn_s + b
            out += [d, s, std[s] / std[d], mean[s] / std[d]]
        for q, w in self.quaternions:
            out += [q, w, *mean[q:q + 4], *std[q:q + 4], *mean[w:w + 3], *std[w:w + 3]]
        return np.asarray(out, dtype=np.float64)

    def width(self):
        """How many floats `constants` has."""
        return HEADER + PAIR_WIDTH * len(self.pairs) + QUATERNION_WIDTH * len(self.quaternions)

    def matrices(self, dx, width, dtype=np.float64):
        """The fixed derivatives as products, for the NumPy path and the exports (which know no
        indices): with xn (..., dx) the normalised states and k (..., width) the network's output,
        ``k * keep + xn @ A + offset + outer(xn @ Sq + mq, xn @ Sw + mw).reshape(..., -1) @ T``.
        ``Sq``, ``Sw`` pick every quaternion and its body rates in the data's units; ``T`` holds
        1/2 q (x) [0, w] per term, in normalised units.  Returns a dict of those arrays."""
        c = self.constants(np.float64)
        nq = len(self.quaternions)
        out = {"keep": np.ones(width), "A": np.zeros((dx, width)), "offset": np.zeros(width),
               "Sq": np.zeros((dx, 4 * nq)), "mq": np.zeros(4 * nq), "Sw": np.zeros((dx, 3 * nq)),
               "mw": np.zeros(3 * nq), "T": np.zeros((4 * nq, 3 * nq, width))}
        o = HEADER
        for d, s in self.pairs:
            out["keep"][d], out["A"][s, d], out["offset"][d] = 0, c[o + 2], c[o + 3]
            o += PAIR_WIDTH
        for g, (q0, w0) in enumerate(self.quaternions):
            mq, sq, mw, sw = c[o + 2:o + 6], c[o + 6:o + 10], c[o + 10:o + 13], c[o + 13:o + 16]
            for i in range(4):
                out["Sq"][q0 + i, 4 * g + i], out["mq"][4 * g + i] = sq[i], mq[i]
                out["keep"][q0 + i] = 0
                out["T"][4 * g:4 * g + 4, 3 * g:3 * g + 3, q0 + i] = 0.5 * QUATERNION_RATE[i] / sq[i]
            for j in range(3):
                out["Sw"][w0 + j, 3 * g + j], out["mw"][3 * g + j] = sw[j], mw[j]
            o += QUATERNION_WIDTH
        out["T"] = out["T"].reshape(12 * nq * nq, width)
        return {k: v.astype(dtype) for k, v in out.items()}


def derivatives_of(mat, x, k):
    """The network's output k with the fixed derivatives at states x put in (`Kinematics.matrices`)."""
    outer = (x @ mat["Sq"] + mat["mq"])[..., :, None] * (x @ mat["Sw"] + mat["mw"])[..., None, :]
    return k * mat["keep"] + x @ mat["A"] + mat["offset"] + outer.reshape(*x.shape[:-1], -1) @ mat["T"]


def _quaternion_rate():
    """(q (x) [0, w])_k = sum over i, j of the result's [k, i, j] q_i w_j, for q = [w, x, y, z]."""
    t = np.zeros((4, 4, 3))
    for k, i, j, sign in ((0, 1, 0, -1), (0, 2, 1, -1), (0, 3, 2, -1), (1, 0, 0, 1), (1, 2, 2, 1), (1, 3, 1, -1),
                          (2, 0, 1, 1), (2, 3, 0, 1), (2, 1, 2, -1), (3, 0, 2, 1), (3, 1, 1, 1), (3, 2, 0, -1)):
        t[k, i, j] = sign
    return t


QUATERNION_RATE = _quaternion_rate()
