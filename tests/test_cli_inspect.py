"""`mpnode inspect`: summary for good files, exit status 2 and one clean message for bad ones."""
import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode import Graph
from mpnode.data import Trajectories, write_trajectories


@pytest.fixture
def good_file(tmp_path):
    path = tmp_path / "ring.h5"
    x = np.zeros((4, 11, 5, 2), dtype=np.float32)
    ring = Graph.from_edges(5, [(i, (i + 1) % 5) for i in range(5)])
    star = Graph.from_edges(5, [(0, i) for i in range(1, 5)])
    write_trajectories(path, Trajectories(
        x=x, graphs=[ring, star], graph_index=np.array([0, 0, 0, 1]), dt=0.05, system="kuramoto",
        attrs={"seed": 42, "solver": "dopri5"}, params={"coupling": np.array(1.5)}))
    return path


def run(*args):
    return CliRunner().invoke(main, ["inspect", *map(str, args)])


def test_summary(good_file):
    result = run(good_file)
    assert result.exit_code == 0, result.output
    out = result.stdout
    for text in ("kuramoto", "B=4", "T=10", "N=5", "dx=2", "du=0", "0.05", "float32",
                 "graphs/0: 5 nodes, 10 directed edges, used by 3 trajectories",
                 "graphs/1: 5 nodes, 8 directed edges, used by 1 trajectory", "coupling", "1.5", "seed = 42", "dopri5"):
        assert text in out, text


def test_json(good_file):
    result = run(good_file, "--json")
    assert result.exit_code == 0
    s = json.loads(result.stdout)
    assert (s["file"], s["B"], s["T"], s["N"], s["dx"], s["du"], s["dt"]) == (str(good_file), 4, 10, 5, 2, 0, 0.05)
    assert [g["edges"] for g in s["graphs"]] == [10, 8]
    assert s["params"]["coupling"]["value"] == 1.5 and s["attrs"] == {"seed": 42, "solver": "dopri5"}


def test_invalid_file_exits_2_with_one_message(good_file):
    with h5py.File(good_file, "r+") as f:
        indices = f["graphs/0/indices"][()]
        indices[1] = indices[0]
        del f["graphs/0/indices"]
        f["graphs/0/indices"] = indices
    result = run(good_file)
    assert result.exit_code == 2 and result.stdout == ""
    assert result.stderr.startswith(f"Error: {good_file}: graphs/0/indices: ")
    assert "twice" in result.stderr and "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1


def test_not_hdf5_exits_2(tmp_path):
    path = tmp_path / "data.csv"
    path.write_text("1,2,3\n")
    result = run(path)
    assert result.exit_code == 2
    assert f"Error: {path}: file: cannot be opened as HDF5" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("make", [lambda p: p / "missing.h5", lambda p: p])  # absent, a directory
def test_not_a_file_exits_2(tmp_path, make):
    result = run(make(tmp_path))
    assert result.exit_code == 2 and "Error: Invalid value for 'FILE'" in result.stderr


def test_help():
    result = CliRunner().invoke(main, ["inspect", "--help"])
    assert result.exit_code == 0 and "--json" in result.output and "exit status 2" in result.output
