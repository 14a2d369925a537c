"""Experiment 8 -- the learning-rate schedule at equal wall time: plateau against cosine.

`mpnode train`'s defaults with --schedule plateau (the paper's constant rate, cut after
`patience` flat epochs) or --schedule cosine (from lr to min_lr over the time budget), each
for the same wall time on pendulum, lorenz3, gene16 (five BA graphs) and kuramoto10; the
best-validation model of each is scored on fresh test trajectories.  The default schedule
should be the one that wins on all four.

    python benchmarks/paper/exp_schedule.py [--quick]
"""
from common import curve, evaluate_nmse, main, pyplot, run_line, table
from runs_shared import SCHEDULE_MINUTES as MINUTES
from runs_shared import SCHEDULE_SYSTEMS as SYSTEMS
from runs_shared import schedule_run as run_spec
from runs_shared import schedule_test as test_data

NAME = "schedule"
TITLE = "8. Learning-rate schedule at equal wall time (plateau vs cosine)"
SCHEDULES = ("plateau", "cosine")


def runs(mode):
    return [run_spec(mode, k, s) for k in SYSTEMS for s in SCHEDULES]


def data(mode):
    return [test_data(mode, k) for k in SYSTEMS]


def analyse(ctx):
    rows, numbers, wins = [], {}, 0
    plt = pyplot()
    fig, axes = plt.subplots(1, len(SYSTEMS), figsize=(4 * len(SYSTEMS), 3.2))
    for ax, key in zip(axes, SYSTEMS):
        test = ctx.data(test_data(ctx.mode, key))
        scores = {}
        for schedule in SCHEDULES:
            name = run_spec(ctx.mode, key, schedule).name
            res = ctx.result(name)
            ev = evaluate_nmse(ctx.model(name), test)
            scores[schedule] = ev.nmse
            numbers[name] = {"nmse": ev.nmse, "epochs": res["epochs"], "best_epoch": res["best_epoch"],
                             "best_val_loss": res["best_val_loss"], "run": run_line(res)}
            rows.append([key, schedule, res["epochs"], res["best_epoch"], res["best_val_loss"], ev.nmse])
            e, v = curve(res, "val_loss")
            ax.semilogy(e, v, label=schedule)
        wins += scores["cosine"] < scores["plateau"]
        ax.set(title=key, xlabel="epoch", ylabel="validation loss (Huber, z-scored)")
        ax.legend()
    numbers["cosine_wins"] = int(wins)
    link = ctx.figure(fig, "schedule_val_loss")
    budget = "3 epochs" if ctx.mode.quick else ctx.mode.wall_time(MINUTES)
    text = [
        f"Each run: `mpnode train` defaults (recipe auto) and the schedule, for {budget} (two trainings at a "
        "time, one numba thread each); test sets: fresh trajectories (seed 1) of the training scene.",
        "",
        table(["system", "schedule", "epochs", "best epoch", "best validation loss", "test nMSE"], rows),
        "",
        f"Cosine has the lower test nMSE on {wins} of {len(SYSTEMS)} systems.",
        "",
        link,
    ]
    return "\n".join(text), numbers


if __name__ == "__main__":
    main(["exp_schedule"], description=__doc__)
