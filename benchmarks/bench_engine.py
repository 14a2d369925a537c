"""Time mpnode's rollout and training step (loss + exact gradient, no optimiser) on S1-S5.

The workloads are those of ../shared/peers (same graphs, sizes, dt = 0.05, T = 50, classic
RK4) so that the figures compare with the torch / JAX peers.  For each case it prints the
FLOP floor (MLP multiply-adds x 4 stages x steps x nodes at a big-GEMM rate; the training
step counts 3x the forward) and our ratio to it.  Medians of >= 7 timed calls after
warm-up; float32 and 2 threads unless told otherwise.

    python benchmarks/bench_engine.py [--json] [--cases S1,S2] [--dtype float64]
"""
import argparse
import json
import statistics
import time

import networkx as nx
import numpy as np

from mpnode.graph import Graph, block_diagonal
from mpnode.integrate import FieldSpec, loss_and_grad, rollout
from mpnode.mlp import glorot_init

CASES = {
    "S1": dict(label="lorenz3", N=3, dx=3, dm=3, B=128, graph=lambda: Graph.complete(3)),
    "S2": dict(label="lorenz10", N=10, dx=3, dm=3, B=128, graph=lambda: Graph.complete(10)),
    "S3": dict(label="gene8x8", N=64, dx=1, dm=3, B=32,
               graph=lambda: Graph.from_networkx(nx.barabasi_albert_graph(64, 32, seed=42))),
    "S4": dict(label="kuramoto10", N=10, dx=3, dm=7, B=128,
               graph=lambda: Graph.from_networkx(nx.barabasi_albert_graph(10, 5, seed=42))),
    "S5": dict(label="big", N=20000, dx=3, dm=3, B=1,
               graph=lambda: Graph.from_networkx(nx.random_regular_graph(6, 20000, seed=0))),
}
H, T, DT = 32, 50, 0.05
BIG_GEMM_GFLOPS = 230.0  # float32 rate of a large SGEMM on this machine class (peers/results/floor.txt)


def timed(call, n_min=7, min_total_s=3.0, max_reps=30):
    """First call (compile or cache load + run), one more warm-up, then >= n_min timed calls (ms)."""
    t0 = time.perf_counter()
    call()
    first = time.perf_counter() - t0
    call()
    times = []
    start = time.perf_counter()
    while len(times) < max_reps and (len(times) < n_min or time.perf_counter() - start < min_total_s):
        t0 = time.perf_counter()
        call()
        times.append(1e3 * (time.perf_counter() - t0))
    return first, statistics.median(times), times


def floor_ms(case):
    c = CASES[case]
    d = c["dx"] + c["dm"]
    macs = (d * H + H * H + H * d) * 4 * T * c["N"] * c["B"]
    return 2 * macs / (BIG_GEMM_GFLOPS * 1e9) * 1e3


def run_case(case, dtype):
    c = CASES[case]
    spec = FieldSpec(c["dx"], 0, c["dm"], H, DT, 1)
    graph = block_diagonal([c["graph"]()] * c["B"])
    m = graph.n_nodes
    theta = glorot_init(c["dx"], 0, c["dm"], H, seed=0, dtype=dtype)
    x = np.random.default_rng(1).standard_normal((T + 1, m, c["dx"])).astype(dtype)
    first_r, roll, _ = timed(lambda: rollout(spec, theta, x[0], graph, n_steps=T))
    first_t, train, _ = timed(lambda: loss_and_grad(spec, theta, x, graph))
    fl = floor_ms(case)
    return {"case": case, "label": c["label"], "dtype": np.dtype(dtype).name, "nodes": m,
            "rollout_ms": round(roll, 3), "train_step_ms": round(train, 3),
            "floor_ms": round(fl, 3), "train_floor_ms": round(3 * fl, 3),
            "rollout_ratio": round(roll / fl, 2), "train_ratio": round(train / (3 * fl), 2),
            "first_call_s": round(max(first_r, first_t), 2)}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of S1..S5")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--json", action="store_true", help="one JSON object per case")
    args = ap.parse_args()
    if not args.json:
        print(f"{'case':<14}{'nodes':>7}{'rollout ms':>12}{'floor':>8}{'x':>6}{'train ms':>10}{'floor':>8}{'x':>6}")
    for case in args.cases.split(","):
        r = run_case(case, np.dtype(args.dtype))
        if args.json:
            print(json.dumps(r), flush=True)
        else:
            print(f"{case + ' ' + r['label']:<14}{r['nodes']:>7}{r['rollout_ms']:>12.2f}{r['floor_ms']:>8.2f}"
                  f"{r['rollout_ratio']:>6.1f}{r['train_step_ms']:>10.2f}{r['train_floor_ms']:>8.2f}"
                  f"{r['train_ratio']:>6.1f}", flush=True)


if __name__ == "__main__":
    main()
