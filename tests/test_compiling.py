"""Compiling the kernels: the VJP compiled ahead in a process of its own, announced once, timed."""
import json
import os

import numba
import numpy as np
import pytest

from mpnode.base.graph import Graph
from mpnode.engine import compiling, forward, forward_with_vjp
from mpnode.model import Model


@pytest.fixture
def fresh_state(monkeypatch, tmp_path):
    """compiling's per-process memory emptied, its figures file in tmp_path, compiling ahead on."""
    monkeypatch.setenv(compiling.VARIABLE, "1")
    monkeypatch.setattr(compiling, "_known", set())
    monkeypatch.setattr(compiling, "_announced", set())
    monkeypatch.setattr(compiling, "_pending", {})
    monkeypatch.setattr(compiling, "_times_path", lambda: str(tmp_path / "seconds.json"))
    said = []
    monkeypatch.setattr(compiling, "_announce", said.append)
    return said


def _tiny_vjp():
    model = Model.create(state_dim=2, message_dim=2, hidden=4, dt=0.1)
    graph = Graph.from_edges(3, [(0, 1), (1, 2)])
    x, vjp = forward_with_vjp(model.spec, model.theta, np.zeros((3, 2), np.float32), graph, None, 2)
    return vjp(np.ones_like(x))


def test_a_driver_that_is_not_compiled_compiles_ahead_in_another_process_and_is_announced_once(
        fresh_state, monkeypatch):
    monkeypatch.setenv(compiling.VARIABLE, "0")  # an empty cache: compiled here, with the suite's warm-up
    _tiny_vjp()  # compiled or loaded here: the process started below then only loads the cache
    monkeypatch.setenv(compiling.VARIABLE, "1")
    monkeypatch.setattr(compiling, "_known", set())
    started = []
    popen = compiling.subprocess.Popen
    monkeypatch.setattr(compiling.subprocess, "Popen", lambda *a, **k: started.append(a[0]) or popen(*a, **k))
    monkeypatch.setattr(compiling, "is_compiled", lambda name, dtype, field: False)
    gtheta, gx0 = _tiny_vjp()
    assert len(started) == 1 and started[0][-3:] == ["float32", "vjp_blocks", "mpnode"]
    assert not compiling._pending  # the VJP waited for it
    assert fresh_state == [f"compiling the MP-NODE kernels for float32, once: ~{compiling.DEFAULT_SECONDS:.0f} s"]
    assert np.isfinite(gtheta).all() and np.abs(gtheta).sum() > 0
    seconds = json.loads(open(compiling._times_path()).read())
    assert set(seconds) == {"vjp_blocks"} and seconds["vjp_blocks"] > 0
    assert compiling.estimate() == seconds["vjp_blocks"]  # the next estimate is this machine's


def test_compiled_drivers_start_nothing_and_say_nothing(fresh_state, monkeypatch):
    _tiny_vjp()
    monkeypatch.setattr(compiling, "_known", set())
    monkeypatch.setattr(compiling.subprocess, "Popen", lambda *a, **k: pytest.fail("started a process"))
    assert compiling.is_compiled("vjp_blocks", np.float32) and compiling.is_compiled("rollout_blocks", np.float32)
    _tiny_vjp()
    assert fresh_state == []


def test_compiling_ahead_can_be_switched_off(fresh_state, monkeypatch):
    monkeypatch.setenv(compiling.VARIABLE, "0")
    monkeypatch.setattr(compiling, "is_compiled", lambda name, dtype, field: False)
    monkeypatch.setattr(compiling.subprocess, "Popen", lambda *a, **k: pytest.fail("started a process"))
    compiling.compile_vjp_ahead(np.float32, "vjp_blocks")
    assert not compiling._pending


def test_an_unreadable_figures_file_gives_the_default_estimate(fresh_state):
    with open(compiling._times_path(), "w") as f:
        f.write("not json")
    assert compiling.estimate() == compiling.DEFAULT_SECONDS


TINY = """
from numba import njit


@njit(cache=True)
def one_more(x):
    return x + 1
"""
WAITER = """
import sys
sys.path.insert(0, sys.argv[1])
from mpnode.engine import codegen, compiling
codegen.build_numba_codegen()  # the test's process built numba's generator so (its vector width is in the cache's key)
import lock_probe as tiny
tiny.one_more._cache = compiling._OneCompileEach(tiny.one_more._cache)
print("calling", flush=True)
tiny.one_more(1)
print(sum(tiny.one_more._cache_hits.values()), sum(tiny.one_more._cache_misses.values()), flush=True)
"""


@pytest.mark.skipif(os.name == "nt", reason="no fcntl: mpnode compiles everything in one process there")
def test_a_compile_under_way_elsewhere_is_waited_for_and_loaded_not_compiled_again(tmp_path, monkeypatch):
    import fcntl
    import importlib
    import subprocess
    import sys

    (tmp_path / "lock_probe.py").write_text(TINY)
    monkeypatch.syspath_prepend(str(tmp_path))
    tiny = importlib.import_module("lock_probe")
    shared = compiling._OneCompileEach(tiny.one_more._cache)
    os.makedirs(os.path.dirname(shared.prefix), exist_ok=True)
    with open(f"{shared.prefix}-{compiling._signature_key((numba.int64,))}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another process, compiling one_more(int64)
        waiter = subprocess.Popen([sys.executable, "-c", WAITER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
        assert waiter.stdout.readline() == "calling\n"
        with pytest.raises(subprocess.TimeoutExpired):
            waiter.wait(timeout=1.5)  # it waits for the lock
        assert tiny.one_more(1) == 2  # compiled here and saved to numba's cache, then the lock released
    hits, misses = map(int, waiter.communicate(timeout=60)[0].split())
    assert (hits, misses) == (1, 0) and waiter.returncode == 0


def test_a_rollout_no_vjp_follows_has_the_neighbour_sums_compiled_ahead(fresh_state, monkeypatch):
    started = []
    monkeypatch.setattr(compiling.subprocess, "Popen", lambda *a, **k: started.append(a[0]))
    monkeypatch.setattr(compiling, "is_compiled", lambda name, dtype, field: False)
    model = Model.create(state_dim=2, message_dim=2, hidden=4, dt=0.1)
    graph = Graph.from_edges(3, [(0, 1), (1, 2)])
    forward(model.spec, model.theta, np.zeros((3, 2), np.float32), graph, None, 2)
    assert [cmd[-3:] for cmd in started] == [["float32", "sums", "mpnode"]]


SUMS_THEN_ROLLOUT = """
import numpy as np
from mpnode.base.graph import Graph
from mpnode.engine import forward
from mpnode.engine.kernels import layers
from mpnode.engine.precompile import compile_sums
from mpnode.model import Model

compile_sums(np.float32)
print(len(layers.aggregate_tile._cache._cache_file._load_index()))
model = Model.create(state_dim=2, message_dim=3, hidden=4, dt=0.1)
ring = Graph.from_edges(40, [(i, (i + 1) % 40) for i in range(40)])
forward(model.spec, model.theta, np.zeros((40, 2), np.float32), ring, None, 2)
print(len(layers.aggregate_tile._cache._cache_file._load_index()))
"""


@pytest.mark.slow
def test_the_neighbour_sums_compiled_ahead_are_the_ones_a_rollout_calls(tmp_path):
    """precompile.compile_sums gives the sums the types the rollout gives them: a rollout after it,
    in an empty cache, compiles no second version of them (a compile of its own, about a minute)."""
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), **{compiling.VARIABLE: "0"})
    out = subprocess.run([sys.executable, "-c", SUMS_THEN_ROLLOUT], env=env, capture_output=True, text=True,
                         timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["1", "1"]  # aggregate_tile's cache index: one signature, then still one
