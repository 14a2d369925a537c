"""Your own data in: `write_trajectories` from plain arrays and `mpnode convert FILE.npz`.

The README's worked example runs in tests/test_readme.py with the rest of the README."""
import os
import re
from pathlib import Path

import networkx as nx
import numpy as np
import pytest
from click.testing import CliRunner

import mpnode
from cli.main import main
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph
from mpnode.data import Trajectories, read_trajectories

DOCS = Path(__file__).resolve().parents[1] / "docs"


def states(B=3, T=4, N=4, dx=2, seed=0):
    return np.random.default_rng(seed).normal(size=(B, T + 1, N, dx))


def csr(rows):
    """The Graph whose node i hears rows[i] (the expected answer, written by hand)."""
    indptr = np.cumsum([0] + [len(r) for r in rows])
    return Graph(indptr, [j for r in rows for j in r])


# ---- write_trajectories(path, x=..., graph=..., ...) --------------------------------------

@pytest.mark.parametrize("graph, directed, rows", [
    # an edge (s, r): r hears s; undirected: both hear each other
    ([(0, 1), (1, 2), (3, 2)], True, [[], [0], [1, 3], []]),
    ([(0, 1), (1, 2), (3, 2)], False, [[1], [0, 2], [1, 3], [2]]),
    (np.array([[2, 0], [2, 1]]), True, [[2], [2], [], []]),
    (np.array([[1, 0], [0, 1], [0, 1]]), True, [[1], [0], [], []]),  # duplicates count once
    (np.array([[0.0, 3.0]]), False, [[3], [], [], [0]]),  # integral floats, e.g. from MATLAB
    (np.zeros((0, 2), int), False, [[], [], [], []]),  # no edges: every node alone
    (nx.DiGraph([(0, 1), (1, 2), (3, 2)]), None, [[], [0], [1, 3], []]),  # u -> v: v hears u
    (nx.path_graph(4), None, [[1], [0, 2], [1, 3], [2]]),
    (Graph.complete(4), None, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]),
])
def test_arrays_and_any_graph_form_round_trip(tmp_path, graph, directed, rows):
    x, u = states(), np.random.default_rng(1).normal(size=(3, 4, 4, 1)).astype(np.float32)
    path = tmp_path / "mine.h5"
    mpnode.write_trajectories(path, x=x, u=u, graph=graph, directed=bool(directed), dt=0.05, system="springs",
                              attrs={"seed": 7, "state_names": ["position (m)", "velocity (m/s)"]})
    t = read_trajectories(path)
    assert np.array_equal(t.x, x) and t.x.dtype == np.float64
    assert np.array_equal(t.u, u) and t.u.dtype == np.float32
    assert t.dt == 0.05 and t.system == "springs" and t.attrs == {"seed": 7, "state_names": ["position (m)",
                                                                                            "velocity (m/s)"]}
    assert len(t.graphs) == 1 and t.graphs[0].equals(csr(rows)), t.graphs[0].edges()


def test_several_graphs_with_graph_index_and_positional_x(tmp_path):
    x = states(B=4)
    graphs = [[(0, 1)], nx.cycle_graph(4), Graph.complete(4)]
    mpnode.write_trajectories(tmp_path / "g.h5", x, graph=graphs, graph_index=[2, 0, 1, 0], dt=0.1, system="s")
    t = read_trajectories(tmp_path / "g.h5")
    assert [g.n_edges for g in t.graphs] == [2, 8, 12] and t.graph_index.tolist() == [2, 0, 1, 0]
    assert t.graphs[1].equals(csr([[1, 3], [0, 2], [1, 3], [0, 2]]))
    # integer states are fine (float64), and a Trajectories still goes in as before
    mpnode.write_trajectories(tmp_path / "i.h5", x=np.arange(40).reshape(1, 5, 4, 2), graph=[(0, 1)], dt=1,
                              system="counts")
    assert read_trajectories(tmp_path / "i.h5").x.dtype == np.float64
    mpnode.write_trajectories(tmp_path / "t.h5", t)
    assert np.array_equal(read_trajectories(tmp_path / "t.h5").x, x)


@pytest.mark.parametrize("changes, field, phrase", [
    (dict(x=np.zeros((5, 4, 2))), "x", "x[None]"),
    (dict(x=[[[[0.0]]], [[[0.0, 1.0]]]]), "x", "rectangular"),
    (dict(x=np.full((3, 5, 4, 2), np.inf)), "x", "finite"),
    (dict(graph=None), "graph", "missing"),
    (dict(graph=[(0, 4)]), "graph", "0..3"),
    (dict(graph=[(0, -1)]), "graph", "0..3"),
    (dict(graph=[(0, 1.5)]), "graph", "integer"),
    (dict(graph=[(0, 1, 2, 3)]), "graph", "(E, 2)"),  # (E, 3) is (sender, receiver, weight)
    (dict(graph=[]), "graph", "np.zeros((0, 2), int)"),
    (dict(graph="ring"), "graph", "edge list"),
    (dict(graph=nx.path_graph(3)), "graph", "3 nodes"),
    (dict(graph=nx.relabel_nodes(nx.path_graph(4), {0: "a"})), "graph", "relabel"),
    (dict(graph=Graph.complete(5)), "graph", "5 nodes"),
    (dict(graph=[[(0, 1)], [(1, 2), (2, 3)]]), "graph_index", "missing"),
    (dict(graph=[[(0, 1)], [(1, 9)]], graph_index=[0, 1, 1]), "graph[1]", "node 9"),
    (dict(graph=[[(0, 1)], [(1, 2)]], graph_index=[0, 2, 1]), "graph_index", "names graph 2"),
    (dict(dt=0), "dt", "> 0"),
    (dict(dt=None), "dt", "> 0"),
    (dict(system=""), "system", "non-empty"),
    (dict(u=np.zeros((3, 5, 4, 1))), "u", "[B, T, N, du]"),
    (dict(attrs={"state_names": ["only one"]}), "state_names", "2 non-empty strings"),
    (dict(attrs={"format": "mine"}), "format", "format attribute"),
])
def test_every_problem_names_the_file_and_the_field(tmp_path, changes, field, phrase):
    kw = {**dict(x=states(), graph=[(0, 1)], dt=0.1, system="s"), **changes}
    path = tmp_path / "bad.h5"
    with pytest.raises(InputError) as e:
        mpnode.write_trajectories(path, **kw)
    assert e.value.source == str(path) and e.value.field == field and phrase in str(e.value), str(e.value)
    assert not os.path.exists(path)


def test_trajectories_and_arrays_do_not_mix(tmp_path):
    t = Trajectories.from_arrays(states(), [(0, 1)], 0.1, "s")
    with pytest.raises(TypeError):
        mpnode.write_trajectories(tmp_path / "a.h5", t, dt=0.2)
    with pytest.raises(TypeError):
        mpnode.write_trajectories(tmp_path / "a.h5")


# ---- mpnode convert ----------------------------------------------------------------------

def convert(npz, out, *extra):
    return CliRunner().invoke(main, ["convert", str(npz), "-o", str(out), *map(str, extra)])


def test_convert_round_trips_an_edge_list_from_networkx(tmp_path):
    g = nx.watts_strogatz_graph(6, 2, 0.5, seed=3)  # any graph a user built with networkx
    x, u = states(B=5, T=7, N=6, dx=3), states(B=5, T=6, N=6, dx=1, seed=2)
    np.savez(tmp_path / "d.npz", x=x, u=u, edges=np.array(g.edges()), dt=0.25, system="my_sim", seed=11,
             temperature=np.float64(300.0), labels=np.arange(5), state_names=np.array(["a", "b", "c"]))
    res = convert(tmp_path / "d.npz", tmp_path / "d.h5")
    assert res.exit_code == 0, res.output
    assert "kept as root attributes: seed, temperature" in res.output and "kept as aux/: labels" in res.output
    t = read_trajectories(tmp_path / "d.h5")
    assert np.array_equal(t.x, x) and np.array_equal(t.u, u) and t.dt == 0.25 and t.system == "my_sim"
    assert t.graphs[0].equals(Graph.from_networkx(g))
    assert t.attrs == {"seed": 11, "temperature": 300.0, "state_names": ["a", "b", "c"]}
    assert np.array_equal(t.aux["labels"], np.arange(5))


def test_convert_csr_several_graphs_times_and_options(tmp_path):
    x = states(B=3, T=4, N=3, dx=1).astype(np.float32)
    ring = Graph.from_networkx(nx.cycle_graph(3))
    np.savez(tmp_path / "c.npz", x=x, indptr_0=ring.indptr, indices_0=ring.indices,
             edges_1=[[0, 1], [0, 2]], directed=True, graph_index=[1, 0, 1], t=np.linspace(2.0, 3.0, 5),
             n_nodes=3)
    res = convert(tmp_path / "c.npz", tmp_path / "c.h5", "--system", "gene_net")
    assert res.exit_code == 0, res.output
    t = read_trajectories(tmp_path / "c.h5")
    assert t.x.dtype == np.float32 and np.array_equal(t.x, x) and t.system == "gene_net"
    assert t.dt == pytest.approx(0.25) and t.attrs == {"t0": 2.0}
    assert t.graphs[0].equals(ring) and t.graphs[1].equals(csr([[], [0], [0]]))
    assert t.graph_index.tolist() == [1, 0, 1]
    np.savez(tmp_path / "s.npz", x=x, edges=[[1, 1], [0, 1]])  # a self-loop, listed explicitly
    assert convert(tmp_path / "s.npz", tmp_path / "s.h5", "--dt", 0.5, "--system", "s").exit_code == 0
    s = read_trajectories(tmp_path / "s.h5")
    assert s.dt == 0.5 and s.graphs[0].self_loops and s.graphs[0].equals(Graph([0, 1, 3, 3], [1, 0, 1], True))


GOOD = dict(x=states(), edges=[[0, 1]], dt=0.1, system="s")


@pytest.mark.parametrize("content, key, phrase", [
    (dict(GOOD, x=None), "x", "missing"),
    (dict(GOOD, x=states()[0]), "x", "4-D"),
    (dict(GOOD, x=np.full((3, 5, 4, 2), np.inf)), "x", "finite"),
    (dict(GOOD, x=np.array(["a"] * 40).reshape(1, 5, 4, 2)), "x", "float32 or float64"),
    (dict(GOOD, u=np.zeros((3, 5, 4, 1))), "u", "[B, T, N, du]"),
    (dict(GOOD, dt=None), "dt", "missing"),
    (dict(GOOD, dt=[0.1, 0.2]), "dt", "one number"),
    (dict(GOOD, dt=-1.0), "dt", "> 0"),
    (dict(GOOD, dt=0.2, t=np.linspace(0, 1, 5)), "dt", "apart"),
    (dict(GOOD, dt=None, t=[0, 1, 3, 3, 5]), "t", "strictly increasing"),
    (dict(GOOD, dt=None, t=[0, 1, 2]), "t", "shape (5,)"),
    (dict(GOOD, system=None), "system", "missing"),
    (dict(GOOD, system=3), "system", "string"),
    (dict(GOOD, edges=None), "edges", "no graph"),
    (dict(GOOD, edges=[[0, 4]]), "edges", "0..3"),
    (dict(GOOD, edges=[[0, 1, 2, 3]]), "edges", "(E, 2)"),
    (dict(GOOD, edges=[[0.5, 1]]), "edges", "integer"),
    (dict(GOOD, indptr=[0, 1]), "edges", "not both"),
    (dict(GOOD, edges=None, indptr=[0, 1, 2, 2, 2]), "indices", "missing"),
    (dict(GOOD, edges=None, indptr=[0, 1, 2, 2], indices=[1, 0]), "indptr", "shape (5,)"),
    (dict(GOOD, edges=None, indptr=[0, 1, 2, 2, 2], indices=[1, 7]), "indices", "0..3"),
    (dict(GOOD, edges=None, indptr=[0, 2, 2, 2, 2], indices=[1, 1]), "indices", "twice"),
    (dict(GOOD, edges=None, indptr=[0.0, 1, 2, 2, 2], indices=[1, 0]), "indptr", "integer"),
    (dict(GOOD, edges=None, edges_0=[[0, 1]], edges_2=[[1, 2]], graph_index=[0, 1, 0]), "edges_0", "no gaps"),
    (dict(GOOD, edges_0=[[0, 1]]), "edges", "numbered"),
    (dict(GOOD, edges=None, edges_0=[[0, 1]], edges_1=[[1, 2]]), "graph_index", "missing"),
    (dict(GOOD, graph_index=[0, 1, 0]), "graph_index", "names graph 1"),
    (dict(GOOD, directed=5), "directed", "0 or 1"),
    (dict(GOOD, n_nodes=9), "n_nodes", "N = 4"),
    (dict(GOOD, state_names=np.array(["a", "b", "c"])), "state_names", "2 non-empty strings"),
    (dict(GOOD, extra=np.array([{"a": 1}], dtype=object)), "extra", "pickle"),
])
def test_a_bad_archive_exits_2_naming_the_key(tmp_path, content, key, phrase):
    np.savez(tmp_path / "bad.npz", **{k: v for k, v in content.items() if v is not None})
    out = tmp_path / "bad.h5"
    res = convert(tmp_path / "bad.npz", out)
    assert res.exit_code == 2, res.output
    assert f"bad.npz: {key}:" in res.output and phrase in res.output, res.output
    assert "Traceback" not in res.output and not os.path.exists(out)


def test_convert_refuses_bad_files_and_its_own_input(tmp_path):
    (tmp_path / "text.npz").write_text("not an archive")
    np.save(tmp_path / "one.npy", states())
    np.savez(tmp_path / "zip.npz", **GOOD)
    truncated = (tmp_path / "zip.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(truncated[: len(truncated) // 2])
    for name, phrase in (("text.npz", "zip"), ("one.npy", "single array"), ("missing.npz", "does not exist"),
                         ("cut.npz", "cannot be read")):
        res = convert(tmp_path / name, tmp_path / "o.h5")
        assert res.exit_code == 2 and f"{name}: file:" in res.output and phrase in res.output, res.output
    assert not os.path.exists(tmp_path / "o.h5")
    before = (tmp_path / "zip.npz").read_bytes()
    res = convert(tmp_path / "zip.npz", tmp_path / ".." / tmp_path.name / "zip.npz")
    assert res.exit_code == 2 and "destroy the input" in res.output
    assert (tmp_path / "zip.npz").read_bytes() == before
    res = convert(tmp_path / "zip.npz", tmp_path / "o.h5", "--dt", 0.3)
    assert res.exit_code == 2 and "--dt" in res.output


def test_help_and_the_format_document_every_key():
    from mpnode.data.npz import KEYS

    res = CliRunner().invoke(main, ["convert", "--help"])
    doc = (DOCS / "trajectory-format.md").read_text()
    for key in KEYS:
        for name in re.findall(r"[a-z][a-z_0-9]*", key.split(" (")[0]):
            if name not in ("anything", "else", "or"):
                assert name in res.output and (f"| `{name}`" in doc or f", `{name}`" in doc), name
