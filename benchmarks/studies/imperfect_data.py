"""What imperfect data cost a model: clean and regular data against jittered times, 20 % missing
values, 5 % measurement noise and one state dimension never measured, at equal training time,
scored against the clean truth.

For each system and condition it generates training data (300 trajectories) and test data (100,
another seed) with `mpnode generate SCENE --jitter/--drop/--noise/--hide` (the test files keep the
clean truth), trains with the defaults for --minutes under the machine's experiment lock, and
evaluates with `mpnode eval --warmup 5` (every condition, so that all are scored on the same
steps 6..T).  Prints a markdown table: test nMSE against the truth, its ratio to the clean run's,
epochs and seconds per epoch.

    python benchmarks/studies/imperfect_data.py --out DIR [--systems coupled_pendulum,lorenz3]
        [--conditions clean,noise] [--minutes 5 | --epochs N] [--extra noise:--encoder-window=5] [--lock FILE]
"""
import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

#: the degradations (mpnode generate flags); "hidden" hides the dimension HIDE names per system
CONDITIONS = {"clean": [], "jitter": ["--jitter", "0.5"], "missing": ["--drop", "0.2"], "noise": ["--noise", "0.05"],
              "hidden": ["--hide", "{hide}"]}
SYSTEMS = {"coupled_pendulum": "coupled_pendulum", "lorenz3": "lorenz3", "kuramoto10": "kuramoto10_er"}
#: the dimension nobody measures in the "hidden" condition: a velocity where there is one
HIDE = {"coupled_pendulum": "1", "lorenz3": "2", "kuramoto10": "2"}
WARMUP = 5


def mpnode(*args, lock=None):
    cmd = (["flock", str(lock)] if lock else []) + ["mpnode", *map(str, args)]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode:
        sys.exit(f"{' '.join(cmd)} failed ({out.returncode}):\n{out.stderr[-2000:]}")
    return out.stdout


def data(folder, system, condition, trajectories, seed):
    path = folder / f"{system}_{condition}_B{trajectories}_s{seed}.h5"
    if not path.exists():
        flags = [f.format(hide=HIDE[system]) for f in CONDITIONS[condition]]
        mpnode("generate", SYSTEMS[system], "-o", path, "-B", trajectories, "--seed", seed, *flags)
    return path


def run(folder, system, condition, label, extra, budget, lock):
    """Train (unless done) and evaluate one cell: its row of the table as a dict."""
    train, test = data(folder, system, condition, 300, 11), data(folder, system, condition, 100, 12)
    model = folder / f"{system}_{label}.h5"
    if not model.exists():
        mpnode("train", train, "-o", model, *budget, *extra, lock=lock)
    report = json.loads(mpnode("eval", model, test, "--warmup", WARMUP, "--json", "--reference-sample", 0))
    log = [json.loads(line) for line in open(f"{model}.log.jsonl")][1:]
    return {"system": system, "condition": label, "nmse": report["nmse"], "nmse_per_dim": report["nmse_per_dim"],
            "epochs": len(log), "seconds_per_epoch": statistics.median(r["seconds"] for r in log)}


def chain_scene(folder, n):
    """A scene file of n coupled pendulums in a chain (each joined by springs to its neighbours)."""
    path = folder / f"pendulum_chain{n}.toml"
    edges = ", ".join(f"[{i}, {i + 1}]" for i in range(n - 1))
    path.write_text(f'description = "{n} pendulums in a chain, springs between neighbours"\n'
                    f'system = "spring_pendulums"\n\n[graph]\nbuilder = "edges"\nnodes = {n}\nedges = [{edges}]\n')
    return path


def chain(folder, budget, lock):
    """Clean regular data: trained on chains of 3, 4 and 5 pendulums (100 trajectories each) for
    ``budget`` (train flags), scored on fresh chains of 3 to 5 and zero-shot on a chain of 10."""
    train = [folder / f"chain{n}_train.h5" for n in (3, 4, 5)]
    for n, path in zip((3, 4, 5), train):
        if not path.exists():
            mpnode("generate", chain_scene(folder, n), "-o", path, "-B", 100, "--seed", 11)
    model = folder / "chain345.h5"
    if not model.exists():
        mpnode("train", *train, "-o", model, *budget, lock=lock)
    rows = []
    for n in (3, 4, 5, 10):
        test = folder / f"chain{n}_test.h5"
        if not test.exists():
            mpnode("generate", chain_scene(folder, n), "-o", test, "-B", 100, "--seed", 12)
        report = json.loads(mpnode("eval", model, test, "--json", "--reference-sample", 0))
        rows.append({"system": f"pendulum chain of {n}", "condition": "clean, trained on 3, 4, 5",
                     "nmse": report["nmse"]})
    return rows


def table(rows):
    lines = ["| system | condition | test nMSE vs truth | / clean | epochs | s per epoch |",
             "| --- | --- | --- | --- | --- | --- |"]
    clean = {r["system"]: r["nmse"] for r in rows if r["condition"] == "clean"}
    for r in rows:
        ratio = f"{r['nmse'] / clean[r['system']]:.2f}" if r["system"] in clean else "-"
        lines.append(f"| {r['system']} | {r['condition']} | {r['nmse']:.4g} | {ratio} | {r['epochs']} | "
                     f"{r['seconds_per_epoch']:.3f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for data, models and results.json")
    p.add_argument("--systems", default=",".join(SYSTEMS))
    p.add_argument("--conditions", default=",".join(CONDITIONS))
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--minutes", type=float, default=5.0, help="training budget of every model (wall time)")
    budget.add_argument("--epochs", type=int, help="training budget of every model in epochs instead (the same work "
                        "whatever else the machine runs; an epoch's cost is in the table)")
    p.add_argument("--extra", action="append", default=[], metavar="CONDITION:FLAG=VALUE",
                   help="also train CONDITION with this train flag (a variant row), e.g. noise:--encoder-window=5")
    p.add_argument("--lock", type=Path, help="hold this file's lock while a model trains (one timed run at a time)")
    p.add_argument("--chain", action="store_true", help="instead: chains of pendulums, trained on 3, 4 and 5 and "
                   "scored zero-shot on 10 (clean, regular data)")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    budget = ["--epochs", args.epochs] if args.epochs else ["--time-limit", f"{args.minutes}m"]
    if args.chain:
        for row in chain(args.out, budget, args.lock):
            print(json.dumps(row), flush=True)
        return
    cells = [(c, c, []) for c in args.conditions.split(",")]
    for spec in args.extra:
        condition, flag = spec.split(":", 1)
        cells.append((condition, f"{condition} {flag}", flag.split("=", 1)))
    rows = []
    for system in args.systems.split(","):
        for condition, label, extra in cells:
            rows.append(run(args.out, system, condition, label.replace(" ", "_").replace("=", ""), extra,
                            budget, args.lock))
            rows[-1]["condition"] = label
            print(json.dumps(rows[-1]), flush=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    print(table(rows))


if __name__ == "__main__":
    main()
