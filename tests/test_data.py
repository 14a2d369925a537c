"""Trajectory files: exact round trips, every validity rule, damaged files, atomic writes."""
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from mpnode import Graph, InputError
from mpnode.data import Trajectories, read_trajectories, summarize, validate_trajectories, write_trajectories

B, T, N, DX, DU = 2, 3, 3, 2, 1
PATH_GRAPH = ([0, 1, 3, 4], [1, 0, 2, 1])  # 0-1-2, undirected
COMPLETE_GRAPH = ([0, 2, 4, 6], [1, 2, 0, 2, 0, 1])


def write_raw(path):
    """A valid file written with plain h5py, the way an outside tool would."""
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        f.attrs.update(format="mpnode.trajectories", format_version=1, dt=0.05, system="kuramoto", seed=7)
        f["x"] = rng.standard_normal((B, T + 1, N, DX))
        f["u"] = rng.standard_normal((B, T, N, DU))
        f["graph_index"] = np.array([1, 0])
        for g, (indptr, indices) in enumerate((PATH_GRAPH, COMPLETE_GRAPH)):
            f[f"graphs/{g}/indptr"] = np.array(indptr)
            f[f"graphs/{g}/indices"] = np.array(indices)
        f["params/coupling"] = np.array(0.5)
        f["aux/load/pos"] = np.zeros((B, T + 1, 3))
    return path


@pytest.fixture
def raw_file(tmp_path):
    return write_raw(tmp_path / "raw.h5")


def put(f, name, value):
    """Replace (or create) dataset ``name``."""
    if name in f:
        del f[name]
    f[name] = value


def nan_at(name, idx, value=np.nan):
    def corrupt(f):
        a = f[name][()]
        a[idx] = value
        put(f, name, a)
    return corrupt


def self_loop_graph(f):
    put(f, "graphs/0/indptr", np.array([0, 2, 4, 5]))
    put(f, "graphs/0/indices", np.array([0, 1, 0, 2, 1]))


# (id, corruption applied to a valid file, field named, phrase in the message)
CORRUPTIONS = [
    ("format-missing", lambda f: f.attrs.__delitem__("format"), "format", "missing"),
    ("format-wrong", lambda f: f.attrs.__setitem__("format", "mpnode.trajectory"), "format", "mpnode.trajectories"),
    ("version-missing", lambda f: f.attrs.__delitem__("format_version"), "format_version", "missing"),
    ("version-4", lambda f: f.attrs.__setitem__("format_version", 4), "format_version", "is 4"),
    ("version-str", lambda f: f.attrs.__setitem__("format_version", "1"), "format_version", "1, 2 or 3"),
    ("version-float", lambda f: f.attrs.__setitem__("format_version", 1.0), "format_version", "1, 2 or 3"),
    ("dt-missing", lambda f: f.attrs.__delitem__("dt"), "dt", "missing"),
    ("dt-zero", lambda f: f.attrs.__setitem__("dt", 0.0), "dt", "> 0"),
    ("dt-negative", lambda f: f.attrs.__setitem__("dt", -0.1), "dt", "> 0"),
    ("dt-nan", lambda f: f.attrs.__setitem__("dt", np.nan), "dt", "finite"),
    ("dt-str", lambda f: f.attrs.__setitem__("dt", "0.05"), "dt", "a finite number"),
    ("dt-array", lambda f: f.attrs.__setitem__("dt", [0.05, 0.1]), "dt", "a finite number"),
    ("system-missing", lambda f: f.attrs.__delitem__("system"), "system", "missing"),
    ("system-int", lambda f: f.attrs.__setitem__("system", 3), "system", "string"),
    ("system-empty", lambda f: f.attrs.__setitem__("system", ""), "system", "non-empty"),
    ("x-missing", lambda f: f.__delitem__("x"), "x", "missing"),
    ("x-group", lambda f: (f.__delitem__("x"), f.create_group("x")), "x", "not a dataset"),
    ("x-3d", lambda f: put(f, "x", np.zeros((B, T + 1, N))), "x", "4-D"),
    ("x-int", lambda f: put(f, "x", np.zeros((B, T + 1, N, DX), dtype=np.int32)), "x", "float32 or float64"),
    ("x-float16", lambda f: put(f, "x", np.zeros((B, T + 1, N, DX), dtype=np.float16)), "x", "float32 or float64"),
    ("x-no-trajectory", lambda f: put(f, "x", np.zeros((0, T + 1, N, DX))), "x", "B = 0"),
    ("x-no-step", lambda f: put(f, "x", np.zeros((B, 1, N, DX))), "x", "T+1 = 1"),
    ("x-no-node", lambda f: put(f, "x", np.zeros((B, T + 1, 0, DX))), "x", "N = 0"),
    ("x-no-state", lambda f: put(f, "x", np.zeros((B, T + 1, N, 0))), "x", "dx = 0"),
    ("x-nan", nan_at("x", (1, 2, 0, 1)), "x", "nan at [1, 2, 0, 1]"),
    ("x-inf", nan_at("x", (0, 3, 2, 0), -np.inf), "x", "-inf at [0, 3, 2, 0]"),
    ("u-steps", lambda f: put(f, "u", np.zeros((B, T + 1, N, DU))), "u", "[B, T, N, du]"),
    ("u-nodes", lambda f: put(f, "u", np.zeros((B, T, N + 1, DU))), "u", "to match x"),
    ("u-du-zero", lambda f: put(f, "u", np.zeros((B, T, N, 0))), "u", "omit u"),
    ("u-int", lambda f: put(f, "u", np.zeros((B, T, N, DU), dtype=np.int64)), "u", "float32 or float64"),
    ("u-nan", nan_at("u", (1, 0, 2, 0)), "u", "nan at [1, 0, 2, 0]"),
    ("graph-index-missing", lambda f: f.__delitem__("graph_index"), "graph_index", "file has 2 graphs"),
    ("graph-index-shape", lambda f: put(f, "graph_index", np.array([0, 1, 1])), "graph_index", "shape (2,)"),
    ("graph-index-float", lambda f: put(f, "graph_index", np.array([0.0, 1.0])), "graph_index", "integer dtype"),
    ("graph-index-too-big", lambda f: put(f, "graph_index", np.array([0, 2])), "graph_index",
     "trajectory 1 names graph 2"),
    ("graph-index-negative", lambda f: put(f, "graph_index", np.array([-1, 0])), "graph_index",
     "trajectory 0 names graph -1"),
    ("graphs-missing", lambda f: f.__delitem__("graphs"), "graphs", "missing"),
    ("graphs-empty", lambda f: (f.__delitem__("graphs"), f.create_group("graphs")), "graphs", "no graphs"),
    ("graphs-gap", lambda f: f.move("graphs/1", "graphs/2"), "graphs", "no gaps"),
    ("graphs-named", lambda f: f.move("graphs/1", "graphs/ring"), "graphs", "no gaps"),
    ("graph-dataset", lambda f: (f.__delitem__("graphs/1"), put(f, "graphs/1", np.zeros(3))), "graphs/1",
     "not a group"),
    ("indptr-missing", lambda f: f.__delitem__("graphs/1/indptr"), "graphs/1/indptr", "missing"),
    ("indices-missing", lambda f: f.__delitem__("graphs/1/indices"), "graphs/1/indices", "missing"),
    ("indptr-float", lambda f: put(f, "graphs/0/indptr", np.array([0.0, 1, 3, 4])), "graphs/0/indptr",
     "integer dtype"),
    ("indices-float", lambda f: put(f, "graphs/0/indices", np.array([1.0, 0, 2, 1])), "graphs/0/indices",
     "integer dtype"),
    ("indptr-wrong-n", lambda f: put(f, "graphs/1/indptr", np.array([0, 2, 4, 6, 6])), "graphs/1/indptr",
     "shape (4,)"),
    ("indptr-start", lambda f: put(f, "graphs/0/indptr", np.array([1, 1, 3, 4])), "graphs/0/indptr",
     "starts at 1"),
    ("indptr-decreasing", lambda f: put(f, "graphs/0/indptr", np.array([0, 3, 2, 4])), "graphs/0/indptr",
     "decreases"),
    ("indptr-end", lambda f: put(f, "graphs/0/indptr", np.array([0, 1, 3, 3])), "graphs/0/indptr",
     "indices has 4 entries"),
    ("indices-too-big", lambda f: put(f, "graphs/0/indices", np.array([1, 0, 3, 1])), "graphs/0/indices",
     "node id 3"),
    ("indices-negative", lambda f: put(f, "graphs/0/indices", np.array([1, 0, -1, 1])), "graphs/0/indices",
     "node id -1"),
    ("indices-duplicate", lambda f: put(f, "graphs/0/indices", np.array([1, 0, 0, 1])), "graphs/0/indices",
     "twice"),
    ("self-loop", self_loop_graph, "graphs/0/indices", "self-loop"),
    ("self-loop-flag-0", lambda f: (self_loop_graph(f), f["graphs/0"].attrs.__setitem__("self_loops", 0)),
     "graphs/0/indices", "self-loop"),
    ("self-loop-flag-2", lambda f: f["graphs/0"].attrs.__setitem__("self_loops", 2), "graphs/0", "self_loops = 2"),
    ("params-dataset", lambda f: (f.__delitem__("params"), put(f, "params", np.zeros(2))), "params",
     "not a group"),
]


@pytest.mark.parametrize("corrupt, field, phrase", [c[1:] for c in CORRUPTIONS], ids=[c[0] for c in CORRUPTIONS])
def test_reader_rejects_each_rule(raw_file, corrupt, field, phrase):
    read_trajectories(raw_file)  # valid before the corruption
    with h5py.File(raw_file, "r+") as f:
        corrupt(f)
    with pytest.raises(InputError) as info:
        read_trajectories(raw_file)
    e = info.value
    assert (e.source, e.field) == (str(raw_file), field)
    assert phrase.lower() in str(e).lower()
    assert str(e).startswith(f"{raw_file}: {field}: ")


def test_read_raw_file(raw_file):
    t = read_trajectories(raw_file)
    assert (t.n_trajectories, t.horizon, t.n_nodes, t.state_dim, t.control_dim) == (B, T, N, DX, DU)
    assert (t.dt, t.system, t.attrs) == (0.05, "kuramoto", {"seed": 7})
    assert type(t.dt) is float and type(t.attrs["seed"]) is int
    assert t.graph_index.tolist() == [1, 0] and t.graph_index.dtype == np.int64
    assert t.graphs[0].equals(Graph(*PATH_GRAPH)) and t.graphs[1].equals(Graph.complete(N))
    assert t.graph_of(0).n_edges == 6
    assert t.params["coupling"] == 0.5
    assert t.aux["load/pos"].shape == (B, T + 1, 3)


def test_one_graph_needs_no_graph_index(raw_file):
    with h5py.File(raw_file, "r+") as f:
        del f["graph_index"], f["graphs/1"]
    assert read_trajectories(raw_file).graph_index.tolist() == [0, 0]


def test_self_loops_allowed_when_flagged(raw_file):
    with h5py.File(raw_file, "r+") as f:
        self_loop_graph(f)
        f["graphs/0"].attrs["self_loops"] = 1
    assert read_trajectories(raw_file).graphs[0].self_loops


def test_outside_tool_encodings_accepted(raw_file):
    """Fixed-length byte strings and big-endian floats are still the format's types."""
    with h5py.File(raw_file, "r+") as f:
        f.attrs["format"] = np.bytes_(b"mpnode.trajectories")
        f.attrs["system"] = np.bytes_(b"kuramoto")
        put(f, "x", f["x"][()].astype(">f8"))
        del f["u"]
    t = read_trajectories(raw_file)
    assert t.system == "kuramoto" and t.u is None
    assert t.x.dtype == np.float64 and t.x.dtype.isnative


def make_traj(dtype=np.float64, n_graphs=2):
    rng = np.random.default_rng(1)
    graphs = [Graph(*PATH_GRAPH), Graph.from_edges(N, [(0, 0), (1, 2)], self_loops=True)][:n_graphs]
    return Trajectories(
        x=rng.standard_normal((B, T + 1, N, DX)).astype(dtype), graphs=graphs, dt=0.1, system="lorenz",
        u=rng.standard_normal((B, T, N, DU)).astype(dtype),
        graph_index=np.array([1, 0]) if n_graphs == 2 else None,
        attrs={"seed": 3, "solver": "rk45", "rtol": 1e-8, "tags": ["a", "b"], "weights": np.array([1.0, 2.0])},
        params={"sigma": np.array(10.0), "K": np.arange(9.0).reshape(3, 3)},
        aux={"load/pos": np.ones((B, T + 1, 3), dtype=np.float32)},
    )


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n_graphs", [1, 2])
def test_round_trip_is_exact(tmp_path, dtype, n_graphs):
    t = make_traj(dtype, n_graphs)
    path = tmp_path / "t.h5"
    write_trajectories(path, t)
    with h5py.File(path, "r") as f:
        assert ("graph_index" in f) == (n_graphs > 1)  # the spec omits it for one graph
        assert f.attrs["format"] == "mpnode.trajectories" and f.attrs["format_version"] == 1
    r = read_trajectories(path)
    for name in ("x", "u", "graph_index"):
        a, b = getattr(t, name), getattr(r, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    assert len(r.graphs) == n_graphs and all(a.equals(b) for a, b in zip(t.graphs, r.graphs))
    assert (r.dt, r.system) == (t.dt, t.system)
    assert r.attrs.keys() == t.attrs.keys()
    for key, value in t.attrs.items():
        assert np.array_equal(r.attrs[key], value), key
    for group in ("params", "aux"):
        got, want = getattr(r, group), getattr(t, group)
        assert got.keys() == want.keys()
        assert all(got[k].dtype == want[k].dtype and np.array_equal(got[k], want[k]) for k in want)


def test_self_loops_flag_written(tmp_path):
    path = tmp_path / "t.h5"
    write_trajectories(path, make_traj())
    with h5py.File(path, "r") as f:
        assert "self_loops" not in f["graphs/0"].attrs and f["graphs/1"].attrs["self_loops"] == 1


def test_controls_optional(tmp_path):
    t = make_traj()
    t.u = None
    write_trajectories(tmp_path / "t.h5", t)
    assert read_trajectories(tmp_path / "t.h5").control_dim == 0


def replace(t, **changes):
    for name, value in changes.items():
        setattr(t, name, value)
    return t


@pytest.mark.parametrize("changes, field, phrase", [
    ({"dt": 0.0}, "dt", "> 0"),
    ({"dt": True}, "dt", "a finite number"),
    ({"system": None}, "system", "string"),
    ({"x": np.full((B, T + 1, N, DX), np.nan)}, "x", "nothing observed at its first time"),
    ({"u": np.zeros((B, T, N, 0))}, "u", "omit u"),
    ({"graphs": []}, "graphs", "non-empty"),
    ({"graphs": [Graph(*PATH_GRAPH), "ring"]}, "graphs/1", "mpnode.Graph"),
    ({"graphs": [Graph(*PATH_GRAPH), Graph.complete(N + 1)]}, "graphs/1/indptr", "shape (4,)"),
    ({"graph_index": np.array([0, 5])}, "graph_index", "names graph 5"),
    ({"attrs": {"dt": 0.2}}, "dt", "format attribute"),
    ({"attrs": {"config": {"a": 1}}}, "config", "cannot be stored"),
    ({"params": {"k": None}}, "params/k", "cannot be stored"),
])
def test_writer_rejects_invalid(tmp_path, changes, field, phrase):
    path = tmp_path / "t.h5"
    with pytest.raises(InputError) as info:
        write_trajectories(path, replace(make_traj(), **changes))
    assert info.value.field == field and phrase in str(info.value)
    assert os.listdir(tmp_path) == []  # nothing written, no temporary file left


def test_validate_is_the_shared_checker():
    t = make_traj()
    assert validate_trajectories(t, "memory") is t
    with pytest.raises(InputError, match="^memory: x: "):
        validate_trajectories(replace(t, x=t.x.astype(np.int64)), "memory")


def test_failed_write_leaves_old_file_and_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "t.h5"
    write_trajectories(path, make_traj(n_graphs=1))
    before = path.read_bytes()

    def fail(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(h5py.Group, "create_group", fail)  # after x and u are written
    with pytest.raises(RuntimeError, match="disk full"):
        write_trajectories(path, make_traj())
    assert os.listdir(tmp_path) == ["t.h5"] and path.read_bytes() == before
    os.remove(path)
    with pytest.raises(RuntimeError, match="disk full"):
        write_trajectories(path, make_traj())
    assert os.listdir(tmp_path) == []


def test_not_hdf5(tmp_path):
    path = tmp_path / "notes.h5"
    path.write_text("x,y\n1,2\n")
    with pytest.raises(InputError, match="cannot be opened as HDF5") as info:
        read_trajectories(path)
    assert (info.value.source, info.value.field) == (str(path), "file")


def test_truncated(raw_file):
    data = raw_file.read_bytes()
    raw_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated") as info:
        read_trajectories(raw_file)
    assert (info.value.source, info.value.field) == (str(raw_file), "file")


def test_missing(tmp_path):
    with pytest.raises(InputError, match="does not exist") as info:
        read_trajectories(tmp_path / "nope.h5")
    assert info.value.field == "file"


def test_summarize(raw_file):
    s = summarize(read_trajectories(raw_file))
    assert {k: s[k] for k in ("system", "B", "T", "N", "dx", "du", "dt", "x_dtype")} == {
        "system": "kuramoto", "B": B, "T": T, "N": N, "dx": DX, "du": DU, "dt": 0.05, "x_dtype": "float64"}
    assert s["graphs"] == [{"nodes": 3, "edges": 4, "self_loops": False, "trajectories": 1},
                           {"nodes": 3, "edges": 6, "self_loops": False, "trajectories": 1}]
    assert s["params"] == {"coupling": {"shape": [], "dtype": "float64", "value": 0.5}}
    assert "value" not in s["aux"]["load/pos"] and s["attrs"] == {"seed": 7}


def test_import_mpnode_stays_light():
    code = "import sys, mpnode, mpnode.data; assert 'h5py' not in sys.modules, 'h5py imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
