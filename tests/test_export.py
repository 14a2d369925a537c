"""`mpnode export`: the NumPy module is the library's NumPy path (it holds the source of
mpnode.engine.numpy_path's model, which uses numpy alone), equals Model.rollout to 1e-6 and runs
with numpy alone; the ONNX rollout, built op by op, equals that NumPy path (onnxruntime, every
kind, both dtypes, with and without controls: float64 to 1e-12, float32 to 1e-5; skipped without
the onnx extra); the command's help says what is and is not exported, and its errors exit 2 with
nothing written (onnx missing included)."""
import importlib.util
import inspect
import os
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner
from engine_helpers import make_graph, random_model
from export_helpers import load_module, onnx_runtime

from cli.main import main
from mpnode import write_trajectories
from mpnode.data import Trajectories
from mpnode.engine.kinematics import Kinematics
from mpnode.engine.numpy_path import NUMPY_ONLY
from mpnode.export import numpy_module_source, write_numpy_module
from mpnode.export.numpy_module import FUNCTIONS

N, DX, DU, B, T = 7, 2, 2, 3, 4

KINDS = {
    "mpnode": dict(message_dim=3),
    "mpnode-sum-self": dict(message_dim=2, aggregation="sum", self_messages=True),
    "mpnode-linear-scaled-state": dict(message_dim=3, linear_aggregate=True, linear_aggregation="scaled",
                                       mean_degree=2.0, linear_target="state"),
    "mpnode-zero-messages": dict(message_dim=2, zero_messages=True),
    "l2s": dict(kind="l2s", aggregation="sum"),
    "l2s-mean-self": dict(kind="l2s", aggregation="mean", self_messages=True),
    "node": dict(kind="node", n_nodes=N),
    "mpnode-encoder": dict(message_dim=3, encoder_window=3),  # format 4: the encoder is not exported
    "mpnode-kinematics": dict(message_dim=3, kinematics=Kinematics.parse("0:1")),
    "node-kinematics": dict(kind="node", n_nodes=N, kinematics=Kinematics.parse("1:0")),
    "mpnode-quaternion": dict(message_dim=3, kinematics=Kinematics.parse("q0:4,4:6")),
}

#: the kinds whose state is not DX wide: a quaternion and its body rates need 7 dimensions
STATE_DIMS = {"mpnode-quaternion": 7}


def dx_of(name):
    return STATE_DIMS.get(name, DX)


def make_model(name, du, dtype, seed=0):
    return random_model(KINDS[name], dx_of(name), du, dtype, seed)


def graph():
    return make_graph(np.random.default_rng(1), N)  # an isolated node and directed edges


def inputs(du, dtype, dx=DX, seed=2):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((B, N, dx)).astype(dtype), (rng.standard_normal((B, T, N, du)).astype(dtype)
                                                           if du else None)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("du", [0, DU], ids=["no-controls", "controls"])
@pytest.mark.parametrize("name", KINDS)
def test_onnx_rollout_equals_the_numpy_path(name, du, dtype):
    """The ONNX graph is the field and RK4 written a second time: held to the NumPy path's."""
    ort = onnx_runtime()
    from mpnode.export.onnx_model import onnx_rollout

    model, g = make_model(name, du, dtype), graph()
    x0, u = inputs(du, dtype, dx_of(name))
    session = ort.InferenceSession(onnx_rollout(model, g, T).SerializeToString(), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    assert names == (["x0", "u"] if du else ["x0"])
    (got,) = session.run(None, dict(zip(names, (x0, u))))
    want = model.rollout(x0, g, u, T, backend="numpy")
    assert got.dtype == dtype and got.shape == (B, T + 1, N, dx_of(name))
    tol = 1e-12 if dtype == np.float64 else 1e-5
    np.testing.assert_allclose(got, want, rtol=tol, atol=tol * np.abs(want).max())
    assert np.abs(want[:, -1] - want[:, 0]).max() > 1e-2 * np.abs(want).max()  # it moves
    (one,) = session.run(None, dict(zip(names, (x0[:1], None if u is None else u[:1]))))  # B is free
    np.testing.assert_allclose(one, got[:1], rtol=1e-6)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("name", KINDS)
def test_numpy_module_equals_model_rollout(tmp_path, name, dtype):
    model, g = make_model(name, DU, dtype), graph()
    x0, u = inputs(DU, dtype, dx_of(name))
    write_numpy_module(model, g, tmp_path / "step.py")
    module = load_module(tmp_path / "step.py")
    got, want = module.rollout(x0, T, u), model.rollout(x0, g, u)
    assert got.dtype == want.dtype == dtype and got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
    same = model.rollout(x0, g, u, backend="numpy")  # the same code, on (B, N) instead of (B * N) nodes
    tol = 1e-12 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(got, same, rtol=tol, atol=tol * np.abs(same).max())
    np.testing.assert_allclose(module.rollout(x0[0], T, u[0]), got[0], rtol=1e-6)  # one trajectory, as Model.rollout
    assert "'E1'" not in (tmp_path / "step.py").read_text()  # an export steps from a given state: no encoder
    with pytest.raises(ValueError, match="on the exported graph"):
        module.rollout(np.zeros((B, N + 1, dx_of(name))), T, u)


def test_numpy_module_holds_the_numpy_paths_model():
    """Its field and RK4 are the library's NumPy path's source, which may use numpy alone."""
    text = numpy_module_source(make_model("mpnode-quaternion", DU, np.float64), graph())
    for f in NUMPY_ONLY:
        assert inspect.getsource(f) in text, f.__name__
    held = {f.__name__ for f in FUNCTIONS}
    for f in FUNCTIONS:
        free = inspect.getclosurevars(f)
        assert not free.nonlocals and set(free.globals) <= held | {"np", "base64"}, (f.__name__, free.globals.keys())


def test_numpy_module_needs_numpy_alone(tmp_path):
    """In a fresh interpreter where mpnode, scipy, numba and h5py cannot be imported."""
    model, g = make_model("mpnode", DU, np.float64), graph()
    write_numpy_module(model, g, tmp_path / "step.py")
    x0, u = inputs(DU, np.float64)
    np.save(tmp_path / "x0.npy", x0)
    np.save(tmp_path / "u.npy", u)
    code = ("import sys\nfor name in ('mpnode', 'scipy', 'numba', 'h5py'): sys.modules[name] = None\n"
            "import numpy as np, step\n"
            "np.save('x.npy', step.rollout(np.load('x0.npy'), 4, np.load('u.npy')))\n")
    subprocess.run([sys.executable, "-c", code], cwd=tmp_path, check=True, env={**os.environ, "PYTHONPATH": ""})
    np.testing.assert_allclose(np.load(tmp_path / "x.npy"), model.rollout(x0, g, u), rtol=1e-6, atol=1e-12)


@pytest.fixture
def files(tmp_path):
    """A float64 model with controls and a trajectory file of its system on graph()."""
    model = make_model("mpnode", DU, np.float64)
    model.save(tmp_path / "model.h5")
    x = np.random.default_rng(0).standard_normal((2, 3, N, DX))
    write_trajectories(tmp_path / "data.h5", Trajectories(x=x, u=np.zeros((2, 2, N, DU)), graphs=[graph()], dt=0.1,
                                                                system="test"))
    return model, str(tmp_path / "model.h5"), str(tmp_path / "data.h5")


def test_export_command_writes_an_onnx_rollout(tmp_path, files):
    ort = onnx_runtime()
    model, model_path, data = files
    out = str(tmp_path / "model.onnx")
    r = CliRunner().invoke(main, ["export", model_path, "-o", out, "--graph", data, "--steps", str(T)])
    assert r.exit_code == 0, r.output
    assert "inputs x0 (B, 7, 2), u (B, 4, 7, 2); output x (B, 5, 7, 2)" in r.output
    x0, u = inputs(DU, np.float64)
    (got,) = ort.InferenceSession(out, providers=["CPUExecutionProvider"]).run(None, {"x0": x0, "u": u})
    np.testing.assert_allclose(got, model.rollout(x0, graph(), u), rtol=1e-5, atol=1e-8)


def test_export_command_writes_a_numpy_module(tmp_path, files):
    model, model_path, data = files
    r = CliRunner().invoke(main, ["export", model_path, "-o", str(tmp_path / "step.py"), "--graph", data])
    assert r.exit_code == 0, r.output
    x0, u = inputs(DU, np.float64)
    np.testing.assert_allclose(load_module(tmp_path / "step.py").rollout(x0, T, u), model.rollout(x0, graph(), u),
                               rtol=1e-6, atol=1e-8)


def test_export_help_says_what_is_and_is_not_exported():
    r = CliRunner().invoke(main, ["export", "--help"])
    assert r.exit_code == 0
    for words in ("What is exported", "What is not", "pip install 'mpnode[onnx]'", "x0 (B, N, dx)",
                  "u (B, T, N, du)", "x (B, T+1, N, dx)", "rollout(x0, steps, u=None)", "numpy alone",
                  "initial-state encoder"):
        assert words in " ".join(r.output.split()), words


@pytest.mark.parametrize("args, words", [
    (["-o", "{tmp}/m.txt", "--graph", "{data}"], "--output: {tmp}/m.txt: has extension .txt"),
    (["-o", "{tmp}/m.py", "--graph", "{data}", "--steps", "3"], "--steps: 3: is given for a NumPy module"),
    (["-o", "{tmp}/m.py"], "--graph: nor --nodes is given"),
    (["-o", "{tmp}/m.py", "--graph", "{data}", "--nodes", "3"], "--graph: and --nodes are both given"),
    (["-o", "{data}", "--graph", "{data}"], "has extension .h5"),
    (["-o", "{tmp}/m.py", "--graph", "{model}"], "{model}: format: is 'mpnode.model'"),
])
def test_export_errors_exit_2_and_write_nothing(tmp_path, files, args, words):
    _, model_path, data = files
    fill = dict(tmp=tmp_path, data=data, model=model_path)
    r = CliRunner().invoke(main, ["export", model_path] + [a.format(**fill) for a in args])
    assert r.exit_code == 2, r.output
    assert words.format(**fill) in r.output and "Traceback" not in r.output
    assert sorted(os.listdir(tmp_path)) == ["data.h5", "model.h5"]


def test_node_model_on_another_size_is_refused(tmp_path):
    model = make_model("node", DU, np.float64)
    model.save(tmp_path / "node.h5")
    r = CliRunner().invoke(main, ["export", str(tmp_path / "node.h5"), "-o", str(tmp_path / "n.py"), "--nodes", "4"])
    assert r.exit_code == 2 and "trained on 7" in r.output
    assert not (tmp_path / "n.py").exists()


def test_without_onnx_the_command_stops_first_with_the_install_line(tmp_path, files):
    _, model_path, data = files
    code = "import sys\nsys.modules['onnx'] = None\nfrom cli.main import main\nmain()\n"
    r = subprocess.run([sys.executable, "-c", code, "export", model_path, "-o", str(tmp_path / "m.onnx"),
                        "--graph", data], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "pip install 'mpnode[onnx]'" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "m.onnx").exists()
