"""The runs and data sets that more than one experiment of the paper suite uses, defined once.

An experiment that trains or reads a run another one also uses takes its definition from
here (a run declared twice is trained once: same name, same settings), so that experiments
import only this module, `paper_numbers` and `common`, never one another.
"""
import dataclasses

from common import DataSpec, RunSpec

# ---------------------------------------------------------------------------
# Experiment 1 (messages): the pendulum and Kuramoto10 models; 5, 6, 11 use them too
# ---------------------------------------------------------------------------
MESSAGE_SYSTEMS = {  # key: (scene, training trajectories full/quick, epochs full/quick)
    "pendulum": ("coupled_pendulum", (500, 12), (4000, 4)),
    "kuramoto": ("kuramoto10_ba", (500, 12), (1000, 4)),
}


def messages_train(mode, key):
    scene, (b_full, b_quick), _ = MESSAGE_SYSTEMS[key]
    return DataSpec(scene, mode.pick(b_full, b_quick), 0)


def messages_test(mode, key):
    return DataSpec(MESSAGE_SYSTEMS[key][0], mode.pick(200, 6), 1)


def messages_run(mode, key, zero, message_dim=3):
    """The run of ``key`` with messages (or zero messages)."""
    _, _, (e_full, e_quick) = MESSAGE_SYSTEMS[key]
    suffix = "zero" if zero else f"dm{message_dim}"
    return RunSpec(f"{key}_{suffix}", (messages_train(mode, key),), mode.epochs(e_full, e_quick),
                   message_dim=message_dim, zero_messages=zero)


# ---------------------------------------------------------------------------
# Experiment 2 (topologies): the gene16 model on five BA graphs and its test sets
# ---------------------------------------------------------------------------
#: networkx seeds of the unseen test graphs (the training graphs used 1..5)
FRESH_SEEDS = (6, 7, 8, 9, 10)
GRAPH_KINDS = ("ba", "er", "ws")


def gene16_run(mode):
    """The gene16 model on five BA graphs; experiment 4 starts its gene64 runs from it."""
    return RunSpec("gene16_ba5", (DataSpec("gene16_ba_multi", mode.pick(500, 10), 0),), mode.epochs(4000, 4))


def gene16_test(mode, kind):
    """Fresh trajectories on five unseen graphs of ``kind`` (ba, er, ws)."""
    return DataSpec(f"gene16_{kind}", mode.pick(200, 5), 1, graph_seeds=FRESH_SEEDS)


def gene16_seen(mode):
    """Fresh trajectories on the five training graphs."""
    return DataSpec("gene16_ba_multi", mode.pick(200, 5), 1)


def gene64_test(mode):
    """gene64 (BA(64, 32)) test trajectories: the test curves of the gene16 -> gene64 transfers."""
    return DataSpec("gene64_ba", mode.pick(100, 4), 1)


def gene64_zero_shot(mode):
    return DataSpec("gene64_ba", mode.pick(200, 5), 1)


def aggregation_test_sets(mode):
    """(label, DataSpec, Table 1 key) of every test set of experiment 7 (Table 1's cells)."""
    sets = [("BA, the 5 training graphs", gene16_seen(mode), "seen")]
    sets += [(f"{k.upper()}, 5 unseen graphs", gene16_test(mode, k), k) for k in GRAPH_KINDS]
    return sets + [("gene64 BA(64, 32), zero-shot", gene64_zero_shot(mode), None)]


def aggregation_hot_test_sets(mode):
    """The same test sets with hot-spot initial states (no gene64: its grid is another size)."""
    return [(label + ", hot spots", dataclasses.replace(d, scene=d.scene + "_hot"), key)
            for label, d, key in aggregation_test_sets(mode)[:4]]


# ---------------------------------------------------------------------------
# Experiment 3 (more nodes): the Lorenz3 model and the Lorenz test sets
# ---------------------------------------------------------------------------
def lorenz3_run(mode):
    """The Lorenz3 model (horizon curriculum 5, 10, full); experiment 4 starts from it."""
    return RunSpec("lorenz3", (DataSpec("lorenz3", mode.pick(1000, 12), 0),), mode.epochs(3000, 4),
                   curriculum=(5, 10), curriculum_epochs=mode.epochs(150, 1))


def lorenz_test(mode, k):
    return DataSpec(f"lorenz{k}", mode.pick(200, 5), 1)


# ---------------------------------------------------------------------------
# Experiment 4 (fine-tuning against scratch); experiment 3 reads its Lorenz10 models
# ---------------------------------------------------------------------------
FINETUNE_SIZES = (50, 100, 500)
#: fine-tuning learning rates tried besides the default 1e-3 at coupling 0.01: there the Lorenz10
#: fine-tunes never improved on their starting model's validation loss, so a careful user would lower it
LORENZ_FINETUNE_LRS = (1e-3, 1e-4)
#: (scene, Fig. 5 panel, what differs from Lorenz3, epochs, fine-tune lrs)
LORENZ_TARGETS = (("lorenz10", "5a", "coupling 0.01", 1000, LORENZ_FINETUNE_LRS),
                  ("lorenz10_medium", "5d", "coupling 1", 1000, (1e-3,)),
                  ("lorenz10_high", "5d", "coupling 5", 1000, (1e-3,)),
                  ("lorenz10_10s", "5e", "coupling 0.01, 10 s", 400, (1e-3,)))


def finetune_name(pattern, lr):
    return pattern.format("finetune" if lr == 1e-3 else f"finetune-lr{lr:g}")


def finetune_cases(mode):
    """(run-name pattern, label, target training data, test data, source run spec, epochs, fine-tune lrs,
    Fig. 5 panel, Table 2 column) per transfer."""
    out = []
    sizes = mode.pick(FINETUNE_SIZES, FINETUNE_SIZES[:1])
    for scene, panel, what, epochs, lrs in LORENZ_TARGETS:
        if mode.quick and scene != "lorenz10":
            continue
        for n in FINETUNE_SIZES if scene == "lorenz10" else sizes:  # quick: three sizes of the same 6 trajectories
            out.append((f"{scene}_{{}}_{n}", f"Lorenz3 -> Lorenz10 ({what}), {n} trajectories",
                        DataSpec(scene, mode.pick(n, 6), 0), DataSpec(scene, mode.pick(200, 5), 1),
                        lorenz3_run(mode), mode.epochs(epochs, 4), lrs, panel, ("lorenz", n)))
    out.append(("gene64_{}", "gene16 (BA x5) -> gene64 (BA), 100 trajectories",
                DataSpec("gene64_ba", mode.pick(100, 6), 0), gene64_test(mode),
                gene16_run(mode), mode.epochs(600, 4), (1e-3,), "5b", ("gene", 100)))
    for n in sizes:
        out.append((f"kuramoto_er_{{}}_{n}", f"Kuramoto10 BA -> ER, {n} trajectories",
                    DataSpec("kuramoto10_er", mode.pick(n, 6), 0), DataSpec("kuramoto10_er", mode.pick(200, 5), 1),
                    messages_run(mode, "kuramoto", False), mode.epochs(1000, 4), (1e-3,), "5c", ("kuramoto", n)))
    return out


def finetune_test_points(mode):
    """Evaluations of the test curve per run (besides epoch 0)."""
    return mode.pick(20, 2)


def finetune_runs(mode):
    """Every transfer's source, fine-tuned runs (one per learning rate) and run from scratch."""
    specs = []
    points = finetune_test_points(mode)
    for pattern, _, train, test, source, epochs, lrs, _, _ in finetune_cases(mode):
        specs.append(source)
        specs += [RunSpec(finetune_name(pattern, lr), (train,), epochs, message_dim=source.message_dim,
                          init_from=source.name, test=test, test_points=points, lr=lr) for lr in lrs]
        specs.append(RunSpec(pattern.format("scratch"), (train,), epochs, message_dim=source.message_dim,
                             curriculum=source.curriculum,
                             curriculum_epochs=scratch_curriculum_epochs(source, epochs),
                             test=test, test_points=points))
    return specs


def scratch_curriculum_epochs(source, epochs):
    """The source recipe's epochs per curriculum window, but at least half the run on the full horizon."""
    if not source.curriculum:
        return source.curriculum_epochs
    return max(1, min(source.curriculum_epochs, epochs // (2 * len(source.curriculum))))


# ---------------------------------------------------------------------------
# Experiment 8 (schedule): defaults for the same wall time; experiments 10 and 13 use them
# ---------------------------------------------------------------------------
SCHEDULE_MINUTES = 5
SCHEDULE_SYSTEMS = {  # key: (scene, training trajectories full/quick)
    "pendulum": ("coupled_pendulum", (500, 12)),
    "lorenz3": ("lorenz3", (1000, 12)),
    "gene16": ("gene16_ba_multi", (500, 10)),
    "kuramoto10": ("kuramoto10_ba", (500, 12)),
}


def schedule_train(mode, key):
    scene, (full, quick) = SCHEDULE_SYSTEMS[key]
    return DataSpec(scene, mode.pick(full, quick), 0)


def schedule_test(mode, key):
    return DataSpec(SCHEDULE_SYSTEMS[key][0], mode.pick(200, 5), 1)


def schedule_run(mode, key, schedule):
    """`mpnode train`'s defaults (recipe auto) with ``schedule``, for SCHEDULE_MINUTES of wall time."""
    extra = (("schedule", schedule),) + mode.time_limit(SCHEDULE_MINUTES)
    return RunSpec(f"sched_{key}_{schedule}", (schedule_train(mode, key),), mode.pick(100_000, 3), recipe="auto",
                   extra=extra)


# ---------------------------------------------------------------------------
# Experiment 9 (quadrotors): the quad6 test set; experiment 12 reads its runs
# ---------------------------------------------------------------------------
def quad6_test(mode):
    return DataSpec("quad6", mode.pick(200, 4), 3)
