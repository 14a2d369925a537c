"""What breaks mpnode when the input is fine: the operating system, impossible sizes, concurrent
runs, data that cannot be learned, and messages that said less than the truth.

Every test asserts the exit status, the message and what is left on disk.  A read-only folder
and a full disk are real: each test runs its commands in a user namespace (``unshare -rm``)
where a tmpfs of a few hundred kB, or a read-only bind mount, can be mounted without
privileges (the tests run as root here, where a folder's permissions stop no write).  Where
the machine does not allow namespaces those tests skip; the training run that cannot write its
checkpoint is also tested in this process, with the write made to fail at a chosen epoch.
"""
import errno
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from dataclasses import replace

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from mpnode.base.errors import InputError
from mpnode.base.oserrors import FileSystemError
from mpnode.data import read_trajectories, write_trajectories
from mpnode.model import Model
from mpnode.training.state import TrainState

QUICK = ["--batch-size", "8", "--hidden", "8", "--message-dim", "2"]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def files(folder):
    return sorted(os.listdir(folder))


def _namespaces():
    """Whether a tmpfs and a read-only bind mount can be made in a user namespace here."""
    probe = ('d=$(mktemp -d) && mount -t tmpfs -o size=64k tmpfs "$d" && mount --bind "$d" "$d" '
             '&& mount -o remount,bind,ro "$d" && umount "$d" && umount "$d" && rmdir "$d"')
    try:
        return subprocess.run(["unshare", "-rm", "sh", "-c", probe], capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


needs_namespace = pytest.mark.skipif(not _namespaces(), reason="user namespaces (unshare -rm) not allowed here")


def in_namespace(script, cwd):
    """Run the bash ``script`` in a user and mount namespace (mounts vanish with it); the
    mpnode command is this Python's."""
    env = {**os.environ, "PATH": os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"]}
    return subprocess.run(["unshare", "-rm", "bash", "-c", "set -u\n" + textwrap.dedent(script)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def statuses(res):
    """{label: (exit status, stderr)} of the script's `check LABEL command...` lines."""
    out = {}
    for block in res.stdout.split("@@")[1:]:
        label, rc, err = block.split("\n", 2)
        out[label] = (int(rc), err)
    return out


CHECK = """
check() {  # check LABEL CMD...: the command's exit status and stderr, for statuses()
    label=$1; shift
    err=$("$@" 2>&1 >/dev/null); rc=$?
    printf '@@%s\\n%s\\n%s\\n' "$label" "$rc" "$err"
}
"""


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A folder with a small trajectory file, a model trained on it, a sweep file and an .npz archive."""
    from data_gen import generate, load_scene

    d = tmp_path_factory.mktemp("world")
    write_trajectories(d / "p.h5", generate(replace(load_scene("coupled_pendulum"), trajectories=12, horizon=8),
                                            workers=1))
    assert run("train", d / "p.h5", "-o", d / "m.h5", "--epochs", 1, *QUICK).exit_code == 0
    (d / "s.toml").write_text('data = ["p.h5"]\n[train]\nepochs = 1\nhidden = 8\n')
    t = read_trajectories(d / "p.h5")
    np.savez(d / "p.npz", x=t.x, edges=[[0, 1], [1, 0]], dt=t.dt, system="coupled_pendulum")
    return d


# ---- the operating system ------------------------------------------------------------------
@needs_namespace
def test_every_command_on_a_read_only_folder_says_so_and_writes_nothing(world, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    # --plot without matplotlib stops first with the install hint (test_plot.py); with it, on the folder
    plot = importlib.util.find_spec("matplotlib") is not None
    res = in_namespace(CHECK + f"""
        mount --bind {ro} {ro} && mount -o remount,bind,ro {ro}
        check generate mpnode generate coupled_pendulum -B 2 -T 3 -o {ro}/g.h5
        check train mpnode train p.h5 -o {ro}/t.h5 --epochs 1
        check eval mpnode eval m.h5 p.h5 --predictions {ro}/pred.h5 --reference-sample 0
        check convert mpnode convert p.npz -o {ro}/c.h5
        check sweep mpnode sweep s.toml -o {ro}/sweep
        {"check plot mpnode eval m.h5 p.h5 --plot " + str(ro) + "/fig.png --reference-sample 0" if plot else ""}
        """, world)
    got = statuses(res)
    assert set(got) == {"generate", "train", "eval", "convert", "sweep"} | ({"plot"} if plot else set()), \
        res.stdout + res.stderr
    for label, (rc, err) in got.items():
        assert rc == 4, (label, err)
        assert err.startswith(f"Error: {ro}/") and "Read-only file system [EROFS]" in err, (label, err)
        assert "write to a folder on a writable disk" in err and "Traceback" not in err, (label, err)
    assert files(ro) == []  # outside the namespace the folder is writable: nothing got through


@needs_namespace
def test_a_full_disk_stops_generate_eval_and_training_leaving_what_is_consistent(world, tmp_path):
    keep = tmp_path / "keep"
    keep.mkdir()
    full = tmp_path / "full"
    full.mkdir()
    res = in_namespace(CHECK + f"""
        mount -t tmpfs -o size=192k tmpfs {full}
        check generate mpnode generate lorenz3 -B 100 -T 50 -o {full}/g.h5
        ls -A {full} > {keep}/after-generate
        head -c {188 * 1024} /dev/zero > {full}/filler  # one page of 4 kB left
        check eval mpnode eval m.h5 p.h5 --predictions {full}/pred.h5 --reference-sample 0
        rm {full}/filler
        ls -A {full} > {keep}/after-eval
        head -c {136 * 1024} /dev/zero > {full}/filler  # room for a few saves and some epochs of the log
        check train mpnode train p.h5 -o {full}/t.h5 --epochs 100000 --time-limit 2m {' '.join(QUICK)}
        rm {full}/filler
        cp -a {full}/. {keep}/
        """, world)
    got = statuses(res)
    for label in ("generate", "eval", "train"):
        rc, err = got[label]
        assert rc == 4 and "No space left on device [ENOSPC]" in err and "Traceback" not in err, (label, err)
        assert "the disk is full: free space on it, or write to another disk" in err, err
    assert (keep / "after-generate").read_text() == "" and (keep / "after-eval").read_text() == ""
    err = got["train"][1]
    assert "Training stopped after epoch" in err and "written together" in err and "--resume" in err, err
    assert files(keep) == ["after-eval", "after-generate", "t.h5", "t.h5.log.jsonl", "t.h5.state"]
    _assert_consistent(keep / "t.h5")
    res = run("train", world / "p.h5", "-o", keep / "t.h5", "--epochs", 3, "--resume")  # with room again
    assert res.exit_code == 0, res.output


def _assert_consistent(model_path):
    """The model file is the best model of the checkpoint beside it."""
    with np.load(f"{model_path}.state") as s:
        best_epoch, best_theta = int(s["best_epoch"]), s["best_theta"]
    model = Model.load(model_path)
    assert int(model.attrs["epoch"]) == best_epoch
    np.testing.assert_array_equal(model.theta, best_theta)


def test_a_checkpoint_that_cannot_be_written_stops_training_with_model_and_checkpoint_a_pair(world, tmp_path,
                                                                                            monkeypatch):
    """The disk fills at the fourth save (epoch 3): the run stops saying so, the model file and its
    checkpoint are both those of epoch 2, and --resume ends where a run without the failure ends."""
    from mpnode import runs

    options = {"epochs": 6, "hidden": 8, "message_dim": 2, "batch_size": 4, "checkpoint_seconds": 0.0,
               "lr": 1e-2}
    runs.train([world / "p.h5"], tmp_path / "straight.h5", options)
    calls, write = [], TrainState.write

    def full_disk(path, snap):
        calls.append(int(snap["epoch"]))
        if len(calls) == 4:
            with open(path, "wb") as f:
                f.write(b"half")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        write(path, snap)

    monkeypatch.setattr(TrainState, "write", staticmethod(full_disk))
    out = tmp_path / "t.h5"
    with pytest.raises(FileSystemError) as e:
        runs.train([world / "p.h5"], out, options)
    message = str(e.value)
    assert message.startswith(f"{out}.state: cannot write: No space left on device [ENOSPC]"), message
    assert f"Training stopped after epoch 3; {out} and its checkpoint {out}.state are those of epoch 2" in message
    assert files(tmp_path) == ["straight.h5", "straight.h5.log.jsonl", "straight.h5.state", "t.h5",
                               "t.h5.log.jsonl", "t.h5.state"]  # no temporary file left
    with np.load(f"{out}.state") as s:
        assert int(s["epoch"]) == 2
    _assert_consistent(out)
    monkeypatch.setattr(TrainState, "write", staticmethod(write))
    runs.train([world / "p.h5"], out, options, resume=True)
    np.testing.assert_array_equal(Model.load(out).theta, Model.load(tmp_path / "straight.h5").theta)


# ---- impossible sizes and time steps --------------------------------------------------------
@pytest.mark.parametrize("args, field", [
    (["generate", "lorenz3", "-B", 10**12], "trajectories"),
    (["generate", "lorenz3", "-T", 10**12], "trajectories"),
    (["simulate", "MODEL", "coupled_pendulum", "-B", 10**12], "trajectories"),
    (["simulate", "MODEL", "coupled_pendulum", "-T", 10**12], "trajectories"),
])
def test_sizes_beyond_the_machine_are_refused_before_any_work(world, tmp_path, args, field):
    args = [world / "m.h5" if a == "MODEL" else a for a in args]
    res = run(*args, "-o", tmp_path / "out.h5")
    assert res.exit_code == 2, res.output
    assert f": {field}: " in res.stderr and "of memory, but this machine has" in res.stderr
    assert "fewer trajectories (-B, --trajectories) or a shorter horizon (-T, --horizon)" in res.stderr
    assert files(tmp_path) == []


def test_a_hidden_width_beyond_the_machine_names_the_flag(world, tmp_path):
    res = run("train", world / "p.h5", "-o", tmp_path / "m.h5", "--hidden", 100000)
    assert res.exit_code == 2, res.output
    assert res.stderr.startswith("Error: --hidden: 100000: training a model of kind mpnode with 10,001,")
    assert "expected a smaller --hidden" in res.stderr and files(tmp_path) == []


def test_a_time_step_far_beyond_the_systems_time_scale_is_refused_not_integrated(tmp_path):
    res = run("generate", "lorenz3", "-B", 1, "-T", 3, "--dt", 1e300, "-o", tmp_path / "g.h5")
    assert res.exit_code == 2
    assert "dt: is 1e+300, 1e+300 times the time scale of lorenz (1: docs/systems.md#time-scales)" in res.stderr
    assert "(expected dt <= 10)" in res.stderr and files(tmp_path) == []


def test_training_without_numba_refuses_before_writing_anything(world, tmp_path):
    code = textwrap.dedent("""
        import sys

        class NoNumba:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("numba", "llvmlite"):
                    raise ImportError(f"No module named {name!r} (blocked by the test)")

        sys.meta_path.insert(0, NoNumba())
        from cli.main import main
        main(sys.argv[1:])
    """)
    for data in (str(world / "p.h5"), "coupled_pendulum"):
        res = subprocess.run([sys.executable, "-c", code, "train", data, "-o", str(tmp_path / "m.h5")],
                             capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert res.returncode == 4, res.stderr
        assert res.stderr.startswith("Error: training needs numba, which cannot be imported here (")
        assert "pip install numba" in res.stderr and "Traceback" not in res.stderr
        assert files(tmp_path) == []


# ---- concurrent runs ------------------------------------------------------------------------
HOLD = """
import sys, time
from mpnode.base.locks import claim
with claim(sys.argv[1], "mpnode train p.h5 -o same.h5 (the test's)"):
    print("held", flush=True)
    time.sleep(600)
"""


def test_an_output_claimed_by_a_running_command_cannot_be_claimed_again(world, tmp_path):
    out = tmp_path / "same.h5"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        res = run("train", world / "p.h5", "-o", out, "--epochs", 1, *QUICK)
        assert res.exit_code == 2, res.output
        assert res.stderr.startswith(f"Error: --output: {out}: is being written by another run (pid {holder.pid} ")
        assert "`mpnode train p.h5 -o same.h5 (the test's)`" in res.stderr
        assert files(tmp_path) == ["same.h5.lock"]  # the holder's lock, and nothing of the refused run
    finally:
        os.kill(holder.pid, signal.SIGKILL)  # killed without releasing: its lock file stays behind
        holder.wait()
    assert files(tmp_path) == ["same.h5.lock"]
    res = run("train", world / "p.h5", "-o", out, "--epochs", 1, *QUICK)  # the dead run's lock is taken over
    assert res.exit_code == 0, res.output
    assert files(tmp_path) == ["same.h5", "same.h5.log.jsonl", "same.h5.state"]  # and released at the end


def test_a_sweep_never_writes_over_its_inputs(world, tmp_path):
    run_folder = tmp_path / "out" / "runs" / "hidden=8"
    run_folder.mkdir(parents=True)
    shutil.copy(world / "p.h5", run_folder / "model.h5")  # the data lie where the sweep writes a run's model
    before = (run_folder / "model.h5").read_bytes()
    (tmp_path / "s.toml").write_text('data = ["out/runs/hidden=8/model.h5"]\n[train]\nepochs = 1\n[grid]\n'
                                     'hidden = [8]\n')
    res = run("sweep", tmp_path / "s.toml", "-o", tmp_path / "out")
    assert res.exit_code == 2, res.output
    assert "lies where the sweep writes" in res.stderr and "a run's folder is emptied when it starts" in res.stderr
    assert (run_folder / "model.h5").read_bytes() == before and files(tmp_path / "out") == ["runs"]


def test_a_sweeps_test_file_that_cannot_fit_its_models_stops_it_before_any_run(world, tmp_path):
    from data_gen import generate, load_scene

    write_trajectories(tmp_path / "l.h5", generate(replace(load_scene("lorenz3"), trajectories=2, horizon=4),
                                                   workers=1))
    (tmp_path / "s.toml").write_text(f'data = ["{world / "p.h5"}"]\ntest = ["l.h5"]\n[train]\nepochs = 1\n')
    res = run("sweep", tmp_path / "s.toml", "-o", tmp_path / "out")
    assert res.exit_code == 2, res.output
    assert "l.h5: x: has 3 dimensions per node but the training data have 2" in res.stderr
    assert not (tmp_path / "out").exists()


def test_a_sweeps_test_file_of_another_system_of_the_same_sizes_is_a_warning(world, tmp_path):
    from mpnode.runs.sweep import read_sweep

    t = read_trajectories(world / "p.h5")
    write_trajectories(tmp_path / "k.h5", replace(t, system="kuramoto_like"))
    (tmp_path / "s.toml").write_text(f'data = ["{world / "p.h5"}"]\ntest = ["k.h5"]\n[train]\nepochs = 1\n')
    [warning] = read_sweep(tmp_path / "s.toml").warnings
    assert warning.startswith("test file ") and warning.endswith("k.h5 holds kuramoto_like data, the runs train on "
                                                                 "coupled_pendulum")


def test_resume_with_a_flag_that_contradicts_the_checkpoint_names_the_flag(world, tmp_path):
    out = tmp_path / "m.h5"
    assert run("train", world / "p.h5", "-o", out, "--epochs", 2, *QUICK).exit_code == 0
    before = {name: (tmp_path / name).read_bytes() for name in files(tmp_path)}
    res = run("train", world / "p.h5", "-o", out, "--epochs", 4, "--resume", "--model", "l2s", "--hidden", 64)
    assert res.exit_code == 2, res.output
    assert res.stderr.startswith(f"Error: --kind: l2s: contradicts the run being resumed: its checkpoint {out}.state "
                                 "has kind = mpnode (expected no --kind with --resume")
    res = run("train", world / "p.h5", "-o", out, "--epochs", 4, "--resume", "--lr", 0.5)
    assert res.exit_code == 2 and "Error: --lr: 0.5: contradicts" in res.stderr and "has lr = " in res.stderr
    assert {name: (tmp_path / name).read_bytes() for name in files(tmp_path)} == before
    res = run("train", world / "p.h5", "-o", out, "--epochs", 4, "--resume", "--hidden", 8, "--batch-size", 8)
    assert res.exit_code == 0, res.output  # the same values as the checkpoint's are no contradiction


# ---- data that cannot be learned ------------------------------------------------------------
def _write_and_train(tmp_path, x, **kw):
    write_trajectories(tmp_path / "d.h5", x=x, graph=[(0, 1)], dt=0.1, system="s", **kw)
    return run("train", tmp_path / "d.h5", "-o", tmp_path / "m.h5", "--epochs", 2, *QUICK)


def test_a_dimension_of_zero_variance_is_named_before_training(tmp_path):
    x = np.random.default_rng(0).standard_normal((6, 5, 2, 3))
    x[..., 1] = 0.25
    res = _write_and_train(tmp_path, x, attrs={"state_names": ["p", "load (kg)", "v"]})
    assert res.exit_code == 2, res.output
    assert res.stderr.startswith(f"Error: {tmp_path / 'd.h5'}: x[..., 1] (load (kg)): is 0.25 in every training")
    assert "expected the data without it (x[..., [0, 2]]), or trajectories in which it varies" in res.stderr
    assert files(tmp_path) == ["d.h5"]


def test_a_dimension_never_observed_is_not_called_constant(tmp_path):
    """NaN throughout is an unmeasured state, not zero variance: the file keeps it (format version 2),
    and the learnability check does not take such a dimension for a constant one."""
    from mpnode.base.graph import Graph
    from mpnode.data import Trajectories
    from mpnode.training import TrainConfig
    from mpnode.training.batches import TrainingData

    x = np.random.default_rng(0).standard_normal((6, 5, 2, 3))
    x[..., 2] = np.nan
    traj = Trajectories(x=x, graphs=[Graph.from_edges(2, [(0, 1)])], dt=0.1, system="s")
    write_trajectories(tmp_path / "never.h5", traj)
    assert read_trajectories(tmp_path / "never.h5").unmeasured_dims().tolist() == [2]
    TrainingData([traj], TrainConfig())  # no complaint of zero variance, nor of overflow


def test_a_single_trajectory_says_no_validation_set_is_left(tmp_path):
    res = _write_and_train(tmp_path, np.random.default_rng(0).standard_normal((1, 30, 2, 2)))
    assert res.exit_code == 2, res.output
    assert "leaves no trajectory for validation" in res.stderr and "(1) trajectories" in res.stderr
    assert "or --val-split 0 to train without validation" in res.stderr and files(tmp_path) == ["d.h5"]
    res = run("train", tmp_path / "d.h5", "-o", tmp_path / "m.h5", "--epochs", 2, "--val-split", 0, *QUICK)
    assert res.exit_code == 0, res.output


def test_values_that_overflow_the_normalisation_are_named_with_the_fix(tmp_path):
    x = np.random.default_rng(0).standard_normal((6, 5, 2, 2)) * 1e300
    np.savez(tmp_path / "big.npz", x=x, edges=[[0, 1]], dt=0.1, system="s")
    assert run("convert", tmp_path / "big.npz", "-o", tmp_path / "d.h5").exit_code == 0
    res = run("train", tmp_path / "d.h5", "-o", tmp_path / "m.h5", "--epochs", 2, *QUICK)
    assert res.exit_code == 2, res.output
    assert res.stderr.startswith(f"Error: {tmp_path / 'd.h5'}: x: has values up to ")
    assert "whose variance overflows" in res.stderr and "expected the data rescaled" in res.stderr
    assert "RuntimeWarning" not in res.output and files(tmp_path) == ["big.npz", "d.h5"]


# ---- warnings and small messages ------------------------------------------------------------
def test_a_model_of_another_system_is_used_with_a_warning_naming_both(world, tmp_path):
    t = read_trajectories(world / "p.h5")
    write_trajectories(tmp_path / "k.h5", replace(t, system="kuramoto", attrs={}, params={}))
    res = run("eval", world / "m.h5", tmp_path / "k.h5", "--reference-sample", 0)
    assert res.exit_code == 0, res.output
    warning = f"the model was trained on coupled_pendulum data, but {tmp_path / 'k.h5'} holds kuramoto"
    assert res.stderr.startswith(f"warning: {warning}")
    res = run("simulate", world / "m.h5", "coupled_pendulum", "-B", 2, "-T", 3, "-o", tmp_path / "s.h5")
    assert res.exit_code == 0 and "warning" not in res.stderr  # the same system: no warning
    res = run("finetune", world / "m.h5", tmp_path / "k.h5", "-o", tmp_path / "f.h5", "--epochs", 1)
    assert res.exit_code == 0 and "warning: the model was trained on coupled_pendulum data" in res.stderr


def test_the_dt_mismatch_names_the_flag_that_allows_it(world, tmp_path):
    t = read_trajectories(world / "p.h5")
    write_trajectories(tmp_path / "d.h5", replace(t, dt=0.1))
    res = run("eval", world / "m.h5", tmp_path / "d.h5")
    assert res.exit_code == 2 and "--allow-dt-mismatch" in res.stderr


def test_the_progress_bar_follows_whichever_budget_ends_the_run_first():
    from cli.train_cmd import done_fraction

    assert done_fraction({"epoch": 10, "elapsed": 19.0}, 4000, 20.0) == pytest.approx(0.95)  # the time limit
    assert done_fraction({"epoch": 30, "elapsed": 1.0}, 40, 600.0) == pytest.approx(0.75)  # the epochs
    assert done_fraction({"epoch": 3, "elapsed": 99.0}, 40, None) == pytest.approx(0.075)
    assert done_fraction({"epoch": 50, "elapsed": 30.0}, 40, 20.0) == 1.0
    assert done_fraction({"epoch": 9000, "elapsed": 5.0}, None, 20.0) == pytest.approx(0.25)  # no cap: the time


def test_eval_says_slower_when_the_learned_model_is_slower():
    from cli.eval_cmd import format_reference

    ref = {"system": "s", "sample": 3, "reached": True, "target_nmse": 0.1, "integrator": "batched RK4, 1 step per dt",
           "reference_seconds_per_trajectory": 1e-4, "reference_nmse_vs_file": 1e-6, "tried": [],
           "learned_seconds_per_trajectory": 1.4545e-4, "learned_seconds_per_trajectory_full_batch": 2e-4,
           "speedup": 1e-4 / 1.4545e-4}
    lines = "\n".join(format_reference(ref))
    assert "the learned model is 1.45x SLOWER" in lines and "faster" not in lines


def test_the_python_api_refuses_a_directed_that_is_not_a_bool(tmp_path):
    x = np.zeros((2, 3, 2, 1))
    with pytest.raises(InputError) as e:
        write_trajectories(tmp_path / "d.h5", x=x, graph=[(0, 1)], dt=0.1, system="s", directed="no")
    assert (e.value.field, e.value.expected) == ("directed", "True or False") and files(tmp_path) == []
    write_trajectories(tmp_path / "u.h5", x=x, graph=[(0, 1)], dt=0.1, system="s", directed=np.bool_(False))
    with h5py.File(tmp_path / "u.h5") as f:
        assert list(f["graphs/0/indices"]) == [1, 0]  # undirected: both directions


def test_atomic_pairs_replace_both_files_or_neither(tmp_path):
    from mpnode.base.atomic import atomic_paths

    (tmp_path / "a").write_text("old a")
    (tmp_path / "b").write_text("old b")
    with pytest.raises(FileSystemError) as e:
        with atomic_paths(tmp_path / "a", tmp_path / "b") as (ta, tb):
            open(ta, "w").write("new a")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert e.value.filename == str(tmp_path / "b") and e.value.errno == errno.ENOSPC
    assert [(tmp_path / n).read_text() for n in "ab"] == ["old a", "old b"] and files(tmp_path) == ["a", "b"]
    with atomic_paths(tmp_path / "a", tmp_path / "b") as (ta, tb):
        open(ta, "w").write("new a")
        open(tb, "w").write("new b")
    assert [(tmp_path / n).read_text() for n in "ab"] == ["new a", "new b"] and files(tmp_path) == ["a", "b"]
    assert json.dumps(str(e.value)).count("ENOSPC") == 1
