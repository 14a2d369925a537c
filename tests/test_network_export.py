"""Node attributes and edge weights beyond the model: the off-range warning names them as it names
states and degrees (each attribute by its name, the weights as "edge weight"), and both export
formats take them as inputs of the rollout, with defaults baked in (the training mean of each
attribute, the exported graph's weights), reproducing Model.rollout to float32 rounding with the
defaults and with others passed in (ONNX skipped without the onnx extra)."""
import warnings

import numpy as np
import pytest
from click.testing import CliRunner
from network_helpers import relaxing_nodes
from export_helpers import load_module, onnx_runtime

from cli.main import main
from mpnode import training
from mpnode.base.graph import Graph
from mpnode.data import Trajectories, write_trajectories
from mpnode.evaluation.evaluate import evaluate
from mpnode.model import Model, ranges
from mpnode.model.config import ModelConfig
from mpnode.runs import train
from mpnode.runs.run import new_model
from mpnode.training.batches import TrainingData

B, T = 3, 6


def redrawn(traj, weights=(0.5, 1.5), rates=(0.0, 2.0), seed=0):
    """``traj``'s states on its ring with edge weights and attributes drawn anew in the given
    ranges, their ends in every trajectory (whichever training keeps): what the ranges tests need
    (the states no longer follow them, which a range does not care about)."""
    rng = np.random.default_rng(seed)
    graphs = [g.reweighted(np.r_[weights, rng.uniform(*weights, g.n_edges - 2)]) for g in traj.graphs]
    attrs = rng.uniform(*rates, np.shape(traj.node_attrs))
    attrs[:, :2, 0] = rates
    return Trajectories.from_arrays(traj.x, graphs, dt=traj.dt, system=traj.system, graph_index=traj.graph_index,
                                    node_attrs=attrs, attr_names=traj.attr_names)


def beyond(traj, weight, rate):
    """``traj`` with the first graph's first edge at ``weight`` and the first node's attribute at ``rate``."""
    graphs = list(traj.graphs)
    graphs[0] = graphs[0].reweighted(np.r_[weight, graphs[0].weights[1:]])
    attrs = np.array(traj.node_attrs)
    attrs[0, 0, 0] = rate
    return Trajectories.from_arrays(traj.x, graphs, dt=traj.dt, system=traj.system, graph_index=traj.graph_index,
                                    node_attrs=attrs, attr_names=traj.attr_names)


@pytest.fixture(scope="module")
def ranged(tmp_path_factory):
    """A model trained by `mpnode.runs.train` (which records the ranges) on weights in [0.5, 1.5]
    and an attribute ``rate`` in [0, 2]."""
    path = tmp_path_factory.mktemp("ranged")
    write_trajectories(path / "train.h5", redrawn(relaxing_nodes(B=12)))
    train([path / "train.h5"], path / "m.h5", {"epochs": 2, "hidden": 8, "message_dim": 2, "batch_size": 4})
    return Model.load(path / "m.h5")


def test_training_records_the_weights_and_attributes_it_saw(ranged):
    seen = ranged.attrs[ranges.KEY]
    assert seen["edge_weight_min"] == [0.5] and seen["edge_weight_max"] == [1.5]
    assert seen["attribute_min"] == [0.0] and seen["attribute_max"] == [2.0]


def test_weights_and_attributes_beyond_training_are_named(ranged):
    data = redrawn(relaxing_nodes(B=4, seed=3), seed=3)
    assert evaluate(ranged, data, check_stability=False).off_range == []
    got = {e["quantity"]: e for e in evaluate(ranged, beyond(data, 3.0, 5.0), check_stability=False).off_range}
    assert {"edge weight", "attribute rate"} <= set(got)  # and what the rate then does to the rollout, if anything
    edge = got["edge weight"]
    node = int(np.repeat(np.arange(4), data.graphs[0].degrees())[0])  # the first edge's receiver
    assert (edge["value"], edge["node"], edge["trajectory"], edge["step"]) == (3.0, node, 0, None)
    assert edge["message"].startswith(f"edge weight 3 on an edge into node {node} (trajectory 0) is above the "
                                      "largest seen in training (1.5) by 1.5, 1.5x the range seen")
    rate = got["attribute rate"]
    assert (rate["value"], rate["node"], rate["channel"], rate["step"]) == (5.0, 0, None, None)
    assert rate["message"].startswith("attribute rate 5 at node 0 (trajectory 0) is above the largest seen in "
                                      "training (2) by 3")


def test_a_stepped_model_is_warned_of_them_too(ranged):
    """mpnode.model.ranges.Watch, which the Simulator runs: the weights when it starts, an
    attribute among the controls (normalised, as the engine takes them) when it steps."""
    data = beyond(redrawn(relaxing_nodes(B=1, seed=4), seed=4), 3.0, 5.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        watch = ranges.Watch(ranged, data.graphs[0], 1)
        z = np.zeros((4, 1 + ranged.spec.message_dim))
        watch(z, ranged.normalize_u(np.asarray(data.node_attrs[0])), 0)
    said = [str(w.message) for w in caught if issubclass(w.category, ranges.OffRangeWarning)]
    assert set(watch.entries) == {"edge weight", "attribute rate"} and len(said) == 2
    assert any("attribute rate 5 at node 0" in s for s in said)


@pytest.fixture(scope="module")
def trained():
    """A float32 model trained a few epochs on the weighted, attributed relaxing nodes, with
    initial states, a graph with its weights and attributes of a new draw."""
    data = relaxing_nodes(B=8, T=10)
    cfg = training.TrainConfig(epochs=3, batch_size=4, lr=1e-2)
    model = training.fit(new_model(TrainingData([data], cfg), ModelConfig(message_dim=2, hidden=8)), [data], cfg).model
    test = relaxing_nodes(B=B, T=1, seed=7)
    return model, np.asarray(test.x[:, 0], dtype=np.float32), test.graphs[0], np.asarray(test.node_attrs)


def cases(model, graph, attrs):
    """(inputs given to the export, the same as Model.rollout takes them): the defaults (the
    training mean of the attribute, the graph's weights), then other attributes per trajectory and
    other weights."""
    mean = np.full((graph.n_nodes, 1), model.u_mean[-1])
    weights = np.linspace(0.3, 2.5, graph.n_edges)
    return [({}, (graph, mean)), ({"node_attrs": attrs, "edge_weights": weights}, (graph.reweighted(weights), attrs))]


def test_the_numpy_module_takes_weights_and_attributes(tmp_path, trained):
    from mpnode.export import write_numpy_module

    model, x0, graph, attrs = trained
    assert model.dtype == np.float32 and model.attr_names == ["rate"] and graph.weighted
    write_numpy_module(model, graph, tmp_path / "m.py")
    module = load_module(tmp_path / "m.py")
    outs = []
    for given, (g, a) in cases(model, graph, attrs):
        got, want = module.rollout(x0, T, **given), model.rollout(x0, g, steps=T, node_attrs=a)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
        outs.append(got)
    assert np.abs(outs[1] - outs[0]).max() > 1e-3  # what is passed in counts
    one = module.rollout(x0[0], T, node_attrs=attrs[0])  # one trajectory: (N, dx) and (N, dp)
    np.testing.assert_array_equal(one, module.rollout(x0[:1], T, node_attrs=attrs[:1])[0])
    with pytest.raises(ValueError, match="edge_weights has shape"):
        module.rollout(x0, T, edge_weights=np.ones(graph.n_edges + 1))
    with pytest.raises(ValueError, match="node_attrs has shape"):
        module.rollout(x0, T, node_attrs=np.ones((graph.n_nodes, 2)))


def test_the_onnx_rollout_takes_weights_and_attributes(trained):
    ort = onnx_runtime()
    from mpnode.export.onnx_model import onnx_rollout

    model, x0, graph, attrs = trained
    proto = onnx_rollout(model, graph, T).SerializeToString()
    session = ort.InferenceSession(proto, providers=["CPUExecutionProvider"])
    for given, (g, a) in cases(model, graph, attrs):
        feed = {"x0": x0, **{k: np.asarray(v, dtype=np.float32) for k, v in given.items()}}
        (got,) = session.run(None, feed)
        want = model.rollout(x0, g, steps=T, node_attrs=a)
        assert got.dtype == np.float32 and got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * np.abs(want).max())
    (shared,) = session.run(None, {"x0": x0, "node_attrs": attrs[:1].astype(np.float32)})  # (1, N, dp): every one's
    want = model.rollout(x0, graph, steps=T, node_attrs=attrs[0])
    np.testing.assert_allclose(shared, want, rtol=1e-5, atol=1e-5 * np.abs(want).max())


def test_the_command_says_what_the_inputs_default_to(tmp_path, trained):
    model, x0, graph, attrs = trained
    model.save(tmp_path / "m.h5")
    data = relaxing_nodes(B=2, T=1, seed=7)
    write_trajectories(tmp_path / "d.h5", data)
    r = CliRunner().invoke(main, ["export", str(tmp_path / "m.h5"), "-o", str(tmp_path / "m.py"), "--graph",
                                  str(tmp_path / "d.h5")])
    assert r.exit_code == 0, r.output
    assert "node_attrs=None, edge_weights=None" in r.output and "the training mean of rate" in r.output
    module = load_module(tmp_path / "m.py")
    np.testing.assert_array_equal(module.MODEL["edge_weights"], data.graphs[0].weights)
    r = CliRunner().invoke(main, ["export", str(tmp_path / "m.h5"), "-o", str(tmp_path / "c.py"), "--nodes", "4"])
    assert r.exit_code == 0 and "(1 on every edge)" in r.output, r.output
    complete = load_module(tmp_path / "c.py")
    want = model.rollout(x0, Graph.complete(4), steps=T, node_attrs=complete.MODEL["node_attrs"])
    np.testing.assert_allclose(complete.rollout(x0, T), want, rtol=1e-6, atol=1e-6 * np.abs(want).max())


def test_a_model_of_unweighted_graphs_leaves_the_files_weights_out(tmp_path):
    """It never heard weights: exported from a weighted file, it runs on the wiring alone, takes no
    edge_weights, and says what a model without attributes says."""
    model = Model.create(1, 0, dt=0.1, message_dim=2, hidden=8, seed=3)
    model.save(tmp_path / "m.h5")
    data = relaxing_nodes(B=2, T=1, seed=7)
    write_trajectories(tmp_path / "d.h5", data)
    r = CliRunner().invoke(main, ["export", str(tmp_path / "m.h5"), "-o", str(tmp_path / "m.py"), "--graph",
                                  str(tmp_path / "d.h5")])
    assert r.exit_code == 0 and "rollout(x0, steps, u=None) of" in r.output and "defaults" not in r.output, r.output
    module = load_module(tmp_path / "m.py")
    x0 = np.asarray(data.x[:, 0], dtype=np.float32)
    want = model.rollout(x0, data.graphs[0].reweighted(None), steps=T)
    np.testing.assert_allclose(module.rollout(x0, T), want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
    with pytest.raises(ValueError, match="trained on unweighted graphs"):
        module.rollout(x0, T, edge_weights=data.graphs[0].weights)
