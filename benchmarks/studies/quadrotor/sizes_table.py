"""Print the tables of benchmarks/studies/quadrotor/sizes.sh (markdown) from its output folder.

usage: python sizes_table.py OUT
Reads OUT/<model>.<test>.json (mpnode eval --json), OUT/<model>.h5.log.jsonl (the training logs)
and OUT/<model>.h5.load (the machine's load before and after each timed run).
"""
import glob
import json
import os
import sys

#: the models sizes.sh makes, in the order of the tables, with what each is
MODELS = [("multi", "quad3 + quad4 + quad5 files (500 + 300 + 300), `mpnode train q3.h5 q4.h5 q5.h5`"),
          ("swarm", "the scene set, `mpnode train quad3-5`"),
          ("source_*", "quad3 only (500), `mpnode train q3.h5`"),
          ("finetuned_multi", "the quad3 + 4 + 5 model fine-tuned on 80 quad6, `mpnode finetune`"),
          ("finetuned_*", "a quad3 model fine-tuned on 80 quad6, `mpnode finetune`"),
          ("kept_norm", "the first quad3 model fine-tuned so, `--keep-norm`")]
STEPS = (1, 5, 10, 20, 50)


def g(v):
    return v if isinstance(v, str) else f"{v:.3g}"


def run_of(out, name):
    """(epochs, minutes, 'load before -> after') of the timed run that made OUT/name.h5."""
    log = [json.loads(line) for line in open(os.path.join(out, name + ".h5.log.jsonl")) if line.strip()]
    loads = [line.split("load average:")[1].split(",")[0].strip()
             for line in open(os.path.join(out, name + ".h5.load")) if "load average" in line]
    return log[-1]["epoch"], log[-1]["elapsed"] / 60, " -> ".join(loads)


def report(out, name, test):
    path = os.path.join(out, f"{name}.{test}.json")
    return json.load(open(path)) if os.path.exists(path) else None


def names(out):
    found = []
    for pattern, what in MODELS:
        for path in sorted(glob.glob(os.path.join(out, pattern + ".h5"))):
            found.append((os.path.basename(path)[:-3], what))
    return found


def main(out):
    models = names(out)
    tests = [t for t in ("q6_test", "q8_test") if any(report(out, n, t) for n, _ in models)]
    hold = {t: next(report(out, n, t) for n, _ in models if report(out, n, t))["hold"] for t in tests}
    print("| model | trained on | epochs (minutes) | load (1-min average, before -> after) | "
          + " | ".join(f"{t} nMSE (last step)" for t in tests) + " |")
    print("| --- | --- | --- | --- |" + " --- |" * len(tests))
    print("| holding the initial state | | | | " + " | ".join(
        f"{g(hold[t]['nmse'])} ({g(hold[t]['nmse_last'])})" for t in tests) + " |")
    for n, what in models:
        epochs, minutes, load = run_of(out, n)
        cells = [(lambda r: "" if r is None else f"{g(r['nmse'])} ({g(r['nmse_last'])})")(report(out, n, t))
                 for t in tests]
        print(f"| {n} | {what} | {epochs} ({minutes:.1f}) | {load} | " + " | ".join(cells) + " |")
    for t in tests:
        print(f"\nPer step on {t} (steps {' / '.join(map(str, STEPS))}), and the first step where the model "
              "is not below holding the initial state:\n")
        print("| model | all | " + " | ".join(hold_groups(out, models, t)) + " | not below holding from |")
        print("| --- | --- |" + " --- |" * (len(hold_groups(out, models, t)) + 1))
        print("| holding the initial state | " + steps(hold[t]["nmse_per_step"]) + " | "
              + " | ".join(steps(hold_group(out, models, t, k)) for k in hold_groups(out, models, t)) + " | |")
        for n, _ in models:
            r = report(out, n, t)
            if r is None:
                continue
            first = r["hold"]["first_step_not_below"]
            print(f"| {n} | {steps(r['nmse_per_step'])} | "
                  + " | ".join(steps(r["groups"][k]["nmse_per_step"]) for k in r["groups"])
                  + f" | {'never' if first is None else first} |")


def steps(per_step):
    return " / ".join(g(per_step[s]) for s in STEPS if s < len(per_step))


def hold_groups(out, models, test):
    r = next(report(out, n, test) for n, _ in models if report(out, n, test))
    return list(r["groups"])


def hold_group(out, models, test, group):
    """Holding the initial state's nMSE per step over one state group (from the group's dimensions)."""
    r = next(report(out, n, test) for n, _ in models if report(out, n, test))
    return r["groups"][group]["hold_nmse_per_step"]


if __name__ == "__main__":
    main(sys.argv[1])
