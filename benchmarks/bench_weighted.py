"""What weighted neighbour sums cost: S5 (a random 6-regular graph of 20,000 nodes, T = 50)
with a weight on every edge against the same graph without, the calls alternating in one process.

A shared virtual host changes its cores' speed by itself over seconds (docs/evidence/steadiness.md),
so two cases timed one after the other, or in two processes, differ by as much as the weights
could.  Here each round times the unweighted call and then the weighted one, back to back, and
the figure is the median over the rounds of each round's ratio: a speed change slower than one
round cancels out of it.  float32, the engine's threads, after two warm-up calls of each.

    python benchmarks/bench_weighted.py [--kinds mpnode,l2s] [--rounds 15] [--json]
"""
import argparse
import json
import statistics

import numpy as np

from bench_engine import CASES, T, edge_weighted, machine, spec_for, timed_once
from mpnode.base.graph import block_diagonal
from mpnode.engine import forward
from mpnode.engine.codegen import ask_for_wide_vectors
from mpnode.engine.layouts import glorot_init
from mpnode.training.losses import value_and_grad


def graphs():
    """S5's graph, and the same graph with bench_engine's S5w weights."""
    plain = block_diagonal([CASES["S5"]["graph"]()])
    return plain, edge_weighted(plain)


def paired(plain_call, weighted_call, rounds):
    """(plain ms, weighted ms, weighted / plain): medians over ``rounds`` back-to-back pairs."""
    for _ in range(2):
        plain_call(), weighted_call()
    pairs = [(1e3 * timed_once(plain_call), 1e3 * timed_once(weighted_call)) for _ in range(rounds)]
    return (statistics.median(p for p, _ in pairs), statistics.median(w for _, w in pairs),
            statistics.median(w / p for p, w in pairs))


def run(kind, rounds, dtype=np.float32):
    spec = spec_for("S5", kind)
    plain, weighted = graphs()
    theta = glorot_init(spec, seed=0, dtype=dtype)
    x = np.random.default_rng(1).standard_normal((T + 1, plain.n_nodes, CASES["S5"]["dx"])).astype(dtype)
    row = {"kind": kind, "dtype": np.dtype(dtype).name, "nodes": plain.n_nodes, "edges": plain.n_edges,
           "rounds": rounds}
    for what, call in (("rollout", lambda g: forward(spec, theta, x[0], g, n_steps=T)),
                       ("train_step", lambda g: value_and_grad(spec, theta, x, g))):
        p, w, ratio = paired(lambda: call(plain), lambda: call(weighted), rounds)
        row.update({f"{what}_ms": round(p, 2), f"{what}_weighted_ms": round(w, 2),
                    f"{what}_weighted_over_plain": round(ratio, 3)})
    row["machine"] = machine()
    return row


def main():
    ask_for_wide_vectors()  # as the `mpnode` command compiles the kernels
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", default="mpnode,l2s", help="comma-separated model kinds: mpnode, l2s")
    ap.add_argument("--rounds", type=int, default=15, help="pairs of calls timed (after two warm-up pairs)")
    ap.add_argument("--json", action="store_true", help="one JSON object per kind")
    args = ap.parse_args()
    for kind in args.kinds.split(","):
        r = run(kind, args.rounds)
        if args.json:
            print(json.dumps(r), flush=True)
        else:
            print(f"{kind:<7} rollout {r['rollout_ms']:8.1f} ms, weighted {r['rollout_weighted_ms']:8.1f} ms: "
                  f"{r['rollout_weighted_over_plain']:.3f}x   training step {r['train_step_ms']:8.1f} ms, weighted "
                  f"{r['train_step_weighted_ms']:8.1f} ms: {r['train_step_weighted_over_plain']:.3f}x")


if __name__ == "__main__":
    main()
