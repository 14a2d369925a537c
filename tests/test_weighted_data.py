"""Weighted edges and node attributes in the data layer: Graph.weights, Trajectories.node_attrs,
format version 3 (written only when the data need it), `mpnode convert` and `mpnode inspect`."""
import json
import os

import h5py
import networkx as nx
import numpy as np
import pytest
from click.testing import CliRunner

import mpnode
from cli.main import main
from mpnode import Graph, InputError, block_diagonal
from mpnode.base.graph import as_graph
from mpnode.data import Trajectories, read_trajectories, summarize, write_trajectories
from mpnode.data import files

B, T, N = 3, 4, 4


def states(B=B, T=T, N=N, dx=2, seed=0):
    return np.random.default_rng(seed).normal(size=(B, T + 1, N, dx))


def version(path):
    with h5py.File(path, "r") as f:
        return int(f.attrs["format_version"])


def rows(graph):
    """{(receiver, sender): weight} of a weighted graph."""
    return {(int(r), int(s)): float(w) for (r, s), w in zip(graph.edges(), graph.weights)}


# ---- Graph ------------------------------------------------------------------------------------

def test_from_edges_doubles_undirected_weights_adds_duplicates_and_sorts_rows():
    g = Graph.from_edges(3, [(2, 0), (0, 1), (0, 1), (1, 1)], weights=[5.0, 1.0, 2.5, -4.0], self_loops=True)
    assert g.weighted and g.weights.dtype == np.float64
    assert rows(g) == {(0, 1): 3.5, (1, 0): 3.5, (0, 2): 5.0, (2, 0): 5.0, (1, 1): -4.0}  # a self-loop once
    assert g.indptr.tolist() == [0, 2, 4, 5] and g.indices.tolist() == [1, 2, 0, 1, 0]
    directed = Graph.from_edges(3, [(2, 0), (0, 1)], directed=True, weights=[5.0, 1.0])
    assert rows(directed) == {(0, 1): 1.0, (2, 0): 5.0}


def test_unweighted_graphs_are_as_before():
    g = Graph.from_edges(3, [(0, 1), (0, 1), (1, 2)])
    assert g.weights is None and not g.weighted
    assert g.edges().tolist() == [[0, 1], [1, 0], [1, 2], [2, 1]]
    assert block_diagonal([g, g]).weights is None
    assert Graph([0, 1, 2], [1, 0]).weights is None


def test_graph_keyword_equals_reweighted_and_block_diagonal():
    g = Graph([0, 1, 2], [1, 0], weights=[2, -1])
    assert g.weights.tolist() == [2.0, -1.0] and g.validate() is g
    assert not g.equals(Graph([0, 1, 2], [1, 0]))  # the weights are compared too
    assert not g.equals(Graph([0, 1, 2], [1, 0], weights=[2.0, 1.0]))
    assert g.equals(Graph([0, 1, 2], [1, 0], weights=[2.0, -1.0]))
    other = g.reweighted([0.5, 0.25])
    assert other.weights.tolist() == [0.5, 0.25] and other.indices is g.indices and other.parts is None
    assert not g.reweighted(None).weighted
    plain = Graph([0, 0, 0], [])
    both = block_diagonal([g, Graph([0, 1, 2], [1, 0]), plain])
    assert both.weights.tolist() == [2.0, -1.0, 1.0, 1.0]  # an unweighted part's edges weigh 1
    assert both.indices.tolist() == [1, 0, 3, 2] and len(both.parts) == 3


@pytest.mark.parametrize("weights, phrase", [
    ([1.0], "shape (1,), but the graph has 2 edges"),
    ([1.0, np.nan], "nan at edge 1"),
    ([np.inf, 1.0], "inf at edge 0"),
    (["a", "b"], "dtype"),
    ([[1.0, 2.0]], "shape (1, 2)"),
])
def test_bad_weights_are_named(weights, phrase):
    with pytest.raises(InputError) as e:
        Graph([0, 1, 2], [1, 0], weights=weights).validate("g.h5", "graphs/0")
    assert e.value.field == "graphs/0/weights" and phrase in str(e.value), str(e.value)
    with pytest.raises(InputError, match="graph/weights"):
        Graph([0, 1, 2], [1, 0]).reweighted(weights)


def test_networkx_weights():
    g = nx.Graph()
    g.add_edge(0, 1, weight=2.0)
    g.add_edge(1, 2, weight=-0.5)
    assert rows(Graph.from_networkx(g)) == {(0, 1): 2.0, (1, 0): 2.0, (1, 2): -0.5, (2, 1): -0.5}
    d = nx.DiGraph()
    d.add_edge(0, 1, weight=3)  # u -> v: v hears u
    d.add_node(2)
    assert rows(as_graph(d, 3)) == {(1, 0): 3.0}
    assert not Graph.from_networkx(nx.path_graph(3)).weighted
    g.add_edge(2, 0)
    with pytest.raises(InputError) as e:
        as_graph(g, 3, source="d.h5", field="graph[1]")
    assert e.value.field == "graph[1]" and "edge (0, 2) has no weight" in str(e.value)  # as networkx lists it
    g[2][0]["weight"] = "strong"
    with pytest.raises(InputError, match="graph/weights: edge \\(0, 2\\) has weight 'strong'"):
        as_graph(g, 3)


def test_edge_list_with_a_weight_column():
    g = as_graph([(0, 1, 0.5), (1, 2, -2.0), (0, 1, 0.25)], 3, directed=True)  # (sender, receiver, weight)
    assert rows(g) == {(1, 0): 0.75, (2, 1): -2.0}
    assert rows(as_graph(np.array([[0, 1, 4.0]]), 2)) == {(1, 0): 4.0, (0, 1): 4.0}
    for bad, phrase in [([(0, 1, np.nan)], "nan at edge 0"), ([(0, 1.5, 1.0)], "integer node ids"),
                        ([(0, 7, 1.0)], "names node 7")]:
        with pytest.raises(InputError, match=phrase):
            as_graph(bad, 3)


# ---- Trajectories and files -------------------------------------------------------------------

def weighted_ring(seed=0):
    w = np.random.default_rng(seed).uniform(-1, 1, N)
    return [(i, (i + 1) % N, w[i]) for i in range(N)]


def test_round_trip_weights_and_per_trajectory_attrs(tmp_path):
    x, attrs = states(), np.random.default_rng(1).normal(size=(B, N, 2))
    graphs = [weighted_ring(k) for k in range(B)]  # one graph per trajectory: weights differ
    path = tmp_path / "w.h5"
    write_trajectories(path, x=x, graph=graphs, graph_index=[0, 1, 2], dt=0.1, system="genes",
                       node_attrs=attrs, attr_names=["decay", "gain"])
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == 3 and f["node_attrs"].shape == (B, N, 2)
        assert list(f.attrs["attr_names"]) == ["decay", "gain"] and f["graphs/2/weights"].dtype == np.float64
    t = read_trajectories(path)
    assert np.array_equal(t.node_attrs, attrs) and t.node_attrs.dtype == np.float64
    assert t.attr_names == ["decay", "gain"] and t.attr_dim == 2 and t.weighted and t.attrs == {}
    want = Trajectories.from_arrays(x, graphs, 0.1, "genes", graph_index=[0, 1, 2], node_attrs=attrs,
                                    attr_names=["decay", "gain"])
    assert all(a.equals(b) for a, b in zip(t.graphs, want.graphs)) and len(t.graphs) == B
    write_trajectories(tmp_path / "again.h5", t)  # a copy keeps them
    back = read_trajectories(tmp_path / "again.h5")
    assert np.array_equal(back.node_attrs, attrs) and all(a.equals(b) for a, b in zip(back.graphs, t.graphs))


def test_shared_attrs_are_written_once_and_read_for_every_trajectory(tmp_path):
    shared = np.arange(N * 3).reshape(N, 3)  # integers become float64
    t = Trajectories.from_arrays(states(), [(0, 1)], 0.1, "s", node_attrs=shared)
    assert t.node_attrs.shape == (B, N, 3) and t.attr_names == ["attr 1", "attr 2", "attr 3"] and not t.weighted
    write_trajectories(tmp_path / "a.h5", t)
    with h5py.File(tmp_path / "a.h5", "r") as f:
        assert f["node_attrs"].shape == (N, 3) and f.attrs["format_version"] == 3 and "weights" not in f["graphs/0"]
    back = read_trajectories(tmp_path / "a.h5")
    assert back.node_attrs.shape == (B, N, 3) and np.array_equal(back.node_attrs[2], shared)
    same = np.broadcast_to(shared, (B, N, 3)).copy()  # per trajectory but all equal: the shared form
    write_trajectories(tmp_path / "b.h5", x=states(), graph=[(0, 1)], dt=0.1, system="s", node_attrs=same,
                       attr_names="k l m".split())
    with h5py.File(tmp_path / "b.h5", "r") as f:
        assert f["node_attrs"].shape == (N, 3)


def test_version_3_only_when_needed(tmp_path):
    x = states()
    write_trajectories(tmp_path / "v1.h5", x=x, graph=[(0, 1)], dt=0.1, system="s")
    gappy = x.copy()
    gappy[0, 2, 1, 0] = np.nan
    write_trajectories(tmp_path / "v2.h5", x=gappy, graph=[(0, 1)], dt=0.1, system="s")
    write_trajectories(tmp_path / "v3w.h5", x=x, graph=[(0, 1, 2.0)], dt=0.1, system="s")
    write_trajectories(tmp_path / "v3a.h5", x=gappy, graph=[(0, 1)], dt=0.1, system="s", node_attrs=np.ones((N, 1)))
    assert [version(tmp_path / f"{n}.h5") for n in ("v1", "v2", "v3w", "v3a")] == [1, 2, 3, 3]
    with h5py.File(tmp_path / "v1.h5", "r") as f:
        assert "node_attrs" not in f and "attr_names" not in f.attrs and list(f["graphs/0"]) == ["indices", "indptr"]
    assert np.isnan(read_trajectories(tmp_path / "v3a.h5").x[0, 2, 1, 0])  # version 3 holds version 2's data
    assert files.FORMAT_VERSION == 3


def test_a_version_2_reader_refuses_version_3_by_its_version(tmp_path, monkeypatch):
    write_trajectories(tmp_path / "w.h5", x=states(), graph=[(0, 1, 2.0)], dt=0.1, system="s")
    monkeypatch.setattr(files, "VERSIONS", (1, 2))
    with pytest.raises(InputError) as e:
        read_trajectories(tmp_path / "w.h5")
    assert e.value.field == "format_version" and "is 3" in str(e.value)


def test_a_trajectories_built_directly_broadcasts_shared_attrs(tmp_path):
    t = Trajectories(x=states(), graphs=[Graph.complete(N)], dt=0.1, system="s", node_attrs=np.ones((N, 2)),
                     attr_names=["a", "b"])
    assert t.node_attrs.shape == (B, N, 2) and t.attr_dim == 2
    write_trajectories(tmp_path / "t.h5", t)
    assert read_trajectories(tmp_path / "t.h5").attr_names == ["a", "b"]


def test_hidden_dims_keep_the_attributes():
    t = Trajectories.from_arrays(states(), [(0, 1, -1.0)], 0.1, "s", node_attrs=np.ones((N, 2)), attr_names=["a", "b"])
    wider = t.with_hidden_dims(2)
    assert wider.state_dim == 4 and wider.attr_names == ["a", "b"] and wider.node_attrs is t.node_attrs
    assert wider.graphs[0].weighted


# ---- every bad input an InputError naming the field -----------------------------------------------

@pytest.mark.parametrize("changes, field, phrase", [
    (dict(node_attrs=np.zeros((B, T + 1, N, 2))), "node_attrs", "static"),
    (dict(node_attrs=np.zeros((B, N + 1, 2))), "node_attrs", "[B, N, dp]"),
    (dict(node_attrs=np.zeros((N + 1, 2))), "node_attrs", "[N, dp]"),
    (dict(node_attrs=np.zeros((N, 0))), "node_attrs", "dp >= 1"),
    (dict(node_attrs=np.zeros(N)), "node_attrs", "[B, N, dp]"),
    (dict(node_attrs=np.full((N, 2), np.nan)), "node_attrs", "finite"),
    (dict(node_attrs=np.array([["a", "b"]] * N)), "node_attrs", "float32 or float64"),
    (dict(node_attrs=np.zeros((N, 2)), attr_names=["a"]), "attr_names", "2 non-empty strings"),
    (dict(node_attrs=np.zeros((N, 2)), attr_names=["a", " "]), "attr_names", "non-empty"),
    (dict(node_attrs=np.zeros((N, 2)), attr_names=["a", "a"]), "attr_names", "'a' twice"),
    (dict(attr_names=["a"]), "attr_names", "no node_attrs"),
    (dict(attrs={"attr_names": ["a"]}), "attr_names", "attr_names="),
    (dict(graph=[(0, 1, np.nan)]), "graph/weights", "finite"),
    (dict(graph=[(0, 1, np.inf), (1, 2, 1.0)]), "graph/weights", "inf at edge 0"),
    (dict(graph=Graph([0, 1, 2, 2, 2], [1, 0], weights=[1.0])), "graph/weights", "one weight per edge"),
    (dict(graph=[[(0, 1, 1.0)], [(0, 1)]], graph_index=[0, 1, 0]), "graph[1]", "has no weights"),
    (dict(graph=[[(0, 1)], [(0, 1, 1.0)]], graph_index=[0, 1, 0]), "graph[0]", "graph[1] has"),
])
def test_every_bad_input_names_its_field(tmp_path, changes, field, phrase):
    kw = {**dict(x=states(), graph=[(0, 1)], dt=0.1, system="s"), **changes}
    path = tmp_path / "bad.h5"
    with pytest.raises(InputError) as e:
        write_trajectories(path, **kw)
    assert e.value.source == str(path) and e.value.field == field and phrase in str(e.value), str(e.value)
    assert os.listdir(tmp_path) == []


def test_a_trajectories_object_is_checked_too(tmp_path):
    t = Trajectories.from_arrays(states(), [[(0, 1, 1.0)], [(1, 2, 1.0)]], 0.1, "s", graph_index=[0, 1, 0])
    t.graphs[1] = t.graphs[1].reweighted(None)
    with pytest.raises(InputError, match="graphs/1: has no weights, but graphs/0 has"):
        write_trajectories(tmp_path / "bad.h5", t)
    t.graphs[1] = Graph(t.graphs[0].indptr, t.graphs[0].indices, weights=[np.nan, 1.0])
    with pytest.raises(InputError, match="graphs/1/weights: is nan at edge 0"):
        write_trajectories(tmp_path / "bad.h5", t)
    assert os.listdir(tmp_path) == []


@pytest.fixture
def v3_file(tmp_path):
    path = tmp_path / "v3.h5"
    write_trajectories(path, x=states(), graph=[[(0, 1, 1.0)], [(1, 2, -1.0)]], graph_index=[0, 1, 0], dt=0.1,
                       system="s", node_attrs=np.ones((B, N, 2)) * np.arange(B)[:, None, None], attr_names=["a", "b"])
    return path


def put(f, name, value):
    if name in f:
        del f[name]
    f[name] = value


@pytest.mark.parametrize("corrupt, field, phrase", [
    (lambda f: f.attrs.__setitem__("format_version", 2), "graphs/0/weights", "format_version 2"),
    (lambda f: (f.attrs.__setitem__("format_version", 1), [f.__delitem__(f"graphs/{g}/weights") for g in "01"]),
     "node_attrs", "format_version 1"),
    (lambda f: (f.attrs.__setitem__("format_version", 2), [f.__delitem__(f"graphs/{g}/weights") for g in "01"],
                f.__delitem__("node_attrs")), "attr_names", "format version 3"),
    (lambda f: f.attrs.__setitem__("format_version", 4), "format_version", "1, 2 or 3"),
    (lambda f: put(f, "graphs/1/weights", np.array([1.0, np.nan])), "graphs/1/weights", "nan at edge 1"),
    (lambda f: put(f, "graphs/1/weights", np.array([1.0])), "graphs/1/weights", "one weight per edge"),
    (lambda f: put(f, "graphs/1/weights", np.array([1, 2])), "graphs/1/weights", "float32 or float64"),
    (lambda f: f.__delitem__("graphs/1/weights"), "graphs/1", "has no weights, but graphs/0 has"),
    (lambda f: put(f, "node_attrs", np.ones((N + 1, 2))), "node_attrs", "[N, dp]"),
    (lambda f: put(f, "node_attrs", np.ones((B, 2, N, 2))), "node_attrs", "static"),
    (lambda f: put(f, "node_attrs", np.full((B, N, 2), np.inf)), "node_attrs", "finite"),
    (lambda f: put(f, "node_attrs", np.ones((N, 2), dtype=np.int32)), "node_attrs", "float32 or float64"),
    (lambda f: f.attrs.__delitem__("attr_names"), "attr_names", "missing"),
    (lambda f: f.attrs.__setitem__("attr_names", ["a", "a"]), "attr_names", "twice"),
    (lambda f: f.__delitem__("node_attrs"), "attr_names", "no node_attrs"),
])
def test_the_reader_checks_every_rule(v3_file, corrupt, field, phrase):
    read_trajectories(v3_file)
    with h5py.File(v3_file, "r+") as f:
        corrupt(f)
    with pytest.raises(InputError) as e:
        read_trajectories(v3_file)
    assert (e.value.source, e.value.field) == (str(v3_file), field) and phrase in str(e.value), str(e.value)


def test_float32_in_a_file_is_read_as_float64(v3_file):
    with h5py.File(v3_file, "r+") as f:
        put(f, "graphs/0/weights", f["graphs/0/weights"][()].astype(np.float32))
        f.attrs["attr_names"] = "only"  # one name may be a plain string
        put(f, "node_attrs", np.ones((N, 1), dtype=np.float32))
    t = read_trajectories(v3_file)
    assert t.node_attrs.dtype == t.graphs[0].weights.dtype == np.float64 and t.attr_names == ["only"]


# ---- summary, mpnode convert and mpnode inspect ----------------------------------------------------

def test_summary_ranges(v3_file):
    s = summarize(read_trajectories(v3_file))
    assert s["weights"] == {"min": -1.0, "max": 1.0, "negative": 0.5}
    assert s["node_attrs"] == {"a": {"min": 0.0, "max": 2.0}, "b": {"min": 0.0, "max": 2.0}}
    plain = summarize(Trajectories.from_arrays(states(), [(0, 1)], 0.1, "s"))
    assert plain["weights"] is None and plain["node_attrs"] == {}


def cli(*args):
    return CliRunner().invoke(main, [*map(str, args)])


def test_inspect_shows_the_ranges(v3_file):
    res = cli("inspect", v3_file)
    assert res.exit_code == 0, res.output
    for text in ("weights:     -1 to 1, 50% negative", "node attrs:  2 per node", "  a: 0 to 2", "  b: 0 to 2"):
        assert text in res.stdout, text
    s = json.loads(cli("inspect", v3_file, "--json").stdout)
    assert s["weights"]["negative"] == 0.5 and s["node_attrs"]["b"] == {"min": 0.0, "max": 2.0}


def test_inspect_refuses_a_bad_version_3_file_with_status_2(v3_file):
    with h5py.File(v3_file, "r+") as f:
        put(f, "graphs/0/weights", np.array([np.nan, 1.0]))
    res = cli("inspect", v3_file)
    assert res.exit_code == 2 and res.stdout == "" and "Traceback" not in res.output
    assert res.stderr.startswith(f"Error: {v3_file}: graphs/0/weights: is nan at edge 0")
    assert res.stderr.count("\n") == 1


def test_convert_an_archive_with_weights_and_attributes(tmp_path):
    x = states()
    np.savez(tmp_path / "d.npz", x=x, edges=np.array([[0, 1], [1, 2]]), weights=np.array([0.5, -2.0]), dt=0.1,
             system="genes", node_attrs=np.arange(N * 2.0).reshape(N, 2), attr_names=np.array(["decay", "gain"]))
    res = cli("convert", tmp_path / "d.npz", "-o", tmp_path / "d.h5")
    assert res.exit_code == 0, res.output
    assert "weighted" in res.stdout and "node attributes: decay, gain" in res.stdout
    t = read_trajectories(tmp_path / "d.h5")
    assert rows(t.graphs[0]) == {(1, 0): 0.5, (0, 1): 0.5, (2, 1): -2.0, (1, 2): -2.0}
    assert t.attr_names == ["decay", "gain"] and t.node_attrs[1, 3].tolist() == [6.0, 7.0]
    assert version(tmp_path / "d.h5") == 3
    np.savez(tmp_path / "csr.npz", x=x, indptr_0=[0, 1, 2, 2, 2], indices_0=[1, 0], weights_0=[3.0, 4.0],
             edges_1=np.array([[0, 1, 1.0]]), graph_index=[0, 1, 1], dt=0.1, system="s")
    assert cli("convert", tmp_path / "csr.npz", "-o", tmp_path / "csr.h5").exit_code == 0
    t = read_trajectories(tmp_path / "csr.h5")
    assert t.graphs[0].weights.tolist() == [3.0, 4.0] and rows(t.graphs[1]) == {(1, 0): 1.0, (0, 1): 1.0}


@pytest.mark.parametrize("content, key, phrase", [
    (dict(edges=[[0, 1], [1, 2]], weights=[1.0]), "weights", "one weight per edge"),
    (dict(edges=[[0, 1], [1, 2]], weights=[1.0, np.nan]), "weights", "nan at edge 1"),
    (dict(edges=[[0, 1, 1.0]], weights=[1.0]), "weights", "already holds"),
    (dict(indptr=[0, 1, 2, 2, 2], indices=[1, 0], weights=[1.0]), "weights", "one weight per edge"),
    (dict(edges_0=[[0, 1]], edges_1=[[0, 1]], weights_1=[1.0], graph_index=[0, 1, 0]), "weights_0", "missing"),
    (dict(edges_0=[[0, 1]], weights_3=[1.0], graph_index=[0, 0, 0]), "weights_3", "no graph"),
    (dict(edges=[[0, 1]], node_attrs=np.zeros((B, T + 1, N, 1))), "node_attrs", "static"),
    (dict(edges=[[0, 1]], node_attrs=np.zeros((N, 2)), attr_names=["a"]), "attr_names", "2 non-empty"),
    (dict(edges=[[0, 1]], node_attrs=np.full((N, 1), np.inf)), "node_attrs", "finite"),
])
def test_convert_refuses_bad_data_with_status_2(tmp_path, content, key, phrase):
    np.savez(tmp_path / "bad.npz", x=states(), dt=0.1, system="s", **content)
    out = tmp_path / "bad.h5"
    res = cli("convert", tmp_path / "bad.npz", "-o", out)
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    assert f"Error: {tmp_path / 'bad.npz'}: {key}: " in res.stderr and phrase in res.stderr, res.stderr
    assert sorted(os.listdir(tmp_path)) == ["bad.npz"]


def test_convert_help_names_the_new_keys():
    out = cli("convert", "--help").output
    assert all(key in out for key in ("weights", "weights_0", "node_attrs", "attr_names", "(E, 3)"))


def test_public_names():
    assert mpnode.Graph is Graph and "weights" in Graph.__dataclass_fields__
    assert list(Graph.__dataclass_fields__) == ["indptr", "indices", "self_loops", "parts", "weights"]
