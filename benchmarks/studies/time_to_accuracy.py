"""Time to accuracy: wall time for `mpnode train` to reach a validation nMSE, beside the same
recipe in torch + torchdiffeq (a finished study; benchmarks/README.md has its table).

For each system a trajectory file is generated once (1000 trajectories, the built-in scene,
as `mpnode generate` makes it; the same file for both sides).  Then, in turn and in fresh
processes (as a user runs them):
- mpnode: `mpnode.runs.train` (the function behind `mpnode train`) with the default recipe
  and options (Lorenz3 adds the horizon curriculum `mpnode train --help` advises for chaotic
  systems, CURRICULUM below), writing the model, log and checkpoint as the command does;
- torch: benchmarks/studies/tta_torch.py, the same recipe written in torch + torchdiffeq (run by
  another interpreter: torch is no dependency of mpnode).
Both report, after every epoch, the normalised MSE of the current weights on the same
validation split (the `val_nmse` of mpnode's training log, computed the same way on the
torch side), and stop at the first epoch whose nMSE is <= the last threshold, or at the
time limit.  The clock starts before the training data are read (imports excluded, reported
apart as startup) and stops at the end of that epoch's validation; an epoch is counted on
both sides the same way.  Each run is one process; with --lock FILE each run holds an
exclusive `flock` on FILE (several --lock: on each, in order), so runs of other jobs that
take the same lock do not share the cores with it; the sides alternate and their order
flips every repetition.

    python benchmarks/studies/time_to_accuracy.py --torch-python PYTHON_WITH_TORCH \\
        [--systems coupled_pendulum,lorenz3] [--reps 2] [--threads 2] [--time-limit 600] \\
        [--sides mpnode,torch] [--lock FILE] [--data DIR] [--json OUT] [--clock wall|cpu]
    python benchmarks/studies/time_to_accuracy.py --report OUT[,OUT2] --time-limit 600   # the table again

--seeds makes repetition k use seed k on both sides.  Without it every repetition repeats seed
0, which both sides run deterministically: it measures timing noise only.  On Lorenz3 the two
sides part after ~100 epochs (rounding differences grow in the chaotic training; see the README),
so the epochs a threshold takes vary from run to run and want several seeds.

--clock cpu tables the processes' CPU seconds instead of wall seconds: at --threads 1 on a
machine shared with other jobs, that is what an epoch costs (the time limit stays on wall time).

The table gives, per threshold, the median seconds of each side ("> limit" when a side did
not get there), their ratio torch / mpnode (the median of the per-repetition ratios), the
epochs each side needed, and each side's epochs per second (so one sees whether the ratio
comes from the speed of an epoch or from the number of epochs).
"""
import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time

T_IMPORT = time.perf_counter()
HERE = os.path.dirname(os.path.abspath(__file__))
#: system (built-in scene) -> validation nMSE thresholds (Lorenz3: what a 1-thread mpnode run reached in
#: its first 300 epochs, 0.05 at epoch 209 and 0.02 at 293; its validation nMSE jumps by 2-10x between epochs)
THRESHOLDS = {"coupled_pendulum": (0.01, 0.002), "lorenz3": (0.05, 0.02)}
#: system -> horizon curriculum: the pendulum takes `mpnode train`'s defaults; Lorenz3 is chaotic and
#: takes what `mpnode train --help` advises for chaotic systems (--horizon-curriculum 5,10,full, 100
#: epochs each): the defaults alone stalled near nMSE 0.42 (530 epochs, 11 minutes)
CURRICULUM = {"coupled_pendulum": (), "lorenz3": (5, 10)}


class Reached(Exception):
    """Raised from the progress callback: every threshold is reached (or the time is up)."""


def mpnode_worker(data, thresholds, time_limit, curriculum, seed=0):
    """Train with `mpnode.runs.train`'s defaults until the thresholds or the limit; print RESULT."""
    from mpnode import runs

    history, reached = [], {}
    state = {"status": "epochs"}
    t_ready = time.perf_counter()

    def progress(record):
        now = time.perf_counter() - t0
        nmse = record["val_nmse"]
        history.append([record["epoch"], round(now, 4), nmse, round(time.process_time() - c0, 4)])
        for thr in thresholds:
            if thr not in reached and nmse is not None and nmse <= thr and record["epoch"] > 0:
                reached[thr] = (record["epoch"], now)
        if len(reached) == len(thresholds):
            state["status"] = "reached"
            raise Reached
        if now >= time_limit:
            state["status"] = "time_limit"
            raise Reached

    with tempfile.TemporaryDirectory() as out:
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            options = {"time_limit": time_limit + 60, "curriculum": curriculum, "seed": seed,
                       "batch_size": 128}  # the paper's batch, as the torch peer's
            runs.train([data], os.path.join(out, "model.h5"), options, progress=progress)
        except Reached:
            pass
    return {"side": "mpnode", "data": os.path.abspath(data), "status": state["status"],
            "startup_seconds": t_ready - T_IMPORT, "reached": {f"{k:g}": {"epoch": e, "seconds": s}
                                                              for k, (e, s) in reached.items()},
            "history": history}


def run_side(side, data, thresholds, curriculum, args, seed=0):
    """One run in a fresh process (holding an exclusive flock on each --lock file): its RESULT record."""
    env = dict(os.environ)
    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[var] = str(args.threads)
    thr = ",".join(f"{t:g}" for t in thresholds)
    windows = ["--curriculum", ",".join(map(str, curriculum))] if curriculum else []
    if side == "mpnode":
        cmd = [sys.executable, os.path.abspath(__file__), "--worker", data, "--thresholds", thr,
               "--time-limit", str(args.time_limit), "--seed", str(seed)] + windows
    else:
        cmd = [args.torch_python, os.path.join(HERE, "tta_torch.py"), data, "--thresholds", thr,
               "--time-limit", str(args.time_limit), "--threads", str(args.threads), "--seed", str(seed)] + windows
    for lock in reversed(args.lock):  # flock A flock B cmd: A taken first
        cmd = ["flock", "-x", lock] + cmd
    wait = time.time()
    out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")]
    if out.returncode or not lines:
        raise SystemExit(f"{side} run failed ({out.returncode}):\n{out.stderr[-3000:]}")
    record = json.loads(lines[-1][len("RESULT "):])
    record.update(threads=args.threads, finished=time.strftime("%H:%M:%S"), block_seconds=time.time() - wait)
    return record


def data_file(folder, scene):
    """The scene's file in ``folder``, generated (1000 trajectories) if missing."""
    sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, where bench_epoch.py is
    from bench_epoch import data_file as make

    return make(folder, scene)


def summary(runs_, system, thresholds, limit, clock="wall"):
    """Rows per threshold: medians per side, the median ratio, epochs, epochs per second, on the
    ``clock`` ("wall", or "cpu": the process's CPU seconds, all threads)."""
    col = CLOCKS[clock]
    rows = []
    for thr in thresholds:
        key = f"{thr:g}"
        row = {"system": system, "threshold": thr, "clock": clock, "limit": limit}
        pairs = {}
        for side in ("mpnode", "torch"):
            mine = [r for r in runs_ if r["side"] == side]
            secs = [time_to(r, key, col) for r in mine]
            row[f"{side}_seconds"] = statistics.median(secs) if secs else None
            row[f"{side}_epochs"] = sorted({r["reached"][key]["epoch"] for r in mine if key in r["reached"]})
            row[f"{side}_epochs_per_s"] = statistics.median(epoch_rate(r, key, col) for r in mine) if mine else None
            row[f"{side}_startup_s"] = statistics.median(r["startup_seconds"] for r in mine) if mine else None
            pairs[side] = secs
        ratios = [t / m for m, t in zip(pairs["mpnode"], pairs["torch"]) if math.isfinite(m)]
        row["ratio"] = statistics.median(ratios) if ratios else None
        row["torch_estimate_s"] = estimate(runs_, key, col)
        rows.append(row)
    return rows


CLOCKS = {"wall": 1, "cpu": 3}


def reached_row(record, key):
    """The history row of the epoch that reached threshold ``key``, or None."""
    hit = record["reached"].get(key)
    return next(h for h in record["history"] if h[0] == hit["epoch"]) if hit else None


def time_to(record, key, col):
    row = reached_row(record, key)
    return row[col] if row else math.inf


def epoch_rate(record, key, col=1):
    """Epochs per second after epoch 0 (which holds reading, setup and the first validation),
    up to the threshold's epoch or the end of the run."""
    h = record["history"]
    end = reached_row(record, key) or h[-1]
    return (end[0] - h[0][0]) / (end[col] - h[0][col]) if end[0] > h[0][0] else float("nan")


def estimate(runs_, key, col=1):
    """When torch stopped at the limit but mpnode got there: torch's epoch-0 time plus the
    epochs mpnode needed at torch's own epochs per second (both sides do the same arithmetic
    from the same start, so they need about the same epochs: see `agreement`).  None otherwise."""
    torch_runs = [r for r in runs_ if r["side"] == "torch"]
    need = [r["reached"][key]["epoch"] for r in runs_ if r["side"] == "mpnode" and key in r["reached"]]
    if not need or not torch_runs or any(key in r["reached"] for r in torch_runs):
        return None
    epochs = statistics.median(need)
    return statistics.median(r["history"][0][col] + epochs / epoch_rate(r, key, col) for r in torch_runs)


def agreement(runs_):
    """(epoch, mpnode nMSE, torch nMSE, max relative difference up to it) at the last epoch both
    sides of the first repetition logged: how closely the two trainings follow each other."""
    first = {r["side"]: {h[0]: h[2] for h in r["history"]} for r in runs_ if r["rep"] == 0}
    if set(first) != {"mpnode", "torch"}:
        return None
    common = sorted(set(first["mpnode"]) & set(first["torch"]))
    rel = max(abs(first["torch"][e] / first["mpnode"][e] - 1) for e in common)
    last = common[-1]
    return last, first["mpnode"][last], first["torch"][last], rel


def fmt_seconds(s, limit):
    return f"> {limit:g}" if s is None or not math.isfinite(s) else f"{s:.1f}"


def table(rows):
    clock = rows[0]["clock"] if rows else "wall"
    out = [f"| system | val nMSE <= | mpnode s ({clock}) | torch s ({clock}) | torch / mpnode | epochs mpnode / torch "
           "| epochs/s mpnode / torch |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = "-" if r["ratio"] is None else f"{r['ratio']:.1f}x"
        if r["ratio"] is not None and not math.isfinite(r["ratio"]):
            ratio = f"> {r['limit'] / r['mpnode_seconds']:.1f}x"
        ep = f"{','.join(map(str, r['mpnode_epochs'])) or '-'} / {','.join(map(str, r['torch_epochs'])) or '-'}"
        rate = " / ".join("-" if r[f"{side}_epochs_per_s"] is None else f"{r[f'{side}_epochs_per_s']:.2f}"
                          for side in ("mpnode", "torch"))
        torch_s = fmt_seconds(r["torch_seconds"], r["limit"])
        if r.get("torch_estimate_s"):
            torch_s += f" (est. {r['torch_estimate_s']:.0f})"
        out.append(f"| {r['system']} | {r['threshold']:g} | {fmt_seconds(r['mpnode_seconds'], r['limit'])} | "
                   f"{torch_s} | {ratio} | {ep} | {rate} |")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default=",".join(THRESHOLDS))
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--time-limit", type=float, default=600.0, help="seconds per run")
    ap.add_argument("--torch-python", default=os.environ.get("TORCH_PYTHON", "python3"),
                    help="an interpreter with torch, torchdiffeq, h5py and numpy "
                         "(default: $TORCH_PYTHON, else python3)")
    ap.add_argument("--sides", default="mpnode,torch")
    ap.add_argument("--lock", action="append", default=[], metavar="FILE",
                    help="each run holds an exclusive flock on FILE (repeatable: each, in order)")
    ap.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "mpnode-bench-data"))
    ap.add_argument("--json", help="write every run's record and the summary here")
    ap.add_argument("--clock", default="wall", choices=sorted(CLOCKS),
                    help="the table's seconds: wall, or the processes' CPU time (for runs on a shared machine)")
    ap.add_argument("--report", help="only print the table of the runs saved in these --json files (comma "
                    "separated; the thresholds are applied again to each run's history)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--thresholds", help=argparse.SUPPRESS)
    ap.add_argument("--curriculum", default="", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--seeds", action="store_true",
                    help="repetition k trains with seed k (split, weights, noise, batch order) on both sides: "
                         "samples the training's own spread in epochs, not only the timing noise")
    args = ap.parse_args()
    if args.report:
        print(table(report(load_runs(args.report.split(",")), args.time_limit, args.clock)))
        return
    if args.worker:
        thresholds = [float(t) for t in args.thresholds.split(",")]
        curriculum = tuple(int(w) for w in args.curriculum.split(",") if w)
        record = mpnode_worker(args.worker, thresholds, args.time_limit, curriculum, args.seed)
        print("RESULT " + json.dumps(record), flush=True)
        return
    os.makedirs(args.data, exist_ok=True)
    sides, systems = args.sides.split(","), args.systems.split(",")
    files = {system: data_file(args.data, system) for system in systems}
    records = []
    for rep in range(args.reps):  # every system once before the next repetition: a cut run still has each
        for system in systems:
            for side in (sides if rep % 2 == 0 else sides[::-1]):
                seed = rep if args.seeds else 0
                r = run_side(side, files[system], THRESHOLDS[system], CURRICULUM[system], args, seed)
                r.update(system=system, rep=rep, seed=seed)
                records.append(r)
                print(f"{system} rep {rep} {side}: {r['status']}, reached {r['reached']}, "
                      f"{len(r['history']) - 1} epochs", file=sys.stderr, flush=True)
                if args.json:
                    save(args.json, records, [])
    rows = report(records, args.time_limit, args.clock)
    if args.json:
        save(args.json, records, rows)
    print(table(rows))


def report(records, limit, clock="wall"):
    """The summary rows of every system in ``records`` (and how closely the sides agree, on stderr)."""
    rows = []
    for system in dict.fromkeys(r["system"] for r in records):
        mine = [r for r in records if r["system"] == system]
        rows += summary(mine, system, THRESHOLDS[system], limit, clock)
        agree = agreement(mine)
        if agree:
            rows[-1]["agreement"] = agree
            print(f"{system}: validation nMSE at epoch {agree[0]}: mpnode {agree[1]:.6g}, torch {agree[2]:.6g} "
                  f"(largest relative difference up to it {agree[3]:.2g})", file=sys.stderr, flush=True)
    return rows


def load_runs(paths):
    """The runs of several --json files, each run's ``reached`` recomputed from its history for
    THRESHOLDS (the first epoch after 0 whose validation nMSE is <= each)."""
    records = []
    for path in paths:
        with open(path) as f:
            records += json.load(f)["runs"]
    for r in records:
        r["reached"] = {}
        for thr in THRESHOLDS[r["system"]]:
            hit = next((h for h in r["history"][1:] if h[2] is not None and h[2] <= thr), None)
            if hit:
                r["reached"][f"{thr:g}"] = {"epoch": hit[0], "seconds": hit[1]}
    return records


def save(path, records, rows):
    with open(path + ".tmp", "w") as f:
        json.dump({"runs": records, "summary": rows, "machine": machine()}, f, indent=1)
    os.replace(path + ".tmp", path)


def machine():
    """The CPU and platform, for the README."""
    import platform

    model = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), model)
    except OSError:
        pass
    return {"cpus": os.cpu_count(), "processor": model, "platform": platform.platform(),
            "python": platform.python_version()}


if __name__ == "__main__":
    main()
