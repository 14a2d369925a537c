"""Data generation on Dask against the local process pool, and what one task costs on Dask.

Start a scheduler and workers first (e.g. `dask scheduler` and two `NUMBA_NUM_THREADS=1
dask worker ADDRESS --nthreads 1` in other shells), then

    python benchmarks/bench_dist.py tcp://127.0.0.1:8786 [--scene quad3] [--trajectories 200] [--repeats 2]

For each repeat, in alternating order: `generate` on the local pool of 2 processes and
`generate --scheduler ADDRESS` (both from a cold start: pool processes or client
connection included), then the ratio dask / pool; the file contents are checked equal.
Then the task overhead: a round trip of an empty task that takes the shared job (one at a
time: latency) and 200 of them at once (throughput), against the mean seconds per chunk
of the generation.
"""
import argparse
import statistics
import time
from dataclasses import replace

import numpy as np

from data_gen import load_scene
from data_gen.simulate import generate
from mpnode.runs.executors import chunk_ranges, open_executor


def _noop(job, chunk):
    return len(chunk)


def timed_generate(scene, scheduler):
    t = time.perf_counter()
    traj = generate(scene, workers=2, scheduler=scheduler)
    return time.perf_counter() - t, traj


def task_overhead(scheduler, n=200):
    job = {"payload": np.zeros(1000)}
    with open_executor(scheduler, 2) as farm:
        shared = farm.share(job)
        farm.submit(_noop, shared, range(1)).result()  # warm
        t = time.perf_counter()
        for i in range(20):
            farm.submit(_noop, shared, range(i, i + 1)).result()
        latency = (time.perf_counter() - t) / 20
        t = time.perf_counter()
        futures = [farm.submit(_noop, shared, range(i, i + 1)) for i in range(n)]
        for f in futures:
            f.result()
        throughput = (time.perf_counter() - t) / n
    return latency, throughput


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scheduler")
    p.add_argument("--scene", default="quad3")
    p.add_argument("--trajectories", type=int, default=200)
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args()
    scene = replace(load_scene(args.scene), trajectories=args.trajectories)
    ratios, rows = [], []
    for r in range(args.repeats):
        order = ((None, args.scheduler) if r % 2 == 0 else (args.scheduler, None))
        times = {}
        for sched in order:
            times[sched], traj = timed_generate(scene, sched)
            times[sched, "x"] = traj.x
        assert np.array_equal(times[None, "x"], times[args.scheduler, "x"])
        ratios.append(times[args.scheduler] / times[None])
        rows.append((times[None], times[args.scheduler]))
        print(f"repeat {r}: pool {times[None]:.2f} s, dask {times[args.scheduler]:.2f} s, "
              f"ratio {ratios[-1]:.3f}", flush=True)
    chunks = len(chunk_ranges(args.trajectories, 2, 10))
    pool = statistics.median(t for t, _ in rows)
    print(f"{args.scene} B={args.trajectories}: pool median {pool:.2f} s, dask median "
          f"{statistics.median(t for _, t in rows):.2f} s, median ratio dask/pool {statistics.median(ratios):.3f}; "
          f"{chunks} chunks, {2 * pool / chunks:.2f} s of work per chunk")
    latency, throughput = task_overhead(args.scheduler)
    print(f"empty task carrying the shared job: {1e3 * latency:.1f} ms round trip one at a time, "
          f"{1e3 * throughput:.2f} ms per task 200 at once")


if __name__ == "__main__":
    main()
