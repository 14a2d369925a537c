"""Training recipes: the settings `mpnode train` and `finetune` use for what the user leaves unset.

``paper`` is the MP-NODE paper's recipe exactly: the mean of the neighbours' messages,
batches of 128 trajectories and a constant learning rate cut on plateaus (TrainConfig's
defaults).  ``auto`` (the default) is the best we measured: for every system, and for the
kind of system the data hold (their ``system`` attribute).  The measurements behind every entry:
docs/evidence/recipes.md.  Every setting stays overridable by its own option.
"""
from mpnode.base.errors import InputError

PAPER = {"aggregation": "mean", "schedule": "plateau", "batch_size": 128}

#: what recipe auto changes from the paper's for the graph models (MP-NODE, L2S) of every system: a
#: batch costs its trajectories, not its count, so batches of 32 take four times the Adam steps
#: per epoch for about the same time, which gave the lower test error at equal wall time.  A plain
#: NODE keeps the paper's 128: there it was a tie (docs/evidence/recipes.md, batch sizes).
AUTO_ALL = {"batch_size": 32}
AUTO_ALL_KINDS = ("mpnode", "l2s")

#: system -> further settings that measured better than the paper's
AUTO = {
    # the gene dynamics sum over neighbours, and the mean hides a node's degree: the MLP hears
    # the degree-free mean (in range on denser graphs) and the degree reaches dx/dt only through
    # a linear path on the scaled sum, which carries a gene16 model to denser graphs; the model
    # is chosen on a held-out graph when the files hold several (docs/evidence/recipes.md, gene)
    "gene": {"aggregation": "mean", "linear_aggregation": "scaled", "linear_target": "state", "val_graphs": 1},
    # data longer than 50 steps train on windows of 50, the model still chosen on the full
    # horizon: lower error on both horizons than training on all of it, and rollouts that held to
    # 4x the 50 steps (docs/evidence/long-rollouts.md); 50-step data are trained as before
    "lorenz": {"train_window": 50},
    # messages of 13 numbers (the earlier quad3 studies' size; not separated from the learning rate
    # in the screens) and a learning rate of 1e-2: at a user's 10-minute budget the run is far from
    # converged, and 1e-2 reaches in 400 epochs about half the quad6 zero-shot error of 1e-3
    # (docs/evidence/quadrotor.md, one module for any swarm).  Started at 1e-2, the validation
    # error jumps from epoch to epoch and the plateau rule cuts the step once in 10 minutes, late;
    # a cosine decay over the run's budget (its time limit, or its epochs) settles the module
    # instead, and cut the swarm's zero-shot error on 6 and 8 carriers at equal epochs
    # (docs/evidence/quadrotor.md, the swarm's learning-rate schedule)
    "quadrotor_load": {"message_dim": 13, "lr": 1e-2, "schedule": "cosine"},
    # springs pull with the sum of their forces, sum_j k_ij (X_j - X_i): under the mean a node
    # hears that sum over its degree, which it cannot undo, and the sum gave 3-4x lower error on
    # chains of 4 and zero-shot on chains of 10 (docs/evidence/networks.md)
    "spring_pendulums_het": {"aggregation": "sum"},
    # weighted systems whose coupling is a weighted mean by construction (kuramoto_het: K / deg_i)
    # or where the sum measured no better (swing: docs/evidence/grids.md) keep the paper's mean
    "kuramoto_het": {"aggregation": "mean"},
    # a grid's lightly damped swings, learned on the full horizon from the start, settle on a damped
    # guess of the frequency; windows of 10 and then 20 steps first (100 epochs each) learn the swing
    # itself, and cut the zero-shot error on every grid but the largest (docs/evidence/grids.md)
    "swing": {"aggregation": "mean", "curriculum": (10, 20), "curriculum_epochs": 100},
}

#: what recipe auto sets for data with edge weights of a system the table above does not name:
#: weights are strengths whose pulls, flows or currents add, and the mean would divide that sum
#: by a degree the node cannot undo (pendulums on springs from a user's own simulator:
#: docs/evidence/networks.md)
AUTO_WEIGHTED = {"aggregation": "sum"}

#: what recipe auto adds for data as they come (values not observed, irregular times): an
#: initial-state encoder that estimates what was not measured from a trajectory's first
#: observations (mpnode.model.encoder; docs/evidence/imperfect-data.md)
AUTO_IMPERFECT = {"encoder_window": 5}

#: what recipe auto changes from the paper's when `mpnode finetune` continues an MP-NODE model (it
#: keeps its kind, sizes and aggregation, so only training options belong here): a fine-tuning set
#: of a few dozen trajectories is one batch of 128, one Adam step an epoch; batches of 8 take
#: several for about the same time, which gave the lower test nMSE (docs/evidence/recipes.md)
FINETUNE_AUTO = {"batch_size": 8}

#: system -> what fine-tuning adds: the quadrotor normalisation refitted on the new swarm size (its
#: attitude spreads shrink with more carriers; refitting weighs them as the metric does, with the
#: weights changed so the model starts from the same predictions; docs/evidence/quadrotor.md)
FINETUNE_SYSTEMS = {"quadrotor_load": {"norm": "refit"}}

#: settings of the linear aggregate path, which only an MP-NODE model with messages has
LINEAR_SETTINGS = ("linear_aggregation", "linear_target")

NAMES = ("auto", "paper")


def _check(name):
    if name not in NAMES:
        raise InputError("--recipe", str(name), "is not a recipe", " or ".join(NAMES))


def recipe(name, system, kind="mpnode", messages=True, complete=True, weighted=False):
    """The settings of recipe ``name`` for data of ``system`` and a model of ``kind`` (a dict of
    runs options); ``complete``: the data are regular and every value observed; ``weighted``: the
    model hears the data's edge weights.  Aggregation and the linear path only concern MP-NODE
    models with messages; l2s keeps its sum unless told, and node models the paper's batch size.
    val_graphs only acts on files with more graphs than it (otherwise the split is random)."""
    _check(name)
    settings = dict(PAPER)
    if name == "auto":
        settings.update(AUTO_ALL if kind in AUTO_ALL_KINDS else {})
        settings.update(AUTO.get(system, AUTO_WEIGHTED if weighted else {}))
        settings.update({} if complete else AUTO_IMPERFECT)
    if kind != "mpnode":
        settings.pop("aggregation")
    if kind != "mpnode" or not messages:
        settings = {k: v for k, v in settings.items() if k not in LINEAR_SETTINGS}
    return settings


def tables(name):
    """Everything recipe ``name`` can set (for cache keys: a run keyed by it trains again when
    the recipe changes)."""
    _check(name)
    if name == "paper":
        return {"paper": PAPER}
    return {"paper": PAPER, "all": AUTO_ALL, "systems": AUTO, "weighted": AUTO_WEIGHTED, "imperfect": AUTO_IMPERFECT,
            "finetune": FINETUNE_AUTO, "finetune_systems": FINETUNE_SYSTEMS}


def finetune_recipe(name, kind="mpnode", system=None):
    """The training settings of recipe ``name`` for fine-tuning a model of ``kind`` on data of
    ``system`` (a dict of runs options; ``paper``, or a kind we did not measure: none, so the
    paper's defaults)."""
    _check(name)
    if name != "auto" or kind != "mpnode":
        return {}
    return {**FINETUNE_AUTO, **FINETUNE_SYSTEMS.get(system, {})}
