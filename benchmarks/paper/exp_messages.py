"""Experiment 1 -- messages matter (paper Fig. 2, 3a, 4).

The coupled pendulum and Kuramoto10 on a BA graph, each trained twice from the same
initial weights and data: with messages, and with messages clamped to zero
(``--zero-messages``: every node then evolves on its own state alone).  Shows the training
and validation loss curves, predicted against true trajectories, the norm of every node's
outgoing message over time, and the test nMSE of both models.

    python benchmarks/paper/exp_messages.py [--quick]
"""
import numpy as np

from common import DataSpec, RunSpec, curve, evaluate_nmse, flatness, main, pyplot, run_line, table
from mpnode import numpy_engine

NAME = "messages"
TITLE = "1. Messages matter (paper Fig. 2, 3a, 4)"

SYSTEMS = {  # key: (scene, training trajectories full/quick, epochs full/quick)
    "pendulum": ("coupled_pendulum", (500, 12), (4000, 4)),
    "kuramoto": ("kuramoto10_ba", (500, 12), (1000, 4)),
}


def train_data(mode, key):
    scene, (b_full, b_quick), _ = SYSTEMS[key]
    return DataSpec(scene, mode.pick(b_full, b_quick), 0)


def test_data(mode, key):
    return DataSpec(SYSTEMS[key][0], mode.pick(200, 6), 1)


def run_spec(mode, key, zero, message_dim=3):
    """The run of ``key`` with messages (or zero messages); exp_message_size reuses it."""
    _, _, (e_full, e_quick) = SYSTEMS[key]
    suffix = "zero" if zero else f"dm{message_dim}"
    return RunSpec(f"{key}_{suffix}", (train_data(mode, key),), mode.pick(e_full, e_quick),
                   message_dim=message_dim, zero_messages=zero)


def runs(mode):
    return [run_spec(mode, k, zero) for k in SYSTEMS for zero in (False, True)]


def data(mode):
    return [test_data(mode, k) for k in SYSTEMS]


def message_trace(model, x0, graph, steps):
    """Predicted states and outgoing messages (data units / model units) of one trajectory.

    The engine keeps only x; the float64 NumPy path (the tests' reference) recomputes the
    messages (and must agree with the engine's x, which is checked).
    """
    xs, ms = numpy_engine.rollout(model.spec, model.theta.astype(np.float64), model.normalize_x(x0).astype(np.float64),
                                  graph, None, steps, with_messages=True)
    x = model.denormalize_x(xs)
    engine = model.rollout(x0, graph, steps=steps)
    scale = np.abs(x).max() + 1.0
    if not np.allclose(x, engine, atol=1e-3 * scale):
        raise AssertionError("the NumPy reference and the engine disagree on the prediction")
    return x, ms


def analyse(ctx):
    plt = pyplot()
    numbers, rows = {}, []
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    for ax, key in zip(axes, SYSTEMS):
        test = ctx.data(test_data(ctx.mode, key))
        for zero, style in ((False, "-"), (True, "--")):
            spec = run_spec(ctx.mode, key, zero)
            res = ctx.result(spec.name)
            ev = evaluate_nmse(ctx.model(spec.name), test)
            label = "zero messages" if zero else "messages"
            for what, color in (("train_loss", "C0"), ("val_loss", "C1")):
                e, v = curve(res, what)
                ax.plot(e, v, style, color=color, lw=1, label=f"{what.split('_')[0]}, {label}")
            numbers[spec.name] = {"test_nmse": ev.nmse, "test_nmse_last_step": ev.nmse_last,
                                  "best_val_loss": res["best_val_loss"], "best_epoch": res["best_epoch"],
                                  "epochs": res["epochs"], "val_improvement_last_20pct": flatness(res),
                                  "run": run_line(res)}
            rows.append([key, label, ev.nmse, ev.nmse_last, res["best_val_loss"], res["best_epoch"],
                         f"{100 * flatness(res):.1f}%"])
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.set_ylabel("Huber loss (normalised states)")
        ax.set_title(SYSTEMS[key][0])
        ax.legend(fontsize=7)
    loss_fig = ctx.figure(fig, "messages_loss")

    traj_fig, msg_fig = trajectory_figures(ctx)
    text = [
        "Each system is trained twice from the same initial weights, data and shuffles: with 3-dimensional",
        "messages, and with messages clamped to zero. Test nMSE is on fresh trajectories (seed 1), over",
        "steps 1..T of a full-horizon rollout from the true initial state.",
        "",
        table(["system", "model", "test nMSE", "nMSE at T", "best val loss", "best epoch",
               "val gain, last 20% of epochs"], rows),
        "",
        "Runs: " + "; ".join(f"**{n}**: {v['run']}" for n, v in numbers.items()) + ".",
        "",
        loss_fig, "", traj_fig, "", msg_fig,
    ]
    return "\n".join(text), numbers


def trajectory_figures(ctx):
    """Fig. 2 / 4: predicted vs true trajectories, and outgoing message norms over time."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(11, 6))
    mfig, maxes = plt.subplots(1, 2, figsize=(11, 3.4))
    for col, key in enumerate(SYSTEMS):
        test = ctx.data(test_data(ctx.mode, key))
        g = test.graphs[int(test.graph_index[0])]
        t = np.arange(test.horizon + 1) * test.dt
        truth = np.asarray(test.x[0])
        for row, zero in enumerate((False, True)):
            spec = run_spec(ctx.mode, key, zero)
            model = ctx.model(spec.name).copy(np.float64)
            x, m = message_trace(model, truth[0], g, test.horizon)
            ax = axes[row, col]
            nodes = range(min(3, test.n_nodes))
            for i in nodes:
                ax.plot(t, truth[:, i, 0], color=f"C{i}", lw=1.2, label=f"node {i} true")
                ax.plot(t, x[:, i, 0], "--", color=f"C{i}", lw=1.2, label=f"node {i} predicted")
            ax.set_title(f"{SYSTEMS[key][0]}, {'zero messages' if zero else 'messages'}: state 0")
            ax.set_xlabel("t")
            ax.legend(fontsize=6, ncol=2)
            if not zero:
                norms = np.linalg.norm(m, axis=2)  # (T+1, N)
                for i in range(test.n_nodes):
                    maxes[col].plot(t, norms[:, i], lw=1, label=f"node {i}" if i < 4 else None)
                maxes[col].set_title(f"{SYSTEMS[key][0]}: |outgoing message| per node")
                maxes[col].set_xlabel("t")
                maxes[col].legend(fontsize=6)
    fig.tight_layout()
    mfig.tight_layout()
    return ctx.figure(fig, "messages_trajectories"), ctx.figure(mfig, "messages_norms")


if __name__ == "__main__":
    main(["exp_messages"], description=__doc__)
