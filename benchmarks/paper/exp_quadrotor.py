"""Experiment 9 -- the quadrotor swarm: message sizes against L2S, and 3 -> 6 quadrotors (paper
Fig. 7, Fig. 9 and Table 2's quadrotor column).

On quad3 (500 trajectories, a fixed wall-time budget each): MP-NODE with message sizes 7, 13
and 20 (the paper's mean), MP-NODE 20 with the scaled sum, and L2S.  Each is scored on fresh
quad3 data and zero-shot on quad6.  On quad6 (80 trajectories, the paper's 4000 epochs, test
curve on fresh quad6 data): MP-NODE 20 fine-tuned from quad3 and from scratch, L2S fine-tuned
and from scratch, and the scaled MP-NODE fine-tuned; efficiency = min test nMSE x its epoch.

    python benchmarks/paper/exp_quadrotor.py [--quick]
"""
from common import (
    DataSpec,
    RunSpec,
    efficiency,
    evaluate_nmse,
    figure_block,
    first_epoch_below,
    hold_nmse,
    main,
    model_curve,
    pyplot,
    run_line,
    table,
    test_curve,
)
from paper_numbers import TABLE2_QUAD as PAPER
from runs_shared import quad6_test as q6_test

NAME = "quadrotor"
TITLE = "9. Quadrotor swarm: message sizes, L2S, 3 -> 6 quadrotors (paper Fig. 7, 9, Table 2)"
MINUTES = 4
DIMS = (7, 13, 20)
FIG9 = "Figure 9: Performance of a 3 Quadrotor MP-NODE finetuned on the 6 Quadrotor System"
#: Fig. 9's pairs: (fine-tuned run, its from-scratch counterpart or None, colour)
FIG9_PAIRS = (("q6_ft_m20", "q6_scratch_m20", "C0"), ("q6_ft_m20_scaled", None, "C2"),
              ("q6_ft_l2s", "q6_scratch_l2s", "C3"))


def q3_train(mode):
    return DataSpec("quad3", mode.pick(500, 6), 0)


def q3_test(mode):
    return DataSpec("quad3", mode.pick(200, 4), 1)


def q6_train(mode):
    return DataSpec("quad6", mode.pick(80, 6), 2)


def source_runs(mode):
    """The quad3 models (name -> RunSpec), each for the same wall time."""
    budget = mode.time_limit(MINUTES)
    epochs = mode.pick(100_000, 3)
    specs = [RunSpec(f"q3_m{m}", (q3_train(mode),), epochs, message_dim=m, extra=budget) for m in DIMS]
    specs.append(RunSpec("q3_m20_scaled", (q3_train(mode),), epochs, message_dim=20, aggregation="scaled",
                         extra=budget))
    specs.append(RunSpec("q3_l2s", (q3_train(mode),), epochs, kind="l2s", extra=budget))
    return {s.name: s for s in specs}


def target_runs(mode):
    """The quad6 runs: (name, label, RunSpec)."""
    common = dict(train=(q6_train(mode),), epochs=mode.epochs(4000, 4), test=q6_test(mode),
                  test_points=mode.pick(10, 2))
    return [
        ("q6_ft_m20", "MP-NODE 20, fine-tuned from quad3", RunSpec("q6_ft_m20", init_from="q3_m20", message_dim=20,
                                                                    **common)),
        ("q6_scratch_m20", "MP-NODE 20, from scratch", RunSpec("q6_scratch_m20", message_dim=20, **common)),
        ("q6_ft_m20_scaled", "MP-NODE 20 scaled, fine-tuned from quad3",
         RunSpec("q6_ft_m20_scaled", init_from="q3_m20_scaled", message_dim=20, **common)),
        ("q6_ft_l2s", "L2S, fine-tuned from quad3", RunSpec("q6_ft_l2s", init_from="q3_l2s", kind="l2s", **common)),
        ("q6_scratch_l2s", "L2S, from scratch", RunSpec("q6_scratch_l2s", kind="l2s", **common)),
    ]


def runs(mode):
    return list(source_runs(mode).values()) + [s for _, _, s in target_runs(mode)]


def data(mode):
    return [q3_test(mode), q6_test(mode)]


def analyse(ctx):
    numbers, rows3, rows6 = {}, [], []
    for name in source_runs(ctx.mode):
        res, model = ctx.result(name), ctx.model(name)
        ev3, ev6 = (evaluate_nmse(model, ctx.data(d(ctx.mode))) for d in (q3_test, q6_test))
        numbers[name] = {"quad3_nmse": ev3.nmse, "quad6_zero_shot_nmse": ev6.nmse, "quad6_blown_up": ev6.n_bad,
                         "epochs": res["epochs"], "aggregation": model.spec.aggregation.mlp, "run": run_line(res)}
        rows3.append([name, model.spec.kind, model.spec.message_dim, model.spec.aggregation.mlp, res["epochs"],
                      ev3.nmse, ev6.nmse])
    for name, label, _ in target_runs(ctx.mode):
        res = ctx.result(name)
        best, epoch, product = efficiency(model_curve(res))
        numbers[name] = {"min_nmse": best, "epoch": epoch, "product": product, "run": run_line(res)}
        rows6.append([label, res["test_curve"][0][1] if res["spec"]["init_from"] else "", best, epoch, product,
                      PAPER.get(name, "N/A" if "scratch" in name and "m20" in name else "")])
    link = message_size_figure(ctx, rows3, rows6)
    fig9, numbers["fig9"] = fig9_finetune(ctx)
    hold = hold_errors(ctx)
    numbers["hold_initial_state"] = hold
    budget = "3 epochs" if ctx.mode.quick else ctx.mode.wall_time(MINUTES) + " each (two at a time, one thread each)"
    text = [
        f"quad3 models ({ctx.result('q3_m20')['train_trajectories']} trajectories, {budget}); test sets: "
        f"{ctx.data(q3_test(ctx.mode)).n_trajectories} fresh quad3 and {ctx.data(q6_test(ctx.mode)).n_trajectories}"
        " quad6 trajectories (paper Fig. 7: MP-NODE message sizes and L2S):",
        "",
        table(["run", "kind", "message size", "aggregation", "epochs", "quad3 nMSE", "quad6 zero-shot nMSE"], rows3),
        "",
        f"Holding the initial state scores nMSE {hold['quad3']:.3g} on quad3 and {hold['quad6']:.3g} on quad6.",
        "",
        f"quad6, {ctx.result('q6_ft_m20')['train_trajectories']} trajectories, "
        f"{ctx.result('q6_ft_m20')['spec']['epochs']} epochs, test curve at {ctx.result('q6_ft_m20')['spec']['test_points']}"
        " evenly spaced epochs (paper Fig. 9 and Table 2; efficiency = min test nMSE x the epoch of that model, the"
        " paper's metric in its units is not nMSE, so compare ratios, not values):",
        "",
        table(["run", "zero-shot nMSE", "min test nMSE", "epoch", "efficiency", "paper (Table 2)"], rows6),
        "",
        link,
        "",
        fig9,
        "",
        "Runs: " + "; ".join(f"**{n}**: {numbers[n]['run']}" for n in numbers if isinstance(numbers[n], dict)
                             and "run" in numbers[n]) + ".",
    ]
    return "\n".join(text), numbers


def message_size_figure(ctx, rows3, rows6):
    """Fig. 7 in spirit: test nMSE of each quad3 model on quad3 and zero-shot on quad6, and of the
    quad6 runs (fine-tuned and from scratch)."""
    plt = pyplot()
    fig, (a3, a6) = plt.subplots(1, 2, figsize=(12, 3.6))
    names = [r[0] for r in rows3]
    x = range(len(names))
    a3.bar([i - 0.2 for i in x], [r[5] for r in rows3], width=0.4, label="quad3 test")
    a3.bar([i + 0.2 for i in x], [r[6] for r in rows3], width=0.4, label="quad6, zero-shot")
    a3.set(xticks=list(x), yscale="log", ylabel="test nMSE", title="trained on 3 quadrotors")
    a3.set_xticklabels(names, rotation=20, fontsize=8)
    a3.legend(fontsize=8)
    a6.bar(range(len(rows6)), [r[2] for r in rows6], color="C2")
    a6.set(xticks=list(range(len(rows6))), ylabel="min test nMSE", title="trained on 6 quadrotors (80 trajectories)")
    a6.set_xticklabels([r[0].replace(" from quad3", "").replace(", ", "\n") for r in rows6], fontsize=7)
    fig.tight_layout()
    return ctx.figure(fig, "quadrotor_message_size")


def fig9_finetune(ctx):
    """Fig. 9: test nMSE against epoch on quad6, each quad3 model fine-tuned (solid) and its
    from-scratch counterpart (dashed, same colour); returns (markdown block, numbers)."""
    plt = pyplot()
    labels = {name: label for name, label, _ in target_runs(ctx.mode)}
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    numbers, bits = {}, []
    for ft, sc, color in FIG9_PAIRS:
        for name, style in ((ft, "o-"), (sc, "s--")):
            if name is not None:
                e, v = test_curve(ctx.result(name))
                ax.plot(e, v, style, ms=3, color=color, lw=1.2, label=labels[name])
        bits.append(fig9_sentence(ctx, ft, sc, labels))
        numbers[ft] = bits[-1][1]
    ax.set(yscale="log", xlabel="epoch (fine-tuning's epoch 0: the quad3 model, zero-shot)",
           ylabel="quad6 test nMSE (best-val model)", title="quad3 -> quad6: fine-tuned (solid) vs scratch (dashed)")
    ax.title.set_fontsize(9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    link = ctx.figure(fig, "fig9_quadrotor_finetune")
    return figure_block(link, FIG9, "; ".join(b for b, _ in bits) + "."), numbers


def fig9_sentence(ctx, ft, sc, labels):
    """What Fig. 9 shows for one fine-tuned run (and its scratch counterpart): (sentence, numbers)."""
    c_ft = model_curve(ctx.result(ft))
    nums = {"min_nmse": efficiency(c_ft)[0]}
    text = f"{labels[ft]}: min test nMSE {nums['min_nmse']:.3g}"
    if sc is None:
        return text + " (no scratch run)", nums
    c_sc = model_curve(ctx.result(sc))
    nums["scratch_min_nmse"] = efficiency(c_sc)[0]
    nums["epochs_to_scratch_best"] = first_epoch_below(c_ft, nums["scratch_min_nmse"])
    (e1, v_ft), (_, v_sc) = ([(e, v) for e, v in zip(*test_curve(ctx.result(n))) if e > 0][0] for n in (ft, sc))
    nums["first_evaluation"] = {"epoch": int(e1), "finetuned": float(v_ft), "scratch": float(v_sc)}
    reach = nums["epochs_to_scratch_best"]
    return (text + f" against {nums['scratch_min_nmse']:.3g} from scratch (at the first evaluation, epoch {int(e1)}: "
            f"{v_ft:.3g} against {v_sc:.3g}), and "
            + (f"it reaches scratch's best by epoch {reach}" if reach is not None
               else "it never reaches scratch's best"),
            nums)


def hold_errors(ctx):
    """nMSE of holding the initial state on the quad3 and quad6 test sets."""
    return {"quad3": hold_nmse(ctx.data(q3_test(ctx.mode))), "quad6": hold_nmse(ctx.data(q6_test(ctx.mode)))}


if __name__ == "__main__":
    main(["exp_quadrotor"], description=__doc__)
