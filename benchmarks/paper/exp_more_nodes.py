"""Experiment 3 -- zero-shot to more nodes: the Lorenz3 model on Lorenz7 and Lorenz10.

The module learned on 3 weakly coupled Lorenz systems (||H||_F = 0.01) is run unchanged on
graphs of 7 and 10 nodes.  For scale, the same test sets are given to the Lorenz10 models
of experiment 4 trained on 500 Lorenz10 trajectories (from scratch and fine-tuned).

    python benchmarks/paper/exp_more_nodes.py [--quick]
"""
from common import evaluate_nmse, flatness, main, run_line, table
from runs_shared import finetune_runs
from runs_shared import lorenz3_run as run_spec
from runs_shared import lorenz_test as test_data

NAME = "more_nodes"
TITLE = "3. Zero-shot to more nodes (Lorenz3 -> Lorenz7, Lorenz10)"
SIZES = (3, 7, 10)
#: experiment 4's Lorenz10 models on 500 trajectories, set beside the zero-shot model for scale
LORENZ10 = ("lorenz10_scratch_500", "lorenz10_finetune_500")


def runs(mode):
    return [run_spec(mode)] + [s for s in finetune_runs(mode) if s.name in LORENZ10]


def data(mode):
    return [test_data(mode, k) for k in SIZES]


def analyse(ctx):
    spec = run_spec(ctx.mode)
    res = ctx.result(spec.name)
    models = [(spec.name, "zero-shot")] + [(n, "trained on Lorenz10") for n in LORENZ10]
    rows, numbers = [], {"run": run_line(res), "val_improvement_last_20pct": flatness(res)}
    for name, how in models:
        model = ctx.model(name)
        for k in SIZES:
            ev = evaluate_nmse(model, ctx.data(test_data(ctx.mode, k)))
            h = {thr: v["median_time"] for thr, v in ev.horizons.items()}
            numbers[f"{name}/lorenz{k}"] = {"nmse": ev.nmse, "nmse_last_step": ev.nmse_last, "blown_up": ev.n_bad,
                                            "horizon_time": h}
            label = f"{name} ({'in distribution' if k == 3 and name == spec.name else how})"
            rows.append([label, f"lorenz{k}", ev.nmse, ev.nmse_last, *(_t(h[thr]) for thr in sorted(h, key=float)), ev.n_bad])
    thresholds = sorted(ev.horizons, key=float)
    text = [
        f"Lorenz3 model: {run_line(res)}. Test sets: {ctx.data(test_data(ctx.mode, 3)).n_trajectories} fresh "
        "trajectories each (seed 1), T = 50 steps of dt = 0.05, initial states uniform(-1, 1).",
        "",
        table(["model", "test", "nMSE", "nMSE at T", *(f"predictable horizon, nMSE < {t}" for t in thresholds),
               "blown up"], rows),
        "",
        "Predictable horizon: the median over trajectories of the first time its own nMSE exceeds the",
        "threshold ('> T': at least half never did). Lorenz is chaotic, so every model parts from the",
        "truth eventually; the horizon says when.",
    ]
    return "\n".join(text), numbers


def _t(v):
    return "> T" if v is None else f"{v:.2f} s"


if __name__ == "__main__":
    main(["exp_more_nodes"], description=__doc__)
