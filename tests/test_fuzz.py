"""Bad input never gets through: every reader answers malformed input with InputError.

Property-based (hypothesis) corruption of valid files -- trajectory files, model files and
scene TOML -- and of the `generate` / `inspect` command lines.  The property is exact: the
reader either returns something that passes its own validation (only possible for blind
byte damage or mutations that keep the file valid) or raises `mpnode.base.errors.InputError`
naming the file; never KeyError, ValueError, OSError, TypeError, UnicodeDecodeError, ...
From the CLI: exit status 2, no "Traceback", no output file.

Known limit (not fixable in a reader): libhdf5 itself can loop forever on some damaged bytes.
Found by this fuzzing: in the `full.h5` base below (16424 bytes), overwriting byte 2168 (in the
attribute storage, right after the string "fuzz base") with 28 makes ``f.attrs.get("format")``
spin inside H5Aopen/H5Aread, never returning and holding the GIL, so neither a timeout nor a
signal in the reading process can turn it into InputError.  Guarding against it would need a
reader in a subprocess; hence the derandomized CI sample (see `fuzz`).

Budget: the whole file runs in well under a minute (max_examples below, deadline off).
Set MPNODE_FUZZ_SCALE=10 (say) to run ten times as many examples when hunting (unshrunk).  The number
of corrupted inputs tried is counted per reader and printed by the last test (run with -s).
"""
import json
import math
import numbers
import os
import re
import shutil
import tempfile
import warnings
from collections import Counter
from dataclasses import replace

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from cli.main import main
from data_gen import generate, read_scene
from data_gen.systems import SYSTEMS
from mpnode.base.errors import InputError, NumericalError
from mpnode.base.graph import Graph
from mpnode.data import Trajectories, read_trajectories, validate_trajectories, write_trajectories
from mpnode.model import Model

SCALE = float(os.environ.get("MPNODE_FUZZ_SCALE", "1"))
TRIED = Counter()  # corrupted inputs tried, per reader


def fuzz(n):
    # CI (scale 1) runs a fixed, derandomized sample: blind byte damage can hit a libhdf5 hang (module
    # docstring), which no in-process reader can interrupt.  Hunting runs are random and report the
    # first failure unshrunk (shrinking through generate is slow).
    hunting = SCALE > 1
    return settings(max_examples=max(1, int(n * SCALE)), deadline=None, database=None, derandomize=not hunting,
                    phases=[Phase.explicit, Phase.generate] if hunting else list(Phase),
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                           HealthCheck.data_too_large, HealthCheck.filter_too_much])


@pytest.fixture(scope="module")
def workdir():
    d = tempfile.mkdtemp(prefix="mpnode-fuzz-")
    yield d
    shutil.rmtree(d, ignore_errors=True)


class Case:
    """A fresh copy of a base file in its own folder, removed afterwards."""

    def __init__(self, workdir, base, name):
        self.dir = tempfile.mkdtemp(dir=workdir)
        self.path = os.path.join(self.dir, name)
        shutil.copyfile(base, self.path)

    def __enter__(self):
        return self.path

    def __exit__(self, *exc):
        shutil.rmtree(self.dir, ignore_errors=True)


def assert_input_error(read, path, allow_valid=False):
    """read(path) raises InputError naming ``path`` (or, if allowed, returns a valid result)."""
    try:
        result = read(path)
    except InputError as e:
        assert e.source == str(path), e
        assert e.field and e.problem, e
        return None
    assert allow_valid, f"{path}: read without complaint"
    return result


# ---- base files -------------------------------------------------------------------------------
RING4 = Graph([0, 2, 4, 6, 8], [1, 3, 0, 2, 1, 3, 0, 2])
STAR4 = Graph.complete(4)


def base_trajectories():
    rng = np.random.default_rng(0)
    return Trajectories(x=rng.standard_normal((3, 5, 4, 2)), u=rng.standard_normal((3, 4, 4, 1)),
                        graphs=[RING4, STAR4], graph_index=np.array([0, 1, 0]), dt=0.05, system="kuramoto",
                        attrs={"seed": 7, "rtol": 1e-9, "note": "fuzz base"},
                        params={"omega": np.array([0.1, 0.2, 0.3])}, aux={"load/pos": np.zeros((3, 5, 3))})


@pytest.fixture(scope="module")
def traj_bases(workdir):
    full = os.path.join(workdir, "full.h5")
    write_trajectories(full, base_trajectories())
    one = os.path.join(workdir, "one.h5")  # one graph (no graph_index), no controls, float32
    t = base_trajectories()
    write_trajectories(one, replace(t, x=t.x.astype(np.float32), u=None, graphs=[RING4],
                                    graph_index=np.zeros(3, dtype=np.int64)))
    for p in (full, one):
        read_trajectories(p)  # the bases are valid
    return [full, one]


@pytest.fixture(scope="module")
def model_bases(workdir):
    out = []
    for i, kw in enumerate([dict(state_dim=2, control_dim=1, message_dim=3, hidden=5),
                            dict(state_dim=3, control_dim=0, message_dim=0, hidden=4, dtype=np.float64)]):
        m = Model.create(**kw)
        m.x_std = np.full(kw["state_dim"], 2.0)
        path = os.path.join(workdir, f"model{i}.h5")
        m.save(path, history="fuzz base")
        Model.load(path)
        out.append(path)
    return out


# ---- blind damage: truncation and overwritten bytes ---------------------------------------------
def damage(path, data):
    """Truncate at a random offset, or overwrite a few random bytes (one of the two)."""
    raw = bytearray(open(path, "rb").read())
    if data.draw(st.booleans(), label="truncate"):
        raw = raw[:data.draw(st.integers(0, len(raw) - 1), label="offset")]
    else:
        for _ in range(data.draw(st.integers(1, 8), label="bytes")):
            at = data.draw(st.integers(0, len(raw) - 1), label="at")
            raw[at] = data.draw(st.integers(0, 255), label="value")
    open(path, "wb").write(bytes(raw))


@fuzz(150)
@given(data=st.data())
def test_damaged_trajectory_bytes(workdir, traj_bases, data):
    base = data.draw(st.sampled_from(traj_bases), label="base")
    with Case(workdir, base, "damaged.h5") as path:
        damage(path, data)
        TRIED["trajectory files"] += 1
        t = assert_input_error(read_trajectories, path, allow_valid=True)
        if t is not None:  # damage in a spot that leaves a valid file: it must really be valid
            validate_trajectories(t, path)


@fuzz(100)
@given(data=st.data())
def test_damaged_model_bytes(workdir, model_bases, data):
    base = data.draw(st.sampled_from(model_bases), label="base")
    with Case(workdir, base, "damaged.h5") as path:
        damage(path, data)
        TRIED["model files"] += 1
        m = assert_input_error(Model.load, path, allow_valid=True)
        if m is not None:
            assert np.all(np.isfinite(m.theta)) and np.all(m.x_std > 0)


# ---- structured corruption of trajectory files ------------------------------------------------------
FINITE_BREAKERS = st.sampled_from([np.nan, np.inf, -np.inf])
NOT_A_NUMBER = st.sampled_from(["0.05", b"0.05", "", np.array([0.05, 0.05]), np.array([], dtype=np.float64),
                                np.array(["a", "b"], dtype="S1"), True, np.bool_(False)])
BAD_STRINGS = st.sampled_from([5, 1.5, b"\xff\xfe", np.array(["mpnode.trajectories"] * 2, dtype=object),
                               np.array([1, 2]), np.array([[1.0]]), "", "mpnode.model", "MPNODE.TRAJECTORIES"])


def put(f, name, value):
    if name in f:
        del f[name]
    f[name] = value


def set_attr(f, name, value, where="/"):
    obj = f[where]
    if isinstance(value, np.ndarray) and value.dtype == object:
        obj.attrs.create(name, value, dtype=h5py.string_dtype())
    else:
        obj.attrs[name] = value


def a_graph(f, data):
    return f"graphs/{data.draw(st.integers(0, len(f['graphs']) - 1), label='graph')}"


def nonfinite(f, data):
    name = data.draw(st.sampled_from(["x", "u"] if "u" in f else ["x"]), label="array")
    a = f[name][()]
    idx = tuple(data.draw(st.integers(0, s - 1)) for s in a.shape)
    a[idx] = data.draw(FINITE_BREAKERS)
    put(f, name, a)


def wrong_dtype(f, data):
    name = data.draw(st.sampled_from(["x", "u", "graph_index", "graphs/0/indptr", "graphs/0/indices"]),
                     label="dataset")
    if name not in f:
        name = "x"
    a = f[name][()]
    if a.dtype.kind == "f":
        kind = data.draw(st.sampled_from(["int", "float16", "complex", "str", "bool", "compound"]))
    else:
        kind = data.draw(st.sampled_from(["float", "str", "bool", "compound"]))
    if kind == "int":
        v = np.round(a).astype(np.int64)
    elif kind == "float16":
        v = a.astype(np.float16)
    elif kind == "complex":
        v = a.astype(np.complex128)
    elif kind == "float":
        v = a.astype(np.float64) + 0.5
    elif kind == "bool":
        v = a != 0
    elif kind == "str":
        v = np.array([str(e) for e in a.ravel()], dtype=object).reshape(a.shape).astype("S")
    else:
        v = np.zeros(a.shape, dtype=[("re", "f8"), ("im", "f8")])
    if name == "graph_index" and kind == "bool":
        v = v.astype(np.float32) + 0.5
    put(f, name, v)


def wrong_shape(f, data):
    name = data.draw(st.sampled_from(["x", "u", "graph_index", "graphs/0/indptr"]), label="dataset")
    if name not in f:
        name = "x"
    old = f[name].shape
    ndim = data.draw(st.integers(0, 5), label="ndim")
    shape = tuple(data.draw(st.lists(st.integers(0, 6), min_size=ndim, max_size=ndim), label="shape"))
    if shape == old:
        shape = shape + (1,)
    if name == "x" and len(shape) == 4 and shape[2] == 4:
        shape = shape[:2] + (5,) + shape[3:]  # N = 5 disagrees with the graphs: never valid
    if name == "u" and len(shape) == 4 and shape[:3] == (3, 4, 4):
        shape = (2,) + shape[1:]  # a different du alone would be valid
    dtype = f[name].dtype
    put(f, name, np.ones(shape, dtype=dtype) if dtype.kind == "f" else np.zeros(shape, dtype=dtype))


def break_csr(f, data):
    g = a_graph(f, data)
    indptr, indices = f[f"{g}/indptr"][()], f[f"{g}/indices"][()]
    n = len(indptr) - 1
    how = data.draw(st.sampled_from(["decreasing", "start", "end", "out_of_range", "duplicate", "self_loop"]),
                    label="csr")
    if how == "decreasing":
        i = data.draw(st.integers(1, n - 1))
        indptr[i] = indptr[i + 1] + data.draw(st.integers(1, 3))
    elif how == "start":
        indptr[0] = data.draw(st.sampled_from([-1, 1, 2]))
    elif how == "end":
        indptr[-1] += data.draw(st.sampled_from([-1, 1, 5]))
    elif how == "out_of_range":
        j = data.draw(st.integers(0, len(indices) - 1))
        indices[j] = data.draw(st.sampled_from([-1, -5, n, n + 3, 2**40]))
    elif how == "duplicate":
        row = data.draw(st.integers(0, n - 1))
        lo = indptr[row]
        indices[lo + 1] = indices[lo]  # every row of the bases has >= 2 entries
    else:
        row = data.draw(st.integers(0, n - 1))
        indices[indptr[row]] = row
        if data.draw(st.booleans(), label="flag"):  # an explicit "no" is no permission either
            set_attr(f, "self_loops", data.draw(st.sampled_from([0, False])), g)
    put(f, f"{g}/indptr", indptr)
    put(f, f"{g}/indices", indices)


def bad_self_loops_flag(f, data):
    set_attr(f, "self_loops", data.draw(st.sampled_from([2, -1, 0.5, "yes", np.array([1, 1]), b"\xff"])),
             a_graph(f, data))


def drop(f, data):
    names = ["x", "graphs", "graphs/0", "graphs/0/indptr", "graphs/0/indices"]
    if "graph_index" in f:
        names.append("graph_index")
    del f[data.draw(st.sampled_from(names), label="drop")]


def graph_index_values(f, data):
    if "graph_index" not in f:
        put(f, "graph_index", np.array([0, 1, 0]))  # names graph 1, which a one-graph file lacks
        return
    gi = f["graph_index"][()]
    gi[data.draw(st.integers(0, len(gi) - 1))] = data.draw(st.sampled_from([-1, 2, 7, -2**40]))
    put(f, "graph_index", gi)


def graph_names(f, data):
    how = data.draw(st.sampled_from(["gap", "extra", "empty", "dataset"]))
    last = len(f["graphs"]) - 1
    if how == "gap":
        f.move(f"graphs/{last}", f"graphs/{last + 1}")
    elif how == "extra":
        f.create_group(f"graphs/{data.draw(st.sampled_from(['a', '-1', '01', 'x y']))}")
    elif how == "empty":
        for name in list(f["graphs"]):
            del f[f"graphs/{name}"]
    else:
        del f["graphs/0"]
        f["graphs/0"] = np.arange(3)


def kind_swap(f, data):
    name = data.draw(st.sampled_from(["x", "graphs/0/indptr", "graph_index", "u"]))
    if name not in f:
        name = "x"
    del f[name]
    how = data.draw(st.sampled_from(["group", "soft", "external", "empty", "scalar"]))
    if how == "group":
        f.create_group(name)
    elif how == "soft":
        f[name] = h5py.SoftLink("/nowhere")
    elif how == "external":
        f[name] = h5py.ExternalLink("no-such-file.h5", "/x")
    elif how == "empty":
        f.create_dataset(name, data=h5py.Empty("f8"))
    else:
        f[name] = 1.0


def bad_root_attr(f, data):
    name = data.draw(st.sampled_from(["format", "format_version", "dt", "system"]), label="attr")
    if data.draw(st.booleans(), label="delete"):
        del f.attrs[name]
        return
    values = {"format": BAD_STRINGS,
              "format_version": st.sampled_from([0, 2, -1, "1", 1.5, True, np.array([1, 1]), b"1", 2**40]),
              "dt": st.one_of(st.sampled_from([0.0, -0.05, -np.inf]), FINITE_BREAKERS, NOT_A_NUMBER),
              "system": st.sampled_from(["", "   ", 5, 0.5, np.array([1, 2]), np.array(["a", "b"], dtype=object)])}
    set_attr(f, name, data.draw(values[name], label="value"))


TRAJ_MUTATIONS = [nonfinite, wrong_dtype, wrong_shape, break_csr, bad_self_loops_flag, drop, graph_index_values,
                  graph_names, kind_swap, bad_root_attr]


@fuzz(300)
@given(data=st.data())
def test_corrupted_trajectory_files_raise_input_error(workdir, traj_bases, data):
    base = data.draw(st.sampled_from(traj_bases), label="base")
    with Case(workdir, base, "bad.h5") as path:
        mutation = data.draw(st.sampled_from(TRAJ_MUTATIONS), label="mutation")
        with h5py.File(path, "r+") as f:
            mutation(f, data)
        TRIED["trajectory files"] += 1
        assert_input_error(read_trajectories, path)


# ---- structured corruption of model files ----------------------------------------------------------
PARAMS = ["W1", "b1", "W2", "b2", "W3", "b3"]


def model_datasets(f):
    return [f"params/{p}" for p in PARAMS] + [f"norm/{n}" for n in f["norm"]]


def m_drop(f, data):
    del f[data.draw(st.sampled_from(model_datasets(f) + ["params", "norm"]), label="drop")]


def m_nonfinite(f, data):
    name = data.draw(st.sampled_from(model_datasets(f)), label="dataset")
    a = f[name][()]
    a[tuple(data.draw(st.integers(0, s - 1)) for s in a.shape)] = data.draw(FINITE_BREAKERS)
    put(f, name, a)


def m_shape(f, data):
    name = data.draw(st.sampled_from(model_datasets(f)), label="dataset")
    old = f[name].shape
    shape = tuple(data.draw(st.lists(st.integers(0, 7), max_size=3), label="shape"))
    if shape == old:
        shape = shape + (1,)
    put(f, name, np.ones(shape))


def m_dtype(f, data):
    name = data.draw(st.sampled_from(model_datasets(f)), label="dataset")
    a = f[name][()]
    put(f, name, data.draw(st.sampled_from([np.round(a).astype(np.int32), a.astype(np.float16),
                                            a.astype(np.complex64), a.astype("S8"), a > 0]), label="value"))


def m_mixed_precision(f, data):
    name = data.draw(st.sampled_from(PARAMS[1:]), label="param")
    a = f[f"params/{name}"][()]
    put(f, f"params/{name}", a.astype(np.float64 if a.dtype == np.float32 else np.float32))


def m_std(f, data):
    name = data.draw(st.sampled_from([n for n in ("x_std", "u_std") if n in f["norm"]]))
    a = f[f"norm/{name}"][()]
    a[data.draw(st.integers(0, len(a) - 1))] = data.draw(st.sampled_from([0.0, -1.0, -1e-300]))
    put(f, f"norm/{name}", a)


def m_kind(f, data):
    name = data.draw(st.sampled_from(model_datasets(f)), label="dataset")
    del f[name]
    how = data.draw(st.sampled_from(["group", "soft", "external", "empty"]))
    if how == "group":
        f.create_group(name)
    elif how == "soft":
        f[name] = h5py.SoftLink("/nowhere")
    elif how == "external":
        f[name] = h5py.ExternalLink("no-such-file.h5", "/x")
    else:
        f.create_dataset(name, data=h5py.Empty("f4"))


INT_ATTRS = ["state_dim", "control_dim", "message_dim", "hidden", "substeps", "zero_messages", "self_messages"]
BAD_INTS = st.sampled_from([-1, 1.5, "3", b"3", np.array([1, 2]), np.array([], dtype=np.int64),
                            np.nan, np.array(["a"], dtype=object)])
BAD_MODEL_ATTRS = {
    "format": st.sampled_from([5, b"\xff\xfe", np.array(["mpnode.model"] * 2, dtype=object), np.array([1, 2]),
                               "", "mpnode.trajectories", "MPNODE.MODEL"]),
    "format_version": st.sampled_from([0, 3, "1", 1.5, np.array([1, 1]), b"\xff"]),
    "kind": st.sampled_from(["gnn", "", 1, b"\xff\xfe", np.array(["mpnode", "l2s"], dtype=object)]),
    "aggregation": st.sampled_from(["max", "Mean", 0, b"\x80", np.array(["sum"], dtype=object)]),
    "activation": st.sampled_from(["relu", "", 1, np.array(["tanh", "tanh"], dtype=object), b"\xff\xfe"]),
    "integrator": st.sampled_from(["euler", "RK4", 4, np.array([1.0]), b"\x80"]),
    "dt": st.one_of(st.sampled_from([0.0, -0.05]), FINITE_BREAKERS, NOT_A_NUMBER),
    **{name: BAD_INTS for name in INT_ATTRS},
    **{name: st.one_of(BAD_INTS, st.just(2**40)) for name in INT_ATTRS if name != "substeps"},  # shapes disagree
}


#: attributes with a default: a file without them is still valid
DEFAULTED_ATTRS = ("kind", "aggregation")


def m_attr(f, data):
    name = data.draw(st.sampled_from(sorted(BAD_MODEL_ATTRS)), label="attr")
    if name not in DEFAULTED_ATTRS and data.draw(st.booleans(), label="delete"):
        del f.attrs[name]
        return
    set_attr(f, name, data.draw(BAD_MODEL_ATTRS[name], label="value"))


MODEL_MUTATIONS = [m_drop, m_nonfinite, m_shape, m_dtype, m_mixed_precision, m_std, m_kind, m_attr]


@fuzz(250)
@given(data=st.data())
def test_corrupted_model_files_raise_input_error(workdir, model_bases, data):
    base = data.draw(st.sampled_from(model_bases), label="base")
    with Case(workdir, base, "bad_model.h5") as path:
        mutation = data.draw(st.sampled_from(MODEL_MUTATIONS), label="mutation")
        with h5py.File(path, "r+") as f:
            mutation(f, data)
        TRIED["model files"] += 1
        assert_input_error(Model.load, path)


def test_model_reader_missing_and_not_hdf5(workdir):
    path = os.path.join(workdir, "nothing.h5")
    assert_input_error(Model.load, path)
    with open(path, "w") as f:
        f.write("not hdf5")
    assert_input_error(Model.load, path)
    os.makedirs(os.path.join(workdir, "adir.h5"), exist_ok=True)
    assert_input_error(Model.load, os.path.join(workdir, "adir.h5"))
    assert_input_error(read_trajectories, os.path.join(workdir, "adir.h5"))


# ---- scene TOML ---------------------------------------------------------------------------------------
class Raw(str):
    """A TOML literal written as is (datetimes, malformed values)."""


def toml_value(v):
    if isinstance(v, Raw):
        return str(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v == np.inf else "-inf" if v == -np.inf else repr(v))
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")  # TOML forbids a raw DEL
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(e) for e in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{toml_key(k)} = {toml_value(e)}" for k, e in v.items()) + "}"
    raise TypeError(v)


def toml_key(k):
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)


def toml_doc(doc):
    lines = [f"{toml_key(k)} = {toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines.append(f"[{toml_key(k)}]")
            lines += [f"{toml_key(kk)} = {toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


ANY_VALUE = st.one_of(
    st.integers(-2**63, 2**63 - 1), st.floats(), st.booleans(), st.text(max_size=8),
    st.sampled_from([Raw("1979-05-27T07:32:00Z"), Raw("07:32:00"), Raw("1979-05-27"), [], {}, [1, "a"],
                     [[0, 1], [1]], {"a": 1}, 0, -1, 0.0, -0.0, 2**63 - 1, -2**63, 1e308, 1e-320]),
    st.lists(st.integers(-3, 10), max_size=4),
)


@st.composite
def valid_scene(draw):
    """A scene document the reader accepts, from the schema of data_gen/scenes.py."""
    system = draw(st.sampled_from(["coupled_pendulum", "lorenz", "gene", "kuramoto"]))
    if system == "coupled_pendulum":
        graph = {"builder": "edges", "nodes": 2, "edges": [[0, 1]]}
    elif system == "lorenz":
        graph = {"builder": "complete", "nodes": draw(st.integers(1, 4))}
    else:
        n = draw(st.integers(4, 9))
        builder = draw(st.sampled_from(["edges", "complete", "gnp", "gnm", "barabasi_albert", "watts_strogatz"]))
        graph = {"builder": builder, "nodes": n}
        if builder == "edges":
            graph["edges"] = draw(st.lists(st.lists(st.integers(0, n - 1), min_size=2, max_size=2), max_size=6))
            if draw(st.booleans()):
                graph["directed"] = draw(st.booleans())
        elif builder != "complete":
            seeds = draw(st.lists(st.integers(0, 99), min_size=1, max_size=2))
            if len(seeds) == 1 and draw(st.booleans()):
                graph["seed"] = seeds[0]
            else:
                graph["seeds"] = seeds
            graph.update({"gnp": {"p": 0.5}, "gnm": {"m": 5}, "barabasi_albert": {"m": 2},
                          "watts_strogatz": {"k": 2, "p": 0.5}}[builder])
    doc = {"system": system}
    optional = {"initial": st.just("uniform"), "description": st.text(max_size=20), "trajectories": st.integers(1, 3), "horizon": st.integers(1, 3),
                "dt": st.sampled_from([0.01, 0.05, 0.1]), "seed": st.integers(0, 2**32),
                "system_seed": st.integers(0, 9), "integrator": st.sampled_from(["DOP853", "RK45", "LSODA", "Radau"]),
                "rtol": st.sampled_from([1e-6, 1e-9]), "atol": st.sampled_from([1e-6, 1e-9])}
    for key, strategy in optional.items():
        if draw(st.booleans()):
            doc[key] = draw(strategy)
    if draw(st.booleans()):
        doc["params"] = {k: v for k, v in SYSTEMS[system].defaults.items() if draw(st.booleans())}
    doc["graph"] = graph
    return doc


TOP_KEYS = ["description", "system", "trajectories", "horizon", "dt", "seed", "system_seed", "initial",
            "integrator", "rtol", "atol", "params", "graph"]
GRAPH_KEYS = ["builder", "nodes", "edges", "directed", "seed", "seeds", "p", "m", "k"]
OUT_OF_RANGE = {
    "trajectories": [0, -1, -2**63], "horizon": [0, -5], "dt": [0.0, -0.05, float("nan"), float("inf"), 1e308],
    "rtol": [0.0, -1e-9, float("nan"), float("inf")], "atol": [0.0, float("-inf"), float("inf")],
    "seed": [-1, -2**63], "system_seed": [-1], "graph.nodes": [0, -3, 1],
    "graph.p": [-0.5, 1.5, float("nan"), float("inf")], "graph.m": [0, -1, 10**6], "graph.k": [0, -2, 10**6],
    "graph.seeds": [[], [-1], [2**63 - 1, -5]], "graph.seed": [-1],
    "graph.edges": [[[0, 99]], [[-1, 0]], [[0]], [[0, 1, 2]], [["0", 1]], [[0.5, 1]], [[True, 0]]],
    "params": [{"b": float("nan")}, {"b": float("inf")}, {"g": float("-inf")}, {"sigma": float("nan")},
               {"K": float("inf")}, {"nope": 1.0}],
    "integrator": ["Euler", "dop853", ""], "initial": ["hotspots", "gauss", "equilibrium", ""],
    "system": ["", "lorenz3", "quadrotor", "GENE"],
}


@st.composite
def mutated_scene(draw):
    """A valid scene document after 1-3 mutations: wrong types, unknown/missing keys, out-of-range numbers."""
    doc = draw(valid_scene())
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["type", "unknown", "missing", "range"]))
        graph = doc.get("graph") if isinstance(doc.get("graph"), dict) else None
        if kind == "type":
            where = draw(st.sampled_from(["top", "graph", "params"]))
            if where == "graph" and graph is not None:
                graph[draw(st.sampled_from(GRAPH_KEYS))] = draw(ANY_VALUE)
            elif where == "params":
                doc.setdefault("params", {})[draw(st.sampled_from(["b", "f", "h", "m", "sigma", "K"]))] = draw(ANY_VALUE)
            else:
                doc[draw(st.sampled_from(TOP_KEYS))] = draw(ANY_VALUE)
        elif kind == "unknown":
            key = draw(st.text(alphabet="abcxyz_", min_size=1, max_size=6))
            (graph if graph is not None and draw(st.booleans()) else doc)[key] = draw(ANY_VALUE)
        elif kind == "missing":
            if graph is not None and draw(st.booleans()):
                graph.pop(draw(st.sampled_from(GRAPH_KEYS)), None)
            else:
                doc.pop(draw(st.sampled_from(TOP_KEYS)), None)
        else:
            key = draw(st.sampled_from(sorted(OUT_OF_RANGE)))
            value = draw(st.sampled_from(OUT_OF_RANGE[key]))
            if key.startswith("graph."):
                if graph is not None:
                    graph[key[6:]] = value
            else:
                doc[key] = value
    return doc


def garbage(text, data):
    raw = bytearray(text.encode())
    how = data.draw(st.sampled_from(["insert", "truncate", "overwrite", "binary"]), label="garbage")
    if how == "insert":
        at = data.draw(st.integers(0, len(raw)))
        raw[at:at] = data.draw(st.binary(min_size=1, max_size=8))
    elif how == "truncate":
        raw = raw[:data.draw(st.integers(0, len(raw)))]
    elif how == "overwrite":
        raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    else:
        raw = bytearray(data.draw(st.binary(max_size=64)))
    return bytes(raw)


def read_and_prepare(path):
    """read_scene, then every check `generate` makes before it integrates (graphs built, samplers,
    seeds): a scene the reader lets through must not fail later with anything but InputError."""
    scene = read_scene(path)
    if scene.graph.n_nodes <= 200 and scene.system != "quadrotor_load":
        # one trajectory of one step when that is cheap: exercises graph building, seeds, parameters
        small = replace(scene, trajectories=1, horizon=1)
        if scene.dt <= 1.0:
            try:
                generate(small, workers=1, max_tries=1)
            except NumericalError:
                pass  # finite but extreme parameters may make the physics fail: exit 3, not bad input
            except InputError as e:
                # generate names the scene (the file's stem), e.g. for a graph the physics cannot run on
                assert e.source == scene.name == os.path.splitext(os.path.basename(path))[0], e
                raise InputError(path, e.field, e.problem, e.expected) from None
    return scene


@fuzz(300)
@given(doc=mutated_scene())
def test_mutated_scene_toml(workdir, doc):
    d = tempfile.mkdtemp(dir=workdir)
    try:
        path = os.path.join(d, "scene.toml")
        with open(path, "w") as f:
            f.write(toml_doc(doc))
        TRIED["scene TOML"] += 1
        assert_input_error(read_and_prepare, path, allow_valid=True)
    finally:
        shutil.rmtree(d, ignore_errors=True)


@fuzz(150)
@given(doc=valid_scene(), data=st.data())
def test_garbage_scene_bytes(workdir, doc, data):
    d = tempfile.mkdtemp(dir=workdir)
    try:
        path = os.path.join(d, "scene.toml")
        with open(path, "wb") as f:
            f.write(garbage(toml_doc(doc), data))
        TRIED["scene TOML"] += 1
        assert_input_error(read_and_prepare, path, allow_valid=True)
    finally:
        shutil.rmtree(d, ignore_errors=True)


@fuzz(40)
@given(doc=valid_scene())
def test_valid_scenes_are_accepted(workdir, doc):
    """The strategy the mutations start from is valid (so the mutations are what is being rejected)."""
    d = tempfile.mkdtemp(dir=workdir)
    try:
        path = os.path.join(d, "scene.toml")
        with open(path, "w") as f:
            f.write(toml_doc(doc))
        read_scene(path)
    finally:
        shutil.rmtree(d, ignore_errors=True)


NAN, INF = float("nan"), float("inf")
GENE = {"system": "gene", "graph": {"builder": "gnp", "nodes": 8, "p": 0.5, "seed": 1}}
STRICT = [  # (base graph override, key, out-of-range value) -- each alone must be rejected, naming key
    ({}, "dt", 0.0), ({}, "dt", -0.05), ({}, "dt", NAN), ({}, "dt", INF), ({}, "dt", 1e308),
    ({}, "rtol", 0.0), ({}, "rtol", NAN), ({}, "rtol", INF), ({}, "atol", -INF),
    ({}, "trajectories", 0), ({}, "horizon", -5), ({}, "seed", -1), ({}, "system_seed", -1),
    ({}, "graph.nodes", 0), ({}, "graph.nodes", -3),
    ({}, "graph.p", -0.5), ({}, "graph.p", 1.5), ({}, "graph.p", NAN),
    ({"builder": "barabasi_albert", "m": 2, "p": None}, "graph.m", 0),
    ({"builder": "barabasi_albert", "m": 2, "p": None}, "graph.m", 8),
    ({"builder": "gnm", "m": 5, "p": None}, "graph.m", 29), ({"builder": "gnm", "m": 5, "p": None}, "graph.m", -1),
    ({"builder": "watts_strogatz", "k": 2}, "graph.k", 9), ({"builder": "watts_strogatz", "k": 2}, "graph.k", -2),
    ({"builder": "watts_strogatz", "k": 2}, "graph.p", INF),
    ({"seed": None}, "graph.seeds", []), ({"seed": None}, "graph.seeds", [1.5]), ({"seed": None}, "graph.seeds", ["a"]),
    *(({"builder": "edges", "p": None, "seed": None}, "graph.edges", e)
      for e in ([[0, 99]], [[-1, 0]], [[0]], [[0, 1, 2]], [["0", 1]], [[0.5, 1]], [[True, 0]])),
    ({}, "params.b", NAN), ({}, "params.b", INF), ({}, "params.nope", 1.0),
    ({}, "integrator", "Euler"), ({}, "initial", "gauss"), ({}, "initial", "hotspots"),
    ({}, "system", ""), ({}, "system", "lorenz3"),
]


@pytest.mark.parametrize("graph,key,value", STRICT, ids=[f"{k}={v!r}" for _, k, v in STRICT])
def test_out_of_range_scene_values_are_rejected(workdir, graph, key, value):
    doc = json.loads(json.dumps(GENE))
    doc["graph"].update(graph)
    doc["graph"] = {k: v for k, v in doc["graph"].items() if v is not None}
    where, name = key.split(".") if "." in key else (None, key)
    (doc if where is None else doc.setdefault(where, {}))[name] = value
    path = os.path.join(tempfile.mkdtemp(dir=workdir), "scene.toml")
    with open(path, "w") as f:
        f.write(toml_doc(doc))
    TRIED["scene TOML"] += 1
    with pytest.raises(InputError) as e:
        read_and_prepare(path)
    assert e.value.source == path and e.value.field == key, e.value


def test_scene_path_that_is_not_a_readable_file(workdir):
    d = os.path.join(workdir, "folder.toml")
    os.makedirs(d, exist_ok=True)
    assert_input_error(read_scene, d)
    assert_input_error(read_scene, os.path.join(workdir, "missing.toml"))


# ---- the command line -----------------------------------------------------------------------------------
def cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def assert_exit_2(r, *absent):
    assert r.exit_code == 2, (r.exit_code, r.output, r.exception)
    assert "Traceback" not in r.output and "Error" in r.stderr
    assert not isinstance(r.exception, Exception) or isinstance(r.exception, SystemExit)
    for p in absent:
        assert not os.path.exists(p), p


CLI_TRAJ = [nonfinite, break_csr, drop, kind_swap, bad_root_attr, graph_names, wrong_dtype]


@fuzz(25)
@given(data=st.data())
def test_cli_inspect_corrupted_file_exits_2(workdir, traj_bases, data):
    with Case(workdir, data.draw(st.sampled_from(traj_bases)), "bad.h5") as path:
        if data.draw(st.booleans(), label="bytes"):
            raw = open(path, "rb").read()
            open(path, "wb").write(raw[:data.draw(st.integers(0, len(raw) // 2))])
        else:
            with h5py.File(path, "r+") as f:
                data.draw(st.sampled_from(CLI_TRAJ), label="mutation")(f, data)
        TRIED["CLI"] += 1
        r = cli("inspect", path, *(["--json"] if data.draw(st.booleans()) else []))
        assert_exit_2(r)
        assert path in r.stderr


@fuzz(25)
@given(doc=mutated_scene())
def test_cli_generate_bad_scene_exits_2_and_writes_nothing(workdir, doc):
    d = tempfile.mkdtemp(dir=workdir)
    try:
        path, out = os.path.join(d, "bad.toml"), os.path.join(d, "out.h5")
        with open(path, "w") as f:
            f.write(toml_doc(doc))
        try:
            read_and_prepare(path)
            return  # the mutation left a valid scene
        except InputError:
            pass
        TRIED["CLI"] += 1
        r = cli("generate", path, "-o", out, "-B", 1, "-T", 1, "--workers", 1)
        assert_exit_2(r, out)
        assert path in r.stderr or r.stderr.startswith("Error: bad: graph: ")  # generate names the scene
        assert os.listdir(d) == ["bad.toml"]
    finally:
        shutil.rmtree(d, ignore_errors=True)


BAD_FLAGS = [["--seed", -1], ["--seed", "x"], ["--dt", 0], ["--dt", -1], ["--dt", "nan"], ["--dt", "inf"],
             ["-B", 0], ["-B", -3], ["-T", 0], ["-T", "1.5"], ["--workers", 0], ["--trajectories", "many"],
             ["--nope"]]


@pytest.mark.parametrize("flags", BAD_FLAGS, ids=[" ".join(map(str, f)) for f in BAD_FLAGS])
def test_cli_generate_bad_flags_exit_2(workdir, flags):
    d = tempfile.mkdtemp(dir=workdir)
    out = os.path.join(d, "out.h5")
    TRIED["CLI"] += 1
    r = cli("generate", "lorenz3", "-o", out, "-B", 1, "-T", 1, "--workers", 1, *flags)
    assert_exit_2(r, out)
    assert os.listdir(d) == []


def test_cli_inspect_bad_flags_exit_2(workdir, traj_bases):
    for args in (["inspect"], ["inspect", os.path.join(workdir, "missing.h5")], ["inspect", workdir],
                 ["inspect", traj_bases[0], "--yaml"]):
        TRIED["CLI"] += 1
        assert_exit_2(cli(*args))


# ---- the Python API ---------------------------------------------------------------------------------
# Every public function checks its arguments as the command line checks its flags: a value of the wrong
# type or out of range is an InputError naming the argument; a valid one is taken as it is (never a
# TypeError from deep inside, never "no" taken for True).  Each example calls one function with one
# argument replaced by a value drawn from all kinds of values, and the property is exact both ways.
def _integer(v, least):
    return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)) and v >= least


def _storable(text):
    """A string HDF5 stores: UTF-8, without NUL."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return "\x00" not in text


def _real(v):
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and math.isfinite(v)


#: kind of argument -> whether a value is valid for it ("never": no value drawn here is, e.g. a file path)
VALID = {
    "bool": lambda v: isinstance(v, (bool, np.bool_)),
    "int>=0": lambda v: _integer(v, 0),
    "int>=1": lambda v: _integer(v, 1),
    "positive": lambda v: _real(v) and v > 0,
    "non-negative": lambda v: _real(v) and v >= 0,
    "split": lambda v: _real(v) and (v == 0 or 1 / 6 <= v < 1),  # of 3 trajectories, one left for validation
    "seconds": lambda v: v is None or (_real(v) and v > 0),
    "mapping": lambda v: v is None or isinstance(v, dict),
    "name": lambda v: isinstance(v, str) and bool(v.strip()) and _storable(v),
    "backend": lambda v: isinstance(v, str) and v in ("auto", "numba", "numpy"),
    "never": lambda v: False,
}
API_VALUES = st.one_of(
    st.none(), st.booleans(), st.just(np.bool_(True)), st.integers(-3, 24), st.just(np.int64(3)),
    st.floats(-10, 10), st.sampled_from([math.nan, math.inf, -math.inf, 0.0, 1e-300, np.float32(0.5)]),
    st.text(max_size=4), st.sampled_from(["no", "yes", "auto", "numpy", " "]), st.lists(st.integers(0, 3), max_size=2),
    st.dictionaries(st.text(alphabet="abc", min_size=1, max_size=3), st.integers(0, 3), max_size=2),
    st.just(object()))
API_X = np.random.default_rng(5).standard_normal((3, 4, 2, 1))


def _api_calls(folder):
    """{name: (call(**one argument), {argument: kind})} of the public functions."""
    from mpnode import Simulator, runs

    arrays = {"x": API_X, "graph": [(0, 1)], "dt": 0.1, "system": "s"}
    data = os.path.join(folder, "api.h5")
    write_trajectories(data, **arrays)
    model = Model.create(1, 0, message_dim=2, hidden=4, dt=0.1)
    traj_args = {"directed": "bool", "dt": "positive", "system": "name", "attrs": "mapping", "params": "mapping",
                 "aux": "mapping"}
    return {
        "write_trajectories": (lambda **kw: write_trajectories(os.path.join(folder, "w.h5"), **{**arrays, **kw}),
                               traj_args),
        "Trajectories.from_arrays": (lambda **kw: Trajectories.from_arrays(**{**arrays, **kw}), traj_args),
        "read_trajectories": (lambda path: read_trajectories(path), {"path": "never"}),
        "Model.create": (lambda **kw: Model.create(**{"state_dim": 2, "dt": 0.1, "hidden": 4, "message_dim": 2, **kw}),
                         {"state_dim": "int>=1", "control_dim": "int>=0", "dt": "positive", "seed": "int>=0",
                          "hidden": "int>=1", "message_dim": "int>=0", "substeps": "int>=1", "self_messages": "bool",
                          "zero_messages": "bool", "linear_aggregate": "bool"}),
        "Simulator": (lambda **kw: Simulator(**{"model": model, "graph": Graph.complete(2), **kw}),
                      {"backend": "backend", "model": "never", "graph": "never"}),
        "Simulator.reset": (lambda x0: Simulator(model, Graph.complete(2)).reset(x0), {"x0": "never"}),
        "runs.train": (lambda **kw: runs.train([data], os.path.join(folder, "m.h5"),
                                               {"epochs": 0, "hidden": 4, "batch_size": 2, **kw}),
                       {"epochs": "int>=0", "batch_size": "int>=1", "lr": "positive", "seed": "int>=0",
                        "val_split": "split", "noise": "non-negative", "patience": "int>=1", "clip": "non-negative",
                        "hidden": "int>=1", "self_messages": "bool", "time_limit": "seconds"}),
    }


@pytest.fixture(scope="module")
def api_calls(workdir):
    return _api_calls(tempfile.mkdtemp(dir=workdir))


@fuzz(200)
@given(data=st.data())
def test_python_api_arguments_are_checked_like_flags(api_calls, data):
    name = data.draw(st.sampled_from(sorted(api_calls)), label="function")
    call, kinds = api_calls[name]
    argument = data.draw(st.sampled_from(sorted(kinds)), label="argument")
    value = data.draw(API_VALUES, label="value")
    valid = VALID[kinds[argument]](value)
    TRIED["Python API"] += not valid
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a valid but huge learning rate diverges
            call(**{argument: value})
    except InputError as e:
        assert not valid, f"{name}({argument}={value!r}) refused a valid value: {e}"
        fields = {"never": None, "split": ("val_split", "x")}.get(kinds[argument], (argument,))  # x: none held out
        assert fields is None or e.field in fields, f"{name}({argument}={value!r}): {e}"
        return
    assert valid, f"{name}({argument}={value!r}) was accepted"


def test_fuzz_counts():
    """Runs last: reports how many corrupted inputs were tried (see the module docstring)."""
    total = sum(TRIED.values())
    print(f"\nfuzz: {total} corrupted inputs tried: " + ", ".join(f"{k} {v}" for k, v in sorted(TRIED.items())))
    if TRIED:  # absent when this test is run alone
        assert all(v > 0 for v in TRIED.values())
