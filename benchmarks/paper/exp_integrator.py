"""Experiment 11 -- the paper's integrator, as near as fixed-step RK4 comes (coupled pendulum).

The Julia code trained its models through Tsit5 at tolerance 1e-4, an adaptive solver that
integrates the learned field accurately; mpnode trains through classic RK4 with one step per
dt.  To see whether that difference matters, the pendulum message model of experiment 1 is
trained again, same data, seed and epochs, with 4 RK4 substeps per dt (an integration error
~256x smaller, near what the adaptive solver delivers), and both models are rolled out at 1
and 4 substeps on the same test set.

    python benchmarks/paper/exp_integrator.py [--quick]
"""
import dataclasses

from common import evaluate_nmse, main, run_line, table
from runs_shared import messages_run, messages_test

NAME = "integrator"
TITLE = "11. The paper's integrator: training at 1 against 4 RK4 substeps per dt (coupled pendulum)"
SUBSTEPS = (1, 4)


def run_specs(mode):
    base = messages_run(mode, "pendulum", False)
    return [base, dataclasses.replace(base, name=base.name + "_rk4x4", extra=(("substeps", 4),))]


def runs(mode):
    return run_specs(mode)


def analyse(ctx):
    traj = ctx.data(messages_test(ctx.mode, "pendulum"))
    rows, numbers = [], {}
    for spec, trained in zip(run_specs(ctx.mode), SUBSTEPS):
        res, model = ctx.result(spec.name), ctx.model(spec.name)
        numbers[spec.name] = {"trained_substeps": trained, "run": run_line(res),
                              "train_minutes": res["seconds"] / 60}
        for s in SUBSTEPS:
            ev = evaluate_nmse(model.with_spec(substeps=s), traj)
            numbers[spec.name][f"nmse_at_{s}"] = ev.nmse
            rows.append([f"{trained}" if s == SUBSTEPS[0] else "", s, ev.nmse, ev.nmse_last,
                         f"{numbers[spec.name]['train_minutes']:.1f}" if s == SUBSTEPS[0] else ""])
    a, b = (numbers[s.name] for s in run_specs(ctx.mode))
    text = [
        f"Test set: {traj.n_trajectories} fresh pendulum trajectories. Each model is rolled out at the",
        "substeps it was trained with and at the other.",
        "",
        table(["trained at (RK4 steps per dt)", "rolled out at", "test nMSE", "nMSE at T", "training minutes"], rows),
        "",
        f"Trained at 4 substeps the model's test nMSE is {b['nmse_at_4'] / a['nmse_at_1']:.2g}x that of the "
        f"1-substep model (each at its own substeps), for {b['train_minutes'] / a['train_minutes']:.1f}x the "
        "training time.",
        "",
        "Runs: " + "; ".join(f"**{name}**: {n['run']}" for name, n in numbers.items()) + ".",
    ]
    return "\n".join(text), numbers


if __name__ == "__main__":
    main(["exp_integrator"], description=__doc__)
