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
    # the gene dynamics sum over neighbours, and the mean hides a node's degree: the MLP hears
    # the degree-free mean (in range on denser graphs) and the degree reaches dx/dt only through
    # a linear path on the scaled sum (unseen gene16 graphs 0.05 -> 0.0002-0.0004, gene64
    # zero-shot 2.5 -> 0.06); choosing the model on a held-out graph, when the files hold several
    "gene": {"aggregation": "mean", "linear_aggregation": "scaled", "linear_target": "state", "val_graphs": 1},
}

#: settings of the linear aggregate path, which only an MP-NODE model with messages has
LINEAR_SETTINGS = ("linear_aggregation", "linear_target")

NAMES = ("auto", "paper")


def recipe(name, system, kind="mpnode", messages=True):
    """The settings of recipe ``name`` for data of ``system`` and a model of ``kind`` (a dict of
    runs options).  Aggregation and the linear path only concern MP-NODE models with messages;
    l2s keeps its sum unless told.  val_graphs only acts on files with more graphs than it
    (otherwise the split is random)."""
    if name not in NAMES:
        raise InputError("--recipe", str(name), "is not a recipe", " or ".join(NAMES))
    settings = dict(PAPER)
    if name == "auto":
        settings.update(AUTO.get(system, {}))
    if kind != "mpnode":
        settings.pop("aggregation")
    if kind != "mpnode" or not messages:
        settings = {k: v for k, v in settings.items() if k not in LINEAR_SETTINGS}
    return settings
