"""Files that behave like files: the user's umask, durable atomic writes, and no command
destroying its own input."""
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode.base import atomic
from mpnode.data import read_trajectories, write_trajectories
from mpnode.model import Model


def mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_written_files_get_the_umask_mode_like_open(tmp_path, umask_022, tiny_linear):
    """0666 less the umask, as open(path, 'w') gives -- not mkstemp's 0600."""
    plain = tmp_path / "plain.txt"
    open(plain, "w").close()
    write_trajectories(tmp_path / "t.h5", tiny_linear(B=2))
    Model.create(2, 0, message_dim=3, hidden=8).save(tmp_path / "m.h5")
    assert mode(tmp_path / "t.h5") == mode(tmp_path / "m.h5") == mode(plain) == 0o644
    os.umask(0o077)
    Model.create(2, 0, message_dim=3, hidden=8).save(tmp_path / "private.h5")
    assert mode(tmp_path / "private.h5") == 0o600


def test_replacing_a_file_keeps_its_mode(tmp_path, umask_022):
    path = tmp_path / "m.h5"
    Model.create(2, 0, message_dim=3, hidden=8).save(path)
    os.chmod(path, 0o640)
    Model.create(2, 0, message_dim=3, hidden=8, seed=1).save(path)
    assert mode(path) == 0o640


def test_training_files_get_the_umask_mode(tmp_path, umask_022, tiny_file):
    data = Path(tiny_file(tmp_path / "d.h5"))
    out = tmp_path / "m.h5"
    res = CliRunner().invoke(main, ["train", str(data), "-o", str(out), "--epochs", "2", "--hidden", "4"])
    assert res.exit_code == 0, res.output
    for p in (out, f"{out}.log.jsonl", f"{out}.state"):
        assert mode(p) == 0o644, p


def test_atomic_write_is_flushed_to_disk_before_and_after_the_rename(tmp_path, monkeypatch, tiny_linear):
    """The file's data, then the folder's entry: fsync of the temporary file before it is
    renamed onto the target, and of the folder afterwards."""
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.path.realpath(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src, dst):
        events.append(("rename", os.path.realpath(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    monkeypatch.setattr(atomic.os, "replace", replace)
    target = tmp_path / "t.h5"
    write_trajectories(target, tiny_linear(B=2))
    kinds = [e[0] for e in events]
    assert kinds == ["fsync", "rename", "fsync"], events
    assert events[0][1] != str(target.resolve()) and os.path.dirname(events[0][1]) == str(tmp_path.resolve())
    assert events[2][1] == str(tmp_path.resolve())


def test_a_failed_write_leaves_nothing_behind(tmp_path):
    target = tmp_path / "m.h5"
    with pytest.raises(RuntimeError):
        with atomic.atomic_path(target) as tmp:
            open(tmp, "w").write("half")
            raise RuntimeError("crash")
    assert os.listdir(tmp_path) == []


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_train_refuses_to_write_the_model_over_its_data(tmp_path, tiny_file):
    data = Path(tiny_file(tmp_path / "d.h5"))
    before = data.read_bytes()
    for out in (data, tmp_path / "sub" / ".." / "d.h5"):
        (tmp_path / "sub").mkdir(exist_ok=True)
        res = run("train", data, "-o", out, "--epochs", 1)
        assert res.exit_code == 2 and "destroy the input" in res.output and "Traceback" not in res.output
    link = tmp_path / "link.h5"
    link.symlink_to(data)
    res = run("train", data, "-o", link, "--epochs", 1)
    assert res.exit_code == 2
    # the log or checkpoint beside the model may not be an input either
    res = run("train", data, tmp_path / "m.h5.state", "-o", tmp_path / "m.h5", "--epochs", 1)
    assert res.exit_code == 2
    assert data.read_bytes() == before
    assert not os.path.exists(tmp_path / "m.h5")


def test_eval_refuses_to_write_predictions_over_the_truth_or_the_model(tmp_path, tiny_file):
    data = Path(tiny_file(tmp_path / "d.h5"))
    Model.create(2, 0, message_dim=3, hidden=8, dt=0.1).save(tmp_path / "m.h5")
    truth = read_trajectories(data).x.copy()
    for target in (data, tmp_path / "m.h5"):
        res = run("eval", tmp_path / "m.h5", data, "--predictions", target)
        assert res.exit_code == 2 and "destroy the input" in res.output
    np.testing.assert_array_equal(read_trajectories(data).x, truth)
    Model.load(tmp_path / "m.h5")


def test_finetune_and_simulate_refuse_to_overwrite_their_model(tmp_path, tiny_file):
    data = Path(tiny_file(tmp_path / "d.h5"))
    Model.create(2, 0, message_dim=3, hidden=8, dt=0.1).save(tmp_path / "m.h5")
    before = (tmp_path / "m.h5").read_bytes()
    res = run("finetune", tmp_path / "m.h5", data, "-o", tmp_path / "m.h5", "--epochs", 1)
    assert res.exit_code == 2 and "destroy the input" in res.output
    res = run("simulate", tmp_path / "m.h5", "coupled_pendulum", "-o", tmp_path / "m.h5", "-B", 2)
    assert res.exit_code == 2
    assert (tmp_path / "m.h5").read_bytes() == before
