"""What the tests share: fixtures, and the compiling of the kernels on both cores.

Fixtures (``pytest --fixtures tests`` lists them with their docstrings):
- ``tiny_linear``, ``tiny_file``, ``fresh``, ``prepared``: the tiny test system (two coupled
  damped oscillators, exact solution) as trajectories and as a trajectory file, an untrained
  model for it, and training data prepared from trajectories;
- ``driver``: run an engine test with each driver (block and stagewise) and check that it ran;
  ``driver_calls``: the drivers a test called.
Plain helpers for the engine tests (the NumPy reference, test graphs) are in engine_helpers.py.

Compiling the kernels on both cores.  With a cold numba cache (a fresh clone, or an edit to
mpnode/engine/kernels), compiling dominates the suite: each of the five drivers (rollout and
VJP, block and stagewise, and the block VJP that recomputes the stages) is compiled for float32
and for float64 and for each field (MP-NODE, L2S), and numba compiles one function at a time.
So the first call to a driver in this process (`_KernelWarmUp`) starts two processes of
tests/warm_kernels.py, which compile the drivers the default tier calls (`WARM_UP_JOBS`) into
numba's on-disk cache on one core each, waits for them, and goes on: numba then loads each driver
from the cache, as in any second run, so the tests run the very code they would have compiled
(same functions, same types, same flags).  With a warm cache the two processes only load it.
The warm-up cannot stall or change the suite: if a process fails, or has not finished after
WARM_UP_TIMEOUT, it is stopped and the tests compile what they need themselves, as without
it; the terminal summary says what happened.  The drivers are wrapped here for that only;
the wrapper passes every call through unchanged.  What it saves: docs/evidence/test-suite.md.

The two tiers: ``pytest`` runs the tests not marked ``slow`` (setup.cfg deselects them), each
meant to take at most DEFAULT_TIER_SECONDS; ``pytest -m slow`` runs the rest, slow by nature
(end-to-end runs of the docs and the paper suite, killed and resumed runs, Dask clusters), and the
tests of float32's stagewise drivers, whose compile no test of the default tier needs
(engine_helpers.DRIVERS_AND_DTYPES).  The terminal summary names any test outside the slow tier
that took longer.
"""
import copy
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from mpnode.base.graph import Graph
from mpnode.data import Trajectories, write_trajectories
from mpnode.engine import compiling, rollout
from mpnode.engine.codegen import ask_for_wide_vectors
from mpnode.model import Model
from mpnode.training import batches

DRIVER_ENTRY_POINTS = ("rollout_blocks", "rollout_stagewise", "vjp_blocks", "vjp_stagewise")
WARM_UP = Path(__file__).with_name("warm_kernels.py")
#: the two warm-up processes' jobs (tests/warm_kernels.py): the drivers the default tier calls, each
#: process about half the compile (docs/evidence/test-suite.md).  float32's block VJP that recomputes the
#: stages and its stagewise drivers are left out: no test of the tier calls them (engine_helpers.DRIVERS_AND_DTYPES).
WARM_UP_JOBS = (("float64:mpnode:stagewise", "float64:l2s:stagewise", "float64:mpnode:recompute",
                 "float64:l2s:recompute"),
                ("float64:mpnode:blocks", "float64:l2s:blocks", "float32:mpnode:blocks", "float32:l2s:blocks"))
#: seconds to wait for the warm-up processes: a safety net, several times what they take on a busy 2-core machine
WARM_UP_TIMEOUT = 900


class _KernelWarmUp:
    """Compile the drivers the tests call, in two processes at once, before the first driver call."""

    def __init__(self):
        self.pid = os.getpid()  # forked children (process pools) just call the kernels
        self.lock = threading.Lock()
        self.started = False
        self.report = None
        self.seconds = 0.0  # what the warm-up took, until the test it ran in is timed

    def wrap(self, fn):
        def call(*args, **kwargs):
            if not self.started and os.getpid() == self.pid:
                self.run_once()
            return fn(*args, **kwargs)

        return call

    def run_once(self):
        with self.lock:
            if not self.started:
                self.started = True
                t0 = time.perf_counter()
                done, failed = self.compile_both()
                self.seconds = time.perf_counter() - t0
                took = f"{self.seconds:.0f} s"
                self.report = (f"numba warm-up: drivers compiled or loaded in {took} ({', '.join(done)})" if not failed
                               else f"numba warm-up FAILED after {took} ({'; '.join(failed)}): the tests compiled "
                                    "what they needed themselves")

    def compile_both(self):
        """Run tests/warm_kernels.py for each list of jobs at once: (what each printed last, what went wrong)."""
        done, failed = [], []
        with tempfile.TemporaryDirectory() as tmp:
            procs = {}
            try:
                for k, jobs in enumerate(WARM_UP_JOBS):
                    log = open(os.path.join(tmp, f"{k}.log"), "w+")
                    command = [sys.executable, str(WARM_UP), *jobs]
                    procs[f"process {k + 1}"] = (subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log,
                                                                  stderr=log), log)
                deadline = time.monotonic() + WARM_UP_TIMEOUT
                for name, (proc, log) in procs.items():
                    try:
                        status = proc.wait(timeout=max(0.0, deadline - time.monotonic()))
                        problem = f"exit status {status}" if status else None
                    except subprocess.TimeoutExpired:
                        problem = f"still running after {WARM_UP_TIMEOUT} s, stopped"
                    log.seek(0)
                    last = (log.read().strip().splitlines() or ["no output"])[-1]
                    if problem:
                        failed.append(f"{name}: {problem}: {last}")
                    else:
                        done.append(f"{name}: {last}")
            finally:
                for proc, log in procs.values():
                    if proc.poll() is None:
                        proc.kill()
                        proc.wait()
                    log.close()
        return done, failed


_warm_up = _KernelWarmUp()


def pytest_configure(config):
    # the kernels compiled as the `mpnode` command compiles them (mpnode.engine.codegen), so that the
    # suite, its warm-up and the commands it starts share one set of compiled code
    ask_for_wide_vectors()
    # the warm-up compiles ahead every driver the default tier calls (WARM_UP_JOBS), so neither its tests nor
    # the commands they start compile a VJP in a process of their own (tests/test_compiling.py switches it
    # back on); the slow tier's float32 stagewise cases compile theirs in this process
    os.environ[compiling.VARIABLE] = "0"
    from mpnode.engine import kernels

    for name in DRIVER_ENTRY_POINTS:
        setattr(kernels, name, _warm_up.wrap(getattr(kernels, name)))


#: seconds a test of the default tier may take (its setup and teardown included, the kernel warm-up
#: not); a slower one is shrunk or marked ``@pytest.mark.slow`` (setup.cfg: run by ``pytest -m slow``)
DEFAULT_TIER_SECONDS = 15
_took = {}  # nodeid -> seconds, for the tests not marked slow


def pytest_runtest_logreport(report):
    if "slow" in report.keywords:
        return
    took, _warm_up.seconds = report.duration - _warm_up.seconds, 0.0
    _took[report.nodeid] = _took.get(report.nodeid, 0.0) + took


def pytest_terminal_summary(terminalreporter):
    if _warm_up.report:
        terminalreporter.write_line(_warm_up.report)
    over = sorted(((s, n) for n, s in _took.items() if s > DEFAULT_TIER_SECONDS), reverse=True)
    if over:
        terminalreporter.write_line(f"{len(over)} tests outside the slow tier took over {DEFAULT_TIER_SECONDS} s "
                                    "(shrink them, or mark them @pytest.mark.slow):", yellow=True)
        for seconds, nodeid in over:
            terminalreporter.write_line(f"  {seconds:.0f} s {nodeid}")


# ---------------------------------------------------------------------------
# Which driver ran
# ---------------------------------------------------------------------------
def _spy(fn, name, calls):
    def wrapper(*args, **kwargs):
        calls.append(name)
        return fn(*args, **kwargs)

    return wrapper


@pytest.fixture
def driver_calls(monkeypatch):
    """The names of the kernel drivers the test called, in order (a spy on each entry point)."""
    from mpnode.engine import kernels

    calls = []
    for name in DRIVER_ENTRY_POINTS:
        monkeypatch.setattr(kernels, name, _spy(getattr(kernels, name), name, calls))
    return calls


@pytest.fixture(params=["blocks", "stagewise"])
def driver(request, monkeypatch, driver_calls):
    """Run the test with the given driver; afterwards check that only that driver ran."""
    if request.param == "stagewise":
        real_plan_for = rollout.plan_for

        def stagewise_plan(*args, **kwargs):
            plan = copy.copy(real_plan_for(*args, **kwargs))  # a copy: the real one is cached
            plan.blocks = None
            return plan

        monkeypatch.setattr(rollout, "plan_for", stagewise_plan)
    yield request.param
    assert driver_calls, "no driver ran"
    assert all(c.endswith(request.param) for c in driver_calls), \
        f"expected the {request.param} driver, ran {driver_calls}"


# ---------------------------------------------------------------------------
# The tiny test system: two damped oscillators coupled by a spring
# ---------------------------------------------------------------------------
def _tiny_linear(B=24, T=10, dt=0.1, seed=0, offset=0.0):
    A = np.array([[-0.1, 1.0], [-1.0, -0.1]])
    k = 0.5
    M = scipy.linalg.block_diag(A, A)
    M[0, 0] -= k
    M[0, 2] += k
    M[2, 2] -= k
    M[2, 0] += k
    E = scipy.linalg.expm(M * dt)
    rng = np.random.default_rng(seed)
    x = np.empty((B, T + 1, 4))
    x[:, 0] = rng.uniform(-1, 1, (B, 4))
    for t in range(T):
        x[:, t + 1] = x[:, t] @ E.T
    return Trajectories(x=x.reshape(B, T + 1, 2, 2) + offset, graphs=[Graph.from_edges(2, [(0, 1)])], dt=dt,
                        system="tiny_linear")


@pytest.fixture
def tiny_linear():
    """tiny_linear(B=24, T=10, dt=0.1, seed=0, offset=0.0) -> Trajectories of the tiny system.

    Two damped oscillators coupled by a spring on their first coordinate, sampled from the
    exact solution: x (B, T+1, 2, 2), node i has (position, velocity), dx/dt = A x_i +
    k (x_j - x_i) on the position; initial states uniform in [-1, 1] drawn from ``seed``.
    """
    return _tiny_linear


@pytest.fixture
def tiny_file(tiny_linear):
    """tiny_file(path, **tiny_linear's options) -> str(path), the tiny system's trajectories written there."""
    def write(path, **kw):
        write_trajectories(path, tiny_linear(**kw))
        return str(path)

    return write


@pytest.fixture
def fresh():
    """fresh(seed=0, hidden=16) -> an untrained float32 Model for the tiny system (dx 2, messages of 3, dt 0.1)."""
    def create(seed=0, hidden=16):
        return Model.create(2, 0, message_dim=3, hidden=hidden, dt=0.1, seed=seed)

    return create


@pytest.fixture
def prepared():
    """prepared(model, datasets, config) -> (train parts, val parts, split) of ``datasets`` under
    ``config``, ``model``'s normalisation set as training sets it."""
    def prepare(model, datasets, config):
        data = batches.TrainingData(datasets, config)
        return (*data.parts(model, config.norm), data.split)

    return prepare
