"""Experiment 5 -- message size (paper Fig. 8): Kuramoto10 (BA) with message dims 1, 3, 7, 13.

Same data, seed, epochs and settings as the Kuramoto run of experiment 1 (which is the dm = 3
run here); only the message dimension changes.

    python benchmarks/paper/exp_message_size.py [--quick]
"""
from common import curve, evaluate_nmse, flatness, main, pyplot, run_line, table
from runs_shared import messages_run, messages_test

NAME = "message_size"
TITLE = "5. Message size (paper Fig. 8): Kuramoto10 BA, dm = 1, 3, 7, 13"
DIMS = (1, 3, 7, 13)


def runs(mode):
    return [messages_run(mode, "kuramoto", False, dm) for dm in DIMS] + [messages_run(mode, "kuramoto", True)]


def analyse(ctx):
    plt = pyplot()
    test = ctx.data(messages_test(ctx.mode, "kuramoto"))
    fig, ax = plt.subplots(figsize=(6, 3.6))
    rows, numbers = [], {}
    for i, spec in enumerate(runs(ctx.mode)):
        res = ctx.result(spec.name)
        ev = evaluate_nmse(ctx.model(spec.name), test)
        label = "zero messages" if spec.zero_messages else f"dm = {spec.message_dim}"
        e, v = curve(res, "val_loss")
        ax.plot(e, v, lw=1, color="k" if spec.zero_messages else f"C{i}", label=label)
        numbers[spec.name] = {"message_dim": 0 if spec.zero_messages else spec.message_dim, "test_nmse": ev.nmse,
                              "best_val_loss": res["best_val_loss"], "best_epoch": res["best_epoch"],
                              "val_improvement_last_20pct": flatness(res), "run": run_line(res)}
        rows.append([label, ev.nmse, ev.nmse_last, res["best_val_loss"], res["best_epoch"],
                     f"{100 * flatness(res):.1f}%", f"{res['seconds'] / 60:.1f}"])
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("validation loss")
    ax.set_title("Kuramoto10 BA: message size")
    ax.legend(fontsize=8)
    link = ctx.figure(fig, "message_size")
    text = [
        f"{test.n_trajectories} test trajectories (seed 1). Every run: "
        f"{run_line(ctx.result(runs(ctx.mode)[0].name)).split('; dm')[0]}.",
        "",
        table(["messages", "test nMSE", "nMSE at T", "best val loss", "best epoch", "val gain, last 20% of epochs",
               "train minutes"], rows),
        "",
        link,
    ]
    return "\n".join(text), numbers


if __name__ == "__main__":
    main(["exp_message_size"], description=__doc__)
