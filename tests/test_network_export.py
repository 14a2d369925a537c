"""Node attributes and edge weights beyond the model: the off-range warning names them as it names
states and degrees (each attribute by its name, the weights as "edge weight")."""
import warnings

import numpy as np
import pytest
from network_helpers import relaxing_nodes

from mpnode.data import Trajectories, write_trajectories
from mpnode.evaluation.evaluate import evaluate
from mpnode.model import Model, ranges
from mpnode.runs import train


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
