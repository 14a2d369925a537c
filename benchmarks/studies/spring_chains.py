"""Pendulums on springs of their own, simulated here as a user's own simulator would, and written
through `write_trajectories` from plain arrays (docs/evidence/networks.md).

Each pendulum i has its own length l_i and mass m_i; a spring of its own stiffness k_ij joins the
bobs of neighbours in a chain and pulls along the horizontal:

    m_i l_i^2 theta_i'' = -m_i g l_i sin(theta_i) + l_i cos(theta_i) sum_j k_ij (X_j - X_i),
    X_i = l_i sin(theta_i),

integrated with scipy's DOP853 (rtol 1e-9).  Every trajectory draws its lengths (1-2 m), masses
(0.5-2 kg), stiffnesses (1-4 N/m) and initial angles (+-pi/4) and rates (+-0.5 rad/s) afresh.
The data are of swinging pendulums, as the built-in scene's: a draw in which a pendulum passes
the horizontal (and may go over the top) is drawn again.

    python benchmarks/studies/spring_chains.py OUT.h5 --nodes 4 --trajectories 400 --seed 0 [--steps 100]
"""
import argparse

import numpy as np
from scipy.integrate import solve_ivp

from mpnode import Graph, write_trajectories

G = 9.81


def chain(n, stiffness):
    """The chain 0-1-...-(n-1), each spring's stiffness on both of its directed edges."""
    pairs = [(i + 1, i) for i in range(n - 1)]  # (receiver, sender); undirected doubles them
    return Graph.from_edges(n, pairs, weights=stiffness)


def rhs(t, y, length, mass, graph):
    n = len(length)
    theta, omega = y[:n], y[n:]
    x = length * np.sin(theta)
    rows = np.repeat(np.arange(n), graph.degrees())
    pull = np.bincount(rows, graph.weights * (x[graph.indices] - x[rows]), minlength=n)
    alpha = (-mass * G * length * np.sin(theta) + length * np.cos(theta) * pull) / (mass * length ** 2)
    return np.concatenate([omega, alpha])


def simulate(n, b, seed, steps=100, dt=0.05):
    """(x (B, T+1, N, 2), graphs, node_attrs (B, N, 2)) of B chains of n pendulums."""
    rng = np.random.default_rng(seed)
    x = np.empty((b, steps + 1, n, 2))
    attrs = np.empty((b, n, 2))
    graphs = []
    t_eval = np.arange(steps + 1) * dt
    for k in range(b):
        while True:
            length, mass = rng.uniform(1.0, 2.0, n), rng.uniform(0.5, 2.0, n)
            graph = chain(n, rng.uniform(1.0, 4.0, n - 1))
            y0 = np.concatenate([rng.uniform(-np.pi / 4, np.pi / 4, n), rng.uniform(-0.5, 0.5, n)])
            sol = solve_ivp(rhs, (0, t_eval[-1]), y0, method="DOP853", t_eval=t_eval, rtol=1e-9, atol=1e-9,
                            args=(length, mass, graph))
            if np.abs(sol.y[:n]).max() < np.pi / 2:
                break
        x[k] = sol.y.reshape(2, n, steps + 1).transpose(2, 1, 0)
        attrs[k] = np.stack([length, mass], axis=1)
        graphs.append(graph)
    return x, graphs, attrs


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("output")
    ap.add_argument("--nodes", type=int, default=4)
    ap.add_argument("--trajectories", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=100, help="steps of dt = 0.05 s per trajectory")
    a = ap.parse_args()
    x, graphs, attrs = simulate(a.nodes, a.trajectories, a.seed, steps=a.steps)
    write_trajectories(a.output, x=x, graph=graphs, graph_index=np.arange(len(graphs)), dt=0.05,
                       system="spring_chains", node_attrs=attrs, attr_names=["length (m)", "mass (kg)"],
                       attrs={"state_names": ["angle (rad)", "angular velocity (rad/s)"]})


if __name__ == "__main__":
    main()
