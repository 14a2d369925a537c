"""Training losses on rollouts, written once on top of the engine's VJP.

A loss compares a rollout ``pred`` with the truth ``x``, both (T+1, M, dx) in the
model's normalised units: summed over the observed entries of steps 1..T (NaN in ``x`` is a
value nobody observed: it adds nothing) and divided by the number of nodes (the rollouts of a
batch are averaged per node).  Each loss returns its
value and its cotangent with respect to ``pred``; `value_and_grad` turns that into the
gradient of the parameters and initial states through `engine.forward_with_vjp`.
"""
import math

import numpy as np

from mpnode import engine
from mpnode.model import encoder
from mpnode.model.model import batch_graph, to_time_major


def huber(pred, x, n_nodes):
    """Huber (delta 1) of pred - x: (value, cotangent like pred).

    With c = clip(e, -1, 1), huber(e) = c (e - c / 2) and its derivative is c.
    """
    return _value_and_cotangent(pred, x, n_nodes, True)


def mse(pred, x, n_nodes):
    """Squared error of pred - x: (value, cotangent like pred)."""
    return _value_and_cotangent(pred, x, n_nodes, False)


def _value_and_cotangent(pred, x, n_nodes, is_huber):
    from .residuals import residual_pass

    g = np.empty_like(pred)
    total, _ = residual_pass(pred, np.asarray(x, dtype=pred.dtype), is_huber, g, 1.0 / n_nodes)
    return total / n_nodes, g


LOSSES = {"huber": huber, "mse": mse}


def value(pred, x, loss="huber", n_nodes=None):
    """The loss alone; inf when a prediction is non-finite (a blown-up validation rollout)."""
    from .residuals import residual_pass

    if loss not in LOSSES:
        raise KeyError(f"unknown loss {loss!r}")
    value_only = pred[:0]  # a cotangent without rows: residual_pass writes none
    total, finite = residual_pass(pred, x, loss == "huber", value_only, 0.0)
    return total / (n_nodes or x.shape[1]) if finite else math.inf


def value_and_grad(spec, theta, x, graph, u=None, loss="huber", n_nodes=None, driver="auto", x0=None,
                   intervals=None):
    """Loss of the rollout from x0 against x[1..T], and its exact gradient.

    x : ndarray, shape (T+1, M, dx), the true states, NaN where not observed;
    x0 : (M, dx) the initial state (default x[0], a value not observed taken as 0: the data's mean);
    u : (T, M, du) or None; intervals : (T, M) times between outputs or None (every dt);
    n_nodes : the divisor (default M; a part of a batch passes the batch's).
    Returns (loss, gtheta like theta, gx0 of shape (M, dx)).
    """
    x0 = np.nan_to_num(x[0], nan=0.0) if x0 is None else x0
    pred, vjp = engine.forward_with_vjp(spec, theta, x0, graph, u, x.shape[0] - 1, driver, intervals=intervals)
    total, gpred = LOSSES[loss](pred, np.asarray(x, dtype=pred.dtype), n_nodes or x.shape[1])
    gtheta, gx0 = vjp(gpred)
    return total, gtheta, gx0


def batch_value_and_grad(spec, theta, batch, loss, visible, start_noise=None):
    """Loss and exact gradient of a training Batch (mpnode.training.batches), from the initial
    states the model's encoder estimates from the first ``visible`` observations (or the first
    observation itself, without an encoder): the encoder's weights get their gradient too.
    start_noise : (M, dx) added to those initial states (the targets stay as they are), or None."""
    x0, cache = encoder.start(spec, theta, batch.x, batch.intervals, visible)
    if start_noise is not None:
        x0 = (x0 + start_noise).astype(x0.dtype)
    total, gtheta, gx0 = value_and_grad(spec, theta, batch.x, batch.graph, batch.u, loss, x0=x0,
                                        intervals=batch.intervals)
    encoder.gradient(spec, theta, cache, gx0, gtheta)
    return total, gtheta


def loss_and_grad(model, x, graph, u=None, loss="huber", node_attrs=None):
    """Loss of the model's rollouts from x[:, 0] against x[:, 1..T], and its exact gradient.

    x : ndarray, shape (B, T+1, N, dx), in data units (normalised with the model's constants)
    graph : Graph shared by all B, or a list of B Graphs; u : (B, T, N, du) or None
    node_attrs : (B, N, dp) or (N, dp) for a model of node attributes, else None
    loss : "huber" (delta 1) or "mse" on normalised states, summed over state dimensions
    and steps 1..T and averaged over the B*N nodes (mpnode.training.losses).
    Returns (loss, gtheta) with gtheta shaped like model.theta.
    """
    x = np.asarray(x)
    b, t1, n, dx = x.shape
    model.check_nodes(n)
    xn = to_time_major(model.normalize_x(x))
    u = model.controls_of(u, node_attrs, b, n, t1 - 1)
    un = None if u is None else to_time_major(model.normalize_u(np.asarray(u)))
    value, gtheta, _ = value_and_grad(model.spec, model.theta, xn, batch_graph(graph, b), un, loss)
    return value, gtheta
