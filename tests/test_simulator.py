"""The stepping API (mpnode.Simulator): T calls of step() are Model.rollout bit for bit, for
every model kind, with and without controls, on both compiled drivers and the NumPy path;
the messages it shows are the integrated ones; its errors say what to fix."""
import networkx as nx
import numpy as np
import pytest
from engine_helpers import DRIVERS_AND_DTYPES, make_graph, random_model, rollout_ref

from mpnode import InputError, Simulator
from mpnode.base.graph import Graph
from mpnode.engine import numpy_path as numpy_engine

N, DX, DU, T, B = 9, 2, 2, 6, 3

KINDS = {
    "mpnode": dict(message_dim=3),
    "mpnode-sum-self": dict(message_dim=2, aggregation="sum", self_messages=True),
    "l2s": dict(kind="l2s", aggregation="sum"),
    "node": dict(kind="node", n_nodes=N),
}


def make_model(name, du, dtype, seed=0):
    return random_model(KINDS[name], DX, du, dtype, seed)


def graph():
    return make_graph(np.random.default_rng(1), N)  # an isolated node and directed edges


def closed_loop(sim, x0, du):
    """Step T times, each control a function of the current state (so no rollout could know it
    in advance); returns the states (B, T+1, N, dx) and the controls used (B, T, N, du)."""
    xs, us = [sim.reset(x0)], []
    for t in range(T):
        u = np.tanh(xs[-1][..., :1] * np.arange(1, du + 1) + t) if du else None
        xs.append(sim.step(u))
        us.append(u)
    return np.stack(xs, 1), (np.stack(us, 1) if du else None)


def check_steps_equal_rollout(name, du, dtype, backend):
    model, g = make_model(name, du, dtype), graph()
    x0 = np.random.default_rng(2).standard_normal((B, N, DX))
    x, u = closed_loop(Simulator(model, g, backend=backend), x0, du)
    want = model.rollout(x0, g, u, steps=T, backend=backend)
    assert x.dtype == want.dtype == dtype
    np.testing.assert_array_equal(x, want)
    assert np.abs(x[:, -1] - x[:, 0]).max() > 1e-2  # it moves


@pytest.mark.parametrize("driver,dtype", DRIVERS_AND_DTYPES, indirect=["driver"])
@pytest.mark.parametrize("du", [0, DU], ids=["no-controls", "controls"])
@pytest.mark.parametrize("name", KINDS)
def test_steps_equal_rollout_bit_for_bit(driver, name, du, dtype):
    check_steps_equal_rollout(name, du, dtype, "numba")


@pytest.mark.parametrize("du", [0, DU], ids=["no-controls", "controls"])
@pytest.mark.parametrize("name", KINDS)
def test_steps_equal_rollout_bit_for_bit_on_the_numpy_path(name, du):
    check_steps_equal_rollout(name, du, np.float64, "numpy")


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_messages_are_the_integrated_ones(backend):
    model, g = make_model("mpnode", DU, np.float64), graph()
    x0 = np.random.default_rng(3).standard_normal((B, N, DX))
    u = np.random.default_rng(4).standard_normal((B, T, N, DU))
    sim = Simulator(model, g, backend=backend)
    sim.reset(x0)
    assert sim.messages.shape == (B, N, 3) and not np.any(sim.messages)  # messages start at 0
    for t in range(T):
        sim.step(u[:, t])
    for b in range(B):  # the NumPy path's messages, trajectory by trajectory in model units
        _, m = rollout_ref(model.spec, model.theta, model.normalize_x(x0[b]), g, model.normalize_u(u[b]), T,
                           with_messages=True)
        np.testing.assert_allclose(sim.messages[b], m[-1], rtol=1e-12, atol=1e-12)
    assert np.abs(sim.messages).max() > 1e-2
    sim.messages[:] = 0  # a copy: the simulator's state is untouched
    assert np.abs(sim.messages).max() > 1e-2


@pytest.mark.parametrize("name", ["l2s", "node"])
def test_kinds_without_messages_show_none(name):
    sim = Simulator(make_model(name, 0, np.float64), graph())
    sim.reset(np.zeros((1, N, DX)))
    sim.step()
    assert sim.messages is None


def test_reset_starts_again_and_counts_steps():
    model, g = make_model("mpnode", 0, np.float32), graph()
    x0 = np.random.default_rng(5).standard_normal((2, N, DX))
    sim = Simulator(model, g)
    first = closed_loop(sim, x0, 0)[0]
    assert sim.steps == T
    np.testing.assert_array_equal(closed_loop(sim, x0, 0)[0], first)
    np.testing.assert_array_equal(sim.state, first[:, -1])
    assert sim.dt == 0.1


def test_a_model_file_and_a_networkx_graph_are_accepted(tmp_path):
    model = make_model("mpnode", 0, np.float32)
    model.save(tmp_path / "m.h5")
    nxg = nx.cycle_graph(N)
    x0 = np.random.default_rng(6).standard_normal((2, N, DX))
    a = closed_loop(Simulator(str(tmp_path / "m.h5"), nxg), x0, 0)[0]
    np.testing.assert_array_equal(a, model.rollout(x0, Graph.from_networkx(nxg), steps=T))


def test_errors_say_what_to_fix():
    model, g = make_model("mpnode", DU, np.float64), graph()
    sim = Simulator(model, g)
    with pytest.raises(RuntimeError, match="reset"):
        sim.step(np.zeros((1, N, DU)))
    with pytest.raises(InputError, match=r"expected \(B, 9, 2\)"):
        sim.reset(np.zeros((N, DX)))
    sim.reset(np.zeros((2, N, DX)))
    with pytest.raises(InputError, match=r"u: has shape \(2, 9, 3\).*\(2, 9, 2\)"):
        sim.step(np.zeros((2, N, 3)))
    with pytest.raises(InputError, match="takes controls"):
        sim.step()
    with pytest.raises(InputError, match="kind node"):
        Simulator(make_model("node", 0, np.float64), Graph.complete(N + 1))
    with pytest.raises(InputError, match="networkx"):
        Simulator(model, [(0, 1)])
    with pytest.raises(InputError, match="backend"):
        Simulator(model, g, backend="torch")


def test_the_numpy_engine_continues_where_it_stopped():
    """numpy_engine.integrate from a full state: two halves are the whole, bit for bit."""
    model, g = make_model("mpnode", DU, np.float64), graph()
    z0 = np.random.default_rng(7).standard_normal((N, DX + 3))
    u = np.random.default_rng(8).standard_normal((T, N, DU))
    x, z = numpy_engine.integrate(model.spec, model.theta, z0, g, u, T)
    x1, z1 = numpy_engine.integrate(model.spec, model.theta, z0, g, u[:2], 2)
    x2, z2 = numpy_engine.integrate(model.spec, model.theta, z1, g, u[2:], T - 2)
    np.testing.assert_array_equal(np.concatenate([x1, x2[1:]]), x)
    np.testing.assert_array_equal(z2, z)
