"""Experiment 13 -- the batch size at equal wall time: Adam steps per epoch.

The paper's batch of 128 trajectories makes a training set of a few hundred trajectories a
few Adam steps per epoch, and a fine-tuning set of a few dozen one step (full-batch
descent).  A smaller batch costs about the same per epoch (the work is the trajectories,
not the batches) and takes more steps.  Each run: `mpnode train`'s defaults (recipe auto)
with --batch-size 128 or 32, for the same wall time, on pendulum, lorenz3, gene16 (five BA
graphs), kuramoto10 and quad3; and `mpnode finetune` of each system's batch-128 model
with --batch-size 128 or 8 on a small target set (Lorenz3 -> Lorenz10, Kuramoto10 BA -> ER,
quad3 -> quad6).  The best-validation model of each is scored on fresh test trajectories.

    python benchmarks/paper/exp_batch.py [--quick]
"""
from common import DataSpec, RunSpec, evaluate_nmse, main, pyplot, run_line, table
from runs_shared import SCHEDULE_SYSTEMS

NAME = "batch"
TITLE = "13. Batch size at equal wall time (Adam steps per epoch)"
MINUTES = 5
FINETUNE_MINUTES = 3
#: key: (scene, training trajectories full/quick): experiment 8's systems (and data) and quad3
SYSTEMS = {**SCHEDULE_SYSTEMS, "quad3": ("quad3", (500, 6))}
TRAIN_BATCHES = (128, 32)
#: target: (source system, scene, training trajectories full/quick)
TARGETS = {
    "lorenz10": ("lorenz3", "lorenz10", (50, 6)),
    "kuramoto10_er": ("kuramoto10", "kuramoto10_er", (50, 6)),
    "quad6": ("quad3", "quad6", (80, 6)),
}
FINETUNE_BATCHES = (128, 8)


def train_data(mode, scene, sizes):
    return DataSpec(scene, mode.pick(*sizes), 0)


def test_data(mode, scene):
    return DataSpec(scene, mode.pick(200, 5), 1)


def run_spec(mode, key, batch):
    scene, sizes = SYSTEMS[key]
    extra = (("batch_size", batch),) + mode.time_limit(MINUTES)
    return RunSpec(f"batch_{key}_b{batch}", (train_data(mode, scene, sizes),), mode.pick(100_000, 3), recipe="auto",
                   extra=extra)


def finetune_spec(mode, target, batch):
    source, scene, sizes = TARGETS[target]
    extra = (("batch_size", batch),) + mode.time_limit(FINETUNE_MINUTES)
    return RunSpec(f"batch_ft_{target}_b{batch}", (train_data(mode, scene, sizes),), mode.pick(100_000, 3),
                   init_from=run_spec(mode, source, TRAIN_BATCHES[0]).name, extra=extra)


def runs(mode):
    return ([run_spec(mode, k, b) for k in SYSTEMS for b in TRAIN_BATCHES]
            + [finetune_spec(mode, t, b) for t in TARGETS for b in FINETUNE_BATCHES])


def data(mode):
    return [test_data(mode, scene) for scene, _ in SYSTEMS.values()] + [test_data(mode, t[1]) for t in TARGETS.values()]


def elapsed_curve(res):
    """(minutes, validation loss) of a run: the epochs' end times when logged, else spread evenly."""
    h = [r for r in res["history"] if r.get("val_loss") is not None and r["epoch"] > 0]
    last = max(h[-1]["epoch"], 1)
    t = [r["elapsed"] / 60 if r.get("elapsed") is not None else r["epoch"] / last * res["seconds"] / 60
         for r in h]
    return t, [r["val_loss"] for r in h]


def score(ctx, rows, numbers, ax, label, names, test):
    """Evaluate the runs ``names`` (batch -> run name) on ``test``; return {batch: test nMSE}."""
    scores = {}
    for batch, name in names.items():
        res = ctx.result(name)
        ev = evaluate_nmse(ctx.model(name), test)
        scores[batch] = ev.nmse
        numbers[name] = {"batch_size": batch, "nmse": ev.nmse, "epochs": res["epochs"],
                         "best_epoch": res["best_epoch"], "best_val_loss": res["best_val_loss"], "run": run_line(res)}
        rows.append([label, batch, res["epochs"], res["best_epoch"], res["best_val_loss"], ev.nmse])
        ax.semilogy(*elapsed_curve(res), label=f"batch {batch}")
    ax.set(title=label, xlabel="minutes", ylabel="validation loss")
    ax.legend()
    return scores


def analyse(ctx):
    mode, plt = ctx.mode, pyplot()
    rows, numbers, wins = [], {}, {}
    fig, axes = plt.subplots(2, max(len(SYSTEMS), len(TARGETS)), figsize=(4 * len(SYSTEMS), 7), layout="constrained")
    for ax, key in zip(axes[0], SYSTEMS):
        names = {b: run_spec(mode, key, b).name for b in TRAIN_BATCHES}
        s = score(ctx, rows, numbers, ax, key, names, ctx.data(test_data(mode, SYSTEMS[key][0])))
        wins[key] = s[TRAIN_BATCHES[1]] < s[TRAIN_BATCHES[0]]
    for ax, target in zip(axes[1], TARGETS):
        source, scene, _ = TARGETS[target]
        names = {b: finetune_spec(mode, target, b).name for b in FINETUNE_BATCHES}
        s = score(ctx, rows, numbers, ax, f"{source} -> {target}", names, ctx.data(test_data(mode, scene)))
        wins[target] = s[FINETUNE_BATCHES[1]] < s[FINETUNE_BATCHES[0]]
    for ax in axes[1][len(TARGETS):]:
        ax.axis("off")
    numbers["smaller_batch_wins"] = {k: bool(v) for k, v in wins.items()}
    link = ctx.figure(fig, "batch_val_loss")
    budget = "3 epochs" if mode.quick else (f"{mode.wall_time(MINUTES)} (training) and "
                                            f"{mode.wall_time(FINETUNE_MINUTES)} (fine-tuning)")
    trained = [k for k in SYSTEMS if wins[k]]
    tuned = [k for k in TARGETS if wins[k]]
    text = [
        f"Each run: `mpnode train` defaults (recipe auto) with the batch size, or `mpnode finetune` of the system's "
        f"batch-{TRAIN_BATCHES[0]} model with it, for {budget} (two trainings at a time, one numba thread each); "
        "test sets: fresh trajectories (seed 1) of the training scene. The training sets are 70% of the trajectories "
        "(the rest validates).",
        "",
        table(["system", "batch size", "epochs", "best epoch", "best validation loss", "test nMSE"], rows),
        "",
        f"Batch {TRAIN_BATCHES[1]} has the lower test nMSE in training on {len(trained)} of {len(SYSTEMS)} systems "
        f"({', '.join(trained) or 'none'}); batch {FINETUNE_BATCHES[1]} in fine-tuning on {len(tuned)} of "
        f"{len(TARGETS)} ({', '.join(tuned) or 'none'}).",
        "",
        link,
    ]
    return "\n".join(text), numbers


if __name__ == "__main__":
    main(["exp_batch"], description=__doc__)
