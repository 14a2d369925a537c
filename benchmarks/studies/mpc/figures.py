"""The MPC study's figures from its results files (needs the plot extra):

- quadrotor_mpc.png: one path's load under each controller against its reference, seen from
  above (x-y) and from the side (x-z), and the load's tracking error over time (a controller
  that lost the swarm ends in a cross);
- pendulum_mpc.png: one run's angles under each controller, with the target.

    python benchmarks/studies/mpc/figures.py [--dir DIR] [--path 0] [--run 0]

With --runs FILE:KEY ... (results files holding several runs under keys, as regularised/*.json)
it draws one quadrotor figure, to --out, of the controllers of those runs on one path: e.g. each
controller at its best setting.
"""
import argparse
import json
import os

import numpy as np

COLOURS = {"scene": "tab:green", "pd": "tab:green", "true": "tab:blue", "learned": "tab:red"}
LABELS = {"scene": "scene's controller", "pd": "PD", "true": "MPC, true equations",
          "learned": "MPC, learned model"}


def quadrotor(results, path, out, labels=LABELS):
    import matplotlib.pyplot as plt

    row = results["paths"][path]
    names = [n for n in ("scene", "true", "learned") if n in row]
    ref = np.array(row[names[0]]["reference"])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for ax, (i, j, title) in zip(axes[:2], ((0, 1, "load from above"), (0, 2, "load from the side"))):
        ax.plot(ref[:, i], ref[:, j], "k--", lw=1.5, label="reference")
        for n in names:
            load = np.array(row[n]["load"])
            lost = " (lost: x)" if row[n]["failure"] else ""
            ax.plot(load[:, i], load[:, j], color=COLOURS[n], label=labels[n] + lost)
            if lost:  # where the swarm was lost (a quadrotor tilted beyond the scene's limit)
                ax.plot(load[-1, i], load[-1, j], "x", color=COLOURS[n], ms=10, mew=2)
        ax.plot(*row["door"][:1], row["door"][j], "ks", ms=8, label="doorway")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)" if j == 1 else "z (m)")
        ax.set_title(title)
    for n in names:
        load = np.array(row[n]["load"])
        err = np.linalg.norm(load - np.array(row[n]["reference"]), axis=1)
        axes[2].plot(0.1 * np.arange(len(err)), err, color=COLOURS[n], label=labels[n])
    axes[2].set_xlabel("time (s)")
    axes[2].set_ylabel("load tracking error (m)")
    axes[2].set_title("tracking error")
    axes[0].legend(fontsize=9)
    anchor = f", both MPCs regularised (--anchor {results['anchor']:g})" if results.get("anchor") else ""
    fig.suptitle(f"quad3, new path {path} (seed {row['seed']}){anchor}")
    fig.tight_layout()
    fig.savefig(out, dpi=100)


def merged_runs(sources):
    """One results dict whose path rows hold the controllers of every FILE:KEY run, and their
    labels with each run's horizon and anchor."""
    merged, labels = None, dict(LABELS)
    for source in sources:
        path, key = source.rsplit(":", 1)
        with open(path) as f:
            run = json.load(f)[key]
        if merged is None:
            merged = {"paths": [{k: v for k, v in row.items() if k not in LABELS} for row in run["paths"]]}
        for row, into in zip(run["paths"], merged["paths"]):
            if row["seed"] != into["seed"]:
                raise SystemExit(f"{source}: its paths are not the first run's (seed {row['seed']}, not {into['seed']})")
            for n in ("scene", "true", "learned"):
                if n in row:
                    into[n] = row[n]
                    if n != "scene":
                        labels[n] = f"{LABELS[n]} (H = {run['horizon']}, W = {run['anchor']:g})"
    return merged, labels


def pendulum(results, run, out):
    import matplotlib.pyplot as plt

    row = results["runs"][run]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharey=True)
    for bob, ax in enumerate(axes):
        for n in ("pd", "true", "learned"):
            th = np.array(row[n]["angles"])[:, bob]
            ax.plot(0.05 * np.arange(len(th)), th, color=COLOURS[n], label=LABELS[n])
        ax.axhline(row["target"][bob], color="k", ls="--", lw=1, label="target")
        ax.set_xlabel("time (s)")
        ax.set_title(f"bob {bob}")
    axes[0].set_ylabel("angle (rad)")
    axes[0].legend(fontsize=9)
    fig.suptitle(f"pendulum_force, run {run} (seed {row['seed']})")
    fig.tight_layout()
    fig.savefig(out, dpi=100)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dir", default=os.path.dirname(os.path.abspath(__file__)))
    ap.add_argument("--path", type=int, default=0)
    ap.add_argument("--run", type=int, default=0)
    ap.add_argument("--runs", nargs="+", metavar="FILE:KEY", help="draw these runs' controllers together")
    ap.add_argument("--out", default="quadrotor_best.png", help="the figure of --runs")
    a = ap.parse_args()
    if a.runs:
        results, labels = merged_runs(a.runs)
        quadrotor(results, a.path, a.out, labels)
        print(f"wrote {a.out}")
        return
    for name, draw, which in (("quadrotor", quadrotor, a.path), ("pendulum", pendulum, a.run)):
        src = os.path.join(a.dir, f"{name}_results.json")
        if os.path.exists(src):
            with open(src) as f:
                draw(json.load(f), which, os.path.join(a.dir, f"{name}_mpc.png"))
            print(f"wrote {os.path.join(a.dir, name + '_mpc.png')}")


if __name__ == "__main__":
    main()
