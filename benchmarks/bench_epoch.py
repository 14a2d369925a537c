"""The epoch around the engine: what a training epoch spends where, and each part against its floor.

A user sees epochs per second, not engine calls.  For each workload this trains for a few epochs
on generated files (`mpnode generate` makes them if they are missing) with `mpnode.runs.train`,
writing the model, log and checkpoint as the command does, and splits the wall time of each epoch
into
- forward: the training batches' rollouts (their states kept for the reverse pass);
- adjoint: those rollouts' reverse passes (the exact gradient);
- validation: the other rollouts (the validation set's);
- the rest: batching, the NumPy loss, clipping, Adam, validation bookkeeping, logging and
  checkpoint writes.
The engine's parts include the Python around each kernel call.  Each is set beside its FLOP
floor: the field's multiply-adds x 2 x 4 RK4 stages x the node-steps it ran, at the rate of a
large SGEMM measured in the same run (the adjoint counts twice the forward's FLOPs); the epoch's
floor is their sum.  Medians over the epochs after the first (which loads the kernels).

Workloads: four systems at the batch of 128 the engine's figures use (1000 trajectories each),
and two as a user runs them, with the command's own recipe: `mpnode train coupled_pendulum` (the
scene's 300 trajectories) and `mpnode train quad3-5` (swarms of 3, 4 and 5 quadrotors).

    python benchmarks/bench_epoch.py [--epochs 6] [--data DIR] [--workloads a,b] [--json]
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from mpnode.engine.codegen import ask_for_wide_vectors

#: name -> (scene or scene set, trajectories to generate (None: the set's own counts), training options)
WORKLOADS = {
    "coupled_pendulum": ("coupled_pendulum", 1000, {"batch_size": 128}),
    "lorenz3": ("lorenz3", 1000, {"batch_size": 128, "self_messages": True}),
    "gene16_ba_multi": ("gene16_ba_multi", 1000, {"batch_size": 128}),
    "kuramoto10_ba": ("kuramoto10_ba", 1000, {"batch_size": 128, "message_dim": 7}),
    "train coupled_pendulum": ("coupled_pendulum", 300, {}),
    "train quad3-5": ("quad3-5", None, {}),
}
PARTS = ("forward", "adjoint", "validation")


class EngineClock:
    """Wall time, node-steps and FLOPs of the engine's calls, by part (`PARTS`)."""

    def __init__(self):
        from mpnode.engine import rollout

        self.seconds = dict.fromkeys(PARTS, 0.0)
        self.flops = dict.fromkeys(PARTS, 0.0)
        run, reverse = rollout._run, rollout._reverse

        def timed_run(spec, theta, z0, graph, u, n_steps, driver, keep_states, *rest):
            t0 = time.perf_counter()
            result = run(spec, theta, z0, graph, u, n_steps, driver, keep_states, *rest)
            part = "forward" if keep_states else "validation"
            self._add(part, t0, spec, z0.shape[0], result[5][0])
            return result

        def timed_reverse(spec, theta, plan, u, grid, states, *rest, **kwargs):
            t0 = time.perf_counter()
            result = reverse(spec, theta, plan, u, grid, states, *rest, **kwargs)
            self._add("adjoint", t0, spec, states.shape[1], grid[0], factor=2)
            return result

        self._originals = run, reverse
        rollout._run, rollout._reverse = timed_run, timed_reverse

    def close(self):
        """Put the engine's own entry points back."""
        from mpnode.engine import rollout

        rollout._run, rollout._reverse = self._originals

    def _add(self, part, t0, spec, nodes, substeps, factor=1):
        self.seconds[part] += time.perf_counter() - t0
        self.flops[part] += factor * 2 * field_macs(spec) * 4 * nodes * int(np.sum(substeps))

    def snapshot(self):
        return dict(self.seconds), dict(self.flops)


def field_macs(spec):
    """Multiply-adds of one field evaluation per node: its weight matrices' entries."""
    from mpnode.engine.layouts import field_shapes

    return sum(int(np.prod(shape)) for shape in field_shapes(spec).values() if len(shape) == 2)


def data_files(folder, workload):
    """The workload's trajectory files in ``folder``, generated the first time."""
    scene, trajectories, _ = WORKLOADS[workload]
    generate = [sys.executable, "-c", "from cli.main import main; main()", "generate", scene]
    if trajectories is None:  # a scene set: one file per member, in a folder of its own
        from data_gen import SETS

        target = os.path.join(folder, scene)
        paths = [os.path.join(target, f"{member}.h5") for member, _ in SETS[scene].members]
        if not all(os.path.exists(p) for p in paths):
            os.makedirs(target, exist_ok=True)  # `generate -o DIR/` needs DIR to exist
            subprocess.run(generate + ["-o", target + os.sep], check=True, stdout=sys.stderr)
        return paths
    path = os.path.join(folder, f"{scene}-{trajectories}.h5")
    if not os.path.exists(path):
        subprocess.run(generate + ["-o", path, "--trajectories", str(trajectories)], check=True, stdout=sys.stderr)
    return [path]


def measure(workload, epochs, folder, gflops):
    from mpnode import runs

    files = data_files(folder, workload)
    clock = EngineClock()
    marks = []

    def progress(record):
        marks.append((time.perf_counter(), *clock.snapshot()))

    try:
        with tempfile.TemporaryDirectory() as out:
            runs.train(files, os.path.join(out, "m.h5"), {"epochs": epochs, **WORKLOADS[workload][2]},
                       progress=progress)
    finally:
        clock.close()
    epochs = [(t1 - t0, {p: s1[p] - s0[p] for p in PARTS}, {p: f1[p] - f0[p] for p in PARTS})
              for (t0, s0, f0), (t1, s1, f1) in zip(marks[1:], marks[2:])]  # from epoch 2: epoch 1 loads the kernels
    wall = statistics.median(w for w, _, _ in epochs)
    r = {"workload": workload, "epoch_ms": round(1e3 * wall, 1), "epochs_per_10_min": round(600 / wall),
         "gemm_gflops": round(gflops, 1)}
    floor_total = 0.0
    for p in PARTS:
        ms = 1e3 * statistics.median(s[p] for _, s, _ in epochs)
        floor = 1e3 * statistics.median(f[p] for _, _, f in epochs) / (gflops * 1e9)
        floor_total += floor
        r.update({f"{p}_ms": round(ms, 1), f"{p}_floor_ms": round(floor, 2),
                  f"{p}_ratio": round(ms / floor, 2) if floor else None})
    r["rest_ms"] = round(r["epoch_ms"] - sum(r[f"{p}_ms"] for p in PARTS), 1)
    r.update({"floor_ms": round(floor_total, 2), "epoch_ratio": round(1e3 * wall / floor_total, 2)})
    return r


def main():
    ask_for_wide_vectors()  # as the `mpnode` command compiles the kernels (MPNODE_WIDE_VECTORS=0: numba's default)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "mpnode-bench-data"))
    ap.add_argument("--workloads", default=",".join(WORKLOADS),
                    help=f"comma-separated subset of {', '.join(WORKLOADS)}")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    os.makedirs(args.data, exist_ok=True)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_engine import gemm_gflops, machine

    gflops = gemm_gflops(np.float32)
    if not args.json:
        print(f"floor: float32 GEMM at {gflops:.0f} GFLOP/s; each part's ms and, in brackets, its ratio to its floor")
        print(f"{'workload':<24}{'epoch ms':>10}{'x':>6}{'forward':>15}{'adjoint':>15}{'validation':>15}{'rest':>8}"
              f"{'/10 min':>9}")
    for workload in args.workloads.split(","):
        r = measure(workload, args.epochs, args.data, gflops)
        if args.json:
            print(json.dumps({**r, "machine": machine()}), flush=True)
            continue
        parts = "".join(f"{r[p + '_ms']:>8.1f} ({r[p + '_ratio'] or 0:>4.1f})" for p in PARTS)
        print(f"{workload:<24}{r['epoch_ms']:>10.1f}{r['epoch_ratio']:>6.1f}{parts}{r['rest_ms']:>8.1f}"
              f"{r['epochs_per_10_min']:>9}", flush=True)


if __name__ == "__main__":
    main()
