"""Time mpnode's rollout and training step (loss + exact gradient, no optimiser) on S1-S5.

The workloads are those of the peer harness (torch / JAX; same graphs, sizes, dt = 0.05,
T = 50, classic RK4) so that the figures compare with it.  For each case and model kind
it prints the FLOP floor -- the field's multiply-adds x 4 stages x steps x nodes at the
rate of a large GEMM *measured in the same run* (the training step counts 3x the
forward) -- and our ratio to it.  Medians of >= 7 timed calls after warm-up; float32 and
2 threads unless told otherwise.

    python benchmarks/bench_engine.py [--json] [--cases S1,S2] [--kinds mpnode,l2s] [--dtype float64]
"""
import argparse
import json
import statistics
import time

import networkx as nx
import numpy as np

from mpnode.engine import FieldSpec, forward
from mpnode.graph import Graph, block_diagonal
from mpnode.layouts import glorot_init
from mpnode.losses import value_and_grad

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


def gemm_gflops(dtype, n=2048, reps=5):
    """The best rate of an (n x n) @ (n x n) product through numpy's BLAS on this machine, now."""
    rng = np.random.default_rng(0)
    a, b = rng.random((n, n)).astype(dtype), rng.random((n, n)).astype(dtype)
    a @ b
    best = min(timed_once(lambda: a @ b) for _ in range(reps))
    return 2 * n ** 3 / best / 1e9


def timed_once(call):
    t0 = time.perf_counter()
    call()
    return time.perf_counter() - t0


def macs_per_node(case, kind):
    """Multiply-adds of one field evaluation per node (dense layers; the neighbour sum is not counted)."""
    c = CASES[case]
    dx, dm = c["dx"], c["dm"]
    if kind == "l2s":
        return dx * H + H * H + H * H + H * dx  # lift, message, update, decoder
    return (dx + dm) * H + H * H + H * (dx + dm)


def spec_for(case, kind):
    c = CASES[case]
    if kind == "l2s":
        return FieldSpec(c["dx"], 0, 0, H, DT, 1, kind="l2s", aggregation="sum")
    return FieldSpec(c["dx"], 0, c["dm"], H, DT, 1)


def run_case(case, kind, dtype, gflops):
    c = CASES[case]
    spec = spec_for(case, kind)
    graph = block_diagonal([c["graph"]()] * c["B"])
    m = graph.n_nodes
    theta = glorot_init(spec, seed=0, dtype=dtype)
    x = np.random.default_rng(1).standard_normal((T + 1, m, c["dx"])).astype(dtype)
    first_r, roll, _ = timed(lambda: forward(spec, theta, x[0], graph, n_steps=T))
    first_t, train, _ = timed(lambda: value_and_grad(spec, theta, x, graph))
    fl = 2 * macs_per_node(case, kind) * 4 * T * m / (gflops * 1e9) * 1e3
    return {"case": case, "label": c["label"], "kind": kind, "dtype": np.dtype(dtype).name, "nodes": m,
            "macs_per_node": macs_per_node(case, kind), "gemm_gflops": round(gflops, 1),
            "rollout_ms": round(roll, 3), "train_step_ms": round(train, 3),
            "floor_ms": round(fl, 3), "train_floor_ms": round(3 * fl, 3),
            "rollout_ratio": round(roll / fl, 2), "train_ratio": round(train / (3 * fl), 2),
            "first_call_s": round(max(first_r, first_t), 2)}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of S1..S5")
    ap.add_argument("--kinds", default="mpnode,l2s", help="comma-separated model kinds: mpnode, l2s")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--json", action="store_true", help="one JSON object per case")
    args = ap.parse_args()
    dtype = np.dtype(args.dtype)
    gflops = gemm_gflops(dtype)
    if not args.json:
        print(f"floor: {dtype.name} GEMM at {gflops:.0f} GFLOP/s (2048^2, measured now)")
        print(f"{'case':<14}{'kind':<8}{'nodes':>7}{'MACs':>6}{'rollout ms':>12}{'floor':>8}{'x':>6}"
              f"{'train ms':>10}{'floor':>8}{'x':>6}")
    for case in args.cases.split(","):
        for kind in args.kinds.split(","):
            r = run_case(case, kind, dtype, gflops)
            if args.json:
                print(json.dumps(r), flush=True)
            else:
                print(f"{case + ' ' + r['label']:<14}{kind:<8}{r['nodes']:>7}{r['macs_per_node']:>6}"
                      f"{r['rollout_ms']:>12.2f}{r['floor_ms']:>8.2f}{r['rollout_ratio']:>6.1f}"
                      f"{r['train_step_ms']:>10.2f}{r['train_floor_ms']:>8.2f}{r['train_ratio']:>6.1f}", flush=True)


if __name__ == "__main__":
    main()
