"""The memory a training run will need, checked before the model is made (mpnode.base.memory).

Three kinds of arrays grow with what a user asks for: those the size of the parameters
(the weights, their gradient, Adam's two moments, the best weights and moments, the
checkpoint's copies and the kernels' per-block gradients: about PARAM_COPIES float64
copies), those the size of the training data (the normalised training and validation
copies, the noise drawn once, the curriculum's windows) and those the size of one batch
(one state per RK4 step for the adjoint, the rollout and its cotangent, and every stage's
inputs and activations up to the engine's KEEP_CACHES_BYTES).  The largest of the three
names the option to change.
"""
import numpy as np

from mpnode.base.memory import check_memory
from mpnode.engine import layouts, rollout

#: float64 copies of the parameter vector a run keeps (see the module docstring)
PARAM_COPIES = 16
#: bytes per data entry beyond the data as read: normalised copy, noise (float64), windows or validation chunks
DATA_BYTES_PER_ENTRY = 24
#: arrays of one batch's rollout kept at once (states for the adjoint, outputs, cotangents, stage values)
BATCH_COPIES = 6


def training_bytes(spec, data, config, dtype):
    """{"parameters", "data", "batch"}: bytes of each kind of array (module docstring).

    spec : the model's FieldSpec;  data : a TrainingData;  config : its TrainConfig;
    dtype : the model's weights' dtype.
    """
    itemsize = np.dtype(dtype).itemsize
    entries = sum(np.asarray(t.x).size for t in data.datasets)
    horizon = max(t.horizon for t in data.datasets)
    nodes = max(t.n_nodes for t in data.datasets)
    width = spec.state_dim + spec.message_dim
    rk4_steps = horizon * spec.substeps
    batch = (rk4_steps + 1) * config.batch_size * nodes * width * itemsize * BATCH_COPIES
    # the stages' inputs and four hidden-wide activations: L2S's widths, above MP-NODE's two
    stages = 4 * rk4_steps * config.batch_size * nodes * (width + spec.control_dim + 4 * spec.hidden) * itemsize
    batch += min(stages, rollout.KEEP_CACHES_BYTES)
    return {"parameters": layouts.n_params(spec) * 8 * PARAM_COPIES, "data": entries * DATA_BYTES_PER_ENTRY,
            "batch": batch}


#: what to change when each kind of array is the largest
FIXES = {"parameters": ("--hidden", "a smaller --hidden (the parameters grow with its square)"),
         "data": ("DATA", "fewer or shorter trajectories"),
         "batch": ("--batch-size", "a smaller --batch-size (or fewer --substeps)")}


def check_training_memory(spec, data, config, dtype):
    """InputError naming the option to change when the run would need more memory than the
    machine has available."""
    need = training_bytes(spec, data, config, dtype)
    largest = max(need, key=need.get)
    flag, fix = FIXES[largest]
    value = {"--hidden": spec.hidden, "--batch-size": config.batch_size}.get(flag, ", ".join(data.sources))
    what = (f"training a model of kind {spec.kind} with {layouts.n_params(spec):,} parameters (hidden {spec.hidden}) and "
            f"batches of {config.batch_size}")
    check_memory(sum(need.values()), flag, value, what, fix)
