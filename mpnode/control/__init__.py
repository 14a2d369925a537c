"""Control with a learned model: shooting model-predictive control through the engine's exact
gradients with respect to the controls.

Owns: `mpc` (`ShootingMPC`: receding-horizon control through a model; `optimise_controls`:
the optimiser it runs, for any predictor with a gradient; `tracking_cost`: the quadratic
tracking cost).  May import: model, engine, base.  Examples: benchmarks/studies/mpc/.
"""
from .mpc import ShootingMPC, optimise_controls, tracking_cost  # noqa: F401
