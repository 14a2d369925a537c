"""The epoch around the engine: how much of a training epoch is engine time, and what the rest is.

A user sees epochs per second, not engine calls.  For each system this trains for a few
epochs on a generated file (1000 trajectories, the suite's size; `mpnode generate` makes
them if they are missing) with `mpnode.runs.train`'s defaults, writing the model, log
and checkpoint as the command does, and splits the wall time of each epoch into
- engine: the compiled calls (forward rollouts, their VJP, validation rollouts);
- the rest: batching, the NumPy loss, clipping, Adam, validation bookkeeping, logging and
  checkpoint writes.
Medians over the epochs after the first (which loads the kernels).

    python benchmarks/bench_epoch.py [--epochs 6] [--data DIR] [--json]
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from mpnode.engine.codegen import ask_for_wide_vectors

SYSTEMS = {"coupled_pendulum": {}, "lorenz3": {"self_messages": True}, "gene16_ba_multi": {},
           "kuramoto10_ba": {"message_dim": 7}}
ENTRY_POINTS = ("rollout_blocks", "rollout_stagewise", "vjp_blocks", "vjp_stagewise")


class EngineClock:
    """Wraps the kernels' entry points and adds up the time spent inside them."""

    def __init__(self):
        from mpnode.engine import kernels

        self.seconds = 0.0
        for name in ENTRY_POINTS:
            setattr(kernels, name, self._timed(getattr(kernels, name)))

    def _timed(self, fn):
        def call(*args):
            t0 = time.perf_counter()
            try:
                return fn(*args)
            finally:
                self.seconds += time.perf_counter() - t0
        return call


def data_file(folder, scene):
    path = os.path.join(folder, f"{scene}.h5")
    if not os.path.exists(path):
        subprocess.run([sys.executable, "-c", "from cli.main import main; main()", "generate", scene, "-o", path,
                        "--trajectories", "1000"], check=True)
    return path


def measure(scene, options, epochs, folder):
    from mpnode import runs

    clock = EngineClock()
    marks = []

    def progress(record):
        marks.append((record["epoch"], time.perf_counter(), clock.seconds))

    with tempfile.TemporaryDirectory() as out:
        runs.train([data_file(folder, scene)], os.path.join(out, "m.h5"),
                   {"epochs": epochs, "batch_size": 128, **options}, progress=progress)  # the published batch
    rows = [(t1 - t0, e1 - e0) for (_, t0, e0), (_, t1, e1) in zip(marks[1:], marks[2:])]  # skip epoch 1
    wall = statistics.median(w for w, _ in rows)
    engine = statistics.median(e for _, e in rows)
    return {"system": scene, "epoch_ms": round(1e3 * wall, 1), "engine_ms": round(1e3 * engine, 1),
            "rest_ms": round(1e3 * (wall - engine), 1), "rest_share": round((wall - engine) / wall, 3)}


def main():
    ask_for_wide_vectors()  # as the `mpnode` command compiles the kernels (MPNODE_WIDE_VECTORS=0: numba's default)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "mpnode-bench-data"))
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    os.makedirs(args.data, exist_ok=True)
    if not args.json:
        print(f"{'system':<18}{'epoch ms':>10}{'engine ms':>11}{'rest ms':>9}{'rest':>7}")
    for scene, options in SYSTEMS.items():
        r = measure(scene, options, args.epochs, args.data)
        print(json.dumps(r) if args.json else f"{scene:<18}{r['epoch_ms']:>10.1f}{r['engine_ms']:>11.1f}"
              f"{r['rest_ms']:>9.1f}{100 * r['rest_share']:>6.1f}%", flush=True)


if __name__ == "__main__":
    main()
