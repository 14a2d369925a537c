"""Training recipes: the settings `mpnode train` uses for what the user leaves unset.

``paper`` is the MP-NODE paper's recipe exactly: the mean of the neighbours' messages and
a constant learning rate cut on plateaus (TrainConfig's defaults).  ``auto`` (the default)
is the best we measured for the kind of system the data hold (their ``system`` attribute;
benchmarks/paper, experiment "aggregation", and the README's recipe table say why); a
system we have not measured gets the paper's recipe.  Every setting stays overridable by
its own option.
"""
from .errors import InputError

PAPER = {"aggregation": "mean", "schedule": "plateau"}

#: system -> settings that measured better than the paper's (the rest stays the paper's)
AUTO = {
    # the gene dynamics sum over neighbours: the mean hides a node's degree
    "gene": {"aggregation": "scaled"},
}

NAMES = ("auto", "paper")


def recipe(name, system, kind="mpnode"):
    """The settings of recipe ``name`` for data of ``system`` and a model of ``kind`` (a dict of
    runs options).  Aggregation only concerns graph models; l2s keeps its sum unless told."""
    if name not in NAMES:
        raise InputError("--recipe", str(name), "is not a recipe", " or ".join(NAMES))
    settings = dict(PAPER)
    if name == "auto":
        settings.update(AUTO.get(system, {}))
    if kind != "mpnode":
        settings.pop("aggregation")
    return settings
