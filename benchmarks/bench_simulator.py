"""The stepping API's cost per step, and the NumPy path's speed against the compiled one.

1. mpnode.Simulator.step on a 10-node graph (complete, dx = 3, dm = 3, H = 32: lorenz10's
   shape) with B = 1, per model kind and backend: the median microseconds per step over
   many steps, beside the cost of a step inside one long rollout (Model.rollout of
   LONG steps / LONG), so the difference is the stepping API's own overhead.  A 1 kHz
   control loop has 1000 us per step for everything.
2. S1 of bench_engine.py (lorenz3-like: 128 copies of a complete 3-node graph, T = 50,
   H = 32) rolled out by the compiled kernels and by the NumPy path (engine.forward,
   backend "numba" / "numpy"): medians of each and the median of the per-repetition ratios.

    python benchmarks/bench_simulator.py [--dtype float64] [--kinds mpnode,l2s,node] [--json]
"""
import argparse
import json
import statistics
import time

import numpy as np
from bench_engine import CASES, DT, H, T

from mpnode import Model, Simulator, engine
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine.layouts import glorot_init

N_STEP, DX, DM = 10, 3, 3
LONG = 1000


def make_model(kind, n_nodes, dtype, dm=DM):
    return Model.create(DX, 0, message_dim=dm, hidden=H, dt=DT, kind=kind, n_nodes=n_nodes if kind == "node" else None, dtype=dtype)


def us_per_step(kind, backend, dtype, n_steps=2000, warmup=200):
    """Median us of Simulator.step (B = 1, 10 nodes), and a step's share of one long rollout."""
    model, graph = make_model(kind, N_STEP, dtype), Graph.complete(N_STEP)
    x0 = np.random.default_rng(0).uniform(-1, 1, (1, N_STEP, DX))
    sim = Simulator(model, graph, backend=backend)
    sim.reset(x0)
    times = []
    for i in range(warmup + n_steps):
        t0 = time.perf_counter()
        sim.step()
        times.append(time.perf_counter() - t0)
        if i % 500 == 0:
            sim.reset(x0)  # stay in the model's range
    model.rollout(x0, graph, steps=LONG, backend=backend)
    long = []
    for _ in range(5):
        t0 = time.perf_counter()
        model.rollout(x0, graph, steps=LONG, backend=backend)
        long.append(time.perf_counter() - t0)
    return 1e6 * statistics.median(times[warmup:]), 1e6 * statistics.median(long) / LONG


def s1_numpy_vs_compiled(kind, dtype, reps=9):
    """S1 rollouts (ms): compiled, NumPy, and the median of the per-repetition ratios."""
    c = CASES["S1"]
    n = c["N"]
    if kind == "l2s":
        spec = engine.FieldSpec(kind="l2s", state_dim=c["dx"], hidden=H, dt=DT)
    elif kind == "node":
        spec = engine.FieldSpec(kind="node", state_dim=c["dx"], hidden=H, dt=DT, n_nodes=n)
    else:
        spec = engine.FieldSpec(state_dim=c["dx"], message_dim=c["dm"], hidden=H, dt=DT)
    graph = block_diagonal([c["graph"]()] * c["B"])
    theta = glorot_init(spec, seed=0, dtype=dtype)
    x0 = np.random.default_rng(1).standard_normal((graph.n_nodes, c["dx"])).astype(dtype)

    def once(backend):
        t0 = time.perf_counter()
        engine.forward(spec, theta, x0, graph, n_steps=T, backend=backend)
        return 1e3 * (time.perf_counter() - t0)

    once("numba"), once("numpy")  # compile or load, warm up
    pairs = [(once("numba"), once("numpy")) for _ in range(reps)]
    return (statistics.median(p[0] for p in pairs), statistics.median(p[1] for p in pairs),
            statistics.median(p[1] / p[0] for p in pairs))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--kinds", default="mpnode,l2s,node", help="comma-separated model kinds")
    ap.add_argument("--json", action="store_true", help="one JSON object per measurement")
    args = ap.parse_args()
    dtype = np.dtype(args.dtype)
    kinds = args.kinds.split(",")
    if not args.json:
        print(f"1. Simulator.step, {N_STEP}-node complete graph, B = 1, H = {H}, {dtype.name} (median us)")
        print(f"{'kind':<8}{'backend':<8}{'us/step':>9}{'in rollout':>12}{'overhead':>10}")
    for kind in kinds:
        for backend in ("numba", "numpy"):
            step, inside = us_per_step(kind, backend, dtype)
            r = {"what": "step", "kind": kind, "backend": backend, "dtype": dtype.name,
                 "us_per_step": round(step, 1), "us_per_step_in_rollout": round(inside, 1)}
            if args.json:
                print(json.dumps(r), flush=True)
            else:
                print(f"{kind:<8}{backend:<8}{step:>9.1f}{inside:>12.1f}{step - inside:>10.1f}", flush=True)
    if not args.json:
        print(f"\n2. S1 rollout (128 x 3 nodes, T = {T}, H = {H}), {dtype.name}: NumPy path against compiled")
        print(f"{'kind':<8}{'numba ms':>10}{'numpy ms':>10}{'ratio':>8}")
    for kind in kinds:
        fast, slow, ratio = s1_numpy_vs_compiled(kind, dtype)
        r = {"what": "S1", "kind": kind, "dtype": dtype.name, "numba_ms": round(fast, 3),
             "numpy_ms": round(slow, 3), "ratio": round(ratio, 1)}
        if args.json:
            print(json.dumps(r), flush=True)
        else:
            print(f"{kind:<8}{fast:>10.3f}{slow:>10.3f}{ratio:>8.1f}", flush=True)


if __name__ == "__main__":
    main()
