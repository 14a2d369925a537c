"""Training a model: losses on the engine's VJP, batches, the training loop with its resumable
state, its log, Adam, and the recipes (the settings used for what a user leaves unset).

Owns: `config` (TrainConfig), `losses` (with `residuals`: their compiled pass), `batches`,
`learnable` (data that cannot be learned as given), `sizes` (a run's memory), `loop` (fit),
`state` (the checkpoint), `log`, `optim`, `recipes`.  May import: mpnode.evaluation,
mpnode.model, mpnode.data, mpnode.engine, mpnode.base.
"""
from .config import TrainConfig  # noqa: F401
from .loop import TrainResult, fit  # noqa: F401
from .losses import loss_and_grad  # noqa: F401
from .state import state_path  # noqa: F401
