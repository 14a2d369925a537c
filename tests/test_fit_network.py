"""fit_network: the loss's gradient is exact, and a fit through the model that made the data names
the node (line) that was changed."""
import json
from pathlib import Path

import numpy as np
import pytest

import mpnode
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph
from mpnode.data import Trajectories
from mpnode.evaluation.network_fit import _AttrParameters, _Problem, _WeightParameters, _windows, lines_of
from mpnode.model import Model
from mpnode.model.config import ModelConfig
from doc_snippets import fenced_blocks, run_python, run_shell
from network_helpers import ring

N, B, T = 6, 8, 12


def chorded_ring(weights=None):
    """A ring of N nodes with one chord, undirected: 7 lines, 14 edges."""
    g = Graph.from_edges(N, [(i, (i + 1) % N) for i in range(N)] + [(0, 3)])
    return g if weights is None else g.reweighted(weights)


def model(seed=2, weighted=True):
    return Model.create(1, 0, dt=0.1, message_dim=2, hidden=8, seed=seed, attr_names=["rate", "size"],
                        weight_scale=1.5 if weighted else None, config=ModelConfig(dtype="float64"))


def nominal():
    rng = np.random.default_rng(0)
    attrs = np.stack([rng.uniform(0.5, 2.0, N), rng.uniform(1.0, 3.0, N)], axis=1)
    line_of, lines = lines_of(chorded_ring())
    w = rng.uniform(0.5, 2.5, len(lines))[line_of]
    return attrs, chorded_ring(w)


def made_by(m, attrs, graph, seed=1):
    """B trajectories the model itself makes on ``graph`` with node attributes ``attrs``."""
    x0 = np.random.default_rng(seed).uniform(-1, 1, (B, N, 1))
    x = m.rollout(x0, graph, steps=T, node_attrs=attrs)
    return Trajectories.from_arrays(x, graph, dt=0.1, system="made", node_attrs=attrs, attr_names=m.attr_names)


def test_lines_tie_an_edge_and_its_reverse_of_equal_weight():
    line_of, lines = lines_of(chorded_ring(np.ones(14)))
    assert len(lines) == 7 and np.all(np.bincount(line_of) == 2) and np.all(lines[:, 0] < lines[:, 1])
    g = Graph.from_edges(3, [(1, 0), (0, 1), (2, 1)], directed=True, weights=[1.0, 2.0, 1.0])
    line_of, lines = lines_of(g)  # unequal weights both ways, and a one-way edge: a line each
    assert len(lines) == 3 and sorted(map(tuple, lines)) == [(0, 1), (1, 0), (2, 1)]


@pytest.mark.parametrize("what", ["node_attrs", "edge_weights"])
def test_the_loss_gradient_matches_central_differences(what):
    m = model()
    attrs, graph = nominal()
    rng = np.random.default_rng(4)
    data = made_by(m, attrs * rng.uniform(0.7, 1.3, attrs.shape), graph.reweighted(graph.weights * 1.2))
    problem = _Problem(m, data, attrs, graph)
    params = _AttrParameters(problem, None) if what == "node_attrs" else _WeightParameters(problem)
    p = params.p0 * rng.uniform(0.8, 1.2, params.p0.shape)
    value, grad = params.loss(p)
    assert value > 0 and grad.shape == p.shape
    for k in range(len(p)):
        e = np.zeros_like(p)
        e[k] = 1e-6 * params.scale[k]
        fd = (params.loss(p + e)[0] - params.loss(p - e)[0]) / (2 * e[k])
        assert abs(fd - grad[k]) <= 1e-6 * max(np.abs(grad).max(), 1e-8), (k, fd, grad[k])


def test_a_fit_names_the_node_whose_attribute_changed():
    m = model()
    attrs, graph = nominal()
    changed = attrs.copy()
    changed[4, 0] *= 0.5
    fit = mpnode.fit_network(m, made_by(m, changed, graph), "node_attrs", attrs=["rate"], node_attrs=attrs)
    assert fit.ranking[0] == 4, fit.describe()
    assert fit.fitted[4, 0] == pytest.approx(changed[4, 0], rel=1e-3)
    np.testing.assert_array_equal(fit.fitted[:, 1], attrs[:, 1])  # the column not fitted stays nominal
    assert fit.loss < 1e-6 * fit.loss_nominal and fit.departure.shape == (N,) and fit.change.shape == (N, 1)
    assert fit.describe(1)[0].startswith("node 4: rate")


def test_windows_are_trajectories_of_their_own_from_every_kth_observation():
    m = model()
    attrs, graph = nominal()
    data = made_by(m, attrs, graph)
    cut = _windows(data, 5)  # T = 12: windows from 0 and 5, the last two steps left out
    assert cut.x.shape == (2 * B, 6, N, 1) and np.array_equal(cut.x[B + 3], data.x[3, 5:11])
    assert cut.node_attrs.shape == (2 * B, N, 2) and _windows(data, T) is data
    changed = attrs.copy()
    changed[4, 0] *= 0.5
    fit = mpnode.fit_network(m, made_by(m, changed, graph), attrs=["rate"], node_attrs=attrs, window=4)
    assert fit.ranking[0] == 4 and fit.fitted[4, 0] < 0.9 * attrs[4, 0]  # not exact: each window's messages start at 0


def test_a_fit_names_the_line_taken_out():
    m = model()
    attrs, graph = nominal()
    line_of, lines = lines_of(graph)
    out = int(np.flatnonzero((lines == [2, 3]).all(axis=1))[0])
    weights = graph.weights.copy()
    weights[line_of == out] = 0.0
    data = made_by(m, attrs, graph.reweighted(weights))
    fit = mpnode.fit_network(m, data, "edge_weights", graph=graph)
    assert fit.ranking[0] == out and tuple(fit.lines[out]) == (2, 3), fit.describe()
    assert fit.fitted[line_of == out] == pytest.approx(0.0, abs=1e-3 * graph.weights.max())
    assert fit.departure[out] == pytest.approx(1.0, abs=1e-3) and fit.fitted.shape == (graph.n_edges,)
    assert fit.to_dict()["ranking"][0] == out


def test_what_cannot_be_fitted_is_refused():
    m = model(weighted=False)
    attrs, graph = nominal()
    data = made_by(m, attrs, ring(N))
    with pytest.raises(InputError, match="what"):
        mpnode.fit_network(m, data, "lines")
    with pytest.raises(InputError, match="does not hear edge weights"):
        mpnode.fit_network(m, data, "edge_weights")
    with pytest.raises(InputError, match="attrs.*distinct names among rate, size"):
        mpnode.fit_network(m, data, attrs=["inertia"])
    with pytest.raises(InputError, match="bounds"):
        mpnode.fit_network(m, data, attrs="rate", bounds=(0.0, np.ones(N + 1)))
    with pytest.raises(InputError, match="graph.*weights"):
        mpnode.fit_network(m, data, graph=graph)


def test_the_command_prints_the_ranking_and_writes_the_fit(tmp_path):
    from click.testing import CliRunner

    from cli.main import main
    from mpnode.data import write_trajectories

    m = model()
    attrs, graph = nominal()
    changed = attrs.copy()
    changed[2, 1] *= 2.0
    m.save(tmp_path / "m.h5")
    write_trajectories(tmp_path / "nominal.h5", made_by(m, attrs, graph))
    write_trajectories(tmp_path / "changed.h5", made_by(m, changed, graph))
    args = ["fit-network", str(tmp_path / "m.h5"), str(tmp_path / "changed.h5"), "--nominal",
            str(tmp_path / "nominal.h5"), "--attrs", "size", "-o", str(tmp_path / "fit.json")]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert "most departed from nominal first:\n  node 2: size" in r.output
    assert json.loads((tmp_path / "fit.json").read_text())["ranking"][0] == 2
    r = CliRunner().invoke(main, args[:-2] + ["--reference", str(tmp_path / "nominal.h5")])
    assert r.exit_code == 0 and "most departed from the reference's fit first:\n  node 2: size" in r.output, r.output
    r = CliRunner().invoke(main, args[:-2] + ["--attrs", "mass", "-o", str(tmp_path / "other.json")])
    assert r.exit_code == 2 and "attrs" in r.output and not (tmp_path / "other.json").exists()


def test_a_reference_from_before_the_change_cancels_what_the_model_gets_wrong():
    """Through a model 10 % off the one that made the data, both fits take up its error alike: the
    departures between them still name the node that changed."""
    truth, attrs, graph = model(), *nominal()
    wrong = truth.copy()
    wrong.theta = truth.theta * (1 + 0.1 * np.random.default_rng(7).standard_normal(truth.theta.size))
    changed = attrs.copy()
    changed[1, 0] *= 0.5
    after, before = made_by(truth, changed, graph), made_by(truth, attrs, graph, seed=2)
    fit = mpnode.fit_network(wrong, after, attrs="rate", node_attrs=attrs, reference=before)
    assert fit.ranking[0] == 1, fit.describe()
    assert np.abs(fit.baseline - attrs).max() > 0.01 and fit.reference_loss < fit.loss_nominal
    np.testing.assert_allclose(fit.change[:, 0], (fit.fitted[:, 0] - fit.baseline[:, 0]) / attrs[:, 0])
    before = mpnode.fit_network(wrong, before, attrs="rate", node_attrs=attrs)  # fitted once, compared with many
    again = mpnode.fit_network(wrong, after, attrs="rate", node_attrs=attrs, reference=before)
    np.testing.assert_allclose(again.change, fit.change, atol=1e-6)
    with pytest.raises(InputError, match="reference"):
        mpnode.fit_network(wrong, after, attrs="size", node_attrs=attrs, reference=before)


@pytest.mark.slow
def test_the_worked_example_runs_as_written(tmp_path, monkeypatch):
    """docs/fit-network.md in one folder: its commands and python in order (a shorter training, and
    fits of a few iterations)."""
    pytest.importorskip("pypower", reason="the example reads ieee39: the extra grids is not installed")
    doc = Path(__file__).resolve().parents[1] / "docs" / "fit-network.md"
    blocks = fenced_blocks(doc.read_text())
    assert [lang for lang, _, _ in blocks] == ["", "python", "", "python"]
    train = "mpnode train grids10-30 -o grids.h5 --time-limit 30m"
    assert blocks[0][1].count(train) == 1
    run_shell(blocks[0][1].replace(train, "mpnode train grid10 -o grids.h5 --trajectories 8 --epochs 1"), tmp_path)
    run_python(blocks[1][1], tmp_path, monkeypatch)
    assert blocks[2][1].count("--reference before.h5") == 2 and blocks[3][1].count("**planned)") == 2
    run_shell(blocks[2][1].replace("--reference before.h5", "--reference before.h5 --iterations 3"), tmp_path)
    assert json.loads((tmp_path / "bus.json").read_text())["reference_file"] == "before.h5"
    run_python(blocks[3][1].replace("**planned)", "**planned, iterations=3)"), tmp_path, monkeypatch)
