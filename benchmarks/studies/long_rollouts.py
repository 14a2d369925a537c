"""Rollouts that hold: the long-horizon training options against the recipe's defaults, scored on
the training horizon and on four times it.

For each system it generates training data (300 trajectories of T steps, seed 11) and two test
files of the same 100 initial states (seed 12): T steps, and 4T steps (`mpnode generate -T`).
Every variant trains with `mpnode train` for the same number of epochs (the same work whatever
else the machine runs; under --lock's lock when given), the baseline with the recipe's settings
and each other variant with one flag more; `mpnode eval --json` scores it on both test files.
Prints a markdown table and appends each row to DIR/results.jsonl: test nMSE over steps 1..T
and 1..4T, at step 4T, their ratio to the baseline's, the best epoch and the seconds per epoch.

    python benchmarks/studies/long_rollouts.py --out DIR [--systems coupled_pendulum,lorenz3]
        [--epochs 200] [--variant noise0.05:--input-noise=0.05] [--seed 0] [--train-horizon 100] [--lock FILE]
"""
import argparse
import json
import statistics
from pathlib import Path

from imperfect_data import mpnode  # the same runner: mpnode's command line, under the lock if given

SYSTEMS = {"coupled_pendulum": "coupled_pendulum", "lorenz3": "lorenz3", "kuramoto10": "kuramoto10_er",
           "gene16": "gene16_er"}
#: label -> train flags added to the recipe's
VARIANTS = {"baseline": [], "noise0.05": ["--input-noise", "0.05"], "window25": ["--train-window", "25"]}
HORIZON = 50


def data(folder, system, trajectories, seed, horizon):
    path = folder / f"{system}_B{trajectories}_s{seed}_T{horizon}.h5"
    if not path.exists():
        mpnode("generate", SYSTEMS[system], "-o", path, "-B", trajectories, "--seed", seed, "-T", horizon)
    return path


def run(folder, system, label, flags, epochs, seed, lock, train_horizon=HORIZON):
    """Train (unless done) and evaluate one variant: its row of the table as a dict.  A
    ``train_horizon`` other than HORIZON trains on longer trajectories of the same initial states."""
    train = data(folder, system, 300, 11, train_horizon)
    longer = "" if train_horizon == HORIZON else f"_T{train_horizon}"
    model = folder / f"{system}{longer}_{label}_seed{seed}.h5"
    if not model.exists():
        mpnode("train", train, "-o", model, "--epochs", epochs, "--seed", seed, *flags, lock=lock)
    row = {"system": system, "variant": label + longer, "seed": seed}
    for name, horizon in (("short", HORIZON), ("long", 4 * HORIZON)):
        report = json.loads(mpnode("eval", model, data(folder, system, 100, 12, horizon), "--json",
                                   "--reference-sample", 0))
        row[f"nmse_{name}"], row[f"last_{name}"] = float(report["nmse"]), float(report["nmse_last"])  # "inf" too
    with open(f"{model}.log.jsonl") as f:
        log = [json.loads(line) for line in f][1:]
    row.update(epochs=len(log), best_epoch=min(log, key=lambda r: r["val_loss"])["epoch"],
               seconds_per_epoch=statistics.median(r["seconds"] for r in log))
    return row


def ratio(row, base, key):
    """row[key] over the baseline's, or "-" without a baseline."""
    return f"{row[key] / base[key]:.2f}" if base else "-"


def table(rows):
    header = (f"| system | seed | variant | nMSE 1..{HORIZON} | / baseline | nMSE 1..{4 * HORIZON} | / baseline | "
              f"nMSE at step {4 * HORIZON} | best epoch | s per epoch |")
    lines = [header, "| --- " * 10 + "|"]
    base = {(r["system"], r["seed"]): r for r in rows if r["variant"] == "baseline"}
    for r in rows:
        b = base.get((r["system"], r["seed"]))
        lines.append(f"| {r['system']} | {r['seed']} | {r['variant']} | {r['nmse_short']:.4g} | "
                     f"{ratio(r, b, 'nmse_short')} | {r['nmse_long']:.4g} | {ratio(r, b, 'nmse_long')} | "
                     f"{r['last_long']:.4g} | "
                     f"{r['best_epoch']} of {r['epochs']} | {r['seconds_per_epoch']:.3f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for data, models and results.json")
    p.add_argument("--systems", default=",".join(SYSTEMS))
    p.add_argument("--epochs", type=int, default=200, help="training budget of every model, in epochs")
    p.add_argument("--seed", type=int, default=0, help="seed of the training runs (weights, split, noise)")
    p.add_argument("--variant", action="append", default=[], metavar="LABEL:FLAG=VALUE",
                   help="train this variant too (baseline plus the train flags), e.g. noise0.1:--input-noise=0.1; "
                        "default: " + ", ".join(VARIANTS))
    p.add_argument("--train-horizon", type=int, default=HORIZON, help="steps of the training trajectories (the "
                   f"test files stay {HORIZON} and {4 * HORIZON} steps): e.g. 100 with --train-window=50")
    p.add_argument("--lock", type=Path, help="hold this file's lock while a model trains (one timed run at a time)")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    variants = dict(VARIANTS)
    if args.variant:
        variants = {"baseline": []}
        for spec in args.variant:
            label, flags = spec.split(":", 1)
            variants[label] = [part for flag in flags.split(",") for part in flag.split("=", 1)]
    rows = []
    for system in args.systems.split(","):
        for label, flags in variants.items():
            rows.append(run(args.out, system, label, flags, args.epochs, args.seed, args.lock, args.train_horizon))
            print(json.dumps(rows[-1]), flush=True)
            with open(args.out / "results.jsonl", "a") as f:  # one line per row: several runs may share --out
                f.write(json.dumps(rows[-1]) + "\n")
    print(table(rows))


if __name__ == "__main__":
    main()
