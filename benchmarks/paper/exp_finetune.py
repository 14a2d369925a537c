"""Experiment 4 -- fine-tuning beats training from scratch (paper Fig. 5a-e, Table 2).

Each transfer is trained twice on the same (small) target data with the same epochs, seed
and settings: once starting from the source model (fine-tuning, keeping the source's
normalisation, as `mpnode finetune` does) and once from fresh weights (scratch):

- Lorenz3 -> Lorenz10 (Fig. 5a) with 50, 100 and 500 training trajectories, and the same at
  higher coupling (`lorenz10_medium`, `lorenz10_high`: Fig. 5d) and over 10 s (`lorenz10_10s`:
  Fig. 5e); scratch runs use the Lorenz3 recipe's horizon curriculum, fine-tuning goes
  straight to the full horizon;
- gene16 (five BA graphs) -> gene64 (BA) (Fig. 5b);
- Kuramoto10 BA -> Kuramoto10 ER with 50, 100 and 500 trajectories (Fig. 5c).

The best-validation model is evaluated on a fixed test set at evenly spaced epochs (the
test-error curve); the paper's efficiency metric is then min(test error) x (the epoch at
which that minimum was first reached): lower is better on both counts.  It is computed on
two test errors: our nMSE, and the paper's units (`common.paper_units`).

    python benchmarks/paper/exp_finetune.py [--quick]
"""
import gene_grid
import numpy as np
from common import efficiency, first_epoch_below, main, model_curve, pyplot, run_line, table, test_curve
from paper_numbers import TABLE2 as PAPER_TABLE2
from runs_shared import finetune_cases as cases
from runs_shared import finetune_name, finetune_runs
from runs_shared import finetune_test_points as test_points

NAME = "finetune"
TITLE = "4. Fine-tuning against training from scratch (paper Fig. 5, Table 2)"


def runs(mode):
    return finetune_runs(mode)


def summarise(res):
    """Efficiency of one run in nMSE and in the paper's units, and its curves."""
    out = {}
    for unit, key in (("nmse", "test_curve"), ("paper_units", "test_curve_paper_units")):
        c = model_curve(res, key)
        out[unit] = dict(zip(("min", "epoch", "product"), efficiency(c)), curve=c)
    out["status"] = res["status"]
    return out


def case_rows(ctx, case):
    """Table rows and numbers of one transfer: one row per fine-tuning learning rate."""
    pattern, label, _, _, _, _, lrs, _, column = case
    sc = ctx.result(pattern.format("scratch"))
    s = summarise(sc)
    paper = PAPER_TABLE2.get(column)
    numbers = {"scratch": s, "column": list(column), "paper": paper, "label": label}
    rows, runs = [], [sc]
    for lr in lrs:
        ft = ctx.result(finetune_name(pattern, lr))
        f = summarise(ft)
        who = "finetune" if lr == 1e-3 else f"finetune_lr{lr:g}"
        f["epochs_to_scratch_best"] = first_epoch_below(f["nmse"]["curve"], s["nmse"]["min"])
        f["zero_shot_nmse"] = ft["test_curve"][0][1]
        numbers[who] = f
        runs.insert(0, ft)
        bad = [f"{w} {r['status']}" for w, r in (("fine-tuned", ft), ("scratch", sc)) if r["status"] != "completed"]
        ratio = s["paper_units"]["product"] / f["paper_units"]["product"]
        rows.append([label + (f" (**{', '.join(bad)}**)" if bad else ""), f"{lr:g}", f["zero_shot_nmse"],
                     f["nmse"]["min"], f["nmse"]["epoch"], s["nmse"]["min"], s["nmse"]["epoch"],
                     f["paper_units"]["product"], s["paper_units"]["product"], f"{ratio:.1f}x",
                     f"{paper[0]:g} / {paper[1]:g} = {paper[1] / paper[0]:.1f}x" if paper else "",
                     f["epochs_to_scratch_best"] if f["epochs_to_scratch_best"] is not None else "never"])
    return rows, numbers, runs


def draw_panel(ax, panel, title, members):
    """One panel of Fig. 5: per training-set size, fine-tuned (solid) and scratch (dashed) test curves."""
    for i, (label, ft, sc) in enumerate(members):
        for res, style, who in ((ft, "-", "fine-tuned"), (sc, "--", "scratch")):
            e, v = test_curve(res, "test_curve_paper_units")
            ax.plot(np.maximum(e, 1), v, style, marker="o", ms=2, color=f"C{i}", lw=1, label=f"{who}, {label}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title(f"Fig. {panel}: {title}", fontsize=8)
    ax.set_xlabel("epoch")
    ax.legend(fontsize=5.5)


def draw_figure(ctx, cs):
    """Fig. 5a-e in the paper's layout: one panel per transfer, curves per data size."""
    plt = pyplot()
    panels = {}
    for pattern, label, train, _, _, _, lrs, panel, _ in cs:
        title = label.rsplit(",", 1)[0]  # without the trajectory count
        panels.setdefault((panel, title), []).append(
            (f"{train.trajectories} traj.", ctx.result(finetune_name(pattern, lrs[0])),
             ctx.result(pattern.format("scratch"))))
    n = len(panels)
    cols = min(3, n)
    fig, axes = plt.subplots((n + cols - 1) // cols, cols, figsize=(3.6 * cols, 3.0 * ((n + cols - 1) // cols)),
                             squeeze=False)
    for ax, ((panel, title), members) in zip(axes.ravel(), sorted(panels.items())):
        draw_panel(ax, panel, title, members)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for row in axes:
        row[0].set_ylabel("test error, paper units")
    fig.tight_layout()
    return ctx.figure(fig, "finetune_curves")


def trained(ctx, case):
    """Whether every run of ``case`` has a result (an analysis of a cache the suite is still filling)."""
    pattern, lrs = case[0], case[6]
    names = [pattern.format("scratch")] + [finetune_name(pattern, lr) for lr in lrs]
    return all(ctx.result(n) is not None for n in names)


def analyse(ctx):
    every = cases(ctx.mode)
    cs = [c for c in every if trained(ctx, c)]
    missing = [c[1] for c in every if c not in cs]
    rows, numbers, runs_text = [], {}, []
    for case in cs:
        r, n, runs = case_rows(ctx, case)
        rows += r
        numbers[case[0].replace("_{}", "")] = n
        runs_text += [f"**{res['name']}**: {run_line(res)}" for res in runs]
    link = draw_figure(ctx, cs)
    fig6a = "Fig. 6a needs the gene64 runs."
    gene = next((c for c in cs if c[0] == "gene64_{}"), None)  # Fig. 6a: the fine-tuned gene64 model, 8x8 grid
    if gene:
        fig6a, numbers["gene64"]["fig6a"] = gene_grid.gene_grid(
            ctx, ctx.model(finetune_name(gene[0], 1e-3)), ctx.data(gene[3]), "fig6_gene_grid_8x8", gene_grid.FIG6A,
            f"gene64 fine-tuned from gene16 (run {finetune_name(gene[0], 1e-3)})")
    text = [
        f"Test curves: the best-validation model so far, evaluated at {test_points(ctx.mode)} "
        "evenly spaced epochs (and, for fine-tuning, at epoch 0: the source model itself, 'zero-shot').",
        "The epoch of a point is the epoch that model was trained to (its last validation improvement),",
        "not the evaluation time. Efficiency = min test error x the epoch of that model (the paper's Table 2",
        "metric, lower is better; a minimum at epoch 0 counts as 1 epoch), here in the paper's units (the",
        "Huber sum over the horizon of the z-scored error, see section 7); ratio = scratch / fine-tuned.",
        "The minima in nMSE are beside them so a reader can compare per-step errors.",
        "",
        table(["transfer", "fine-tune lr", "zero-shot nMSE", "fine-tuned: min nMSE", "epoch",
               "scratch: min nMSE", "epoch", "fine-tuned efficiency (paper units)",
               "scratch efficiency (paper units)", "ratio", "paper: fine-tuned / scratch = ratio",
               "fine-tuned epochs to scratch's best nMSE"], rows),
        "",
        link,
        "",
        fig6a,
        "",
        "Runs: " + "; ".join(runs_text) + ".",
    ]
    if missing:
        text += ["", "**Not trained yet in this cache** (analysed without them): " + "; ".join(missing) + "."]
    return "\n".join(text), numbers


if __name__ == "__main__":
    main(["exp_finetune"], description=__doc__)
