"""Training recipes: the settings `mpnode train` uses for what the user leaves unset.

``paper`` is the MP-NODE paper's recipe exactly: the mean of the neighbours' messages and
a constant learning rate cut on plateaus (TrainConfig's defaults).  ``auto`` (the default)
is the best we measured for the kind of system the data hold (their ``system`` attribute;
benchmarks/paper, experiment 7, and the README's recipe table say why); a
system we have not measured gets the paper's recipe.  Every setting stays overridable by
its own option.
"""
from .errors import InputError

PAPER = {"aggregation": "mean", "schedule": "plateau"}

#: system -> settings that measured better than the paper's (the rest stays the paper's)
AUTO = {
    # the gene dynamics sum over neighbours: the mean hides a node's degree (unseen-graph nMSE
    # 0.05 -> 0.002-0.007); choosing the model on a held-out graph (when the files hold several)
    # lowered it further, to 0.0014-0.0048
    "gene": {"aggregation": "scaled", "val_graphs": 1},
}

NAMES = ("auto", "paper")


def recipe(name, system, kind="mpnode"):
    """The settings of recipe ``name`` for data of ``system`` and a model of ``kind`` (a dict of
    runs options).  Aggregation only concerns MP-NODE models; l2s keeps its sum unless told.
    val_graphs only acts on files with more graphs than it (otherwise the split is random)."""
    if name not in NAMES:
        raise InputError("--recipe", str(name), "is not a recipe", " or ".join(NAMES))
    settings = dict(PAPER)
    if name == "auto":
        settings.update(AUTO.get(system, {}))
    if kind != "mpnode":
        settings.pop("aggregation")
    return settings
