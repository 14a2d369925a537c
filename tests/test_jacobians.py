"""Step Jacobians (mpnode.Simulator.jacobians) against central finite differences of one step,
in float64, for every kind with controls: dense and sparse agree, the sparse pattern follows the
graph (every entry outside it is zero in the finite differences too), the simulator does not move,
and the units are the data's."""
import copy

import numpy as np
import pytest
from engine_helpers import random_theta, spec_

from mpnode import Model, Simulator
from mpnode.base.graph import Graph
from mpnode.engine import jacobians
from mpnode.engine.kinematics import Kinematics

N, DX, DU, B = 12, 2, 2, 2

KINDS = {
    "mpnode": dict(message_dim=3),
    "mpnode-sum-self-linear-2substeps": dict(message_dim=2, aggregation="sum", self_messages=True,
                                             linear_aggregate=True, substeps=2),
    "l2s": dict(kind="l2s", aggregation="sum"),
    "node": dict(kind="node", n_nodes=N),
    "mpnode-encoder": dict(message_dim=3, encoder_window=3),  # format 4: the encoder's weights follow the field's
    "mpnode-kinematics": dict(message_dim=3, kinematics=Kinematics.parse("0:1")),
    "node-kinematics": dict(kind="node", n_nodes=N, kinematics=Kinematics.parse("1:0")),
}


def path_graph():
    """A path 0-1-...-(N-3) with one directed edge (N-2 hears 0) and an isolated node (N-1):
    long enough that one step's reach leaves most pairs of nodes out."""
    pairs = [(i, i + 1) for i in range(N - 3)] + [(i + 1, i) for i in range(N - 3)] + [(N - 2, 0)]
    return Graph.from_edges(N, pairs, directed=True)


def make_model(name, seed=0):
    """Random float64 weights and normalisation constants that are not 0/1."""
    rng = np.random.default_rng(seed)
    spec = spec_(state_dim=DX, control_dim=DU, hidden=8, dt=0.1, **{"message_dim": 0, "substeps": 1, **KINDS[name]})
    return Model(random_theta(rng, spec), spec, x_mean=rng.standard_normal(DX), x_std=1 + rng.random(DX),
                 u_mean=rng.standard_normal(DU), u_std=1 + rng.random(DU))


def stepped(model, graph, rng):
    """A simulator two steps in (messages no longer 0), and the next controls (B, N, du)."""
    sim = Simulator(model, graph)
    sim.reset(rng.standard_normal((B, N, DX)))
    for _ in range(2):
        sim.step(rng.standard_normal((B, N, DU)))
    return sim, rng.standard_normal((B, N, DU))


def next_state(sim, x, u):
    """The state after one step from x (B, N, dx, data units), sim's messages held."""
    other = copy.copy(sim)
    other._z = sim._z.copy()
    other._z[:, :DX] = sim.model.normalize_x(x).reshape(-1, DX)
    return other.step(u).reshape(B, -1)


def finite_differences(sim, u, eps=1e-5):
    """Central differences of one step in every state and control entry: (B, N*dx, N*dx), (B, N*dx, N*du)."""
    x = sim.state
    jx = np.empty((B, N * DX, N * DX))
    ju = np.empty((B, N * DX, N * DU))
    for k in range(N * DX):
        e = np.zeros(N * DX)
        e[k] = eps
        e = np.broadcast_to(e.reshape(N, DX), x.shape)
        jx[:, :, k] = (next_state(sim, x + e, u) - next_state(sim, x - e, u)) / (2 * eps)
    for k in range(N * DU):
        e = np.zeros(N * DU)
        e[k] = eps
        e = np.broadcast_to(e.reshape(N, DU), u.shape)
        ju[:, :, k] = (next_state(sim, x, u + e) - next_state(sim, x, u - e)) / (2 * eps)
    return jx, ju


@pytest.mark.parametrize("name", KINDS)
def test_step_jacobians_match_finite_differences(name):
    model, graph = make_model(name), path_graph()
    sim, u = stepped(model, graph, np.random.default_rng(3))
    before, steps = sim._z.copy(), sim.steps
    jx, ju = sim.jacobians(u)
    assert np.array_equal(sim._z, before) and sim.steps == steps  # it does not advance
    assert jx.shape == (B, N * DX, N * DX) and ju.shape == (B, N * DX, N * DU) and jx.dtype == np.float64
    fx, fu = finite_differences(sim, u)
    for got, want in ((jx, fx), (ju, fu)):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
    sx, su = sim.jacobians(u, sparse=True)
    assert len(sx) == len(su) == B
    for k in range(B):
        np.testing.assert_array_equal(sx[k].toarray(), jx[k])
        np.testing.assert_array_equal(su[k].toarray(), ju[k])
        # the pattern holds every entry the finite differences see
        outside = np.ones_like(fx[k], dtype=bool)
        outside[sx[k].nonzero()] = False
        assert np.abs(fx[k][outside]).max(initial=0) < 1e-9 * np.abs(fx[k]).max()
    if not name.startswith("node"):  # the pattern follows the graph: the isolated node hears only itself
        assert sx[0].nnz < 0.75 * (N * DX) ** 2
        assert set(sx[0][[N * DX - 1]].nonzero()[1]) == {N * DX - 2, N * DX - 1}


def test_reach_follows_the_stages():
    """An MP-NODE step reaches 3 hops (messages move from the second stage on), L2S 4, per substep."""
    graph = Graph.from_edges(20, [(i, i + 1) for i in range(19)])
    for kind, dm, substeps, hops in (("mpnode", 3, 1, 3), ("mpnode", 3, 2, 7), ("mpnode", 0, 2, 0),
                                     ("l2s", 0, 1, 4)):
        spec = spec_(kind=kind, message_dim=dm, substeps=substeps)
        assert jacobians.reach_hops(spec) == hops
        pattern = jacobians.reach_pattern(spec, graph)
        assert set(pattern[[10]].nonzero()[1]) == set(range(max(0, 10 - hops), min(20, 11 + hops)))


def test_row_colours_never_share_a_column():
    graph = Graph.from_edges(30, [(i, (i + 1) % 30) for i in range(30)] + [(0, 15)])
    pattern = jacobians.reach_pattern(spec_(substeps=1), graph)
    colour = jacobians.row_colours(pattern)
    dense = pattern.toarray()
    for c in range(colour.max() + 1):
        assert dense[colour == c].sum(axis=0).max() == 1
    assert colour.max() + 1 < 30  # far fewer VJPs than rows


def test_a_model_with_controls_needs_them():
    sim, _ = stepped(make_model("mpnode"), path_graph(), np.random.default_rng(0))
    with pytest.raises(ValueError, match="controls"):
        sim.jacobians()
    with pytest.raises(ValueError, match="expected"):
        sim.jacobians(np.zeros((B, N, DU + 1)))
