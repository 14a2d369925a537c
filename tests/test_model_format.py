"""A model file is enough to reproduce mpnode's predictions: a rollout written from the model
format alone (h5py + the NumPy path mpnode.engine.numpy_path, no mpnode.Model, no kernels)
agrees with `mpnode eval --predictions` for every kind."""
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from engine_helpers import rollout_ref

from cli.main import main
from mpnode.base.graph import Graph
from mpnode.data import read_trajectories

MLP_ARRAYS = ("W1", "b1", "W2", "b2", "W3", "b3")
L2S_ARRAYS = ("W_lift", "b_lift", "W_msg", "b_msg", "psi", "W_upd", "b_upd", "W_out", "b_out")


def rollout_from_file(path, traj):
    """Predictions of the model in ``path`` for every initial state of ``traj``, from the file alone."""
    with h5py.File(path, "r") as f:
        a = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        kind = a.get("kind", "mpnode")
        names = L2S_ARRAYS if kind == "l2s" else MLP_ARRAYS + (("W_agg",) if a.get("linear_aggregate") else ())
        theta = np.concatenate([f[f"params/{n}"][()].astype(np.float64).ravel() for n in names])
        x_mean, x_std = f["norm/x_mean"][()], f["norm/x_std"][()]
    aggregation = SimpleNamespace(mlp=a.get("aggregation", "mean"), mean_degree=a.get("mean_degree"),
                                  own_linear=a.get("linear_aggregation"), target=a.get("linear_target", "all"),
                                  weight_scale=a.get("weight_scale"))
    spec = SimpleNamespace(kind=kind, state_dim=int(a["state_dim"]), control_dim=int(a["control_dim"]),
                           message_dim=int(a["message_dim"]), hidden=int(a["hidden"]), dt=float(a["dt"]),
                           substeps=int(a["substeps"]), zero_messages=bool(a["zero_messages"]),
                           self_messages=bool(a["self_messages"]), aggregation=aggregation, n_nodes=a.get("n_nodes"),
                           linear_path=bool(a.get("linear_aggregate", 0)), encoder_window=0,
                           kinematics=None)
    assert "kinematics" not in a  # (these tests' models have none: test_kinematics covers them)
    B, T1, N, dx = traj.x.shape
    out = np.empty((B, T1, N, dx))
    for b in range(B):
        g = traj.graphs[int(traj.graph_index[b])]
        xn = rollout_ref(spec, theta, (traj.x[b, 0] - x_mean) / x_std, g, None, T1 - 1)
        out[b] = xn * x_std + x_mean
    return out


@pytest.mark.parametrize("kind,extra", [("mpnode", ["--aggregate", "scaled"]), ("l2s", []), ("node", []),
                                        ("mpnode", ["--aggregate", "scaled", "--linear-aggregate"]),
                                        ("mpnode", ["--aggregate", "mean", "--linear-aggregation", "scaled"]),
                                        ("mpnode", ["--aggregate", "mean", "--linear-aggregation", "scaled",
                                                    "--linear-target", "state"])])
def test_a_rollout_from_the_file_alone_reproduces_eval_predictions(tmp_path, kind, extra, tiny_file):
    data = tiny_file(tmp_path / "d.h5", B=6)
    model = tmp_path / "m.h5"
    run = CliRunner().invoke
    res = run(main, ["train", data, "-o", str(model), "--model", kind, "--epochs", "3", "--hidden", "8",
                     "--batch-size", "4", "--lr", "1e-2", *extra])
    assert res.exit_code == 0, res.output
    res = run(main, ["eval", str(model), data, "--predictions", str(tmp_path / "p.h5"), "--reference-sample", "0"])
    assert res.exit_code == 0, res.output
    pred = read_trajectories(tmp_path / "p.h5").x
    mine = rollout_from_file(model, read_trajectories(data))
    scale = np.abs(mine).max()
    assert np.abs(pred - mine).max() < 1e-5 * scale  # the file's float32 weights, rolled out in float64
    assert np.abs(mine[:, -1] - mine[:, 0]).max() > 1e-2 * scale  # it moves


def test_the_reference_rollout_sees_graph_structure(tmp_path, tiny_file):
    """Control: the file-only rollout depends on the graph for mpnode/l2s (so the agreement
    above is not vacuous), and not for node."""
    from mpnode.model import Model

    for kind in ("mpnode", "l2s"):
        m = Model.create(2, 0, message_dim=3, hidden=8, dt=0.1, kind=kind, seed=1, dtype=np.float64)
        m.params["b1" if kind == "mpnode" else "b_msg"][:] = 0.5
        m.save(tmp_path / f"{kind}.h5")
        traj = read_trajectories(tiny_file(tmp_path / "d.h5", B=2))
        a = rollout_from_file(tmp_path / f"{kind}.h5", traj)
        traj.graphs = [Graph.from_edges(2, [])]
        assert not np.allclose(a, rollout_from_file(tmp_path / f"{kind}.h5", traj))
