"""Where a rollout starts, fitted: the initial state that makes the model, as it is, pass closest
to a trajectory's first K observations, found by gradient descent through the engine's exact
VJP.  The other way to the same end as the initial-state encoder (mpnode.model.encoder): it
needs no training and sees every observation of the warm-up, at the price of a few hundred
rollouts of K steps per evaluation; `mpnode eval --start` chooses (docs/evidence/imperfect-data.md
says what each measured).
"""
import numpy as np

from mpnode import engine

#: Adam on the normalised initial state: steps and rate
FIT_STEPS = 200
FIT_LR = 0.05


def fit_initial_state(model, observations, graph, times=None, u=None, start=None, steps=FIT_STEPS):
    """(B, N, dx) initial states in the data's units: least squares over the observed values of
    the first K observations (B, K, N, dx; NaN where not observed) with the model fixed,
    starting from ``start`` (default: the model's own estimate, `Model.initial_state`).

    graph : the batch's graph (mpnode.model.batch_graph of the B trajectories'); times (B, K) or
    None (every dt); u (B, K-1, N, du) or None.
    """
    from .model import node_intervals, to_time_major

    obs = np.asarray(observations, dtype=np.float64)
    b, k, n, dx = obs.shape
    x = to_time_major(model.normalize_x(obs).astype(np.float64))
    seen = ~np.isnan(x)
    target = np.where(seen, x, 0.0)
    z = model.normalize_x(model.initial_state(obs, times) if start is None else start).astype(np.float64)
    z = z.reshape(b * n, dx)
    theta = model.theta.astype(np.float64)
    iv = None if times is None else np.repeat(node_intervals(times), n, axis=1)
    un = None if u is None else to_time_major(model.normalize_u(np.asarray(u))).astype(np.float64)
    m1, m2 = np.zeros_like(z), np.zeros_like(z)
    for step in range(1, steps + 1):
        pred, vjp = engine.forward_with_vjp(model.spec, theta, z, graph, un, k - 1, intervals=iv)
        _, gz = vjp(np.where(seen, pred - target, 0.0))
        m1 = 0.9 * m1 + 0.1 * gz
        m2 = 0.999 * m2 + 0.001 * gz * gz
        z -= FIT_LR * (m1 / (1 - 0.9 ** step)) / (np.sqrt(m2 / (1 - 0.999 ** step)) + 1e-8)
    return model.denormalize_x(z.reshape(b, n, dx)).astype(model.dtype)
