"""Kinematics (mpnode.engine.kinematics): the fixed derivatives are the physics' whatever the
weights, the kernels equal the NumPy path and their gradient equals central finite differences
(float64, both drivers, mpnode and node models), the model file holds them (format 6, older
versions refused), and bad terms are refused with the field named."""
import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from engine_helpers import mixed_graph, problem, rollout_ref, spec_

from cli.main import main
from mpnode import InputError, Model
from mpnode.engine import forward, forward_with_vjp, numpy_path
from mpnode.engine.kinematics import Kinematics

# a quaternion at 0..3 turned by the body rates at 4..6; x_7' = x_4 and x_8' = x_6
TERMS = "q0:4,7:4,8:6"
DX = 9


def hamilton(a, b):
    """The quaternion product a (x) b, [w, x, y, z], written out apart from the library's table."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def model_with_kinematics(seed=0, **options):
    rng = np.random.default_rng(seed)
    spec = spec_(state_dim=DX, control_dim=2, kinematics=Kinematics.parse(TERMS), **options)
    theta = problem(spec, mixed_graph(seed, big=20), 1, seed)[0]
    return Model(theta, spec, x_mean=rng.standard_normal(DX), x_std=1 + rng.random(DX))


def test_the_fixed_derivatives_are_the_physics_whatever_the_weights():
    model = model_with_kinematics()
    graph = mixed_graph(0, big=20)
    rng = np.random.default_rng(1)
    x = rng.standard_normal((graph.n_nodes, DX))
    z = np.concatenate([model.normalize_x(x), rng.standard_normal((graph.n_nodes, 3))], axis=1)
    u = rng.standard_normal((graph.n_nodes, 2))
    for theta in (model.theta, 3 * model.theta + 1):
        k = numpy_path.make_field(model.spec, theta, graph)(z, u)[:, :DX] * model.x_std  # data units
        for i in range(graph.n_nodes):
            want = 0.5 * hamilton(x[i, 0:4], np.r_[0, x[i, 4:7]])
            np.testing.assert_allclose(k[i, 0:4], want, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(k[:, 7], x[:, 4], rtol=1e-12)
        np.testing.assert_allclose(k[:, 8], x[:, 6], rtol=1e-12)
    free = numpy_path.make_field(model.spec, 3 * model.theta + 1, graph)(z, u)[:, 4:7]
    assert np.abs(free - numpy_path.make_field(model.spec, model.theta, graph)(z, u)[:, 4:7]).min() > 0


@pytest.mark.parametrize("kind", ["mpnode", "node"])
def test_kernels_equal_the_numpy_path(driver, kind):
    options = {"kind": "node", "n_nodes": 9, "message_dim": 0} if kind == "node" else {}
    graph = mixed_graph(2, big=200) if kind == "mpnode" else mixed_graph(2, big=18)
    spec = model_with_kinematics(2, **options).spec
    theta, x0, u = problem(spec, graph, 4, seed=3)
    got = forward(spec, theta, x0, graph, u, 4)
    np.testing.assert_allclose(got, rollout_ref(spec, theta, x0, graph, u, 4), rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize("kind", ["mpnode", "node"])
def test_gradient_matches_finite_differences(driver, kind):
    options = {"kind": "node", "n_nodes": 9, "message_dim": 0} if kind == "node" else {}
    graph = mixed_graph(4, big=200) if kind == "mpnode" else mixed_graph(4, big=18)
    model = model_with_kinematics(4, **options)
    spec = model.spec
    T = 3
    theta, x0, u = problem(spec, graph, T, seed=5)
    x, vjp = forward_with_vjp(spec, theta, x0, graph, u, T)
    rng = np.random.default_rng(6)
    gx = rng.standard_normal(x.shape)
    gtheta, gx0, gu = vjp(gx, controls=True)

    def value(th, x0_, u_):
        return np.sum(gx * forward(spec, th, x0_, graph, u_, T))

    eps = 1e-5
    for arg, grad in ((0, gtheta), (1, gx0), (2, gu)):
        for _ in range(3):
            base = [theta, x0, u]
            d = rng.standard_normal(base[arg].shape)
            d /= np.linalg.norm(d)
            plus, minus = list(base), list(base)
            plus[arg], minus[arg] = base[arg] + eps * d, base[arg] - eps * d
            fd = (value(*plus) - value(*minus)) / (2 * eps)
            assert abs(fd - np.sum(grad * d)) < 1e-6 * abs(fd), (arg, fd, np.sum(grad * d))
    # the network's outputs for the fixed derivatives are not used: their weights get no gradient
    g3 = model.params["W3"].copy()
    start = sum(v.size for k, v in model.params.items() if k in ("W1", "b1", "W2", "b2"))
    g3[:] = gtheta[start:start + g3.size].reshape(g3.shape)
    fixed = [i * DX + d for i in range(g3.shape[1] // DX or 1) for d in Kinematics.parse(TERMS).fixed]
    assert np.all(g3[:, fixed] == 0) and np.all(g3[:, 4:7] != 0)


def test_the_model_file_holds_them_and_older_versions_are_refused(tmp_path):
    model = model_with_kinematics()
    path = tmp_path / "m.h5"
    model.save(path)
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == 6 and f.attrs["kinematics"] == "7:4,8:6,q0:4"
    back = Model.load(path)
    assert back.spec == model.spec
    graph = mixed_graph(0, big=20)
    x0 = np.random.default_rng(0).standard_normal((1, graph.n_nodes, DX))
    u = np.zeros((1, 2, graph.n_nodes, 2))
    np.testing.assert_array_equal(back.rollout(x0[0], graph, u[0]), model.rollout(x0[0], graph, u[0]))
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 5
    with pytest.raises(InputError, match="format_version.*6 exactly for a model with kinematics"):
        Model.load(path)


@pytest.mark.parametrize("text,words", [("0:7,0:8", "fixes a derivative twice"), ("q0:20", "names state dimension"),
                                        ("0-7", "has the term"), ("x0:1", "has the term")])
def test_bad_terms_are_refused_with_the_field_named(text, words):
    with pytest.raises(InputError, match=words) as e:
        spec_(state_dim=DX, kinematics=Kinematics.parse(text))
    assert e.value.field == "kinematics"


def test_l2s_has_no_kinematics():
    with pytest.raises(InputError, match="l2s"):
        Model.create(DX, kind="l2s", kinematics=TERMS)


def test_train_resume_finetune_and_inspect_keep_them(tmp_path, tiny_file):
    data, out = tiny_file(tmp_path / "d.h5"), tmp_path / "m.h5"

    def run(*args):
        return CliRunner().invoke(main, [str(a) for a in args])

    quick = ("--hidden", 8, "--batch-size", 8, "--kinematics", "0:1")
    assert run("train", data, "-o", out, "--epochs", 2, *quick).exit_code == 0
    with np.load(str(out) + ".state") as checkpoint:  # an older reader refuses it instead of dropping them
        assert int(checkpoint["version"]) == 2
    res = run("train", data, "-o", out, "--epochs", 3, "--resume", *quick)
    assert res.exit_code == 0 and "resuming at epoch 2" in res.output, res.output
    res = run("train", data, "-o", out, "--epochs", 4, "--resume", "--kinematics", "1:0")
    assert res.exit_code == 2 and "contradicts the run being resumed" in res.output
    assert run("finetune", out, data, "-o", tmp_path / "f.h5", "--epochs", 1).exit_code == 0
    assert Model.load(tmp_path / "f.h5").spec.kinematics.text() == "0:1"
    res = run("inspect", tmp_path / "f.h5")
    assert res.exit_code == 0 and "kinematics 0:1 (fixed, not learned)" in res.output


def test_train_refuses_terms_beyond_the_state(tmp_path, tiny_file):
    out = tmp_path / "m.h5"
    result = CliRunner().invoke(main, ["train", tiny_file(tmp_path / "d.h5"), "-o", str(out), "--epochs", "1",
                                       "--kinematics", "0:5"])
    assert result.exit_code == 2 and "kinematics" in result.output and "state dimension 5" in result.output
    assert not out.exists()


def test_both_exports_carry_them(tmp_path):
    """The NumPy module always; the ONNX rollout where the onnx extra is installed."""
    import importlib.util

    from mpnode.export import write_numpy_module

    model = model_with_kinematics(7)
    graph = mixed_graph(7, big=20)
    rng = np.random.default_rng(8)
    x0, u = rng.standard_normal((2, graph.n_nodes, DX)), rng.standard_normal((2, 3, graph.n_nodes, 2))
    want = model.rollout(x0, graph, u)
    write_numpy_module(model, graph, tmp_path / "step.py")
    spec = importlib.util.spec_from_file_location("exported", tmp_path / "step.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    np.testing.assert_allclose(module.rollout(x0, 3, u), want, rtol=1e-11, atol=1e-11)

    pytest.importorskip("onnx", reason="the onnx extra is not installed (pip install '.[onnx]')")
    onnxruntime = pytest.importorskip("onnxruntime", reason="the onnx extra is not installed (pip install '.[onnx]')")
    from mpnode.export.onnx_model import onnx_rollout

    session = onnxruntime.InferenceSession(onnx_rollout(model, graph, 3).SerializeToString(),
                                           providers=["CPUExecutionProvider"])
    (got,) = session.run(None, {"x0": x0, "u": u})
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
