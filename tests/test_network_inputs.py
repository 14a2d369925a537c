"""Node attributes and edge weights in the model: what it hears, what its file keeps, what it
refuses, and that training learns a system whose nodes and edges differ."""
from dataclasses import replace

import numpy as np
import pytest

from mpnode import engine, training
from mpnode.base.errors import InputError
from mpnode.data import Trajectories, read_trajectories, write_trajectories
from mpnode.model import Model
from mpnode.model.config import ModelConfig
from mpnode.model.file import NETWORK_VERSION
from mpnode.model.inputs import for_model
from mpnode.runs.run import new_model
from mpnode.training.batches import TrainingData
from network_helpers import relaxing_nodes, ring


def test_a_model_hears_its_attributes_as_controls_held_over_every_step():
    m = Model.create(1, 0, dt=0.1, message_dim=2, hidden=8, seed=1, attr_names=["rate"], config=ModelConfig(dtype="float64"))
    x0 = np.random.default_rng(0).uniform(-1, 1, (3, 4, 1))
    a = np.random.default_rng(1).uniform(0.2, 2, (3, 4, 1))
    got = m.rollout(x0, ring(4), steps=5, node_attrs=a)
    plain = Model(m.theta, replace(m.spec, attr_dim=0), m.x_mean, m.x_std, m.u_mean, m.u_std)
    np.testing.assert_array_equal(got, plain.rollout(x0, ring(4), np.broadcast_to(a[:, None], (3, 5, 4, 1))))
    np.testing.assert_array_equal(m.rollout(x0[:1], ring(4), steps=5, node_attrs=a[0]), got[:1])  # (N, dp): shared
    assert np.abs(m.rollout(x0, ring(4), steps=5, node_attrs=a * 3) - got).max() > 1e-3
    with pytest.raises(InputError, match="node_attrs"):
        m.rollout(x0, ring(4), steps=5)


def test_the_attributes_cotangent_matches_finite_differences():
    """What fitting a network's parameters through a model reads (vjp(..., node_attrs=True): the
    attributes' control columns summed over the steps), against central differences in float64."""
    m = Model.create(1, 0, dt=0.1, message_dim=2, hidden=8, seed=2, attr_names=["rate"], config=ModelConfig(dtype="float64"))
    rng = np.random.default_rng(3)
    x0, a = rng.uniform(-1, 1, (4, 1)), rng.uniform(0.2, 2, (4, 1))
    gx = rng.standard_normal((7, 4, 1))
    held = np.broadcast_to(a, (6, 4, 1))
    _, vjp = engine.forward_with_vjp(m.spec, m.theta, x0, ring(4), held, 6)
    ga = vjp(gx, node_attrs=True)[2]
    assert ga.shape == (4, 1)
    for i in range(4):
        e = np.zeros_like(a)
        e[i] = 1e-5
        f = [np.sum(gx * engine.forward(m.spec, m.theta, x0, ring(4), np.broadcast_to(a + s * e, (6, 4, 1)), 6))
             for s in (1, -1)]
        fd = (f[0] - f[1]) / 2e-5
        assert abs(fd - ga[i, 0]) < 1e-6 * max(abs(fd), 1e-3), (i, fd, ga[i, 0])


def test_the_model_file_keeps_attributes_and_weights(tmp_path):
    data = TrainingData([relaxing_nodes(B=6)], training.TrainConfig())
    m = new_model(data, ModelConfig(message_dim=2, hidden=8, dtype="float64"))
    assert m.spec.attr_dim == 1 and m.attr_names == ["rate"]
    assert m.spec.aggregation.weight_scale == pytest.approx(np.mean([g.weights for g in data.datasets[0].graphs]))
    m.save(tmp_path / "m.h5")
    import h5py

    with h5py.File(tmp_path / "m.h5") as f:
        assert f.attrs["format_version"] == NETWORK_VERSION
    back = Model.load(tmp_path / "m.h5")
    assert back.spec == m.spec and back.attr_names == ["rate"]
    traj = relaxing_nodes(B=2, seed=5)
    args = (traj.x[:, 0], traj.graphs, None, 6)
    np.testing.assert_array_equal(back.rollout(*args, node_attrs=traj.node_attrs), m.rollout(*args, node_attrs=traj.node_attrs))


def test_attributes_and_weights_that_are_not_the_models_are_refused():
    traj = relaxing_nodes(B=3)
    plain = Model.create(1, 0, dt=0.1, hidden=8)
    with pytest.raises(InputError, match="trained without any.*--ignore-attrs"):
        for_model(plain, traj, "data.h5")
    dropped = for_model(plain, traj, "data.h5", ignore_attrs=True)
    assert dropped.node_attrs is None and dropped.control_dim == 0 and not dropped.weighted
    m = new_model(TrainingData([traj], training.TrainConfig()), ModelConfig(hidden=8))
    unweighted = Trajectories.from_arrays(traj.x, ring(4), dt=0.1, system="relaxing", node_attrs=traj.node_attrs,
                                          attr_names=["rate"])
    with pytest.raises(InputError, match="weights.*missing"):
        for_model(m, unweighted, "data.h5")
    renamed = Trajectories.from_arrays(traj.x, traj.graphs, dt=0.1, graph_index=traj.graph_index, system="relaxing",
                                       node_attrs=traj.node_attrs, attr_names=["decay"])
    with pytest.raises(InputError, match="decay.*rate"):
        for_model(m, renamed, "data.h5")
    heard = for_model(m, traj, "data.h5")
    assert heard.control_dim == 1 and np.array_equal(heard.u[:, 3], traj.node_attrs)


@pytest.mark.slow
def test_training_learns_nodes_and_edges_that_differ(tmp_path):
    """Through a format-3 file: trained 300 epochs, the model with attributes and weights predicts
    new draws better than one trained on the same data without them (0.025 against 0.054 when
    this was written)."""
    write_trajectories(tmp_path / "train.h5", relaxing_nodes(B=96, seed=0))
    write_trajectories(tmp_path / "test.h5", relaxing_nodes(B=16, seed=9))
    train, test = read_trajectories(tmp_path / "train.h5"), read_trajectories(tmp_path / "test.h5")
    assert train.attr_names == ["rate"] and train.weighted
    cfg = training.TrainConfig(epochs=300, batch_size=16, lr=1e-2)

    def test_error(ignore):
        from mpnode.evaluation.evaluate import evaluate

        c = replace(cfg, ignore_attrs=ignore)
        m = new_model(TrainingData([train], c), ModelConfig(message_dim=2, hidden=16))
        assert (m.spec.attr_dim, m.spec.aggregation.weight_scale is None) == ((0, True) if ignore else (1, False))
        r = training.fit(m, [train], c)
        return evaluate(r.model, test, "test.h5", ignore_attrs=ignore, check_stability=False).nmse

    with_them, without = test_error(False), test_error(True)
    assert with_them < 0.035 and with_them < 0.6 * without, (with_them, without)
