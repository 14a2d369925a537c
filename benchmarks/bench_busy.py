"""Training beside other work: the main job's epochs with one core taken by another process.

A user's machine is rarely idle.  This trains on the `coupled_pendulum` scene's data (its 300
trajectories, generated once) for a fixed number of epochs, idle and then beside a busy process
(a pure-Python loop, one core), with the kernels on every thread and on one thread, and reports
the training time (the log's ``elapsed`` at the last epoch) of each, as medians over ``--repeats``
fresh processes.  The figure that matters is busy / idle with every thread: how much of the
machine another process takes from a run.

    python benchmarks/bench_busy.py [--epochs 400] [--repeats 3] [--json OUT]

Run it on a warm kernel cache with nothing else running: it makes its own busy process.
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CLI = "from cli.main import main; main()"
BUSY = "while True: pass"


def mpnode(cwd, *args, threads=None):
    env = dict(os.environ)
    if threads is not None:
        env["NUMBA_NUM_THREADS"] = str(threads)
    done = subprocess.run([sys.executable, "-c", CLI, *args], cwd=cwd, env=env, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True)
    if done.returncode:
        raise RuntimeError(f"mpnode {' '.join(args)} failed: {done.stderr[-2000:]}")


def training_seconds(cwd, epochs, threads=None):
    """The log's training time at the last of ``epochs`` epochs on ``data.h5``."""
    for path in Path(cwd).glob("model.h5*"):  # a fresh run, not a resumed one
        path.unlink()
    mpnode(cwd, "train", "data.h5", "-o", "model.h5", "--epochs", str(epochs), threads=threads)
    log = Path(cwd) / "model.h5.log.jsonl"
    lines = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    return max(line["elapsed"] for line in lines if "elapsed" in line)


def measure(cwd, epochs, repeats, busy, threads=None):
    """Median training seconds over ``repeats`` runs, beside a busy process if ``busy``."""
    hog = subprocess.Popen([sys.executable, "-c", BUSY]) if busy else None
    try:
        return statistics.median(training_seconds(cwd, epochs, threads) for _ in range(repeats))
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--epochs", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", help="write the figures here as JSON")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_engine import machine

    with tempfile.TemporaryDirectory() as cwd:
        mpnode(cwd, "generate", "coupled_pendulum", "-o", "data.h5", "-B", "300")
        rows = {}
        for busy in (False, True):
            for threads in (None, 1):
                name = f"{'busy' if busy else 'idle'}, {'one thread' if threads else 'every thread'}"
                rows[name] = measure(cwd, args.epochs, args.repeats, busy, threads)
                print(f"{name:28s} {rows[name]:7.2f} s", flush=True)
    ratio = rows["busy, every thread"] / rows["idle, every thread"]
    print(f"busy / idle, every thread: {ratio:.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": machine(), "epochs": args.epochs, "seconds": rows, "busy_ratio": ratio}, f, indent=1)


if __name__ == "__main__":
    main()
