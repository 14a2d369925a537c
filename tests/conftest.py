"""Fixtures shared by the tests, and the compilation of the kernels on both cores.

Compiling the kernels on both cores.  With a cold numba cache, compiling dominates the suite:
each of the four drivers (mpnode.engine.kernels: rollout and VJP, block and stagewise) is
compiled for float32 and float64, one function at a time, about a minute and a half per dtype
on this project's 2-core machine.  So the first call to a driver in this process
(`_KernelWarmUp`) starts two processes, tests/warm_kernels.py float64 and float32, which compile
the drivers into numba's on-disk cache on one core each, waits for them, and goes on: numba
then loads each driver from the cache, as in any second run, so the tests run the very code
they would have compiled (same functions, same types, same flags).  With a warm cache the two
processes only load it (a second or two).  The warm-up cannot stall or change the suite: if a
process fails, or has not finished after WARM_UP_TIMEOUT, it is stopped and the tests compile
what they need themselves, as without it; the terminal summary says what happened.  The
drivers are wrapped here for that only; the wrapper passes every call through unchanged.
"""
import copy
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from mpnode.engine import kernels, rollout

DRIVER_ENTRY_POINTS = ("rollout_blocks", "rollout_stagewise", "vjp_blocks", "vjp_stagewise")
WARM_UP = Path(__file__).with_name("warm_kernels.py")
#: seconds to wait for the warm-up processes (a safety net: on a loaded 2-core machine they take ~3 minutes)
WARM_UP_TIMEOUT = 900


class _KernelWarmUp:
    """Compile the drivers of both dtypes at once, in two processes, before the first driver call."""

    def __init__(self):
        self.pid = os.getpid()  # forked children (process pools) just call the kernels
        self.lock = threading.Lock()
        self.started = False
        self.report = None

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
                failed = self.compile_both()
                took = f"{time.perf_counter() - t0:.0f} s"
                self.report = (f"numba warm-up: float64 and float32 drivers compiled or loaded in {took}" if not failed
                               else f"numba warm-up FAILED after {took} ({'; '.join(failed)}): the tests compiled "
                                    "what they needed themselves")

    def compile_both(self):
        """Run tests/warm_kernels.py for each dtype at once; a list of what went wrong."""
        failed = []
        with tempfile.TemporaryDirectory() as tmp:
            procs = {}
            try:
                for dtype in ("float64", "float32"):
                    log = open(os.path.join(tmp, dtype + ".log"), "w+")
                    procs[dtype] = (subprocess.Popen([sys.executable, str(WARM_UP), dtype, os.path.join(tmp, "lock")],
                                                     stdin=subprocess.DEVNULL, stdout=log, stderr=log), log)
                deadline = time.monotonic() + WARM_UP_TIMEOUT
                for dtype, (proc, log) in procs.items():
                    try:
                        status = proc.wait(timeout=max(0.0, deadline - time.monotonic()))
                        problem = f"exit status {status}" if status else None
                    except subprocess.TimeoutExpired:
                        problem = f"still running after {WARM_UP_TIMEOUT} s, stopped"
                    if problem:
                        log.seek(0)
                        last = (log.read().strip().splitlines() or ["no output"])[-1]
                        failed.append(f"{dtype}: {problem}: {last}")
            finally:
                for proc, log in procs.values():
                    if proc.poll() is None:
                        proc.kill()
                        proc.wait()
                    log.close()
        return failed


_warm_up = _KernelWarmUp()


def pytest_configure(config):
    for name in DRIVER_ENTRY_POINTS:
        setattr(kernels, name, _warm_up.wrap(getattr(kernels, name)))


def pytest_terminal_summary(terminalreporter):
    if _warm_up.report:
        terminalreporter.write_line(_warm_up.report)


def _spy(fn, name, calls):
    def wrapper(*args, **kwargs):
        calls.append(name)
        return fn(*args, **kwargs)

    return wrapper


@pytest.fixture(params=["blocks", "stagewise"])
def driver(request, monkeypatch):
    """Run the test with the given driver; afterwards check that only that driver ran."""
    calls = []
    for name in DRIVER_ENTRY_POINTS:
        monkeypatch.setattr(kernels, name, _spy(getattr(kernels, name), name, calls))
    if request.param == "stagewise":
        real_plan_for = rollout.plan_for

        def stagewise_plan(*args, **kwargs):
            plan = copy.copy(real_plan_for(*args, **kwargs))  # a copy: the real one is cached
            plan.blocks = None
            return plan

        monkeypatch.setattr(rollout, "plan_for", stagewise_plan)
    yield request.param
    assert calls, "no driver ran"
    assert all(c.endswith(request.param) for c in calls), f"expected the {request.param} driver, ran {calls}"
