"""What observation times of their own cost: a batch whose trajectories are each observed at
their own times against a regular batch taking the same number of RK4 steps.

For S1 (lorenz3, B = 128) and S4 (kuramoto10, B = 128), T = 50, float32, 2 threads: the
rollout and the training step (loss and exact gradient) of a regular batch (every interval
dt, one RK4 step each) and of a batch whose intervals are drawn per trajectory in
[0.5 dt, dt] (so again one step each, now of a size of its own per trajectory), interleaved,
medians of --repeats timed calls.  Prints one JSON object per line and case.

    python benchmarks/bench_irregular.py [--repeats 15]
"""
import argparse
import json
import os
import statistics
import time

import numpy as np

from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import FieldSpec, forward
from mpnode.engine.layouts import glorot_init
from mpnode.training.losses import value_and_grad

CASES = {"S1": ("lorenz3", 3, 3, 3, [(0, 1), (1, 2), (2, 0)]),
         "S4": ("kuramoto10", 10, 3, 3, [(i, (i + k) % 10) for i in range(10) for k in (1, 3)])}
B, T, DT, H = 128, 50, 0.05, 32


def seconds(fn):
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def case(name, repeats):
    label, n, dx, dm, edges = CASES[name]
    spec = FieldSpec(state_dim=dx, message_dim=dm, hidden=H, dt=DT)
    theta = glorot_init(spec, seed=0, dtype=np.float32)
    graph = block_diagonal([Graph.from_edges(n, edges)] * B)
    rng = np.random.default_rng(1)
    x = rng.standard_normal((T + 1, B * n, dx)).astype(np.float32)
    per_trajectory = rng.uniform(0.5 * DT, DT, size=(T, B))
    grids = {"regular": None, "irregular": np.repeat(per_trajectory, n, axis=1)}
    calls = {g: {"rollout": lambda iv=iv: forward(spec, theta, x[0], graph, None, T, intervals=iv),
                 "train_step": lambda iv=iv: value_and_grad(spec, theta, x, graph, intervals=iv)}
             for g, iv in grids.items()}
    times = {g: {k: [] for k in c} for g, c in calls.items()}
    for r in range(repeats + 1):  # interleaved, so that the host's changes fall on both alike; the first warms up
        for g, c in calls.items():
            for k, fn in c.items():
                took = seconds(fn)
                if r:
                    times[g][k].append(took)
    med = {g: {k: 1e3 * statistics.median(v) for k, v in t.items()} for g, t in times.items()}
    return {"case": name, "label": label, "nodes": B * n, "regular_rollout_ms": round(med["regular"]["rollout"], 3),
            "irregular_rollout_ms": round(med["irregular"]["rollout"], 3),
            "regular_train_step_ms": round(med["regular"]["train_step"], 3),
            "irregular_train_step_ms": round(med["irregular"]["train_step"], 3),
            "rollout_ratio": round(med["irregular"]["rollout"] / med["regular"]["rollout"], 3),
            "train_step_ratio": round(med["irregular"]["train_step"] / med["regular"]["train_step"], 3)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=15)
    args = p.parse_args(argv)
    os.environ.setdefault("NUMBA_NUM_THREADS", "2")
    for name in CASES:
        print(json.dumps(case(name, args.repeats)), flush=True)


if __name__ == "__main__":
    main()
