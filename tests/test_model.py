"""Model: create/save/load round trips, rollouts in data units, model-file validation, lazy imports."""
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from engine_helpers import make_graph, rollout_ref

from mpnode import InputError, NumericalError, engine
from mpnode.base.graph import Graph, block_diagonal
from mpnode.engine import dims
from mpnode.model.model import Model, to_time_major
from mpnode.training import loss_and_grad, losses

DX, DU, DM, H = 2, 2, 3, 8


def make_model(dtype=np.float64, seed=3):
    m = Model.create(DX, control_dim=DU, message_dim=DM, hidden=H, dt=0.05, substeps=2, self_messages=True,
                     seed=seed, dtype=dtype)
    m.x_mean = np.array([0.5, -1.25])
    m.x_std = np.array([2.0, 0.3])
    m.u_mean = np.array([-0.1, 3.0])
    m.u_std = np.array([0.7, 1.5])
    # Glorot init has zero biases: give them values so a bias lost in the round trip shows
    rng = np.random.default_rng(seed)
    for name in ("b1", "b2", "b3"):
        m.params[name][:] = rng.uniform(-0.5, 0.5, m.params[name].shape)
    return m


def data(B=3, N=9, T=4, seed=0):
    rng = np.random.default_rng(seed)
    x0 = rng.standard_normal((B, N, DX)) * [2.0, 0.3] + [0.5, -1.25]
    u = rng.standard_normal((B, T, N, DU)) * [0.7, 1.5] + [-0.1, 3.0]
    return x0, u


@pytest.fixture
def graph():
    return make_graph(np.random.default_rng(1), 9)


# ---------------------------------------------------------------------------
# create -> save -> load
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_save_load_round_trip_is_bit_for_bit(tmp_path, graph, dtype):
    m = make_model(dtype)
    m.attrs["note"] = "hello"
    path = tmp_path / "model.h5"
    m.save(path, epochs=7, data_file="traj.h5", best_loss=0.125)
    back = Model.load(path)
    assert back.dtype == dtype and back.theta.dtype == dtype
    np.testing.assert_array_equal(back.theta, m.theta)
    assert back.spec == m.spec
    for name in ("x_mean", "x_std", "u_mean", "u_std"):
        np.testing.assert_array_equal(getattr(back, name), getattr(m, name))
    assert back.attrs == {"seed": 3, "note": "hello", "epochs": 7, "data_file": "traj.h5", "best_loss": 0.125}
    x0, u = data()
    np.testing.assert_array_equal(back.rollout(x0, graph, u), m.rollout(x0, graph, u))


def test_saved_file_follows_the_model_format(tmp_path):
    """Read back with plain h5py, the way a tool without mpnode would."""
    m = make_model()
    path = tmp_path / "model.h5"
    m.save(path)
    with h5py.File(path, "r") as f:
        a = dict(f.attrs)
        assert a["format"] == "mpnode.model" and a["format_version"] == 2
        assert a["kind"] == "mpnode" and a["aggregation"] == "mean" and "mean_degree" not in a
        assert (a["state_dim"], a["control_dim"], a["message_dim"], a["hidden"]) == (DX, DU, DM, H)
        assert a["activation"] == "tanh" and a["integrator"] == "rk4"
        assert a["dt"] == 0.05 and a["substeps"] == 2
        assert a["zero_messages"] == 0 and a["self_messages"] == 1
        shapes = {"W1": (DX + DU + DM, H), "b1": (H,), "W2": (H, H), "b2": (H,), "W3": (H, DX + DM), "b3": (DX + DM,)}
        for name, shape in shapes.items():
            assert f[f"params/{name}"].shape == shape
            np.testing.assert_array_equal(f[f"params/{name}"][()], m.params[name])
        np.testing.assert_array_equal(f["norm/x_std"][()], m.x_std)
        np.testing.assert_array_equal(f["norm/u_mean"][()], m.u_mean)


def test_model_without_controls_has_no_u_norm(tmp_path, graph):
    m = Model.create(DX, control_dim=0, message_dim=DM, hidden=H, dtype=np.float64)
    path = tmp_path / "m.h5"
    m.save(path)
    with h5py.File(path, "r") as f:
        assert "u_mean" not in f["norm"] and "u_std" not in f["norm"]
    back = Model.load(path)
    x0, _ = data()
    np.testing.assert_array_equal(back.rollout(x0, graph, steps=3), m.rollout(x0, graph, steps=3))


# ---------------------------------------------------------------------------
# Rollout in data units
# ---------------------------------------------------------------------------
def test_rollout_in_data_units_is_normalise_integrate_denormalise(graph):
    m = make_model()
    x0, u = data()
    B, T, N = u.shape[0], u.shape[1], x0.shape[1]
    got = m.rollout(x0, graph, u)
    assert got.shape == (B, T + 1, N, DX) and got.dtype == np.float64

    flat = block_diagonal([graph] * B)
    xn0 = ((x0 - m.x_mean) / m.x_std).reshape(B * N, DX)
    un = np.ascontiguousarray(((u - m.u_mean) / m.u_std).transpose(1, 0, 2, 3)).reshape(T, B * N, DU)
    xs = engine.forward(m.spec, m.theta, xn0, flat, un, T)
    want = xs.reshape(T + 1, B, N, DX).transpose(1, 0, 2, 3) * m.x_std + m.x_mean
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)
    # and against the independent NumPy reference, graph by graph
    for b in range(B):
        ref = rollout_ref(m.spec, m.theta, xn0[b * N:(b + 1) * N], graph, un[:, b * N:(b + 1) * N], T)
        np.testing.assert_allclose(got[b], ref * m.x_std + m.x_mean, rtol=1e-12, atol=1e-12)
    # the initial state comes back exactly as given (up to the normalise/denormalise rounding)
    np.testing.assert_allclose(got[:, 0], x0, rtol=1e-14, atol=1e-14)
    # a single trajectory (2-D x0) is the same as a batch of one
    np.testing.assert_array_equal(m.rollout(x0[1], graph, u[1]), m.rollout(x0[1:2], graph, u[1:2])[0])


def test_rollout_with_a_list_of_graphs_equals_one_by_one():
    rng = np.random.default_rng(4)
    graphs = [make_graph(rng, 9) for _ in range(3)]
    m = make_model()
    x0, u = data()
    got = m.rollout(x0, graphs, u)
    for b, g in enumerate(graphs):
        np.testing.assert_allclose(got[b], m.rollout(x0[b], g, u[b]), rtol=1e-12, atol=1e-12)


def test_loss_and_grad_in_data_units_matches_the_engine(graph):
    m = make_model()
    x0, u = data()
    x = m.rollout(x0, graph, u)
    x[:, 1:] += np.random.default_rng(5).uniform(-0.2, 0.2, x[:, 1:].shape)
    value, g = loss_and_grad(m, x, graph, u)
    B = x.shape[0]
    v2, g2, _ = losses.value_and_grad(m.spec, m.theta, to_time_major((x - m.x_mean) / m.x_std),
                                        block_diagonal([graph] * B), to_time_major((u - m.u_mean) / m.u_std))
    assert abs(value - v2) <= 1e-12 * v2
    np.testing.assert_allclose(g, g2, rtol=1e-11, atol=1e-13)


def test_wrong_number_of_graphs_is_an_input_error(graph):
    m = make_model()
    x0, u = data(B=3)
    with pytest.raises(InputError) as e:
        m.rollout(x0, [graph, graph], u)
    assert e.value.field == "graph"
    with pytest.raises(InputError):
        m.rollout(x0, [graph] * 4, u)
    x = m.rollout(x0, graph, u)
    with pytest.raises(InputError):
        loss_and_grad(m, x, [graph, graph], u)


# ---------------------------------------------------------------------------
# Invalid model files
# ---------------------------------------------------------------------------
def write_raw(path, dtype="f8"):
    """A valid model file written with plain h5py from the format spec alone."""
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        f.attrs.update(format="mpnode.model", format_version=1, state_dim=DX, control_dim=DU, message_dim=DM,
                       hidden=H, activation="tanh", dt=0.1, substeps=3, integrator="rk4", zero_messages=0,
                       self_messages=1, seed=42)
        shapes = {"W1": (DX + DU + DM, H), "b1": (H,), "W2": (H, H), "b2": (H,), "W3": (H, DX + DM), "b3": (DX + DM,)}
        for name, shape in shapes.items():
            f[f"params/{name}"] = rng.standard_normal(shape).astype(dtype)
        f["norm/x_mean"], f["norm/x_std"] = [0.1, 0.2], [1.5, 2.5]
        f["norm/u_mean"], f["norm/u_std"] = [0.0, 1.0], [0.5, 4.0]
    return path


def test_raw_file_loads(tmp_path):
    path = write_raw(tmp_path / "raw.h5", "f4")
    m = Model.load(path)
    assert m.dtype == np.float32 and m.spec.substeps == 3 and m.spec.self_messages and not m.spec.zero_messages
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(m.params["W2"], f["params/W2"][()])
    np.testing.assert_array_equal(m.x_std, [1.5, 2.5])
    assert m.attrs == {"seed": 42}


REQUIRED_ATTRS = ["format", "format_version", "state_dim", "control_dim", "message_dim", "hidden", "activation",
                  "dt", "substeps", "integrator", "zero_messages", "self_messages"]
WRONG_VALUES = [
    ("format", "mpnode.trajectories"), ("format_version", 3), ("format_version", "1"),
    ("kind", "l2s"),  # a version-1 file is an MP-NODE
    ("aggregation", "sum"),  # ... with the mean
    ("state_dim", 0), ("state_dim", 2.0), ("control_dim", -1), ("message_dim", -1), ("hidden", 0),
    ("activation", "relu"), ("dt", 0.0), ("dt", -0.1), ("dt", np.nan), ("dt", "fast"),
    ("substeps", 0), ("substeps", 1.5), ("integrator", "rk38"), ("zero_messages", 2), ("self_messages", -1),
]


def load_error(path):
    with pytest.raises(InputError) as e:
        Model.load(path)
    assert str(path) in str(e.value)
    return e.value


@pytest.mark.parametrize("name", REQUIRED_ATTRS)
def test_missing_attribute_is_named(tmp_path, name):
    path = write_raw(tmp_path / "m.h5")
    with h5py.File(path, "a") as f:
        del f.attrs[name]
    err = load_error(path)
    assert err.field == name and name in str(err)


@pytest.mark.parametrize("name,value", WRONG_VALUES, ids=[f"{n}={v!r}" for n, v in WRONG_VALUES])
def test_wrong_attribute_is_named(tmp_path, name, value):
    path = write_raw(tmp_path / "m.h5")
    with h5py.File(path, "a") as f:
        f.attrs[name] = value
    err = load_error(path)
    assert err.field == name and name in str(err)


def _reshape(name, shape):
    def mutate(f):
        del f[name]
        f[name] = np.zeros(shape)
    return mutate


def _set(name, index, value):
    def mutate(f):
        f[name][index] = value
    return mutate


def _delete(name):
    def mutate(f):
        del f[name]
    return mutate


DATASET_CASES = [
    ("params/W2", _reshape("params/W2", (H, H + 1))),
    ("params/W1", _reshape("params/W1", (DX + DM, H))),  # control rows missing
    ("params/b3", _reshape("params/b3", (DX,))),  # message outputs missing
    ("params/W3", _delete("params/W3")),
    ("params/b1", _set("params/b1", 3, np.nan)),
    ("params/W2", _set("params/W2", (1, 2), np.inf)),
    ("norm/x_mean", _set("norm/x_mean", 0, np.nan)),
    ("norm/x_std", _set("norm/x_std", 1, 0.0)),
    ("norm/x_std", _set("norm/x_std", 0, -1.0)),
    ("norm/u_std", _set("norm/u_std", 1, 0.0)),
    ("norm/u_std", _delete("norm/u_std")),
    ("norm/x_mean", _reshape("norm/x_mean", (DX + 1,))),
]


@pytest.mark.parametrize("field,mutate", DATASET_CASES,
                         ids=[f"{f}-{i}" for i, (f, _) in enumerate(DATASET_CASES)])
def test_bad_dataset_is_named(tmp_path, field, mutate):
    path = write_raw(tmp_path / "m.h5")
    with h5py.File(path, "a") as f:
        mutate(f)
    err = load_error(path)
    assert err.field == field and field in str(err)


# ---------------------------------------------------------------------------
# Version 2: kinds and aggregations
# ---------------------------------------------------------------------------
def write_raw_v2(path, kind, aggregation=None, **extra):
    """A version-2 file of ``kind`` written with plain h5py from the format alone (version 3 when
    ``extra`` asks for the linear aggregate path, as the format says)."""
    rng = np.random.default_rng(1)
    dm = DM if kind == "mpnode" else 0
    version = 3 if extra.get("linear_aggregate") == 1 else 2
    attrs = dict(format="mpnode.model", format_version=version, kind=kind, state_dim=DX, control_dim=0, message_dim=dm,
                 hidden=H, activation="tanh", dt=0.1, substeps=1, integrator="rk4", zero_messages=0, self_messages=0)
    if aggregation:
        attrs["aggregation"] = aggregation
    if kind == "l2s":
        shapes = {"W_lift": (DX, H), "b_lift": (H,), "W_msg": (H, H), "b_msg": (H,), "psi": (H,), "W_upd": (H, H),
                  "b_upd": (H,), "W_out": (H, DX), "b_out": (DX,)}
    else:
        n = extra.get("n_nodes", 1)
        shapes = {"W1": (n * DX + dm, H), "b1": (H,), "W2": (H, H), "b2": (H,), "W3": (H, n * DX + dm),
                  "b3": (n * DX + dm,)}
        if extra.get("linear_aggregate"):
            shapes["W_agg"] = (dm, DX if extra.get("linear_target") == "state" else DX + dm)
    attrs.update(extra)
    with h5py.File(path, "w") as f:
        f.attrs.update(attrs)
        for name, shape in shapes.items():
            f[f"params/{name}"] = rng.standard_normal(shape)
        f["norm/x_mean"], f["norm/x_std"] = [0.1, 0.2], [1.5, 2.5]
    return path


@pytest.mark.parametrize("kind,aggregation,extra,want", [
    ("mpnode", None, {}, ("mean", None)),
    ("mpnode", "scaled", {"mean_degree": 7.5}, ("scaled", 7.5)),
    ("l2s", None, {}, ("sum", None)),  # the sum is l2s's default
    ("l2s", "mean", {}, ("mean", None)),
    ("node", None, {"n_nodes": 3}, ("mean", None)),
])
def test_version_2_files_of_every_kind_load_and_round_trip(tmp_path, kind, aggregation, extra, want):
    m = Model.load(write_raw_v2(tmp_path / "m.h5", kind, aggregation, **extra))
    assert m.kind == kind and (m.spec.aggregation.mlp, m.spec.aggregation.mean_degree) == want
    m.save(tmp_path / "again.h5")
    back = Model.load(tmp_path / "again.h5")
    assert back.spec == m.spec and np.array_equal(back.theta, m.theta)


@pytest.mark.parametrize("kind,aggregation,extra,field", [
    ("gnn", None, {}, "kind"),
    ("mpnode", "max", {}, "aggregation"),
    ("mpnode", "scaled", {}, "mean_degree"),
    ("mpnode", "scaled", {"mean_degree": 0.0}, "mean_degree"),
    ("node", None, {}, "n_nodes"),
    ("l2s", None, {"message_dim": 3}, "message_dim"),
    ("l2s", None, {"zero_messages": 1}, "zero_messages"),
    ("mpnode", None, {"linear_aggregate": 2}, "linear_aggregate"),
    ("mpnode", None, {"linear_aggregate": 1, "zero_messages": 1}, "linear_aggregate"),
    ("mpnode", None, {"linear_aggregate": 1, "message_dim": 0}, "linear_aggregate"),
    ("l2s", None, {"linear_aggregate": 1}, "linear_aggregate"),
    ("mpnode", None, {"linear_aggregate": 1, "linear_aggregation": "max"}, "linear_aggregation"),
    ("mpnode", None, {"linear_aggregation": "sum"}, "linear_aggregation"),
    ("mpnode", None, {"linear_aggregate": 1, "linear_aggregation": "scaled"}, "mean_degree"),
    ("mpnode", None, {"linear_aggregate": 1, "linear_target": "messages"}, "linear_target"),
    ("mpnode", None, {"linear_target": "state"}, "linear_target"),
    ("mpnode", None, {"format_version": 3}, "format_version"),  # 3 is only for the linear path
    ("mpnode", None, {"linear_aggregate": 1, "format_version": 2}, "format_version"),  # a v2 reader would drop it
])
def test_version_2_files_that_break_a_rule_are_refused(tmp_path, kind, aggregation, extra, field):
    err = load_error(write_raw_v2(tmp_path / "m.h5", kind, aggregation, **extra))
    assert err.field == field, err


def test_linear_aggregate_round_trips_and_files_without_it_load_as_off(tmp_path):
    """The switch and W_agg come back exactly; a file without the attribute (every file
    before it) is a model without the path, and is written back without it."""
    on = Model.load(write_raw_v2(tmp_path / "on.h5", "mpnode", "scaled", mean_degree=2.0, linear_aggregate=1))
    assert on.spec.linear_path and on.params["W_agg"].shape == (DM, DX + DM) and np.any(on.params["W_agg"])
    off = Model.load(write_raw_v2(tmp_path / "off.h5", "mpnode"))
    assert not off.spec.linear_path and "W_agg" not in off.params
    for m, name in ((on, "on"), (off, "off")):
        m.save(tmp_path / f"{name}2.h5")
        back = Model.load(tmp_path / f"{name}2.h5")
        assert back.spec == m.spec and np.array_equal(back.theta, m.theta)
        with h5py.File(tmp_path / f"{name}2.h5", "r") as f:
            assert ("linear_aggregate" in f.attrs) == ("W_agg" in f["params"]) == (name == "on")
            assert f.attrs["format_version"] == (3 if name == "on" else 2)


def test_the_linear_paths_own_aggregation_round_trips(tmp_path):
    """mean for the MLP, scaled for the linear path: the file records both and the mean degree."""
    path = write_raw_v2(tmp_path / "m.h5", "mpnode", "mean", mean_degree=2.0, linear_aggregate=1,
                        linear_aggregation="scaled")
    m = Model.load(path)
    agg = m.spec.aggregation
    assert (agg.mlp, agg.linear, agg.mean_degree) == ("mean", "scaled", 2.0)
    m.save(tmp_path / "back.h5")
    back = Model.load(tmp_path / "back.h5")
    assert back.spec == m.spec and np.array_equal(back.theta, m.theta)


def test_a_linear_path_to_the_state_alone_round_trips(tmp_path):
    """linear_target state: W_agg is (dm, dx), the file says so, and it comes back exactly."""
    path = write_raw_v2(tmp_path / "m.h5", "mpnode", "mean", mean_degree=2.0, linear_aggregate=1,
                        linear_aggregation="scaled", linear_target="state")
    m = Model.load(path)
    assert m.spec.aggregation.target == "state" and m.params["W_agg"].shape == (DM, DX)
    m.save(tmp_path / "back.h5")
    back = Model.load(tmp_path / "back.h5")
    assert back.spec == m.spec and np.array_equal(back.theta, m.theta)
    with h5py.File(tmp_path / "back.h5", "r") as f:
        assert f.attrs["linear_target"] == "state"


def test_create_takes_the_linear_aggregation_as_the_switch_and_refuses_unknown_ones():
    m = Model.create(DX, message_dim=DM, linear_aggregation="scaled", mean_degree=3.0)
    assert m.spec.linear_path and m.spec.dims[dims.LINEAR] == dims.LINEAR_ON | dims.LINEAR_OWN and "W_agg" in m.params
    with pytest.raises(InputError, match="linear_aggregation"):
        Model.create(DX, message_dim=DM, linear_aggregation="max")


def test_a_file_with_the_switch_but_no_w_agg_is_refused(tmp_path):
    path = write_raw_v2(tmp_path / "m.h5", "mpnode", linear_aggregate=1)
    with h5py.File(path, "a") as f:
        del f["params/W_agg"]
    assert load_error(path).field == "params/W_agg"


def test_linear_aggregate_starts_as_the_model_without_it(graph):
    """W_agg starts at 0 and the MLP's draws do not change: the same rollout, bit for bit."""
    kw = dict(control_dim=DU, message_dim=DM, hidden=H, seed=4, dtype=np.float64, aggregation="sum")
    on, off = Model.create(DX, linear_aggregate=True, **kw), Model.create(DX, **kw)
    assert not np.any(on.params["W_agg"]) and np.array_equal(on.theta[:off.theta.size], off.theta)
    x0, u = data()
    np.testing.assert_array_equal(on.rollout(x0, graph, u), off.rollout(x0, graph, u))


@pytest.mark.parametrize("kw", [dict(kind="l2s"), dict(message_dim=0), dict(zero_messages=True)])
def test_create_refuses_a_linear_aggregate_without_messages(kw):
    with pytest.raises(InputError, match="linear_aggregate"):
        Model.create(DX, linear_aggregate=True, **kw)


def test_a_node_model_refuses_a_graph_of_another_size(tmp_path, graph):
    m = Model.load(write_raw_v2(tmp_path / "m.h5", "node", n_nodes=3))
    x0 = np.zeros((2, 3, DX))
    assert m.rollout(x0, Graph.complete(3), steps=2).shape == (2, 3, 3, DX)
    with pytest.raises(InputError, match="exactly 3 nodes"):
        m.rollout(np.zeros((2, 4, DX)), Graph.complete(4), steps=2)


def test_missing_and_non_hdf5_files_are_input_errors(tmp_path):
    load_error(tmp_path / "nope.h5")
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    load_error(bad)


# ---------------------------------------------------------------------------
# Saving refuses broken models
# ---------------------------------------------------------------------------
def test_save_refuses_nan_weight_and_leaves_no_file(tmp_path):
    m = make_model()
    m.theta[5] = np.nan
    path = tmp_path / "model.h5"
    with pytest.raises(NumericalError):
        m.save(path)
    assert os.listdir(tmp_path) == []


def test_save_refusal_keeps_the_previous_file(tmp_path):
    path = tmp_path / "model.h5"
    good = make_model()
    good.save(path)
    before = path.read_bytes()
    bad = make_model()
    bad.theta[-1] = np.inf
    with pytest.raises(NumericalError):
        bad.save(path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["model.h5"]


# ---------------------------------------------------------------------------
# import mpnode stays light
# ---------------------------------------------------------------------------
def test_import_mpnode_does_not_load_heavy_modules():
    code = ("import sys, mpnode\n"
            "heavy = [m for m in ('h5py', 'scipy', 'numba', 'click') if m in sys.modules]\n"
            "print(','.join(heavy))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"import mpnode loaded: {out.stdout.strip()}"


def test_undecodable_string_attribute_names_its_field(tmp_path):
    """Bytes that are not UTF-8 in a model attribute are reported against that attribute."""
    import h5py

    path = tmp_path / "m.h5"
    Model.create(3).save(path)
    with h5py.File(path, "r+") as f:
        f.attrs["format"] = np.bytes_(b"\xff\xfe")
    with pytest.raises(InputError, match=r"m\.h5: format: "):
        Model.load(path)
