"""A quadrotor scene's trajectories with the doorway moved per trajectory: manoeuvres that differ.

The built-in quadN scenes fly one doorway (the load's start and goal shifted by at most 0.3 and
0.5 m, the controller's gains by 15%), so every trajectory is nearly the same manoeuvre.  Here
each trajectory first draws its doorway from its own generator, moved as the MPC study's new
paths move it (sideways by up to 0.4 m, up by up to 0.3 m), then everything else as the scene
draws it.  With --transport-times LO,HI the whole 10 s transport takes a time drawn from
[LO, HI] s instead (so the 5 s of a trajectory fly further or less far, faster or slower).
Written as `mpnode generate` writes a scene (the drawn doorways and times are not recorded).

    python benchmarks/studies/quadrotor/moved_doors.py OUT.h5 [--nodes 6] [-B 200] [--seed 3] [--transport-times 7,13]
"""
import argparse
import dataclasses

import numpy as np

import data_gen.quadrotor as quad
from data_gen.scenes import load_scene
from mpnode import write_trajectories

SIDEWAYS, UP = 0.4, 0.3


def moved_doorway(one_doorway, transport_times=None):
    """``one_doorway`` (quad.closed_loop) through a doorway, and in a transport time drawn from
    ``transport_times`` (low, high) s unless None, drawn from the trajectory's generator first."""

    def closed_loop(rng, n, n_steps, dt, physics, ctrl=None, *args, **kwargs):
        door = np.asarray(quad.CONTROL["doorway"], float) + [0.0, rng.uniform(-SIDEWAYS, SIDEWAYS),
                                                             rng.uniform(0.0, UP)]
        drawn = {"doorway": tuple(door)}
        if transport_times is not None:
            drawn["transport_time"] = rng.uniform(*transport_times)
        return one_doorway(rng, n, n_steps, dt, physics, {**(ctrl or {}), **drawn}, *args, **kwargs)

    return closed_loop


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--nodes", type=int, default=6, help="quadrotors (the scene quadN)")
    ap.add_argument("-B", "--trajectories", type=int, default=200)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--transport-times", metavar="LO,HI", help="draw the transport's duration (s) per trajectory")
    a = ap.parse_args()
    times = tuple(float(v) for v in a.transport_times.split(",")) if a.transport_times else None
    quad.closed_loop = moved_doorway(quad.closed_loop, times)  # the generator's workers are forked and keep it
    scene = dataclasses.replace(load_scene(f"quad{a.nodes}"), trajectories=a.trajectories, seed=a.seed)
    write_trajectories(a.out, quad.generate(scene, workers=2))


if __name__ == "__main__":
    main()
