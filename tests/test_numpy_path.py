"""The NumPy-only path: Model.rollout(backend="numpy") equals the compiled one for every kind
and aggregation (float64 to 1e-12, float32 to float32 rounding), and it is what runs, with a
warning, where numba cannot be imported -- checked in a subprocess whose imports of numba
fail, where `import mpnode`, a rollout, the Simulator and `mpnode eval` must still work.
(test_kinds checks the engine against this path on both drivers and on awkward graphs.)"""
import subprocess
import sys
import tempfile
import textwrap

import numpy as np
import pytest
from engine_helpers import make_graph, random_theta, spec_

from mpnode import Model

N, DX, DU, T = 9, 2, 2, 8

SPECS = {
    "mpnode-mean": dict(message_dim=3),
    "mpnode-scaled-zero": dict(message_dim=3, aggregation="scaled", mean_degree=2.0, zero_messages=True),
    "mpnode-sum-self": dict(message_dim=2, aggregation="sum", self_messages=True),
    "mpnode-scaled-linear": dict(message_dim=3, aggregation="scaled", mean_degree=2.0, linear_aggregate=True),
    "mpnode-mean-linear-scaled": dict(message_dim=3, mean_degree=2.0, linear_aggregate=True,
                                      linear_aggregation="scaled"),
    "mpnode-mean-linear-scaled-state": dict(message_dim=3, mean_degree=2.0, linear_aggregate=True,
                                            linear_aggregation="scaled", linear_target="state"),
    "l2s-sum": dict(kind="l2s", aggregation="sum"),
    "l2s-mean-self": dict(kind="l2s", aggregation="mean", self_messages=True),
    "node": dict(kind="node", n_nodes=N),
}


def make_model(name, dtype, seed=0):
    rng = np.random.default_rng(seed)
    spec = spec_(state_dim=DX, control_dim=DU, hidden=8, dt=0.1, substeps=2, **{"message_dim": 0, **SPECS[name]})
    return Model(random_theta(rng, spec, dtype=dtype), spec, x_mean=rng.standard_normal(DX),
                 x_std=1 + rng.random(DX), u_mean=rng.standard_normal(DU), u_std=1 + rng.random(DU))


def problem(seed=1, B=4):
    rng = np.random.default_rng(seed)
    return make_graph(rng, N), rng.standard_normal((B, N, DX)), rng.standard_normal((B, T, N, DU))


@pytest.mark.parametrize("dtype,rtol", [(np.float64, 1e-12), (np.float32, 1e-4)])
@pytest.mark.parametrize("name", SPECS)
def test_numpy_path_equals_the_compiled_one(name, dtype, rtol):
    model = make_model(name, dtype)
    g, x0, u = problem()
    compiled = model.rollout(x0, g, u, backend="numba")
    slow = model.rollout(x0, g, u, backend="numpy")
    assert slow.dtype == compiled.dtype == dtype and slow.shape == compiled.shape
    scale = np.abs(compiled).max()
    assert np.abs(slow - compiled).max() <= rtol * scale
    assert np.abs(compiled[:, -1] - compiled[:, 0]).max() > 1e-2 * scale  # it moves


def test_unknown_backend_is_refused():
    model = make_model("mpnode-mean", np.float64)
    g, x0, u = problem()
    with pytest.raises(ValueError, match="backend must be one of"):
        model.rollout(x0, g, u, backend="torch")


BLOCK_NUMBA = """
import sys

class NoNumba:
    '''numba and llvmlite cannot be imported, as on a server where they are not installed.'''
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("numba", "llvmlite"):
            raise ImportError(f"No module named {name!r} (blocked by the test)")

sys.meta_path.insert(0, NoNumba())
"""

WITHOUT_NUMBA = BLOCK_NUMBA + """
import warnings
import numpy as np
import mpnode
from mpnode import Model, Simulator
from mpnode.base.graph import Graph
assert "numba" not in sys.modules
model_path, graph_path, out_path = sys.argv[1:4]
model = Model.load(model_path)
z = np.load(graph_path)
g, x0, u = Graph(z["indptr"], z["indices"]), z["x0"], z["u"]
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    x = model.rollout(x0, g, u)
assert any("numba cannot be imported" in str(w.message) for w in caught), [str(w.message) for w in caught]
sim = Simulator(model, g)
steps = [sim.reset(x0)] + [sim.step(u[:, t]) for t in range(u.shape[1])]
assert np.array_equal(np.stack(steps, 1), x)
for call in (lambda: model.rollout(x0, g, u, backend="numba"), lambda: mpnode.loss_and_grad(model, x, g, u)):
    try:
        call()
        raise AssertionError("ran without numba")
    except ImportError as e:
        assert "needs numba" in str(e) and "blocked by the test" in str(e), e
assert "numba" not in sys.modules
np.save(out_path, x)
"""


def run_python(code, *args):
    # outside the checkout, so the installed mpnode (with cli) is the one imported
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(code), *map(str, args)], capture_output=True,
                         text=True, timeout=300, cwd=tempfile.gettempdir())
    assert res.returncode == 0, res.stdout + res.stderr
    return res


def test_without_numba_a_model_still_rolls_out_and_steps(tmp_path):
    model = make_model("mpnode-mean", np.float64)
    model.save(tmp_path / "m.h5")
    g, x0, u = problem()
    np.savez(tmp_path / "g.npz", indptr=g.indptr, indices=g.indices, x0=x0, u=u)
    run_python(WITHOUT_NUMBA, tmp_path / "m.h5", tmp_path / "g.npz", tmp_path / "x.npy")
    compiled = model.rollout(x0, g, u)
    np.testing.assert_allclose(np.load(tmp_path / "x.npy"), compiled, rtol=1e-12, atol=1e-12 * np.abs(compiled).max())


def test_without_numba_the_cli_evaluates(tmp_path, tiny_file):
    data = tiny_file(tmp_path / "d.h5", B=3)
    Model.create(2, 0, message_dim=3, hidden=8, dt=0.1, dtype=np.float32).save(tmp_path / "m.h5")
    res = run_python(BLOCK_NUMBA + """
from cli.main import main
main(["eval", sys.argv[1], sys.argv[2]])
""", tmp_path / "m.h5", data)
    assert "normalised MSE" in res.stdout, res.stdout


def test_import_mpnode_does_not_import_numba():
    run_python("""
import sys
import mpnode
mpnode.Model, mpnode.Simulator, mpnode.read_trajectories
assert "numba" not in sys.modules, "import mpnode loaded numba"
""")
