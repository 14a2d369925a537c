"""mpnode.plot (the optional plot extra): skipped when matplotlib is not installed."""
import numpy as np
import pytest

from mpnode.data import Trajectories, write_trajectories
from mpnode.graph import Graph


def _swarm(path, x, load=None):
    aux = {} if load is None else {"load": load}
    write_trajectories(path, Trajectories(x=x, graphs=[Graph.complete(x.shape[2])], dt=0.1, system="quadrotor_load",
                                          u=np.zeros(x.shape[:1] + (x.shape[1] - 1,) + x.shape[2:3] + (4,)), aux=aux))


def test_plot_swarm_writes_png(tmp_path):
    pytest.importorskip("matplotlib")
    from mpnode.plot import plot_swarm

    rng = np.random.default_rng(0)
    B, T, N = 2, 10, 3
    x = np.zeros((B, T + 1, N, 13))
    x[..., 0:3] = np.cumsum(rng.normal(0, 0.1, (B, T + 1, N, 3)), axis=1) + [0, 0, 1]
    x[..., 3] = 1.0  # unit quaternion
    load = np.zeros((B, T + 1, 6))
    load[..., 0] = np.linspace(0, 1, T + 1)
    _swarm(tmp_path / "true.h5", x, load)
    _swarm(tmp_path / "pred.h5", x + 0.05)  # predictions carry no load
    out = plot_swarm(tmp_path / "true.h5", tmp_path / "pred.h5", trajectory=1, out=tmp_path / "s.png")
    data = open(out, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    with pytest.raises(IndexError):
        plot_swarm(tmp_path / "true.h5", tmp_path / "pred.h5", trajectory=5, out=tmp_path / "t.png")
