"""Shooting MPC: at every step, choose the controls of the next H steps that minimise a cost
of the predicted states, apply the first, repeat from the next observed state.

The optimiser is scipy's L-BFGS-B over the controls (box bounds, e.g. a rotor's thrust
range), warm-started from the previous plan shifted by one step; its gradient is exact:
one rollout of H steps and one VJP through the engine (`forward_with_vjp`'s controls'
cotangent), whatever the number of controls.  A cost is any function
``cost(X, U) -> (value, dX, dU)`` of the predicted states X (B, H+1, N, dx) and controls
U (B, H, N, du), both in the data's units (`tracking_cost` makes the usual one).
"""
import time

import numpy as np

from mpnode import engine
from mpnode.base.arguments import check_int
from mpnode.base.errors import InputError
from mpnode.engine.backend import single_threaded_blas
from mpnode.model.ensemble import models_of
from mpnode.model.model import batch_graph, to_time_major
from mpnode.model.simulator import check_weighting, held_attrs


def tracking_cost(x_ref, q, r, u_ref=0.0):
    """cost(X, U) = sum q (X - x_ref)^2 over steps 1..H + sum r (U - u_ref)^2, with its gradients.

    x_ref : broadcastable to X (B, H+1, N, dx) (its step 0, the current state, is not charged);
    q (dx,) and r (du,) per-dimension weights; u_ref : broadcastable to U.
    """
    q, r = np.asarray(q, dtype=np.float64), np.asarray(r, dtype=np.float64)

    def cost(X, U):
        ex = X - x_ref
        ex[:, 0] = 0
        eu = U - u_ref
        return float(np.sum(q * ex * ex) + np.sum(r * eu * eu)), 2 * q * ex, 2 * r * eu

    return cost


def optimise_controls(predict, cost, U0, bounds=None, iterations=30):
    """Minimise cost(predict(U), U) over U from U0 with L-BFGS-B: (U*, info).

    predict : U (B, H, N, du) -> (X (B, H+1, N, dx), vjp) with vjp(dX) -> dU, the gradient of
    sum(dX * X) with respect to U; bounds : (low, high) scalars or arrays broadcastable to U,
    or None.  info: cost, iterations, evaluations, seconds.
    """
    from scipy.optimize import minimize

    U0 = np.asarray(U0, dtype=np.float64)
    start = time.perf_counter()

    def value_and_grad(flat):
        U = flat.reshape(U0.shape)
        X, vjp = predict(U)
        value, dX, dU = cost(X, U)
        return value, (np.asarray(vjp(dX), dtype=np.float64) + dU).ravel()

    box = None
    if bounds is not None:
        low, high = (np.broadcast_to(np.asarray(b, dtype=np.float64), U0.shape).ravel() for b in bounds)
        box = list(zip(low, high))
    with single_threaded_blas():  # its vectors are small: a BLAS thread pool only spins a second core
        res = minimize(value_and_grad, U0.ravel(), jac=True, method="L-BFGS-B", bounds=box,
                       options={"maxiter": iterations})
    info = dict(cost=float(res.fun), iterations=int(res.nit), evaluations=int(res.nfev),
                seconds=time.perf_counter() - start)
    return res.x.reshape(U0.shape), info


class ShootingMPC:
    """Receding-horizon control of B copies of a graph through a learned model.

    model : a Model with controls; graph : an mpnode Graph (N nodes) shared by the copies;
    horizon : H steps of the model's dt; bounds : (low, high) of the controls, data units;
    iterations : L-BFGS-B iterations per step; messages : what an MP-NODE's messages (its
    hidden state) start each plan from: "carry" (those the model reached stepping from the
    previous observation under the control applied) or "zero" (0, as every training window
    starts: right when the data start anywhere in the state space, and in a loop longer than
    the training horizon, where carried messages may drift where training never took them).
    offset_free: every plan's prediction at step h also gets h times the model's last one-step
    error (the observed state minus what the model predicted for it under the control applied):
    a learned model's errors along a path change slowly, so the last one is the best guess of the
    next, as offset-free MPC estimates a constant disturbance; the gradient is the model's.
    The model runs in float64 (a float32 model is copied: the line search needs its cost to
    more digits than float32 gives).  An Ensemble plans through its members' mean prediction
    (the gradient is the mean of theirs), each member carrying its own messages.  A model with
    node attributes takes them (node_attrs (N, dp) or (B, N, dp), as `mpnode.Simulator`) and
    hears them after the controls on every step; the plans are of the du controls alone.

    >>> mpc = ShootingMPC(model, graph, horizon=10, bounds=(0.0, 4.66))
    >>> mpc.reset(x0, u_guess)                      # (B, N, dx), (B, N, du)
    >>> for t in range(T):
    ...     u = mpc.control(x, tracking_cost(x_ref[t], q, r))   # x: the observed state
    ...     x = plant.step(u)

    """

    def __init__(self, model, graph, horizon, bounds=None, iterations=30, messages="carry", offset_free=False,
                 node_attrs=None):
        self.du = model.spec.control_dim - model.spec.attr_dim  # the controls planned: not the attributes
        if not self.du:
            raise InputError("ShootingMPC", "model", "has no controls to optimise (du = 0)", "a model with controls")
        if messages not in ("carry", "zero"):
            raise InputError("ShootingMPC", "messages", f"is {messages!r}", "'carry' or 'zero'")
        horizon = check_int(horizon, "ShootingMPC", "horizon", 1)
        iterations = check_int(iterations, "ShootingMPC", "iterations", 1)
        self.model = model.copy(np.float64)
        self.members = models_of(self.model)
        self.graph, self.horizon, self.bounds, self.iterations = graph, horizon, bounds, iterations
        check_weighting(model, graph, "ShootingMPC")
        self.node_attrs = held_attrs(model, node_attrs, None, graph.n_nodes, "ShootingMPC")
        self.messages, self.offset_free = messages, offset_free
        self.info = None  # the last optimisation's cost, iterations, evaluations, seconds

    def reset(self, x0, u_guess):
        """Start from x0 (B, N, dx), messages at 0; the first plan starts as u_guess held (B, N, du)."""
        x0 = np.asarray(x0, dtype=np.float64)
        self._shape = x0.shape
        self._flat = batch_graph(self.graph, x0.shape[0])
        self._attrs = held_attrs(self.model, self.node_attrs, *x0.shape[:2], "ShootingMPC.reset")
        xn = self.model.normalize_x(x0).reshape(-1, x0.shape[2])
        self._z = [engine.initial_state(m.spec, xn) for m in self.members]
        guess = np.broadcast_to(np.asarray(u_guess, dtype=np.float64), x0.shape[:2] + (self.du,))
        self.plan = np.repeat(guess[:, None], self.horizon, axis=1)
        self._expected, self._offset = None, 0.0

    def control(self, x, cost):
        """The control (B, N, du) to apply now, from the observed state x (B, N, dx)."""
        m, dx = self.model, self.model.spec.state_dim  # an ensemble's members share one normalisation
        x = np.asarray(x, dtype=np.float64)
        if self.offset_free and self._expected is not None:  # step h of every plan: h times the last error
            self._offset = (x - self._expected)[:, None] * np.arange(self.horizon + 1)[:, None, None]
        xn = m.normalize_x(x).reshape(-1, dx)
        for z in self._z:
            z[:, :dx] = xn
            if self.messages == "zero":
                z[:, dx:] = 0
        z0 = [z.copy() for z in self._z]
        self.plan, self.info = optimise_controls(lambda U: self._predict(z0, U), cost, self.plan, self.bounds,
                                                 self.iterations)
        u = self.plan[:, 0].copy()
        un = self._heard(m, u[:, None])
        self._z = [engine.integrate(member.spec, member.theta, z, self._flat, un, 1)[1]
                   for member, z in zip(self.members, z0)]
        if self.offset_free:
            self._expected = np.mean([m.denormalize_x(z[:, :dx].reshape(x.shape)) for z in self._z], axis=0)
        self.plan = np.concatenate([self.plan[:, 1:], self.plan[:, -1:]], axis=1)  # the next warm start
        return u

    def _predict(self, z0, U):
        """(X (B, H+1, N, dx) in data units, vjp: dX -> dU): the members' mean from their full states z0."""
        each = [self._predict_member(m, z, U) for m, z in zip(self.members, z0)]
        X = np.mean([x for x, _ in each], axis=0) + self._offset
        if len(each) == 1:
            return X, each[0][1]
        return X, lambda dX: np.mean([grad(dX) for _, grad in each], axis=0)

    def _predict_member(self, m, z0, U):
        """One model's (X, vjp) from its full state z0."""
        spec = m.spec
        b, n, dx = self._shape
        un = self._heard(m, U)
        xs, vjp = engine.integrate_with_vjp(spec, m.theta, z0, self._flat, un, U.shape[1])
        X = m.denormalize_x(xs.reshape(-1, b, n, dx).transpose(1, 0, 2, 3))

        def grad(dX):
            gx = np.ascontiguousarray((dX * m.x_std).transpose(1, 0, 2, 3)).reshape(xs.shape)
            gu = vjp(gx, controls=True)[2][..., :self.du]  # the attributes' columns are no plan's
            return gu.reshape(U.shape[1], b, n, -1).transpose(1, 0, 2, 3) / m.u_std[:self.du]

        return X, grad

    def _heard(self, m, U):
        """The controls U (B, H, N, du) and the node attributes held beside them, as the engine
        takes them: normalised, time-major (H, B*N, du + dp)."""
        b, n, _ = self._shape
        return to_time_major(m.normalize_u(m.controls_of(U, self._attrs, b, n, U.shape[1], "ShootingMPC")))
