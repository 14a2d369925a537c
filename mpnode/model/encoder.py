"""The initial-state encoder: a node's first observations -> its whole state at the first time.

A rollout needs every state dimension of every node at its start; data as they come have
values nobody observed (a dimension never measured, a sensor that dropped out) and noise on
the ones they have.  The encoder reads a node's first W observations -- each slot's values
(missing ones as 0), which of them were seen, and when (time since the first observation in
units of dt) -- and returns a correction to the first observation (missing values taken as
the data's mean, 0 in normalised units):  z0 = fill(x_0) + E2^T tanh(E1^T f + e1) + e2.
E2 starts at 0, so a new encoder starts as that fill.  It is one small network per node,
shared by all nodes like the field itself, so it works on any graph and any N.  Its weights
follow the field's in the model's flat parameter vector (mpnode.engine.layouts); the
engine's VJP gives the initial state's cotangent, `backward` carries it to the weights.
Slots past the K observations a caller lets it see (a warm-up of K) are masked out.
"""
import numpy as np

#: the arrays of the encoder, in layout order
ARRAYS = ("E1", "e1", "E2", "e2")


def n_features(window, state_dim):
    """Inputs per node: for each of the W slots its values, which were seen, and when."""
    return window * (2 * state_dim + 1)


def features(x_first, times_first, visible, dt):
    """(M, W (2 dx + 1)) encoder inputs of every node.

    x_first : (W, M, dx) the first W observations in normalised units, NaN where not observed
    times_first : (W, M) their times (any origin); visible : int, or (M,) ints: the number of
    slots the encoder may see (the warm-up); slots from there on read as not observed.
    """
    W, M, dx = x_first.shape
    shown = np.arange(W)[:, None] < np.broadcast_to(np.asarray(visible), (M,))[None, :]  # (W, M)
    seen = np.isfinite(x_first) & shown[:, :, None]
    values = np.where(seen, x_first, 0.0)
    tau = np.where(shown, (times_first - times_first[:1]) / dt, 0.0)
    feats = np.concatenate([values, seen.astype(values.dtype), tau[:, :, None]], axis=2)  # (W, M, 2dx+1)
    return np.ascontiguousarray(feats.transpose(1, 0, 2).reshape(M, -1))


def forward(params, feats, first):
    """(z0 (M, dx), cache): the initial state from the features and the first observation
    ``first`` (M, dx), normalised, NaN where not observed."""
    h = np.tanh(feats @ params["E1"] + params["e1"])
    z0 = np.where(np.isnan(first), 0.0, first) + h @ params["E2"] + params["e2"]
    return z0, (feats, h)


def backward(params, cache, gz0, grads):
    """Add the cotangents of the encoder's weights for the initial state's cotangent ``gz0``
    into ``grads`` (a dict of arrays shaped like ``params``)."""
    feats, h = cache
    grads["E2"] += h.T @ gz0
    grads["e2"] += gz0.sum(axis=0)
    gh = (gz0 @ params["E2"].T) * (1.0 - h * h)
    grads["E1"] += feats.T @ gh
    grads["e1"] += gh.sum(axis=0)


def params_of(spec, theta):
    """Views of the encoder's arrays in the flat vector ``theta`` (or a gradient shaped like it)."""
    from mpnode.engine import layouts

    views = layouts.split(theta, layouts.param_shapes(spec))
    return {name: views[name] for name in ARRAYS}


def start(spec, theta, x, intervals, visible):
    """(z0 (M, dx) in theta's dtype, cache or None): where a time-major batch's rollouts start.

    x : (T+1, M, dx) normalised observations, NaN where not observed; intervals : (T, M) or None
    (every dt); visible : the observations (int or (M,)) the encoder may see.  Without an encoder
    the first observation, its missing values at the data's mean (0); cache goes to `gradient`.
    """
    first = x[0]
    if not spec.encoder_window:
        return np.where(np.isnan(first), first.dtype.type(0), first), None
    W = spec.encoder_window
    steps = min(W, x.shape[0]) - 1
    xw = np.full((W,) + x.shape[1:], np.nan)
    xw[:steps + 1] = x[:steps + 1]
    gaps = np.full((W - 1, x.shape[1]), spec.dt) if intervals is None else np.zeros((W - 1, x.shape[1]))
    if intervals is not None:
        gaps[:steps] = intervals[:steps]
    times = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(gaps, axis=0)])
    z0, cache = forward(params_of(spec, theta), features(xw, times, visible, spec.dt), first)
    return z0.astype(theta.dtype), cache


def gradient(spec, theta, cache, gz0, gtheta):
    """Add the encoder's part of the gradient (for the initial states' cotangent gz0) into gtheta."""
    if cache is not None:
        backward(params_of(spec, theta), cache, gz0, params_of(spec, gtheta))
