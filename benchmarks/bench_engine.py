"""Time mpnode's rollout and training step (loss + exact gradient, no optimiser) on S1-S6.

S1-S5 are the workloads of the peer harness (torch / JAX; same graphs, sizes, dt = 0.05,
T = 50, classic RK4) so that the figures compare with it; S5w is S5 with a weight on every edge
(uniform in [0.5, 1.5]: what weighted neighbour sums cost).  For each case and model kind
it prints the FLOP floor -- the field's multiply-adds x 4 stages x steps x nodes at the
rate of a large GEMM *measured in the same run* (the training step counts 3x the
forward) -- and our ratio to it.  Medians of >= 7 timed calls after warm-up; float32 and
2 threads unless told otherwise.  ``recomp``: the training step with every step's stages
recomputed in the reverse pass, over the step with the forward's stage caches kept (the
engine's choice up to rollout.KEEP_CACHES_BYTES), measured in the same process.  Each JSON row
names its machine (``machine``: the CPU's model and vector extensions, the BLAS, the threads)
beside the GEMM rate it was measured against, and ``host_probe_gflops``: the median rate of a
small one-core SGEMM timed between the timed calls (`host_probe`), which tells a case slowed by the
host (a shared machine's cores change speed by themselves) from one slowed by the engine.

Large graphs (rollout only, B = 1, T = 50; each case in a fresh process so that its
memory peak is its own): R200k and S6, random 6-regular graphs of 200,000 and 1,000,000
nodes (with S5's 20,000: time per node-step against size), and L6, a 1000 x 1000 grid
whose nodes are numbered at random (a graph with locality, as a user's file may number
it), run with the engine's locality ordering and without it (L6-none).  Peak memory is
the process's resident-set high-water mark (Linux VmHWM) over the rollouts, reset just
before them, so it counts everything resident -- Python, the kernels, the graph, the
rollout -- but not building the graph.  ``--train-big`` also times their training step (three
calls, the stages recomputed as the engine does at that size) with its own memory peak.
``--profile`` splits the large cases' time:
the rollout without neighbour sums (zero_messages: same dense work, no gather), the
dense layers alone, and one thread.

    python benchmarks/bench_engine.py [--json] [--cases S1,S2] [--kinds mpnode,l2s] [--dtype float32,float64]
                                      [--batch B]
    python benchmarks/bench_engine.py --cases S5,R200k,S6,L6,L6-none --kinds mpnode [--profile] [--train-big]
    python benchmarks/bench_engine.py --host-probe 60
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import networkx as nx
import numpy as np

from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import FieldSpec, forward, rollout
from mpnode.engine.codegen import ask_for_wide_vectors
from mpnode.engine.layouts import glorot_init
from mpnode.training.losses import value_and_grad


def machine():
    """Which machine a figure came from: the CPU's model, family and vector extensions (a VM may
    name every AMD EPYC alike; family 25 is Zen 3 or 4, 26 Zen 5), the BLAS numpy calls (for the
    GEMM floor) and the threads the kernels run on."""
    import platform

    from threadpoolctl import threadpool_info

    from mpnode.engine.backend import n_threads

    flags, model, ids = set(), platform.processor(), {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name":
                    model = value.strip()
                elif key == "flags":
                    flags = set(value.split())
                elif key in ("cpu family", "model") and key not in ids:
                    ids[key] = int(value) if value.strip().isdigit() else value.strip()
    except OSError:
        pass
    vectors = [f for f in ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512vl", "avx512_bf16", "amx_tile")
               if f in flags]
    blas = [{k: lib.get(k) for k in ("internal_api", "version", "architecture", "num_threads")}
            for lib in threadpool_info() if lib.get("user_api") == "blas"]
    return {"cpu": model, "cpu_family": ids.get("cpu family"), "cpu_model": ids.get("model"),
            "cores": os.cpu_count(), "vector_extensions": vectors, "blas": blas, "numba_threads": n_threads()}


def random_regular(d, n, seed=0):
    """A random d-regular graph by the pairing model: shuffle d stubs per node, pair them,
    and re-pair the stubs of self-loops and repeated pairs (with as many random good pairs)
    until none is left.  networkx's generator takes 45 s and 1.4 GB for a million nodes."""
    rng = np.random.default_rng(seed)
    stubs = np.repeat(np.arange(n, dtype=np.int64), d)
    rng.shuffle(stubs)
    pairs = stubs.reshape(-1, 2)
    for _ in range(100):
        lo, hi = pairs.min(axis=1), pairs.max(axis=1)
        key = lo * n + hi
        order = np.argsort(key, kind="stable")
        bad = lo == hi
        bad[order[1:]] |= key[order[1:]] == key[order[:-1]]
        if not bad.any():
            return Graph.from_edges(n, pairs)
        good = np.flatnonzero(~bad)
        redo = np.concatenate([np.flatnonzero(bad), rng.choice(good, size=min(bad.sum(), len(good)), replace=False)])
        s = pairs[redo].ravel()
        rng.shuffle(s)
        pairs[redo] = s.reshape(-1, 2)
    raise RuntimeError(f"no simple {d}-regular pairing of {n} nodes")


def shuffled_grid(side, seed=0):
    """A side x side 4-neighbour grid with its nodes numbered in a random order."""
    ids = np.random.default_rng(seed).permutation(side * side).reshape(side, side)
    pairs = np.concatenate([np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], 1),
                            np.stack([ids[:-1].ravel(), ids[1:].ravel()], 1)])
    return Graph.from_edges(side * side, pairs)


CASES = {
    "S1": dict(label="lorenz3", N=3, dx=3, dm=3, B=128, graph=lambda: Graph.complete(3)),
    "S2": dict(label="lorenz10", N=10, dx=3, dm=3, B=128, graph=lambda: Graph.complete(10)),
    "S3": dict(label="gene8x8", N=64, dx=1, dm=3, B=32,
               graph=lambda: Graph.from_networkx(nx.barabasi_albert_graph(64, 32, seed=42))),
    "S4": dict(label="kuramoto10", N=10, dx=3, dm=7, B=128,
               graph=lambda: Graph.from_networkx(nx.barabasi_albert_graph(10, 5, seed=42))),
    "S5": dict(label="big", N=20000, dx=3, dm=3, B=1,
               graph=lambda: Graph.from_networkx(nx.random_regular_graph(6, 20000, seed=0))),
    "S5w": dict(label="big weighted", N=20000, dx=3, dm=3, B=1, weighted=True,
                graph=lambda: Graph.from_networkx(nx.random_regular_graph(6, 20000, seed=0))),
    "R200k": dict(label="rr6 200k", N=200_000, dx=3, dm=3, B=1, big=True, graph=lambda: random_regular(6, 200_000)),
    "S6": dict(label="rr6 1M", N=1_000_000, dx=3, dm=3, B=1, big=True, graph=lambda: random_regular(6, 1_000_000)),
    "L6": dict(label="grid 1M", N=1_000_000, dx=3, dm=3, B=1, big=True, graph=lambda: shuffled_grid(1000)),
    "L6-none": dict(label="grid 1M", N=1_000_000, dx=3, dm=3, B=1, big=True, ordering="none",
                    graph=lambda: shuffled_grid(1000)),
}
H, T, DT = 32, 50, 0.05


def timed(call, n_min=7, min_total_s=3.0, max_reps=30, warm=True, probes=None):
    """First call (compile or cache load + run), one more warm-up, then >= n_min timed calls (ms).
    ``probes``: a list that receives a `host_probe` after each timed call."""
    t0 = time.perf_counter()
    call()
    first = time.perf_counter() - t0
    if warm:
        call()
    times = []
    start = time.perf_counter()
    while len(times) < max_reps and (len(times) < n_min or time.perf_counter() - start < min_total_s):
        t0 = time.perf_counter()
        call()
        times.append(1e3 * (time.perf_counter() - t0))
        if probes is not None:
            probes.append(host_probe())
    return first, statistics.median(times), times


_PROBE = np.random.default_rng(3).random((256, 256)).astype(np.float32)


def host_probe(reps=8):
    """GFLOP/s of a fixed one-core SGEMM that stays in cache, now.  On a shared (virtual) host
    the cores' speed changes by itself over seconds; this rate, taken between a case's calls,
    says which speed the case ran at."""
    a = _PROBE
    _blas_pinned(lambda: [a @ a for _ in range(reps)])
    t0 = time.perf_counter()
    _blas_pinned(lambda: [a @ a for _ in range(reps)])
    return reps * 2 * a.shape[0] ** 3 / (time.perf_counter() - t0) / 1e9


def gemm_gflops(dtype, n=2048, reps=5):
    """The best rate of an (n x n) @ (n x n) product through numpy's BLAS on this machine, now."""
    rng = np.random.default_rng(0)
    a, b = rng.random((n, n)).astype(dtype), rng.random((n, n)).astype(dtype)
    a @ b
    best = min(timed_once(lambda: a @ b) for _ in range(reps))
    return 2 * n ** 3 / best / 1e9


def edge_weighted(graph):
    """The same graph with a weight on every edge, uniform in [0.5, 1.5]: what weighted sums cost."""
    return graph.reweighted(np.random.default_rng(2).uniform(0.5, 1.5, graph.n_edges))


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


def spec_for(case, kind, zero_messages=False):
    c = CASES[case]
    if kind == "l2s":
        return FieldSpec(kind="l2s", state_dim=c["dx"], hidden=H, dt=DT)
    return FieldSpec(state_dim=c["dx"], message_dim=c["dm"], hidden=H, dt=DT, zero_messages=zero_messages)


# ---------------------------------------------------------------------------
# Memory: the resident-set high-water mark, reset before what is measured
# ---------------------------------------------------------------------------
def _status_mb(field):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def reset_peak():
    """Reset VmHWM to the current RSS (Linux >= 4.0); False where that is not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def run_case(case, kind, dtype, gflops, profile=False, batch=None, train_big=False):
    c = CASES[case]
    big = c.get("big", False)
    spec = spec_for(case, kind)
    graph = block_diagonal([c["graph"]()] * (batch or c["B"]))
    if c.get("weighted"):
        graph = edge_weighted(graph)
    m = graph.n_nodes
    theta = glorot_init(spec, seed=0, dtype=dtype)
    x = np.random.default_rng(1).standard_normal((T + 1, m, c["dx"])).astype(dtype)
    ordering = c.get("ordering", "auto")
    rss_before = _status_mb("VmRSS")
    exact_peak = reset_peak()
    reps = dict(n_min=3, min_total_s=0, warm=False) if big else {}
    probes = []
    first_r, roll, _ = timed(lambda: forward(spec, theta, x[0], graph, n_steps=T, ordering=ordering), probes=probes,
                             **reps)
    peak = _status_mb("VmHWM")
    first_t, train, recomputed, train_peak = time_training(spec, theta, x, graph, big, train_big, probes)
    fl = 2 * macs_per_node(case, kind) * 4 * T * m / (gflops * 1e9) * 1e3
    r = {"case": case, "label": c["label"], "kind": kind, "dtype": np.dtype(dtype).name, "nodes": m,
         "edges": graph.n_edges, "ordering": ordering,
         "macs_per_node": macs_per_node(case, kind), "gemm_gflops": round(gflops, 1),
         "rollout_ms": round(roll, 3), "train_step_ms": round(train, 3),
         "ns_per_node_step": round(roll * 1e6 / (m * T), 1),
         "floor_ms": round(fl, 3), "train_floor_ms": round(3 * fl, 3),
         "rollout_ratio": round(roll / fl, 2), "train_ratio": round(train / (3 * fl), 2),
         "train_recomputed_ms": round(recomputed, 3), "recomputed_over_kept": round(recomputed / train, 2),
         "first_call_s": round(max(first_r, first_t) if not big else first_r, 2),
         "host_probe_gflops": round(statistics.median(probes), 1),
         "train_ns_per_node_step": round(train * 1e6 / (m * T), 1),
         "rss_before_mb": round(rss_before), "peak_rss_mb": round(peak) if exact_peak else None,
         "train_peak_rss_mb": round(train_peak) if train_peak is not None else None,
         "rollout_output_mb": round(x.nbytes / 2**20), "machine": machine()}
    if profile:
        r.update(stage_profile(case, kind, spec, theta, x[0], graph, ordering, roll))
    return r


def time_training(spec, theta, x, graph, big, train_big, probes):
    """(first call s, median ms, median ms recomputing the stages, peak RSS MB or None) of the
    training step; a large graph's only with ``train_big`` (three calls: minutes), which recomputes
    its stages anyway (no separate figure), with the memory peak of the steps alone."""
    nan = float("nan")
    if big and not train_big:
        return nan, nan, nan, None
    step = lambda: value_and_grad(spec, theta, x, graph)  # noqa: E731
    if big:
        exact = reset_peak()
        first, train, _ = timed(step, n_min=2, min_total_s=0, warm=False, probes=probes)
        return first, train, nan, _status_mb("VmHWM") if exact else None
    first, train, _ = timed(step, probes=probes)
    return first, train, train_recomputing(step), None


def train_recomputing(call):
    """The training step's median ms with the reverse pass recomputing every step's stages
    instead of reading the forward's kept caches (the engine's way for rollouts whose caches
    exceed rollout.KEEP_CACHES_BYTES), in the same process as the kept figure."""
    kept = rollout.KEEP_CACHES_BYTES
    rollout.KEEP_CACHES_BYTES = 0
    try:
        return timed(call)[1]
    finally:
        rollout.KEEP_CACHES_BYTES = kept


# ---------------------------------------------------------------------------
# Where the time goes on one large graph
# ---------------------------------------------------------------------------
def stage_profile(case, kind, spec, theta, x0, graph, ordering, full_ms):
    """Split a rollout (ms, T steps) into: the neighbour sums (the rollout minus the same
    rollout with zero_messages, which skips them), the dense layers alone (the MLP over
    every node's inputs, 4 x T times, in 256-row tiles on the same threads), and the rest
    (the stage buffers: inputs, RK combination, caches; barriers).  Also one thread."""
    import numba

    once = dict(n_min=3, min_total_s=0, warm=False)
    zspec = spec_for(case, kind, zero_messages=True)
    no_sum = timed(lambda: forward(zspec, theta, x0, graph, n_steps=T, ordering=ordering), **once)[1]
    V = np.random.default_rng(2).standard_normal((graph.n_nodes, spec.state_width)).astype(theta.dtype)
    sweeps = _mlp_sweeps_kernel()
    dense = timed(lambda: _blas_pinned(sweeps, theta, V, 4 * T), **once)[1]
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        one = timed(lambda: forward(spec, theta, x0, graph, n_steps=T, ordering=ordering), **once)[1]
    finally:
        numba.set_num_threads(threads)
    return {"no_sum_ms": round(no_sum, 1), "sum_ms": round(full_ms - no_sum, 1), "dense_ms": round(dense, 1),
            "rest_ms": round(no_sum - dense, 1), "one_thread_ms": round(one, 1)}


def _blas_pinned(fn, *args):
    from mpnode.engine.backend import single_threaded_blas

    with single_threaded_blas():
        fn(*args)


def _mlp_sweeps_kernel():
    """A compiled loop: the MP-NODE MLP over every row of V, n_sweeps times, 256-row tiles
    in parallel (as the stagewise driver tiles a graph)."""
    from numba import njit, prange

    from mpnode.engine.kernels.layers import JIT
    from mpnode.engine.kernels.mpnode_field import mlp_forward

    @njit(parallel=True, **dict(JIT, cache=False))
    def sweeps(theta, V, n_sweeps):
        M, dz = V.shape
        ntiles = (M + 255) // 256
        for _ in range(n_sweeps):
            for k in prange(ntiles):
                i0 = k * 256
                i1 = min(M, i0 + 256)
                H1T = np.empty((H, i1 - i0), V.dtype)
                H2T = np.empty((H, i1 - i0), V.dtype)
                mlp_forward(theta, V[i0:i1].reshape(dz, i1 - i0), H1T, H2T, dz)  # feature-major tile

    return sweeps


def run_isolated(case, kind, dtype, profile, train_big):
    """run_case in a fresh process (large graphs: the memory peak is the case's own)."""
    cmd = [sys.executable, os.path.abspath(__file__), "--one", case, "--kinds", kind, "--dtype", dtype]
    cmd += ["--profile"] * profile + ["--train-big"] * train_big
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def print_row(r):
    mem = f"{r['peak_rss_mb']:>8}" if r["peak_rss_mb"] is not None else f"{'-':>8}"
    print(f"{r['case'] + ' ' + r['label']:<18}{r['kind']:<8}{r['dtype'][5:]:<4}{r['nodes']:>9}"
          f"{r['rollout_ms']:>11.2f}{r['floor_ms']:>9.2f}{r['rollout_ratio']:>6.1f}"
          f"{r['train_step_ms']:>10.2f}{r['train_floor_ms']:>9.2f}{r['train_ratio']:>6.1f}"
          f"{r['ns_per_node_step']:>9.1f}{mem}{r['recomputed_over_kept']:>8.2f}", flush=True)
    if "sum_ms" in r:
        print(f"{'':<18}profile: no sums {r['no_sum_ms']:.0f} ms -> sums {r['sum_ms']:.0f}, dense layers "
              f"{r['dense_ms']:.0f}, rest {r['rest_ms']:.0f}; one thread {r['one_thread_ms']:.0f} ms", flush=True)


def watch_host(seconds):
    """Print `host_probe` every half second, and the spread of the rates (max / min)."""
    rates, start = [], time.perf_counter()
    while time.perf_counter() - start < seconds:
        rates.append(host_probe())
        print(f"{time.perf_counter() - start:6.1f} s  {rates[-1]:6.1f} GFLOP/s", flush=True)
        time.sleep(0.5)
    print(f"one-core SGEMM: median {statistics.median(rates):.1f} GFLOP/s, max / min {max(rates) / min(rates):.2f}")


def main():
    ask_for_wide_vectors()  # as the `mpnode` command compiles the kernels (MPNODE_WIDE_VECTORS=0: numba's default)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="S1,S2,S3,S4,S5", help=f"comma-separated subset of {', '.join(CASES)}")
    ap.add_argument("--kinds", default="mpnode,l2s", help="comma-separated model kinds: mpnode, l2s")
    ap.add_argument("--dtype", default="float32", help="float32, float64 or both, comma-separated")
    ap.add_argument("--profile", action="store_true", help="split the large cases' rollout time (see above)")
    ap.add_argument("--json", action="store_true", help="one JSON object per case")
    ap.add_argument("--batch", type=int, help="graphs per batch instead of each case's B (S1-S4)")
    ap.add_argument("--train-big", action="store_true",
                    help="also time the large graphs' training step (minutes each), with its own memory peak")
    ap.add_argument("--host-probe", type=float, metavar="SECONDS",
                    help="only time `host_probe` every half second for this long: does this machine change speed?")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: one case, JSON, in this process
    args = ap.parse_args()
    if args.host_probe is not None:
        watch_host(args.host_probe)
        return
    if args.one:
        dtype = np.dtype(args.dtype)
        print(json.dumps(run_case(args.one, args.kinds, dtype, gemm_gflops(dtype), args.profile,
                                  train_big=args.train_big)))
        return
    for name in args.dtype.split(","):
        dtype = np.dtype(name)
        gflops = gemm_gflops(dtype)
        if not args.json:
            print(f"floor: {dtype.name} GEMM at {gflops:.0f} GFLOP/s (2048^2, measured now); peak = VmHWM MB")
            print(f"{'case':<18}{'kind':<8}{'':<4}{'nodes':>9}{'rollout ms':>11}{'floor':>9}{'x':>6}"
                  f"{'train ms':>10}{'floor':>9}{'x':>6}{'ns/n-st':>9}{'peak':>8}{'recomp':>8}")
        for case in args.cases.split(","):
            for kind in args.kinds.split(","):
                if CASES[case].get("big"):
                    r = run_isolated(case, kind, dtype.name, args.profile, args.train_big)
                else:
                    r = run_case(case, kind, dtype, gflops, args.profile and case == "S5", args.batch)
                if args.json:
                    print(json.dumps(r), flush=True)
                else:
                    print_row(r)


if __name__ == "__main__":
    main()
