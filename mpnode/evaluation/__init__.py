"""Using a model where the truth is known or not: error measures (normalised MSE, blow-ups,
predictable horizon), evaluation and simulation of whole files, RK4 substeps chosen by
step doubling, and the network parameters that explain observations best.

Owns: `metrics`, `evaluate`, `nodes` (each node's error), `spread` (an ensemble's bands and spread),
`stepsize`, `network_fit` (fit_network: which node or line of a network changed).  May import:
mpnode.model, mpnode.data,
mpnode.engine, mpnode.base.
"""
from .evaluate import EvalResult, SimulationResult, evaluate, simulate  # noqa: F401
from .network_fit import NetworkFit, fit_network  # noqa: F401
