"""The engine: fixed-step RK4 rollouts of a model's field over a block-diagonal graph, and their
exact vector-Jacobian product (the discrete adjoint).

Owns: `spec` (FieldSpec: what the kernels need besides the weights), `layouts` (each kind's
parameters in one flat vector), `plan` (how the kernels cover a graph), `backend` (threads,
numba or NumPy), `codegen` (the vector width numba compiles for), `compiling` (compiled once per
machine, the VJP on the other core), `rollout` (the entry points), `jacobians` (one step's
Jacobians), `numpy_path` (every kind in plain NumPy) and
`kernels` (the numba code).  Arrays are time-major and flat over nodes.  May import:
mpnode.base.  It knows nothing of files, data sets or training.
"""
from .backend import BACKENDS, numba_problem, resolve_backend  # noqa: F401
from .rollout import compile_vjp_ahead, forward, forward_with_vjp, initial_state, integrate, integrate_with_vjp  # noqa: F401
from .spec import AGGREGATIONS, KINDS, LINEAR_TARGETS, FieldSpec, default_aggregation  # noqa: F401
