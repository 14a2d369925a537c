"""What a model saw in training (mpnode.model.ranges): recorded by training, kept by the model
file, and the inputs off it reported by eval, simulate and the Simulator; eval's error by
block of steps and the drift of a conserved quantity (data_gen.invariants)."""
import json
import warnings

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from data_gen.invariants import invariant_of, pendulum_energy
from mpnode import Simulator
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph
from mpnode.data import Trajectories, write_trajectories
from mpnode.evaluation.evaluate import evaluate
from mpnode.evaluation.metrics import by_block
from mpnode.model import Model, ranges


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def star(n):
    """Node 0 hears every other node, and they hear it: in-degrees n-1 and 1."""
    return Graph.from_edges(n, [(0, k) for k in range(1, n)])


def with_ranges(model, traj):
    """``model`` with the ranges of ``traj`` (every trajectory a training one) recorded."""
    model.attrs[ranges.KEY] = ranges.training_ranges(model, [traj], [(np.arange(traj.n_trajectories), [])])
    return model


def trajectories(graph, b=6, t=8, scale=1.0, seed=0):
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(0, 0.05, (b, t + 1, graph.n_nodes, 2)), axis=1) + rng.uniform(-1, 1, (b, 1, 1, 2))
    return Trajectories(x=scale * x, graphs=[graph], dt=0.1, system="tiny_linear")


@pytest.fixture
def model(fresh):
    return with_ranges(fresh(), trajectories(star(4)))


def test_recorded_ranges_hold_the_training_data_and_its_graphs(model):
    seen = model.attrs[ranges.KEY]
    x = trajectories(star(4)).x
    assert np.all(np.asarray(seen["state_min"]) <= x.min(axis=(0, 1, 2)))
    assert np.all(np.asarray(seen["state_max"]) >= x.max(axis=(0, 1, 2)))
    assert seen["in_degree_min"] == [1.0] and seen["in_degree_max"] == [3.0] and seen["nodes_max"] == [4.0]
    assert len(seen["aggregate_min"]) == model.spec.message_dim  # the messages the MLP hears, per channel


def test_the_training_data_themselves_are_not_off_the_range(model):
    assert evaluate(model, trajectories(star(4)), check_stability=False).off_range == []


def test_a_denser_graph_and_larger_states_are_reported_with_value_bound_and_node(model):
    res = evaluate(model, trajectories(star(9), scale=5.0, seed=1), check_stability=False)
    got = {e["quantity"]: e for e in res.off_range}
    assert got["in-degree"]["value"] == 8 and got["in-degree"]["node"] == 0
    assert got["in-degree"]["message"].startswith("in-degree 8 at node 0 is above the largest seen in training (3)")
    assert got["number of nodes"]["value"] == 9
    assert {"state x[0]", "state x[1]"} & set(got)
    assert all(e["beyond_width"] is None or e["beyond_width"] > ranges.MARGIN for e in res.off_range)
    assert res.summary()["off_range"] == res.off_range and res.summary()["training_ranges_recorded"]


def test_within_the_margin_is_not_off_the_range():
    tally = ranges.Tally()
    tally.add("state", np.array([[[0.0], [1.0]]]), 0)
    seen = ranges.record(tally)
    inside, outside = ranges.Tally(), ranges.Tally()
    inside.add("state", np.array([[[1.0 + 0.9 * ranges.MARGIN]]]), 3)
    outside.add("state", np.array([[[-0.5], [0.2]]]), 7, first_trajectory=2)
    assert ranges.off_range(seen, inside) == []
    (e,) = ranges.off_range(seen, outside, state_names=["angle"])
    assert (e["quantity"], e["side"], e["node"], e["trajectory"], e["step"]) == ("state angle", "below", 0, 2, 7)
    assert e["beyond"] == pytest.approx(0.5) and e["beyond_width"] == pytest.approx(0.5)


def test_a_model_without_recorded_ranges_is_not_checked(fresh):
    res = evaluate(fresh(), trajectories(star(9)), check_stability=False)
    assert res.off_range is None and res.summary()["off_range"] == []
    assert not res.summary()["training_ranges_recorded"]


def test_the_model_file_keeps_the_ranges_and_refuses_a_damaged_group(tmp_path, model):
    path = tmp_path / "m.h5"
    model.save(path)
    with h5py.File(path, "r") as f:
        assert "seen" in f and f.attrs["format_version"] == 2  # optional data: no new version
    assert Model.load(path).attrs[ranges.KEY] == model.attrs[ranges.KEY]
    with h5py.File(path, "a") as f:
        del f["seen/state_min"]
        f["seen/state_min"] = np.array(["a"], dtype="S1")
    with pytest.raises(InputError, match="seen/state_min"):
        Model.load(path)


def test_the_simulator_warns_once_per_quantity(model):
    sim = Simulator(model, star(9))
    x0 = trajectories(star(9)).x[:2, 0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sim.reset(x0)
        for _ in range(3):
            sim.step()
    off = [w for w in caught if issubclass(w.category, ranges.OffRangeWarning)]
    quantities = [e["quantity"] for e in sim.off_range]
    assert len(off) == len(quantities) == len(set(quantities)) and "in-degree" in quantities
    with warnings.catch_warnings():
        warnings.simplefilter("error", ranges.OffRangeWarning)
        quiet = Simulator(model, star(4))
        quiet.reset(trajectories(star(4)).x[:2, 0])
        assert quiet.off_range == []


def test_eval_json_has_off_range_and_the_error_by_block(tmp_path, model):
    model.save(tmp_path / "m.h5")
    write_trajectories(tmp_path / "dense.h5", trajectories(star(9), seed=2))
    res = run("eval", tmp_path / "m.h5", tmp_path / "dense.h5", "--json", "--reference-sample", 0)
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)  # standard output holds the object alone
    assert "in-degree" in {e["quantity"] for e in report["off_range"]}
    assert "warning: off the training range: in-degree 8 at node 0" in res.stderr
    assert [b["steps"] for b in report["nmse_by_block"]] == [[1, 2], [3, 4], [5, 6], [7, 7], [8, 8]]
    text = run("eval", tmp_path / "m.h5", tmp_path / "dense.h5", "--reference-sample", 0)
    assert "OFF THE TRAINING RANGE" in text.stdout and "error against horizon" in text.stdout


def test_by_block_means_steps_first_to_last():
    blocks = by_block(np.array([0.0, 1, 2, 3, 4, np.nan, 6]), first=1, blocks=3)
    assert blocks == [{"steps": [1, 2], "value": 1.5}, {"steps": [3, 4], "value": 3.5},
                      {"steps": [5, 6], "value": 6.0}]


def test_the_pendulum_energy_is_conserved_by_the_reference_and_reported_by_eval(tmp_path, fresh):
    run("generate", "coupled_pendulum", "-o", tmp_path / "p.h5", "-B", 3, "-T", 40, "--workers", 1)
    from mpnode.data import read_trajectories

    traj = read_trajectories(tmp_path / "p.h5")
    assert traj.attrs["invariant"] == "energy"
    name, energy = invariant_of(traj)
    e = energy(np.asarray(traj.x))
    assert name == "energy" and np.max(np.abs(e / e[:, :1] - 1)) < 1e-6
    still = np.asarray(traj.x)[:, :1].repeat(2, axis=1)
    still[:, 1, :, 1] += 0.1  # a pendulum that speeds up gains energy
    g = traj.graphs[0]
    assert np.all(pendulum_energy(still, g, 1.0, 1.5, 2.0, 9.81)[:, 1] != pendulum_energy(still, g, 1.0, 1.5, 2.0,
                                                                                         9.81)[:, 0])
    m = Model.create(2, 0, message_dim=2, hidden=8, dt=traj.dt, seed=0)
    m.save(tmp_path / "m.h5")
    res = run("eval", tmp_path / "m.h5", tmp_path / "p.h5", "--json", "--reference-sample", 0)
    report = json.loads(res.stdout)
    drift = report["invariant_drift_by_block"]
    assert report["invariant"] == "energy" and all(b["truth"] < 1e-6 for b in drift)
    assert drift[-1]["value"] > 1e-3  # an untrained model does not conserve it


def test_train_and_finetune_record_the_ranges_of_their_own_data(tmp_path, tiny_file):
    quick = ["--epochs", 1, "--hidden", 8, "--batch-size", 32]
    first, later = tiny_file(tmp_path / "a.h5"), tiny_file(tmp_path / "b.h5", seed=1, offset=3.0)
    assert run("train", first, "-o", tmp_path / "m.h5", *quick).exit_code == 0
    assert run("finetune", tmp_path / "m.h5", later, "-o", tmp_path / "f.h5", "--epochs", 1).exit_code == 0
    trained, tuned = (Model.load(tmp_path / name).attrs[ranges.KEY] for name in ("m.h5", "f.h5"))
    assert trained["in_degree_max"] == [1.0] and trained["nodes_max"] == [2.0]
    assert max(trained["state_max"]) < 1.5 and min(tuned["state_max"]) > 2.0  # the fine-tuning data's own


def test_simulate_warns_on_standard_error_and_still_writes(tmp_path, model):
    model.save(tmp_path / "m.h5")
    write_trajectories(tmp_path / "dense.h5", trajectories(star(9), seed=3))
    res = run("simulate", tmp_path / "m.h5", tmp_path / "dense.h5", "-o", tmp_path / "sim.h5", "-T", 4)
    assert res.exit_code == 0, res.output
    assert "warning: off the training range: in-degree 8 at node 0" in res.stderr
    assert "off the training range" not in res.stdout and (tmp_path / "sim.h5").exists()


def test_blown_up_values_leave_the_report_valid_json():
    tally = ranges.Tally()
    tally.add("state", np.array([[[0.0], [1.0]]]), 0)
    seen = ranges.record(tally)
    wild = ranges.Tally()
    wild.add("state", np.array([[[np.inf], [np.nan], [2.0]]]), 5)
    (e,) = ranges.off_range(seen, wild)
    assert e["value"] == 2.0 and e["node"] == 2
    blocks = by_block(np.array([0.0, 1.0, np.inf]), blocks=2)
    assert blocks[-1]["value"] == np.inf  # metrics keep the number; EvalResult.summary writes it as "inf"


@pytest.mark.parametrize("kind", ["l2s", "node"])
def test_every_kind_records_and_checks_its_inputs(kind):
    traj = trajectories(star(4))
    m = with_ranges(Model.create(2, 0, kind=kind, hidden=8, dt=0.1, seed=0, n_nodes=4 if kind == "node" else None),
                    traj)
    seen = m.attrs[ranges.KEY]
    assert ("aggregate_min" in seen) == (kind == "l2s") and len(seen.get("aggregate_min", [0] * 8)) == 8
    assert evaluate(m, traj, check_stability=False).off_range == []
    far = trajectories(star(4), scale=10.0, seed=4)
    assert any(e["quantity"].startswith("state") for e in evaluate(m, far, check_stability=False).off_range)
