"""Changing a model's normalisation constants must not change what it computes."""
import numpy as np
import pytest
from engine_helpers import make_graph

from mpnode.model import Model
from mpnode.model.renormalise import renormalised

DX, DU = 2, 2
KINDS = [dict(kind="mpnode", message_dim=3), dict(kind="mpnode", message_dim=3, linear_aggregation="scaled",
                                                   mean_degree=2.5),
         dict(kind="mpnode", message_dim=3, linear_target="state"), dict(kind="l2s"), dict(kind="node", n_nodes=9)]


def model_of(kind):
    m = Model.create(DX, control_dim=DU, hidden=8, dt=0.05, seed=3, dtype=np.float64, **kind)
    rng = np.random.default_rng(4)
    m.theta[:] = rng.uniform(-0.6, 0.6, m.theta.shape)  # every weight, W_agg and biases included, non-zero
    m.x_mean, m.x_std = np.array([0.5, -1.25]), np.array([2.0, 0.3])
    m.u_mean, m.u_std = np.array([-0.1, 3.0]), np.array([0.7, 1.5])
    return m


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: "-".join(str(v) for v in k.values()))
def test_renormalised_model_rolls_out_the_same_in_data_units(kind):
    m = model_of(kind)
    rng = np.random.default_rng(0)
    graph = make_graph(rng, 9)
    x0 = rng.standard_normal((3, 9, DX)) * m.x_std + m.x_mean
    u = rng.standard_normal((3, 6, 9, DU)) * m.u_std + m.u_mean
    r = renormalised(m, [3.0, 0.1], [0.5, 0.05], [1.0, -2.0], [4.0, 0.2])
    assert np.allclose(r.x_std, [0.5, 0.05]) and np.allclose(r.u_mean, [1.0, -2.0])
    assert not np.allclose(r.theta, m.theta)
    np.testing.assert_allclose(r.rollout(x0, graph, u), m.rollout(x0, graph, u), rtol=1e-10, atol=1e-10)
    # the original is untouched
    assert np.allclose(m.x_std, [2.0, 0.3])


def test_renormalised_keeps_the_controls_constants_when_none_are_given():
    m = model_of(KINDS[0])
    r = renormalised(m, m.x_mean + 1.0, m.x_std * 2.0)
    assert np.array_equal(r.u_mean, m.u_mean) and np.array_equal(r.u_std, m.u_std)
