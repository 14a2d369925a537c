"""What a learned model costs in a control loop and out of mpnode: step Jacobians and exports.

1. ``Simulator.jacobians`` (dense and sparse) of an MP-NODE model (dx 4, du 2, dm 4, H 32, one
   substep) against one ``Simulator.step``, on N = 10 (complete graph) and N = 1000 (a random
   3-regular graph), B = 1: the colours (VJP copies per state dimension) and the time.
2. One step of a rollout as ``Simulator.step``, the ONNX export on onnxruntime (CPU provider,
   its default threads) and the exported NumPy module, on the same two graphs, float32 and float64,
   and how far the exports' step is from the Simulator's (largest difference over the largest |x|).

Medians of >= 7 timed calls after two warm-up calls.

    python benchmarks/bench_deploy.py [--json]
"""
import argparse
import importlib.util
import json
import os
import statistics
import tempfile
import time

import numpy as np

from mpnode import Model, Simulator
from mpnode.base.graph import Graph
from mpnode.engine.jacobians import reach_pattern, row_colours
from mpnode.export import write_numpy_module


def timed(call, n_min=7, min_total_s=1.0):
    call()
    call()
    times, start = [], time.perf_counter()
    while len(times) < n_min or time.perf_counter() - start < min_total_s:
        t0 = time.perf_counter()
        call()
        times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times)


def graphs():
    import networkx as nx

    return {10: Graph.complete(10), 1000: Graph.from_networkx(nx.random_regular_graph(3, 1000, seed=0))}


def model(dtype):
    return Model.create(4, 2, message_dim=4, hidden=32, dt=0.05, seed=0, dtype=dtype)


def jacobian_rows(dtype=np.float64):
    rows = []
    for n, g in graphs().items():
        m = model(dtype)
        sim = Simulator(m, g)
        sim.reset(np.random.default_rng(0).standard_normal((1, n, 4)))
        u = np.zeros((1, n, 2))
        sim.step(u)
        colours = int(row_colours(reach_pattern(m.spec, g)).max()) + 1
        step_ms = timed(lambda: sim.step(u))
        dense = timed(lambda: sim.jacobians(u), n_min=3) if n <= 100 else float("nan")
        sparse = timed(lambda: sim.jacobians(u, sparse=True), n_min=3)
        nnz = sim.jacobians(u, sparse=True)[0][0].nnz
        rows.append(dict(N=n, dtype=np.dtype(dtype).name, colours=colours, vjp_copies=colours * 4, step_ms=step_ms,
                         dense_ms=dense, sparse_ms=sparse, jx_nnz=nnz, jx_entries=(4 * n) ** 2))
    return rows


def export_rows():
    import onnxruntime

    from mpnode.export.onnx_model import onnx_rollout

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n, g in graphs().items():
            for dtype in (np.float32, np.float64):
                m = model(dtype)
                x0 = np.random.default_rng(0).standard_normal((1, n, 4)).astype(dtype)
                u = np.random.default_rng(1).standard_normal((1, 1, n, 2)).astype(dtype)
                sim = Simulator(m, g)
                sim.reset(x0)
                want = sim.step(u[:, 0])
                sim.reset(x0)
                session = onnxruntime.InferenceSession(onnx_rollout(m, g, 1).SerializeToString(),
                                                       providers=["CPUExecutionProvider"])
                path = os.path.join(tmp, f"step{n}{np.dtype(dtype).name}.py")
                write_numpy_module(m, g, path)
                spec = importlib.util.spec_from_file_location("step", path)
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
                scale = np.abs(want).max()
                onnx_x = session.run(None, {"x0": x0, "u": u})[0][:, 1]
                numpy_x = module.rollout(x0, 1, u)[:, 1]
                rows.append(dict(N=n, dtype=np.dtype(dtype).name, simulator_ms=timed(lambda: sim.step(u[:, 0])),
                                 onnx_rel_diff=float(np.abs(onnx_x - want).max() / scale),
                                 numpy_module_rel_diff=float(np.abs(numpy_x - want).max() / scale),
                                 onnx_ms=timed(lambda: session.run(None, {"x0": x0, "u": u})),
                                 numpy_module_ms=timed(lambda: module.rollout(x0, 1, u))))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = {"jacobians": jacobian_rows(), "export": export_rows()}
    if a.json:
        print(json.dumps(out, indent=1))
        return
    for r in out["jacobians"]:
        print(f"jacobians N={r['N']:5d} {r['dtype']}: {r['colours']} colours ({r['vjp_copies']} VJP copies), "
              f"step {r['step_ms']:.3f} ms, dense {r['dense_ms']:.1f} ms, sparse {r['sparse_ms']:.1f} ms, "
              f"Jx nnz {r['jx_nnz']} of {r['jx_entries']}")
    for r in out["export"]:
        print(f"one step N={r['N']:5d} {r['dtype']}: Simulator {r['simulator_ms']:.3f} ms, ONNX {r['onnx_ms']:.3f} ms, "
              f"NumPy module {r['numpy_module_ms']:.3f} ms; relative difference ONNX {r['onnx_rel_diff']:.1e}, "
              f"NumPy module {r['numpy_module_rel_diff']:.1e}")


if __name__ == "__main__":
    main()
