"""quad3 data whose thrusts carry more independent excitation: the scene's closed loop (same
controller, paths, seeds and physics as `mpnode generate quad3`) with the per-rotor thrust noise
raised from the scene's 0.03 N to --noise (N), so that a model can tell what the thrusts do from
what the state does (in the scene's data the thrusts are the controller's function of the state
plus little else).

    python benchmarks/studies/mpc/excited_data.py OUT.h5 [-B 500] [--noise 0.1] [--workers 2]
"""
import argparse
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from data_gen import quadrotor as quad
from data_gen.scenes import BUILTIN
from mpnode import write_trajectories
from mpnode.base.errors import NumericalError
from mpnode.data import Trajectories


def one(args):
    """Trajectory b (re-drawn from its own generator when the closed loop loses the swarm)."""
    b, noise = args
    scene = BUILTIN["quad3"]
    rng = np.random.default_rng(np.random.SeedSequence(scene.seed, spawn_key=(b,)))
    for _ in range(20):
        try:
            return quad.closed_loop(rng, 3, scene.horizon, scene.dt, quad.Physics(), {"thrust_noise": noise})
        except NumericalError:
            continue
    raise NumericalError(f"trajectory {b} failed 20 times")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("output")
    ap.add_argument("-B", "--trajectories", type=int, default=500)
    ap.add_argument("--noise", type=float, default=0.1, help="per-rotor thrust noise (N) added at every step")
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args()
    scene = BUILTIN["quad3"]
    with ProcessPoolExecutor(a.workers) as pool:
        runs = list(pool.map(one, [(b, a.noise) for b in range(a.trajectories)], chunksize=10))
    traj = Trajectories(x=np.stack([r["x"] for r in runs]), u=np.stack([r["u"] for r in runs]),
                        graphs=scene.graph.build(), dt=scene.dt, system=quad.SYSTEM,
                        attrs={**quad.PARAMS, "scene": "quad3", "ctrl_thrust_noise": a.noise,
                               "description": "quad3 with more thrust noise (benchmarks/studies/mpc/excited_data.py)"},
                        params=quad.draw_params(None, 3, None),
                        aux={"load": np.stack([r["load"] for r in runs])})
    write_trajectories(a.output, traj)
    print(f"wrote {a.output}: {a.trajectories} trajectories, thrust noise {a.noise} N")


if __name__ == "__main__":
    main()
