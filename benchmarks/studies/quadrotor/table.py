"""Print the results table (markdown) of benchmarks/studies/quadrotor/run.sh from its output folder.

usage: python table.py OUT
Reads OUT/eval_*.json (mpnode eval --json) and the training logs OUT/*.h5.log.jsonl.
"""
import json
import os
import sys


def log(path):
    rows = [json.loads(line) for line in open(path) if line.strip()]
    last = rows[-1]
    best = min((r for r in rows if r.get("val_loss") is not None), key=lambda r: r["val_loss"])
    return {"epochs": last["epoch"], "minutes": last["elapsed"] / 60, "best_epoch": best["epoch"],
            "best_val": best["val_loss"], "s_per_epoch": last["elapsed"] / max(last["epoch"], 1)}


def ev(path):
    if not os.path.exists(path):
        return None
    r = json.load(open(path))
    return r


def fmt(v):
    return "n/a" if v is None else (v if isinstance(v, str) else f"{v:.3g}")


def cell(r, key):
    if r is None:
        return "n/a"
    s = fmt(r[key])
    if r.get("first_bad_step") is not None:
        s += f" ({r['blown_up_trajectories']} blew up, first at step {r['first_bad_step']})"
    return s


def main(out):
    best = open(os.path.join(out, "best_dim.txt")).read().strip() if os.path.exists(os.path.join(out, "best_dim.txt")) else None
    print("| model | trained on | epochs (min, s/epoch) | best val. loss (epoch) | test data | nMSE mean 1..T | nMSE step T |")
    print("|---|---|---|---|---|---|---|")
    runs = [(f"q3_m{m}", f"quad3, message size {m}", "q3_train.h5") for m in (7, 13, 20)]
    runs += [("q6_finetuned", f"quad3 m={best} fine-tuned on quad6", "q6_train.h5"),
             ("q6_scratch", f"quad6 from scratch, m={best}", "q6_train.h5"),
             ("q6_finetuned_t", f"quad3 m={best} fine-tuned on quad6, time limit only", "q6_train.h5"),
             ("q6_scratch_t", f"quad6 from scratch, m={best}, time limit only", "q6_train.h5")]
    for name, label, data in runs:
        lp = os.path.join(out, name + ".h5.log.jsonl")
        if not os.path.exists(lp):
            continue
        L = log(lp)
        tr = f"{L['epochs']} ({L['minutes']:.1f} min, {L['s_per_epoch']:.2f} s)"
        bv = f"{L['best_val']:.4g} ({L['best_epoch']})"
        tests = [("quad3 fresh", "q3"), ("quad6 zero-shot", "q6")] if name.startswith("q3") else [("quad6", "q6")]
        for i, (tname, tk) in enumerate(tests):
            r = ev(os.path.join(out, f"eval_{name}.{tk}.json"))
            first = (label, data, tr, bv) if i == 0 else ("", "", "", "")
            print(f"| {first[0]} | {first[1]} | {first[2]} | {first[3]} | {tname} | {cell(r, 'nmse')} | {cell(r, 'nmse_last')} |")


if __name__ == "__main__":
    main(sys.argv[1])
