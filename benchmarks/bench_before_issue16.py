"""float32 S1-S4 against the engine as it was when issue 16 was filed (commit d84c069),
interleaved call by call in one process.

Timing two builds in alternating processes on a shared host measured the process, not the
code: the same S1 rollout took 6 to 20 ms from one process to the next.  Here both engines
run in one process (the old package copied under the name ``mpnode_old``; its imports are
relative), on the same graphs, inputs and weights, and each round times old and new back to
back, alternating which goes first.  The median of the per-round ratios is the figure.

    git worktree add /tmp/mpnode-d84c069 d84c069
    python benchmarks/bench_before_issue16.py /tmp/mpnode-d84c069 [--rounds 40] [--cases S1,S2,S3,S4]
"""
import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import bench_engine as bench
import networkx as nx
import numpy as np

from mpnode.base.graph import block_diagonal
from mpnode.engine import forward
from mpnode.engine.layouts import glorot_init
from mpnode.training.losses import value_and_grad


def import_old(checkout):
    """The package of an old checkout, importable as ``mpnode_old``."""
    root = Path(tempfile.mkdtemp(prefix="mpnode-old-"))
    shutil.copytree(Path(checkout) / "mpnode", root / "mpnode_old", ignore=shutil.ignore_patterns("__pycache__"))
    sys.path.insert(0, str(root))
    import mpnode_old.graph
    import mpnode_old.integrate
    return mpnode_old


def old_graph(old, case):
    """The case's graph built by the old package (its Graph class)."""
    G = old.graph.Graph
    return {"S1": lambda: G.complete(3), "S2": lambda: G.complete(10),
            "S3": lambda: G.from_networkx(nx.barabasi_albert_graph(64, 32, seed=42)),
            "S4": lambda: G.from_networkx(nx.barabasi_albert_graph(10, 5, seed=42))}[case]()


def calls_for(old, case):
    """{name: zero-argument call}: old and new rollout and training step of one case."""
    c = bench.CASES[case]
    spec = bench.spec_for(case, "mpnode")
    graph = block_diagonal([c["graph"]()] * c["B"])
    ograph = old.graph.block_diagonal([old_graph(old, case)] * c["B"])
    ospec = old.integrate.FieldSpec(c["dx"], 0, c["dm"], bench.H, bench.DT, 1)
    theta = glorot_init(spec, seed=0, dtype=np.float32)
    x = np.random.default_rng(1).standard_normal((bench.T + 1, graph.n_nodes, c["dx"])).astype(np.float32)
    return {"old_roll": lambda: old.integrate.rollout(ospec, theta, x[0], ograph, n_steps=bench.T),
            "new_roll": lambda: forward(spec, theta, x[0], graph, n_steps=bench.T),
            "old_train": lambda: old.integrate.loss_and_grad(ospec, theta, x, ograph),
            "new_train": lambda: value_and_grad(spec, theta, x, graph)}


def interleaved(calls, rounds):
    """ms per call, rounds x (old, new) back to back, the first of each pair alternating."""
    for f in calls.values():
        f()
        f()
    t = {k: [] for k in calls}
    for r in range(rounds):
        for what in ("roll", "train"):
            pair = ("old_" + what, "new_" + what)
            for k in (pair if r % 2 == 0 else pair[::-1]):
                t0 = time.perf_counter()
                calls[k]()
                t[k].append(1e3 * (time.perf_counter() - t0))
    return t


def summary(case, t, rounds):
    out = {"case": case, "rounds": rounds}
    for what in ("roll", "train"):
        o, n = t["old_" + what], t["new_" + what]
        ratios = [b / a for a, b in zip(o, n)]
        out[what] = {"old_min_ms": round(min(o), 3), "new_min_ms": round(min(n), 3),
                     "median_ratio": round(statistics.median(ratios), 3),
                     "ratio_quartiles": [round(v, 3) for v in statistics.quantiles(ratios, n=4)]}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("old_checkout", help="a checkout of commit d84c069 (its mpnode/ is copied, not changed)")
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--cases", default="S1,S2,S3,S4")
    args = ap.parse_args()
    old = import_old(args.old_checkout)
    for case in args.cases.split(","):
        print(json.dumps(summary(case, interleaved(calls_for(old, case), args.rounds), args.rounds)), flush=True)


if __name__ == "__main__":
    main()
