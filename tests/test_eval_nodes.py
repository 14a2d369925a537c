"""Where on the network the error lies: each node's error (mpnode.evaluation.nodes), `mpnode eval`'s
report and JSON of it (a grid's frequency per bus), and the network in `eval --plot`."""
import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode.base.graph import Graph
from mpnode.data import Trajectories, write_trajectories
from mpnode.evaluation.evaluate import evaluate
from mpnode.evaluation.nodes import busiest_graph, node_errors
from mpnode.model import Model
from network_helpers import ring


def wandering(B=4, T=12, N=6, dx=2, graphs=None, graph_index=None, seed=0):
    """Smooth random states on rings of N nodes (one ring unless ``graphs`` are given), dt 0.1."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(0, 0.1, (B, T + 1, N, dx)), axis=1) + rng.uniform(-1, 1, (B, 1, N, dx))
    return Trajectories(x=x, graphs=graphs or [ring(N)], dt=0.1, system="wandering", graph_index=graph_index)


@pytest.mark.parametrize("warmup", [0, 4])
def test_the_nodes_errors_average_back_to_the_overall_error(fresh, warmup):
    traj = wandering()
    r = evaluate(fresh(), traj, warmup=warmup)
    assert r.first_bad_step is None and r.nodes.nmse.shape == (6, 2)
    np.testing.assert_allclose(r.nodes.nmse.mean(axis=0), r.nmse_per_dim, rtol=1e-12)
    np.testing.assert_allclose(r.nodes.error.mean(), r.nmse, rtol=1e-12)
    # the RMS error is in the data's units: the squared errors' mean, unnormalised
    first = max(warmup, 1)
    sq = (r.predictions[:, first:].astype(np.float64) - traj.x[:, first:]) ** 2
    np.testing.assert_allclose(r.nodes.rmse, np.sqrt(sq.mean(axis=(0, 1))), rtol=1e-12)
    assert list(r.nodes.trajectories) == [0, 1, 2, 3] and r.nodes.dims == [0, 1]


def test_the_view_is_of_the_graph_most_trajectories_run_on(fresh):
    assert busiest_graph([1, 0, 1, 2])[0] == 1 and list(busiest_graph([1, 0, 1, 2])[1]) == [0, 2]
    assert busiest_graph([2, 0, 1, 2, 0])[0] == 0  # a tie: the first graph
    path = Graph.from_edges(6, [(i, i + 1) for i in range(5)])
    r = evaluate(fresh(), wandering(B=5, graphs=[ring(6), path], graph_index=[1, 0, 1, 1, 0]))
    assert r.nodes.graph == 1 and list(r.nodes.trajectories) == [0, 2, 3]
    summary = r.summary()["per_node"]
    assert summary["trajectories"] == 3 and summary["all_trajectories"] is False


def test_the_worst_nodes_are_those_of_largest_error_on_the_watched_dimensions():
    rng = np.random.default_rng(1)
    truth = rng.normal(size=(3, 6, 8, 3))
    scale = rng.permutation(8) + 1.0  # node i's error on dimension 2
    pred = truth + rng.normal(size=truth.shape) * 0.01
    pred[..., 2] += scale * 0.1 * rng.choice([-1, 1], size=truth.shape[:3])
    pred[:, :, 5, 0] += 100.0  # node 5 is the worst on dimension 0, not on the watched one
    nodes = node_errors(pred, truth, truth, np.zeros(3, dtype=int), dims=[2], names=[f"bus {i + 1}" for i in range(8)])
    want = ((pred[:, 1:, :, 2] - truth[:, 1:, :, 2]) ** 2).mean(axis=(0, 1)) / truth[..., 2].var()
    np.testing.assert_allclose(nodes.error, want)
    assert nodes.worst() == list(np.argsort(-want)[:5]) and nodes.worst(1) == [int(np.argmax(scale))]
    assert nodes.median() == int(np.argsort(want)[3])  # the lower median of eight
    assert node_errors(pred, truth, truth, np.zeros(3, dtype=int)).worst(1) == [5]  # the whole state
    summary = nodes.summary(3)
    assert summary["worst"][0] == {"node": nodes.worst(1)[0], "name": f"bus {nodes.worst(1)[0] + 1}",
                                   "nmse": pytest.approx(want.max()), "rmse": pytest.approx(nodes.rms.max())}
    # a node nobody observed is not ranked; one whose prediction became non-finite is the worst
    truth[:, :, 3] = np.nan
    pred[1, 4, 6, 2] = np.inf
    nodes = node_errors(pred, truth, truth, np.zeros(3, dtype=int), dims=[2])
    assert 3 not in nodes.ranked() and nodes.worst(1) == [6] and nodes.name(6) == "node 6"
    summary = nodes.summary(3)
    assert summary["nmse"][3] == "nan" and summary["worst"][0]["nmse"] == "inf"


@pytest.fixture(scope="module")
def ieee14(tmp_path_factory):
    """An IEEE 14-bus file (three short trajectories) and an untrained model of its state."""
    pytest.importorskip("pypower", reason="the IEEE cases need PYPOWER (the grids extra)")
    from dataclasses import replace

    from data_gen import generate, load_scene

    folder = tmp_path_factory.mktemp("ieee14")
    write_trajectories(folder / "d.h5", generate(replace(load_scene("ieee14"), trajectories=3, horizon=20), workers=1))
    Model.create(3, 0, message_dim=3, hidden=8, dt=0.05).save(folder / "m.h5")
    return folder


def test_eval_reports_the_frequency_error_per_bus_and_the_reference(ieee14):
    args = ["eval", str(ieee14 / "m.h5"), str(ieee14 / "d.h5"), "--ignore-attrs", "--reference-sample", "2"]
    res = CliRunner().invoke(main, args + ["--json"])
    assert res.exit_code == 0, res.output
    report = json.loads(res.output)
    v = report["per_node"]
    assert v["dims"] == [2] and report["state_names"][2] == "frequency deviation (rad/s)"
    assert v["names"] == [f"bus {i}" for i in range(1, 15)] and v["all_trajectories"] and v["graph"] == 0
    assert len(v["nmse"]) == len(v["rmse"]) == len(v["nmse_per_dim"]) == 14
    assert all(isinstance(e, float) and math.isfinite(e) for e in v["nmse"] + v["rmse"])
    assert [e["nmse"] for e in v["worst"]] == sorted(v["nmse"], reverse=True)[:5]
    assert v["worst"][0]["name"] == f"bus {v['worst'][0]['node'] + 1}"
    assert v["median"]["nmse"] == sorted(v["nmse"])[6]
    assert np.mean(v["nmse"]) == pytest.approx(report["nmse_per_dim"][2], rel=1e-9)
    ref = report["reference"]  # the speed-against-error line on the same grid
    assert ref["system"] == "swing" and ref["speedup"] > 0 and math.isfinite(ref["learned_seconds_per_trajectory"])
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "per node, by frequency deviation (rad/s) (graph 0, all 3 trajectories" in res.output
    assert f"median {v['median']['name']} (node {v['median']['node']})" in res.output
    assert "    worst: bus " in res.output and "speed against error: learned" in res.output


def test_eval_plot_draws_the_grid_and_its_worst_and_median_bus(ieee14, tmp_path):
    pytest.importorskip("matplotlib", reason="the figures need matplotlib (the plot extra)")
    from mpnode.data import read_trajectories
    from mpnode.plot import plot_eval

    res = CliRunner().invoke(main, ["eval", str(ieee14 / "m.h5"), str(ieee14 / "d.h5"), "--ignore-attrs",
                                    "--reference-sample", "0", "--plot", str(tmp_path / "e.png")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "e.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    traj = read_trajectories(ieee14 / "d.h5")
    r = evaluate(Model.load(ieee14 / "m.h5"), traj, ignore_attrs=True, node_dims=[2],
                 node_names=[f"bus {i}" for i in range(1, 15)])
    fig = plot_eval(traj, r)
    assert tuple(fig.get_size_inches() * fig.dpi) == (1200, 1200)
    words = {t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text")) if t.get_text()}
    worst, median = r.nodes.worst(1)[0], r.nodes.median()
    assert f"worst: bus {worst + 1}, nMSE {r.nodes.error[worst]:.3g}" in words
    assert f"median: bus {median + 1}, nMSE {r.nodes.error[median]:.3g}" in words
    assert {"graph 0, 3 trajectories: error per node", "nMSE of frequency deviation (rad/s)"} <= words
    assert len(fig.axes) == 3 * 2 + 1 + 3 + 1  # dims x 2 trajectories + error; network, worst, median; colourbar

