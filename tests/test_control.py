"""Shooting MPC through a learned model (mpnode.control): its gradient in the data's units equals
central finite differences of the cost (float64), its controls stay in their bounds, and in closed
loop on the model itself it brings the state nearer a target than holding the first guess."""
import numpy as np
import pytest
from engine_helpers import make_graph, random_theta, spec_

from mpnode import Ensemble, InputError, Model, Simulator
from mpnode.control import ShootingMPC, optimise_controls, tracking_cost

N, DX, DU, B, H = 6, 2, 2, 2, 4

KINDS = {
    "mpnode": dict(message_dim=3),
    "l2s": dict(kind="l2s", aggregation="sum"),
    "node": dict(kind="node", n_nodes=N),
}


def make_model(name, dtype=np.float64, seed=0):
    rng = np.random.default_rng(seed)
    spec = spec_(state_dim=DX, control_dim=DU, hidden=8, dt=0.1, substeps=1, **{"message_dim": 0, **KINDS[name]})
    return Model(random_theta(rng, spec, dtype=dtype), spec, x_mean=rng.standard_normal(DX),
                 x_std=1 + rng.random(DX), u_mean=rng.standard_normal(DU), u_std=1 + rng.random(DU))


def graph():
    return make_graph(np.random.default_rng(1), N)


@pytest.mark.parametrize("name", KINDS)
def test_the_cost_gradient_matches_finite_differences(name):
    rng = np.random.default_rng(2)
    mpc = ShootingMPC(make_model(name), graph(), H)
    mpc.reset(rng.standard_normal((B, N, DX)), 0.0)
    cost = tracking_cost(rng.standard_normal((B, H + 1, N, DX)), [1.0, 0.5], [0.1, 0.2])
    z0 = [z.copy() for z in mpc._z]
    U = rng.standard_normal((B, H, N, DU))

    def total(U):
        X, vjp = mpc._predict(z0, U)
        value, dX, dU = cost(X, U)
        return value, vjp(dX) + dU

    value, grad = total(U)
    eps = 1e-6
    for _ in range(3):
        d = rng.standard_normal(U.shape)
        d /= np.linalg.norm(d)
        fd = (total(U + eps * d)[0] - total(U - eps * d)[0]) / (2 * eps)
        assert abs(fd - np.sum(grad * d)) < 1e-6 * abs(fd), (fd, np.sum(grad * d))


def make_ensemble(name):
    """Two members of one normalisation, other weights."""
    first = make_model(name)
    other = Model(random_theta(np.random.default_rng(9), first.spec), first.spec, first.x_mean, first.x_std,
                  first.u_mean, first.u_std)
    return Ensemble([first, other])


@pytest.mark.parametrize("name", ["mpnode", "node"])
def test_an_ensemble_plans_through_its_members_mean(name):
    """The prediction is Ensemble.rollout's (the members' mean) and its gradient matches finite differences."""
    rng = np.random.default_rng(3)
    ensemble, g = make_ensemble(name), graph()
    x0, U = rng.standard_normal((B, N, DX)), rng.standard_normal((B, H, N, DU))
    mpc = ShootingMPC(ensemble, g, H)
    mpc.reset(x0, 0.0)
    z0 = [z.copy() for z in mpc._z]
    X, vjp = mpc._predict(z0, U)
    np.testing.assert_allclose(X, ensemble.rollout(x0, g, U), rtol=1e-12, atol=1e-12)
    dX = rng.standard_normal(X.shape)
    grad, d, eps = vjp(dX), rng.standard_normal(U.shape), 1e-6
    fd = (np.sum(dX * mpc._predict(z0, U + eps * d)[0]) - np.sum(dX * mpc._predict(z0, U - eps * d)[0])) / (2 * eps)
    assert abs(fd - np.sum(grad * d)) < 1e-6 * abs(fd)
    assert mpc.control(x0, tracking_cost(np.zeros(DX), [1.0, 1.0], [0.1, 0.1])).shape == (B, N, DU)


@pytest.mark.parametrize("name", KINDS)
def test_offset_free_plans_add_the_last_one_step_error_per_step(name, one_thread):
    """offset_free: after a step that landed at x1 where the model expected x1_hat, every plan
    predicts the model's rollout from x1 plus h (x1 - x1_hat) at step h; the gradient is unchanged."""
    model, g = make_model(name), graph()
    rng = np.random.default_rng(6)
    x0, U = rng.standard_normal((B, N, DX)), rng.standard_normal((B, H, N, DU))
    cost = tracking_cost(np.zeros(DX), [1.0, 1.0], [0.1, 0.1])
    mpc = ShootingMPC(model, g, H, bounds=(-1.0, 1.0), iterations=5, messages="zero", offset_free=True)
    mpc.reset(x0, 0.0)
    u = mpc.control(x0, cost)
    x1_hat = model.rollout(x0, g, u[:, None])[:, 1]
    x1 = x1_hat + rng.standard_normal(x1_hat.shape)
    mpc.control(x1, cost)
    z1 = [z.copy() for z in mpc._z]
    for z in z1:
        z[:, :DX], z[:, DX:] = model.normalize_x(x1).reshape(-1, DX), 0
    X, vjp = mpc._predict(z1, U)
    steps = np.arange(H + 1)[None, :, None, None]
    np.testing.assert_allclose(X, model.rollout(x1, g, U) + steps * (x1 - x1_hat)[:, None], rtol=1e-10, atol=1e-10)
    plain = ShootingMPC(model, g, H, messages="zero")
    plain.reset(x1, 0.0)
    dX = rng.standard_normal(X.shape)
    np.testing.assert_allclose(vjp(dX), plain._predict(z1, U)[1](dX), rtol=1e-12, atol=1e-12)


def cumulative(U):
    """x_k = the sum of the controls so far, from 0: (X, vjp) as optimise_controls takes them."""
    X = np.concatenate([np.zeros((1, 1, 1, 2)), np.cumsum(U, axis=1)], axis=1)
    return X, lambda dX: np.cumsum(dX[:, :0:-1], axis=1)[:, ::-1]


def test_optimise_controls_keeps_to_its_bounds():
    """x_k = the sum of the controls so far, a target beyond reach: every control at its bound."""
    cost = tracking_cost(np.array([1.0, -1.0]), [1.0, 1.0], [0.0, 0.0])
    U, info = optimise_controls(cumulative, cost, np.zeros((1, H, 1, 2)), bounds=(-0.06, 0.1), iterations=50)
    np.testing.assert_allclose(U[0, :, 0], np.broadcast_to([0.1, -0.06], (H, 2)), atol=1e-9)
    assert info["iterations"] >= 1 and info["evaluations"] >= 1


def test_the_optimiser_runs_blas_on_one_thread():
    """L-BFGS-B's small vector products on a BLAS thread pool kept a second core spinning: twice
    the CPU a control step needs.  Pinned while the optimiser runs, restored after it."""
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas_threads():
        return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}

    seen = []

    def predict(U):
        seen.append(blas_threads())
        return cumulative(U)

    cost = tracking_cost(np.array([1.0, -1.0]), [1.0, 1.0], [0.0, 0.0])
    with threadpool_limits(limits=2, user_api="blas"):
        assert blas_threads() == {2}
        optimise_controls(predict, cost, np.zeros((1, H, 1, 2)), iterations=5)
        assert blas_threads() == {2}
    assert seen and all(s == {1} for s in seen)


@pytest.fixture
def one_thread():
    """numba on one thread while the test runs: a control loop of a dozen nodes is too small to
    share between threads."""
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(before)


@pytest.mark.parametrize("name", KINDS)
def test_closed_loop_on_the_model_follows_a_reachable_reference(name, one_thread):
    """The reference is the model's own path under u = 0.5 (unknown to the controller, which
    starts from u = 0): MPC on the model itself as the plant follows it, messages carried along."""
    model, g = make_model(name), graph()
    rng = np.random.default_rng(4)
    x0, steps = rng.standard_normal((B, N, DX)), 6
    ref = model.rollout(x0, g, np.full((B, steps + H, N, DU), 0.5))
    plant = Simulator(model, g)
    mpc = ShootingMPC(model, g, H, bounds=(-1.0, 1.0), iterations=20)
    x = plant.reset(x0)
    mpc.reset(x0, 0.0)
    for t in range(steps):
        u = mpc.control(x, tracking_cost(ref[:, t:t + H + 1], [1.0, 1.0], [1e-6, 1e-6]))
        assert u.shape == (B, N, DU) and np.abs(u).max() <= 1.0
        x = plant.step(u)
    held = model.rollout(x0, g, np.zeros((B, steps, N, DU)))[:, -1]
    assert np.linalg.norm(x - ref[:, steps]) < 0.05 * np.linalg.norm(held - ref[:, steps])


def test_a_model_without_controls_is_refused():
    spec = spec_(state_dim=DX, control_dim=0, message_dim=2)
    with pytest.raises(InputError, match="no controls"):
        ShootingMPC(Model(random_theta(np.random.default_rng(0), spec), spec), graph(), H)
    model = make_model("mpnode")
    for kw, field in ((dict(horizon=0), "horizon"), (dict(horizon=2, iterations=1.5), "iterations"),
                      (dict(horizon=2, messages="none"), "messages")):
        with pytest.raises(InputError) as e:
            ShootingMPC(model, graph(), **kw)
        assert e.value.field == field


def test_zero_messages_start_every_plan_as_a_fresh_reset_would(one_thread):
    """messages="zero": a plan after steps equals the plan of a controller reset at that state."""
    model, g = make_model("mpnode"), graph()
    rng = np.random.default_rng(5)
    x = rng.standard_normal((B, N, DX))
    cost = tracking_cost(np.zeros(DX), [1.0, 1.0], [0.1, 0.1])
    mpc = ShootingMPC(model, g, H, bounds=(-1.0, 1.0), iterations=5, messages="zero")
    mpc.reset(x, 0.0)
    plant = Simulator(model, g)
    plant.reset(x)
    for _ in range(3):
        x = plant.step(mpc.control(x, cost))
    fresh = ShootingMPC(model, g, H, bounds=(-1.0, 1.0), iterations=5)
    fresh.reset(x, 0.0)
    fresh.plan = mpc.plan.copy()
    np.testing.assert_array_equal(fresh.control(x, cost), mpc.control(x, cost))
