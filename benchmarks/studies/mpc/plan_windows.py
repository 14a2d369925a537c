"""Cut a trajectory file into consecutive windows of W steps, each a trajectory of its own (the
windows `mpnode train --train-window W` trains on: when W does not divide the horizon, a last
window ends at it).

A shooting MPC asks its model for W steps from whatever state it observes, messages at 0
(`quadrotor_mpc.py --messages zero`).  A model trained on whole flights only ever started from
the flights' first state; fine-tuned on their windows it is trained, and chosen by its
validation error, on exactly what a plan asks.  The load (`aux/load`) is cut with the states.

    python benchmarks/studies/mpc/plan_windows.py FLIGHTS.h5 OUT.h5 [--steps 5]
"""
import argparse

import numpy as np

from mpnode import read_trajectories, write_trajectories
from mpnode.data import Trajectories
from mpnode.training.batches import window_starts


def windows(a, starts, length):
    """(B * len(starts), length, ...): a[:, k:k + length] for every start k, start after start."""
    return np.concatenate([a[:, k:k + length] for k in starts])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", help="a trajectory file (e.g. `mpnode generate quad3`)")
    ap.add_argument("output")
    ap.add_argument("--steps", type=int, default=5, help="steps per window (the MPC's horizon)")
    a = ap.parse_args()
    d = read_trajectories(a.flights)
    if not 1 <= a.steps <= d.horizon:
        raise SystemExit(f"{a.flights}: --steps must lie in 1..{d.horizon}, the file's horizon (got {a.steps})")
    starts = window_starts(d.horizon, a.steps)  # as --train-window cuts them
    aux = {"load": windows(d.aux["load"], starts, a.steps + 1)} if "load" in d.aux else {}
    u = None if d.u is None else windows(d.u, starts, a.steps)
    traj = Trajectories(x=windows(d.x, starts, a.steps + 1), u=u,
                        graphs=d.graphs, graph_index=np.tile(d.graph_index, len(starts)), dt=d.dt,
                        system=d.system, attrs={**d.attrs, "window_source": a.flights, "window_steps": a.steps},
                        params=d.params, aux=aux)
    write_trajectories(a.output, traj)
    print(f"wrote {a.output}: {traj.n_trajectories} windows of {a.steps} steps")


if __name__ == "__main__":
    main()
