"""The model: a kind, its weights, integration settings and normalisation (`Model`), its file
(docs/model-format.md), a change of normalisation that keeps what it computes, and
`Simulator`, which steps it one dt at a time.

Owns: `model`, `ensemble` (K models in one file, their calibrated spread), `file`, `renormalise`, `simulator`,
`provenance` (the data a model was trained on against the data it meets), `ranges` (what a model saw in training, and
the inputs that leave it), `inputs` (node attributes and edge weights as a model hears them).  May import: mpnode.engine, mpnode.base.
"""
from .ensemble import Ensemble  # noqa: F401
from .model import Model, batch_graph, check_data  # noqa: F401
from .simulator import Simulator  # noqa: F401
