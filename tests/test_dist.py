"""Running on Dask (mpnode[dist]): executors, `generate --scheduler`, sweeps and their faults.

The Dask tests use a real LocalCluster of two process workers (one thread each), are in the slow
tier (`pytest -m slow`) and skip when Dask is not installed; the sweep file, the executor's own
errors and the command on the local pool are tested without it.  So is a sweep stopped and
resumed, in the slow tier: it trains thousands of epochs to be stopped in the middle.
"""
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from data_gen import BUILTIN, generate
from mpnode.base.errors import InputError
from mpnode.data import write_trajectories
from mpnode.model import Model
from mpnode.runs.executors import open_executor, parse_scheduler
from mpnode.runs.sweep import FINISHED, point_epochs, read_sweep, run_sweep, run_task
from mpnode.training import state_path

try:
    import distributed  # noqa: F401
    HAVE_DASK = True
except ImportError:
    HAVE_DASK = False
needs_dask = pytest.mark.skipif(not HAVE_DASK, reason="Dask not installed (pip install '.[dist]')")


def on_dask(test):
    """A test on a LocalCluster: in the slow tier (a cluster's processes start, import and load the
    kernels), skipped without Dask."""
    return pytest.mark.slow(needs_dask(test))

MINIMAL = """
data = ["train.h5"]      # training files; every run trains on all of them
[train]                  # settings shared by every run: any `mpnode train` option, with underscores
epochs = 300
[grid]                   # every combination is one run
message_dim = [1, 3, 7]
seed = [0, 1]
"""


def small(name, B, T, **kw):
    return replace(BUILTIN[name], trajectories=B, horizon=T, **kw)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dist")
    write_trajectories(folder / "train.h5", generate(small("coupled_pendulum", 10, 12), workers=1))
    write_trajectories(folder / "test.h5", generate(small("coupled_pendulum", 3, 12, seed=7), workers=1))
    (folder / "bad.h5").write_text("not a trajectory file")
    return folder


@pytest.fixture(scope="module")
def farm():
    if not HAVE_DASK:
        pytest.skip("Dask not installed")
    with open_executor("local", 2) as f:
        yield f


def sweep_file(folder, name, text):
    path = folder / name
    path.write_text(text)
    return read_sweep(path)


# ---- without Dask --------------------------------------------------------------------------
def test_importing_mpnode_and_its_commands_does_not_import_dask(tmp_path):
    code = ("import sys, mpnode, mpnode.runs.executors, mpnode.runs.sweep, cli.main, data_gen; "
            "print(any(m.split('.')[0] in ('dask', 'distributed') for m in sys.modules))")
    # run outside the checkout: its mpnode/ folder has no cli/ (that installs as cli)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path)
    assert out.stdout.strip() == "False"


def test_asking_for_a_scheduler_without_dask_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed now raises ImportError
    with pytest.raises(InputError, match=r"pip install 'mpnode\[dist\]'"):
        with open_executor("local"):
            pass


def test_scheduler_settings():
    assert parse_scheduler(None) == ("pool", None) == parse_scheduler("none")
    assert parse_scheduler("local") == ("local", None)
    assert parse_scheduler("tcp://10.0.0.1:8786") == ("address", "tcp://10.0.0.1:8786")
    assert parse_scheduler(__file__) == ("file", __file__)
    with pytest.raises(InputError, match="scheduler file"):
        parse_scheduler("no-such-file.json")


def test_the_issue_minimal_sweep_file_is_six_runs(data):
    sweep = sweep_file(data, "minimal.toml", MINIMAL)
    assert [p.name for p in sweep.runs] == [f"message_dim={d},seed={s}" for d in (1, 3, 7) for s in (0, 1)]
    assert all(p.options["epochs"] == 300 and p.data == [str(data / "train.h5")] for p in sweep.runs)
    assert sweep.runs[3].options["message_dim"] == 3 and sweep.runs[3].options["seed"] == 1
    assert len({p.key for p in sweep.runs}) == 6


def test_a_runs_key_changes_with_what_its_recipe_sets(data, monkeypatch):
    from mpnode.training import recipes

    text = 'data = ["train.h5"]\n[[run]]\nname = "auto"\n[[run]]\nname = "paper"\nrecipe = "paper"\n'
    before = {p.name: p.key for p in sweep_file(data, "recipes.toml", text).runs}
    monkeypatch.setattr(recipes, "AUTO_ALL", {"batch_size": 16})  # a later mpnode's recipe
    after = {p.name: p.key for p in sweep_file(data, "recipes.toml", text).runs}
    assert after["auto"] != before["auto"] and after["paper"] == before["paper"]


@pytest.mark.parametrize("text, field", [
    ('data = ["train.h5"]\n[grid]\nmesage_dim = [1]\n', "mesage_dim"),
    ('data = ["missing.h5"]\n', "data"),
    ('data = ["train.h5"]\n[[run]]\nname = "a"\nfrom = "b"\n', "from"),
    ('data = ["train.h5"]\n[[run]]\nname = "a"\n[[run]]\nname = "b"\nfrom = "a"\nmessage_dim = 7\n', "message_dim"),
    ('data = ["train.h5"]\n[train]\nepochs = -1\n', "epochs"),
    ('data = ["train.h5"]\nepochs = 3\n', "epochs"),
    ('data = ["train.h5"]\ntest_points = 2\n', "test_points"),
    ('data = ["train.h5"]\ntest = ["test.h5"]\ntest_points = -1\n', "test_points"),
    ('data = ["train.h5"]\ntest = ["test.h5"]\ntest_points = 2\n[train]\nschedule = "cosine"\n', "test_points"),
    ('data = ["train.h5"]\n[[run]]\nname = "a"\ntest = ["missing.h5"]\n', "test"),
])
def test_a_bad_sweep_file_names_the_key(data, text, field):
    with pytest.raises(InputError, match=field):
        sweep_file(data, "bad.toml", text)


def test_test_points_refuse_the_cosine_schedule_a_recipe_chooses(tmp_path):
    # recipe auto decays the quadrotor swarm's learning rate over the run; test points train it in
    # segments, each of which would end the decay: refused before any run, as a cosine in the file is
    write_trajectories(tmp_path / "q3.h5", generate(small("quad3", 3, 2), workers=1))
    write_trajectories(tmp_path / "q3_test.h5", generate(small("quad3", 2, 2, seed=5), workers=1))
    text = 'data = ["q3.h5"]\ntest = ["q3_test.h5"]\ntest_points = 2\n'
    with pytest.raises(InputError, match="test_points.*cosine schedule recipe auto chooses for quadrotor_load"):
        sweep_file(tmp_path, "auto.toml", text)
    assert sweep_file(tmp_path, "paper.toml", 'recipe = "paper"\n' + text).runs[0].test_points == 2
    told = sweep_file(tmp_path, "plateau.toml", text + '[train]\nschedule = "plateau"\n')
    assert told.runs[0].options["schedule"] == "plateau"


# ---- on a LocalCluster ---------------------------------------------------------------------
@on_dask
@pytest.mark.parametrize("scene", ["lorenz3", "quad3"])
def test_generate_on_dask_writes_the_same_file_bit_for_bit(tmp_path, scene):
    args = ["generate", scene, "-B", "7", "-T", "6", "--seed", "3"]
    runner = CliRunner()
    here = runner.invoke(main, [*args, "-o", str(tmp_path / "pool.h5")])
    assert here.exit_code == 0, here.output
    there = runner.invoke(main, [*args, "-o", str(tmp_path / "dask.h5"), "--scheduler", "local", "--workers", "2"])
    assert there.exit_code == 0, there.output
    assert (tmp_path / "pool.h5").read_bytes() == (tmp_path / "dask.h5").read_bytes()


@on_dask
def test_a_two_run_sweep_with_a_finetune_child(data, farm, tmp_path):
    sweep = sweep_file(data, "tune.toml", """
data = ["train.h5"]
test = ["test.h5"]
[train]
epochs = 4
batch_size = 4
[[run]]
name = "base"
message_dim = 2
[[run]]
name = "tuned"
from = "base"
epochs = 2
lr = 1e-4
""")
    seen = []
    records = run_sweep(sweep, tmp_path, farm, progress=seen.append)
    assert [r["name"] for r in seen] == ["base", "tuned"]
    assert all(records[n]["status"] == "completed" for n in ("base", "tuned"))
    assert records["tuned"]["from"] == "base" and records["tuned"]["epochs"] == 2
    # the worker trained what this process trains from the same files (to float32 rounding: the
    # workers run one numba thread, this process may run more, and threads change summation order)
    plan = {**vars(sweep.runs[0])}
    here = run_task(plan, ["test.h5"], None, str(data / "train.h5"), str(data / "test.h5"))["result"]
    for key in ("val_nmse", "test_nmse"):
        assert here[key] == pytest.approx(records["base"][key], rel=1e-5)
    tuned = tmp_path / "runs" / "tuned" / "model.h5"
    from mpnode.model import Model

    model = Model.load(tuned)
    assert model.spec.message_dim == 2  # the parent's, not the default 3
    # the model names the client's files, not the worker's copies
    assert model.attrs["finetuned_from"] == str(tmp_path / "runs" / "base" / "model.h5")
    assert model.attrs["trained_on"] == str(data / "train.h5")
    summary = (tmp_path / "summary.csv").read_text().splitlines()
    assert len(summary) == 3 and all(",completed," in row for row in summary[1:])
    # resumable: nothing is redone, nothing rewritten
    stamp = tuned.stat().st_mtime_ns
    again = []
    run_sweep(sweep, tmp_path, farm, progress=again.append)
    assert again == [] and tuned.stat().st_mtime_ns == stamp


@on_dask
def test_a_failing_run_is_reported_and_the_sweep_goes_on(data, farm, tmp_path):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "spoilt.h5").write_bytes((data / "train.h5").read_bytes())
    sweep = sweep_file(tmp_path / "in", "fail.toml", f"""
data = ["{data / 'train.h5'}"]
[train]
epochs = 2
[[run]]
name = "good"
[[run]]
name = "broken"
data = ["spoilt.h5"]
[[run]]
name = "child"
from = "broken"
""")
    # every file is checked when the sweep is read (a bad one stops it before any run: test_failures.py);
    # what can still fail is what changes afterwards: this file, spoilt once the sweep has started
    (tmp_path / "in" / "spoilt.h5").write_bytes((data / "bad.h5").read_bytes())
    tmp_path = tmp_path / "out"
    records = run_sweep(sweep, tmp_path, farm)
    assert records["good"]["status"] == "completed"
    assert records["broken"]["status"] == "failed" and "spoilt.h5" in records["broken"]["error"]
    assert records["child"]["status"] == "skipped"
    md = (tmp_path / "summary.md").read_text()
    assert "| broken | failed |" in md and "| good | completed |" in md
    assert not (tmp_path / "runs" / "broken").exists()


@on_dask
def test_a_killed_worker_costs_only_a_retry(data, farm, tmp_path):
    sweep = sweep_file(data, "kill.toml", """
data = ["train.h5"]
[train]
epochs = 100000
time_limit = "4s"
[grid]
seed = [0, 1]
""")
    client = farm.client
    pids = client.run(os.getpid)
    result = {}
    worker = threading.Thread(target=lambda: result.update(run_sweep(sweep, tmp_path, farm)))
    worker.start()
    deadline = time.monotonic() + 120
    while not any(client.processing().values()) and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.0)  # mid-training
    busy = next(addr for addr, tasks in client.processing().items() if tasks)
    os.kill(pids[busy], signal.SIGKILL)
    worker.join(timeout=300)
    assert not worker.is_alive()
    assert all(result[p.name]["status"] in FINISHED for p in sweep.runs), result
    client.wait_for_workers(2, timeout=60)  # the nanny restarted the killed one
    assert set(client.run(os.getpid).values()) != set(pids.values())


def test_sweep_command_on_the_local_pool(data, tmp_path):
    """The command without Dask: a failing run gives exit status 1 and a summary row; a rerun
    redoes only the failed run."""
    (tmp_path / "spoilt.h5").write_bytes((data / "train.h5").read_bytes())
    (tmp_path / "cli.toml").write_text(f'data = ["{data / "train.h5"}"]\n[train]\nepochs = 2\n'
                                       '[[run]]\nname = "good"\n[[run]]\nname = "broken"\ndata = ["spoilt.h5"]\n')
    out = tmp_path / "out"
    args = ["sweep", str(tmp_path / "cli.toml"), "-o", str(out), "--scheduler", "none", "--workers", "1"]

    def spoil():  # once the files are checked (the summary is written next): "broken" runs after "good"
        deadline = time.monotonic() + 300
        while not (out / "summary.csv").exists() and time.monotonic() < deadline:
            time.sleep(0.005)
        (tmp_path / "spoilt.h5").write_bytes((data / "bad.h5").read_bytes())

    spoiler = threading.Thread(target=spoil)
    spoiler.start()
    first = CliRunner().invoke(main, args)
    spoiler.join()
    assert first.exit_code == 1, first.output
    rows = (out / "summary.csv").read_text().splitlines()
    assert rows[1].startswith("good,completed,") and rows[2].startswith("broken,failed,")
    stamp = (out / "runs" / "good" / "model.h5").stat().st_mtime_ns
    (tmp_path / "spoilt.h5").write_bytes((data / "train.h5").read_bytes())  # mended: the rerun redoes "broken" only
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 0, again.output
    assert (out / "runs" / "good" / "model.h5").stat().st_mtime_ns == stamp
    assert (out / "summary.csv").read_text().splitlines()[2].startswith("broken,completed,")


@on_dask
def test_ctrl_c_leaves_every_finished_run_and_a_rerun_continues(data, farm, tmp_path):
    sweep = sweep_file(data, "stop.toml", 'data = ["train.h5"]\n[train]\nepochs = 2\n[grid]\nseed = [0, 1, 2]\n')

    def stop(record):
        raise KeyboardInterrupt  # as Ctrl-C in the client, right after the first run is written

    with pytest.raises(KeyboardInterrupt):
        run_sweep(sweep, tmp_path, farm, progress=stop)
    rows = (tmp_path / "summary.csv").read_text().splitlines()[1:]
    first = [r.split(",")[0] for r in rows if ",completed," in r]
    assert len(first) == 1 and (tmp_path / "runs" / first[0] / "model.h5").exists()
    redone = []
    records = run_sweep(sweep, tmp_path, farm, progress=redone.append)
    assert all(r["status"] == "completed" for r in records.values())
    assert first[0] not in [r["name"] for r in redone]


# ---- test points and resuming a killed training ----------------------------------------------
POINTS = """
data = ["train.h5"]
test = ["test.h5"]
[train]
epochs = 6
batch_size = 4
[[run]]
name = "base"
test_points = 3
[[run]]
name = "plain"
[[run]]
name = "tuned"
from = "base"
epochs = 4
test_points = 2
"""


def check_points(records, out):
    base, plain, tuned = (records[n] for n in ("base", "plain", "tuned"))
    assert [p["epoch"] for p in base["test_curve"]] == [0, 2, 4, 6] == point_epochs(6, 3)
    assert [p["epoch"] for p in tuned["test_curve"]] == [0, 2, 4] and plain["test_curve"] == []
    # the last point is the final model; a fine-tuned run's first point is its parent's model
    assert base["test_curve"][-1]["nmse"] == base["test_nmse"]
    assert tuned["test_curve"][0]["nmse"] == pytest.approx(base["test_nmse"], rel=1e-6)
    # each point's model is kept beside the run's; nothing of the training under way is left
    folder = out / "runs" / "base"
    assert sorted(os.listdir(folder)) == ["model.h5", "model.h5.log.jsonl", "points", "result.json"]
    for point in base["test_curve"]:
        assert Model.load(folder / point["model"]).attrs["epoch"] == point["best_epoch"]


def test_test_points_on_the_local_pool(data, tmp_path):
    """A run with test points trains in segments, its best model evaluated after each; the
    segments train exactly what one pass trains (the plateau schedule resumes bit for bit)."""
    sweep = sweep_file(data, "points.toml", POINTS)
    with open_executor(None, 2, one_thread=True) as farm:
        records = run_sweep(sweep, tmp_path, farm)
    check_points(records, tmp_path)
    a, b = (Model.load(tmp_path / "runs" / n / "model.h5") for n in ("base", "plain"))
    assert np.array_equal(a.theta, b.theta)


@on_dask
def test_test_points_on_dask(data, farm, tmp_path):
    """On Dask the run trains in a temporary folder and the worker sends the points' models back."""
    records = run_sweep(sweep_file(data, "points.toml", POINTS), tmp_path, farm)
    check_points(records, tmp_path)


def _default_sigint():
    """The command starts as from a terminal, Ctrl-C not ignored: an ignored SIGINT would be
    inherited from whatever the test process last did with it, and Python keeps it ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
@pytest.mark.parametrize("stop", [signal.SIGKILL, signal.SIGINT], ids=["killed", "ctrl-c"])
def test_a_stopped_sweep_resumes_its_half_finished_training(data, tmp_path, stop):
    """Killed mid-training (the command and its pool process at once), or stopped by Ctrl-C, a
    sweep run on the local pool continues from its checkpoint next time: the log keeps the epochs
    before it, byte for byte (a new start would rewrite them with other times), and the test
    points recorded stay."""
    (data / "long.toml").write_text('data = ["train.h5"]\ntest = ["test.h5"]\n[train]\nepochs = 4000\n'
                                    'checkpoint_seconds = 0.3\n[[run]]\nname = "long"\ntest_points = 4\n')
    out = tmp_path / "out"
    args = [sys.executable, "-c", "from cli.main import main; main()", "sweep", str(data / "long.toml"), "-o", str(out),
            "--scheduler", "none", "--workers", "1"]
    folder = out / "runs" / "long"
    log, state = folder / "model.h5.log.jsonl", state_path(folder / "model.h5")
    proc = subprocess.Popen(args, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=_default_sigint)
    try:
        # generous: in a cold-cache run of the suite the kernel warm-up may still hold both cores
        deadline, past = time.monotonic() + 1200, False
        while time.monotonic() < deadline and proc.poll() is None:  # past the first test point (epoch 1000)
            past = (folder / "points" / "epoch-1000.h5").exists() and os.path.exists(state) \
                and len(log.read_text().splitlines()) > 1100  # thousands of epochs before the end
            if past:
                break
            time.sleep(0.05)
        assert proc.poll() is None, "the sweep finished before it could be stopped: " + proc.stderr.read().decode()
        assert past, "the sweep did not pass epoch 1,100 in 1,200 s"
        os.killpg(proc.pid, stop)  # as Ctrl-C in a terminal reaches the command and its pool process
        assert proc.wait(timeout=120) == (130 if stop == signal.SIGINT else -signal.SIGKILL)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    with np.load(state) as checkpoint:
        resumed_at = int(checkpoint["epoch"])
    before = log.read_text().splitlines(keepends=True)
    points = {p: (folder / "points" / p).read_bytes() for p in os.listdir(folder / "points")}
    assert 1000 <= resumed_at < 4000 and not (folder / "result.json").exists()
    if stop == signal.SIGINT:  # the training saw Ctrl-C and saved its last finished epoch (or the one
        # before, when Ctrl-C came between that epoch's log line and its snapshot), not an older checkpoint
        assert resumed_at >= json.loads(before[-1])["epoch"] - 1

    again = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    res = json.loads((folder / "result.json").read_text())
    after = log.read_text().splitlines(keepends=True)
    assert res["status"] == "completed" and res["epochs"] == 4000
    assert [json.loads(line)["epoch"] for line in after] == list(range(4001))
    assert after[:resumed_at + 1] == before[:resumed_at + 1]  # kept, not trained again
    assert [p["epoch"] for p in res["test_curve"]] == [0, 1000, 2000, 3000, 4000]
    assert all((folder / "points" / p).read_bytes() == blob for p, blob in points.items())
