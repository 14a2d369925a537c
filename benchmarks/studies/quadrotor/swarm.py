"""The quadrotor swarm figure: a predicted swarm against the true one (top view, side view,
position error).

It lives beside its benchmark, not in mpnode.plot, because it knows the quadrotor system:
positions are x[..., 0:3] in metres and the load's path is the file's ``aux/load``.  The
library's figures (mpnode.plot: plot_eval, plot_simulation, plot_training) know no system.

usage: python benchmarks/studies/quadrotor/swarm.py TRUE.h5 PRED.h5 -o swarm.png [--trajectory 0] [--title ...]
(PRED.h5 from `mpnode eval MODEL TRUE.h5 --predictions PRED.h5`; needs the plot extra)
"""
import argparse

import numpy as np

from mpnode.data import read_trajectories
from mpnode.plot import check_output, save_figure


def plot_swarm(true_file, pred_file, trajectory=0, out="swarm.png", title=None, dpi=110):
    """A predicted quadrotor swarm against the true one: top view, side view and position error.

    true_file : trajectory file of the reference simulator (x (B, T+1, N, 13), optionally
    ``aux/load`` (B, T+1, 6));  pred_file : the model's predictions of the same trajectories.
    True paths solid, predicted dashed, one colour per quadrotor; circles mark the start,
    squares the true and crosses the predicted end.  The load is drawn from the TRUE file
    only (black): it is not a graph node, so the model never predicts it.  Grey lines are the
    true cables at the first and last step.  The third panel is each quadrotor's position
    error |r_pred - r_true| over time.  Writes ``out`` (atomically) and returns its path.
    """
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    check_output(out, "out")
    truth, pred = read_trajectories(true_file), read_trajectories(pred_file)
    if not 0 <= trajectory < min(truth.n_trajectories, pred.n_trajectories):
        raise IndexError(f"trajectory {trajectory} not in both files ({truth.n_trajectories} and "
                         f"{pred.n_trajectories} trajectories)")
    xt = np.asarray(truth.x[trajectory], dtype=np.float64)[..., 0:3]  # (T+1, N, 3)
    xp = np.asarray(pred.x[trajectory], dtype=np.float64)[..., 0:3]
    if xt.shape != xp.shape:
        raise ValueError(f"true positions {xt.shape} and predicted {xp.shape} differ in shape")
    load = truth.aux.get("load")
    load = None if load is None else np.asarray(load[trajectory], dtype=np.float64)[:, 0:3]
    n = xt.shape[1]
    colors = [f"C{i % 10}" for i in range(n)]

    fig = Figure(figsize=(15.5, 4.9), dpi=dpi)
    axes = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.15, 1.15, 1]})
    for ax, (a, b), name in ((axes[0], (0, 1), "top view (x-y)"), (axes[1], (0, 2), "side view (x-z)")):
        _view(ax, xt, xp, load, a, b, colors)
        ax.set_title(name)
    _error(axes[2], xt, xp, float(truth.dt), colors)
    handles = [Line2D([], [], color="0.3", lw=1.8, label="quadrotor, true"),
               Line2D([], [], color="0.3", lw=1.6, ls="--", label="quadrotor, predicted (colours: right panel)"),
               Line2D([], [], color="k", lw=2,
                      label="load, true only (not a graph node: the model does not predict it)"),
               Line2D([], [], color="0.7", lw=0.8, label="true cables at the first and last step")]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8.5, frameon=False)
    head = title or f"{n} quadrotors, trajectory {trajectory}"
    fig.suptitle(f"{head}: true solid, predicted dashed (o start, \u25a1 true end, \u00d7 predicted end)", fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 0.95))
    return save_figure(fig, out)


def _view(ax, xt, xp, load, a, b, colors):
    """One projection (axes a, b) of the true and predicted paths, the load and its cables."""
    n = xt.shape[1]
    if load is not None:
        for k in (0, -1):
            for i in range(n):
                ax.plot([load[k, a], xt[k, i, a]], [load[k, b], xt[k, i, b]], color="0.7", lw=0.8, zorder=1)
        ax.plot(load[:, a], load[:, b], color="k", lw=2)
        ax.plot(load[0, a], load[0, b], "o", color="k", ms=5)
    for i in range(n):
        ax.plot(xt[:, i, a], xt[:, i, b], "-", color=colors[i], lw=1.8)
        ax.plot(xp[:, i, a], xp[:, i, b], "--", color=colors[i], lw=1.6)
        ax.plot(xt[0, i, a], xt[0, i, b], "o", color=colors[i], ms=5)
        ax.plot(xt[-1, i, a], xt[-1, i, b], "s", color=colors[i], ms=5)
        ax.plot(xp[-1, i, a], xp[-1, i, b], "x", color=colors[i], ms=7, mew=2)
    ax.set_xlabel("xyz"[a] + " (m)")
    ax.set_ylabel("xyz"[b] + " (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)


def _error(ax, xt, xp, dt, colors):
    t = np.arange(xt.shape[0]) * dt
    err = np.linalg.norm(xp - xt, axis=-1)  # (T+1, N)
    for i in range(xt.shape[1]):
        ax.plot(t, err[:, i], color=colors[i], lw=1.5, label=f"quad {i + 1}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("|r_pred - r_true| (m)")
    ax.set_title("position error")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=2)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("true_file")
    p.add_argument("pred_file")
    p.add_argument("-o", "--out", default="swarm.png")
    p.add_argument("--trajectory", type=int, default=0)
    p.add_argument("--title")
    a = p.parse_args(argv)
    print(plot_swarm(a.true_file, a.pred_file, a.trajectory, a.out, a.title))


if __name__ == "__main__":
    main()
