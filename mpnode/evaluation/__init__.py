"""Using a model where the truth is known or not: error measures (normalised MSE, blow-ups,
predictable horizon), evaluation and simulation of whole files, and RK4 substeps chosen by
step doubling.

Owns: `metrics`, `evaluate`, `nodes` (each node's error), `spread` (an ensemble's bands and spread),
`stepsize`.  May import: mpnode.model, mpnode.data,
mpnode.engine, mpnode.base.
"""
from .evaluate import EvalResult, SimulationResult, evaluate, simulate  # noqa: F401
