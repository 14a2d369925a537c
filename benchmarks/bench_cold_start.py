"""How long a new user waits: `mpnode train coupled_pendulum -o model.h5` to its first epoch, and
`mpnode eval` of the saved model, each with an empty numba cache and then with the cache warm.

    python benchmarks/bench_cold_start.py [--tree PATH] [--json OUT]

Each command runs in a fresh folder with its own NUMBA_CACHE_DIR (empty for the cold runs), from
the source tree ``--tree`` (default: this checkout), as the `mpnode` command would.  "Epoch 1" is
the moment the run's log (model.h5.log.jsonl) holds its epoch-1 line, from the command's start,
data generation included; the run is then stopped with Ctrl-C.  Nothing else should run meanwhile:
the figures are compile times on all of the machine's cores.
"""
import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = "from cli.main import main; main()"


def mpnode(tree, cache, cwd, *args, **popen):
    """Start `mpnode *args` from source tree ``tree`` with numba's cache in ``cache``."""
    env = dict(os.environ, PYTHONPATH=str(tree), NUMBA_CACHE_DIR=str(cache))
    return subprocess.Popen([sys.executable, "-c", CLI, *args], cwd=cwd, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **popen)


def seconds_to_epoch_1(tree, cache, cwd, timeout=1800):
    """Seconds from the start of `mpnode train coupled_pendulum -o model.h5` until its log holds
    epoch 1; the run is then interrupted (it saves the model it has)."""
    log = Path(cwd) / "model.h5.log.jsonl"
    log.unlink(missing_ok=True)
    start = time.perf_counter()
    proc = mpnode(tree, cache, cwd, "train", "coupled_pendulum", "-o", "model.h5")
    while time.perf_counter() - start < timeout:
        if proc.poll() is not None:
            raise RuntimeError(f"train ended before epoch 1: {proc.stderr.read()[-2000:]}")
        if log.exists() and any(json.loads(line).get("epoch") == 1 for line in log.read_text().splitlines()
                                if line.strip()):
            took = time.perf_counter() - start
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=600)
            return took
        time.sleep(0.1)
    proc.kill()
    raise RuntimeError(f"no epoch 1 within {timeout} s")


def seconds_to_run(tree, cache, cwd, *args):
    start = time.perf_counter()
    proc = mpnode(tree, cache, cwd, *args)
    _, err = proc.communicate()
    if proc.returncode:
        raise RuntimeError(f"mpnode {' '.join(args)} failed: {err[-2000:]}")
    return time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tree", default=str(Path(__file__).resolve().parents[1]), help="the source tree to time")
    parser.add_argument("--json", help="write the figures here as JSON")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        train_cache, eval_cache, cwd = (Path(tmp) / name for name in ("train-cache", "eval-cache", "work"))
        cwd.mkdir()
        rows = {"train to epoch 1, empty cache": seconds_to_epoch_1(args.tree, train_cache, cwd),
                "train to epoch 1, cache warm": seconds_to_epoch_1(args.tree, train_cache, cwd)}
        seconds_to_run(args.tree, train_cache, cwd, "generate", "coupled_pendulum", "-o", "test.h5", "-B", "100",
                       "--seed", "7")
        rows["eval, empty cache"] = seconds_to_run(args.tree, eval_cache, cwd, "eval", "model.h5", "test.h5")
        rows["eval, cache warm"] = seconds_to_run(args.tree, eval_cache, cwd, "eval", "model.h5", "test.h5")
    for name, value in rows.items():
        print(f"{name:32s} {value:7.1f} s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"tree": args.tree, "seconds": rows}, f, indent=1)


if __name__ == "__main__":
    main()
