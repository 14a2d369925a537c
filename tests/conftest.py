"""Fixtures shared by the engine tests."""
import copy

import pytest

from mpnode.engine import kernels, rollout

DRIVER_ENTRY_POINTS = ("rollout_blocks", "rollout_stagewise", "vjp_blocks", "vjp_stagewise")


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
