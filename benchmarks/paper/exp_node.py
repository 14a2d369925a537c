"""Experiment 10 -- the monolithic reference: a plain neural ODE of the whole system.

`mpnode train --model node` on the data of experiment 8 (pendulum, lorenz3, gene16 on five
BA graphs, kuramoto10), for the same wall time as the MP-NODE runs of experiment 8 (whose
plateau runs, `mpnode train`'s defaults, are the comparison), scored on the same test sets;
then each NODE is asked to run on a graph of another size, which it must refuse.

    python benchmarks/paper/exp_node.py [--quick]
"""
import numpy as np
from common import RunSpec, evaluate_nmse, main, run_line, table
from runs_shared import SCHEDULE_MINUTES, SCHEDULE_SYSTEMS, schedule_run, schedule_test

NAME = "node"
TITLE = "10. Messages against a monolithic neural ODE (plain NODE, same wall time)"


def node_run(mode, key):
    base = schedule_run(mode, key, "plateau")
    extra = tuple((k, v) for k, v in base.extra if k != "schedule")
    return RunSpec(f"node_{key}", base.train, base.epochs, kind="node", recipe="auto", extra=extra)


def runs(mode):
    return [s for key in SCHEDULE_SYSTEMS for s in (schedule_run(mode, key, "plateau"), node_run(mode, key))]


def data(mode):
    return [schedule_test(mode, key) for key in SCHEDULE_SYSTEMS]


def refusal(model, n_nodes):
    """What a NODE says when asked to roll out a graph of ``n_nodes`` nodes (its message)."""
    from mpnode.base.errors import InputError
    from mpnode.base.graph import Graph

    x0 = np.zeros((1, n_nodes, model.spec.state_dim))
    try:
        model.rollout(x0, Graph.complete(n_nodes), steps=1)
    except InputError as e:
        return str(e)
    raise AssertionError(f"a NODE of {model.spec.n_nodes} nodes rolled out a graph of {n_nodes}")


def analyse(ctx):
    rows, numbers = [], {}
    for key in SCHEDULE_SYSTEMS:
        test = ctx.data(schedule_test(ctx.mode, key))
        for label, spec in (("MP-NODE (defaults)", schedule_run(ctx.mode, key, "plateau")),
                            ("plain NODE", node_run(ctx.mode, key))):
            res, model = ctx.result(spec.name), ctx.model(spec.name)
            ev = evaluate_nmse(model, test)
            numbers[spec.name] = {"nmse": ev.nmse, "epochs": res["epochs"], "parameters": int(model.theta.size),
                                  "run": run_line(res)}
            rows.append([key, label, int(model.theta.size), res["epochs"], ev.nmse])
    node = ctx.model(node_run(ctx.mode, "kuramoto10").name)
    message = refusal(node, node.spec.n_nodes + 3)
    numbers["refusal"] = message
    budget = "3 epochs" if ctx.mode.quick else ctx.mode.wall_time(SCHEDULE_MINUTES)
    text = [
        f"Each model: {budget}, `mpnode train` defaults (recipe auto), test sets of experiment 8. The NODE sees",
        "the whole system's state (node-major) and no graph: on gene16's five BA graphs it cannot tell them apart.",
        "",
        table(["system", "model", "parameters", "epochs", "test nMSE"], rows),
        "",
        f"Asked to run the kuramoto10 NODE on {node.spec.n_nodes + 3} nodes: \"{message}\"",
    ]
    return "\n".join(text), numbers


if __name__ == "__main__":
    main(["exp_node"], description=__doc__)
