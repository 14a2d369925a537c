"""Clean reference data made into data as they come: times that jitter, values that went
missing, measurement noise and state dimensions nobody measured, with the clean truth kept.

So that every user (and the tests) can see what imperfect data cost a model, measured against
the truth behind them (`mpnode generate SCENE --jitter F --drop P --noise REL --hide DIMS`).
Jittered times need the states between the saved steps: the scene is integrated on a grid
OVERSAMPLE times finer, and each observation takes the state at its own time on that grid.
"""
from dataclasses import dataclass, replace

import numpy as np

from mpnode.base.errors import InputError
from mpnode.data import Trajectories

#: how much finer the grid of a jittered scene is integrated: observation times fall on it
OVERSAMPLE = 20


@dataclass(frozen=True)
class Degradation:
    """jitter : an observation's time moves by up to jitter/2 dt either way (0: on the grid)
    drop : the fraction of the observed values that go missing (each value on its own)
    noise : measurement noise, its std relative to each dimension's std in the clean data
    hide : state dimensions never measured
    seed : the draws' seed"""

    jitter: float = 0.0
    drop: float = 0.0
    noise: float = 0.0
    hide: tuple = ()
    seed: int = 0

    def __post_init__(self):
        for name, hi in (("jitter", 0.9), ("drop", 0.95), ("noise", 10.0)):
            value = getattr(self, name)
            if not 0 <= value <= hi:
                raise InputError(f"--{name}", name, f"is {value}", f"a number in [0, {hi:g}]")

    @property
    def any(self):
        return bool(self.jitter or self.drop or self.noise or self.hide)


def fine_scene(scene, degradation):
    """The scene to integrate: OVERSAMPLE times finer when the times jitter, else as it is."""
    if not degradation.jitter:
        return scene
    return replace(scene, dt=scene.dt / OVERSAMPLE, horizon=scene.horizon * OVERSAMPLE)


def degrade(traj, degradation, dt):
    """The observations of ``traj`` (integrated by `fine_scene`) under ``degradation``, at the
    scene's step ``dt``: a Trajectories (format version 2) with its clean ``truth``."""
    d = degradation
    if traj.u is not None and d.jitter:
        raise InputError("--jitter", "jitter", f"is {d.jitter} for a system with controls ({traj.system})",
                         "no --jitter for a controlled system (its controls change between observations)")
    rng = np.random.default_rng([d.seed, 7])
    clean = np.asarray(traj.x, dtype=np.float64)
    step = OVERSAMPLE if d.jitter else 1
    index = _observation_index(rng, traj.n_trajectories, clean.shape[1], step, d.jitter)
    rows = np.arange(traj.n_trajectories)[:, None]
    truth = clean[rows, index]
    x = truth.copy()
    if d.hide:
        bad = [k for k in d.hide if not 0 <= k < x.shape[3]]
        if bad:
            raise InputError("--hide", "hide", f"names dimension {bad[0]}", f"dimensions 0..{x.shape[3] - 1}")
        x[..., list(d.hide)] = np.nan
    if d.noise:
        x += d.noise * truth.reshape(-1, x.shape[3]).std(axis=0) * rng.standard_normal(x.shape)
    if d.drop:
        gone = rng.random(x.shape) < d.drop
        gone[:, 0] &= ~_first_kept(rng, x.shape, d.hide)  # something stays observed at each start
        x[gone] = np.nan
    t = index * (dt / step) if d.jitter else None
    attrs = {**traj.attrs, "degraded": 1, "jitter": d.jitter, "drop": d.drop, "noise": d.noise,
             "hidden_dims": list(d.hide), "degradation_seed": d.seed}
    return Trajectories(x=x, graphs=traj.graphs, dt=dt, system=traj.system,
                        u=None if traj.u is None else np.asarray(traj.u), graph_index=traj.graph_index,
                        attrs=attrs, params=traj.params, aux={}, t=t, truth=truth, node_attrs=traj.node_attrs,
                        attr_names=traj.attr_names)


def _observation_index(rng, n_trajectories, n_fine, step, jitter):
    """(B, T+1) the fine-grid index of every observation: step k's, moved by up to jitter/2 dt
    either way (the first stays at 0).  With jitter < 1 a move stays under half a step, so the
    order of the observations is kept."""
    steps = (n_fine - 1) // step
    base = np.arange(steps + 1) * step
    if not jitter:
        return np.broadcast_to(base, (n_trajectories, steps + 1))
    reach = int(np.floor(jitter * step / 2))
    moved = base + rng.integers(-reach, reach + 1, size=(n_trajectories, steps + 1))
    moved[:, 0] = 0
    return np.minimum(moved, n_fine - 1)


def _first_kept(rng, shape, hidden):
    """(B, N, dx) one measured value of each trajectory's first observation that no drop may remove."""
    keep = np.zeros((shape[0],) + shape[2:], dtype=bool)
    measured = np.array([k for k in range(shape[3]) if k not in hidden])
    b = np.arange(shape[0])
    keep[b, rng.integers(0, shape[2], size=shape[0]), rng.choice(measured, size=shape[0])] = True
    return keep
