"""Hard cases for the reference simulators, each test stating the property that must hold.

* chaotic Lorenz over a long horizon (T = 400 steps of dt = 0.05, 20 time units): the data do
  not depend on the solver tolerance over the predictable horizon, and the tolerance-induced
  difference grows at the Lorenz Lyapunov rate (~0.9), which says where predictability ends;
* the coupled pendulum next to its singularity (|theta| -> pi/2): the generator re-draws or
  refuses, it never writes a state with |cos theta| < 1e-6;
* gene regulation with large initial values and on its stiff side (large b): the generator
  notices stiffness, switches to Radau, records it, and still matches a tight reference.

Measured when these tests were written (lorenz3 scene, seeds 0..5, DOP853):
  relative difference (||x - x_ref|| / ||x_ref|| over all nodes) first exceeds 1e-6 at
  t = 9.5 .. 11.5 for rtol = atol = 1e-7 and at t = 15.8 .. 18.1 for the default 1e-9 (the
  reference being 1e-11 / 1e-13); the growth rate of log(difference) over t in [10, 20],
  averaged over trajectories, is 0.77 .. 0.81 (0.87 .. 0.90 over [12, 20]: the rate approaches
  the maximal Lyapunov exponent 0.906 once the early, locally injected errors have aligned with
  the unstable direction).  So 1e-9 data are good to 1e-6 for ~16 time units (~14 Lyapunov
  times); extrapolating at 0.9 the difference reaches O(1) -- predictability ends -- near
  t ~ 17 + ln(1e6)/0.9 ~ 32, beyond the 20 time units of T = 400.
"""
import importlib
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from data_gen import BUILTIN, generate, make_rhs
from data_gen.simulate import (
    FALLBACK_METHOD,
    STIFF_NFEV_PER_STEP,
    StiffnessDetected,
    integrate,
    integrate_switching,
    simulate,
)
from data_gen.systems import PENDULUM_COS_MIN, SYSTEMS
from mpnode.base.errors import NumericalError
from mpnode.data import read_trajectories, write_trajectories

# the module (the package attribute `simulate` is the function of that name)
simulate_module = importlib.import_module("data_gen.simulate")
LYAPUNOV_LORENZ = 0.906  # maximal Lyapunov exponent of sigma=10, rho=28, beta=8/3


# ---- chaotic Lorenz, long horizon ----------------------------------------------------------
def relative_difference(x, ref):
    """||x(t) - ref(t)|| / ||ref(t)|| over all nodes and coordinates, shape (T+1,)."""
    return np.sqrt(((x - ref) ** 2).sum(axis=(-2, -1))) / np.sqrt((ref ** 2).sum(axis=(-2, -1)))


@pytest.fixture(scope="module")
def lorenz_long():
    """lorenz3 at T = 400 (20 time units): the generator's data (1e-9) and re-integrations at 1e-7, 1e-11."""
    t = generate(replace(BUILTIN["lorenz3"], trajectories=6, horizon=400), workers=2)
    f = make_rhs("lorenz", {**t.attrs, **t.params}, t.graphs[0])
    runs = {tol: np.stack([integrate(f, t.x[b, 0], t.horizon, t.dt, rtol=tol, atol=tol)
                           for b in range(t.n_trajectories)]) for tol in (1e-7, 1e-11)}
    runs[1e-9] = t.x
    times = np.arange(t.horizon + 1) * t.dt
    return t, times, runs


def test_lorenz_default_tolerance_is_what_the_file_says(lorenz_long):
    t, _, runs = lorenz_long
    assert t.attrs["rtol"] == t.attrs["atol"] == 1e-9 and t.attrs["integrator"] == "DOP853"
    assert t.attrs["fallback_used"] == 0  # chaotic is not stiff: DOP853 throughout
    assert t.x.shape == (6, 401, 3, 3)


def test_lorenz_is_tolerance_independent_over_the_predictable_horizon(lorenz_long):
    """Property: 1e-9 (the default) and 1e-11 agree to 1e-6 relative for t <= 12 (~11 Lyapunov times).

    12 is chosen from the measured crossing times of 1e-6 (15.8 .. 18.1, module docstring)
    with a margin of ~4 time units (a factor e^(0.9*4) ~ 40 in the difference).
    """
    _, times, runs = lorenz_long
    d9 = relative_difference(runs[1e-9], runs[1e-11])  # (B, T+1)
    d7 = relative_difference(runs[1e-7], runs[1e-11])
    horizon = 12.0
    early = times <= horizon
    assert d9[:, early].max() < 1e-6, d9[:, early].max()
    # ... and the coarse 1e-7 run is good to 1e-6 for a shorter while (about 5 time units less)
    assert d7[:, times <= 7.0].max() < 1e-6, d7[:, times <= 7.0].max()
    # where each curve leaves 1e-6: later for the tighter tolerance, by about ln(100)/lambda
    cross9 = np.array([times[np.argmax(d > 1e-6)] if (d > 1e-6).any() else times[-1] for d in d9])
    cross7 = np.array([times[np.argmax(d > 1e-6)] for d in d7])
    print(f"\nLorenz: 1e-6 agreement horizon 1e-7: {cross7.min():.2f}..{cross7.max():.2f}, "
          f"1e-9: {cross9.min():.2f}..{cross9.max():.2f} time units")
    assert cross9.min() > horizon
    shift = np.median(cross9 - cross7)
    expected = np.log(100.0) / LYAPUNOV_LORENZ  # 5.1: a factor 100 in tolerance buys ln(100)/lambda
    assert 0.5 * expected < shift < 2.0 * expected, shift


def test_lorenz_difference_grows_at_the_lyapunov_rate(lorenz_long):
    """Property: log(difference) grows at ~0.9 per time unit (band 0.6 .. 1.3) over t in [10, 20].

    The slope is fitted to the mean over trajectories of log(difference), in the window after
    the early error-accumulation transient and while the difference is still far from O(1).
    """
    _, times, runs = lorenz_long
    window = times >= 10.0
    rates = {}
    for tol in (1e-7, 1e-9):
        d = relative_difference(runs[tol], runs[1e-11])[:, window]
        assert d.max() < 0.1  # not saturated: the measurement is of growth, not of the attractor's size
        rates[tol] = np.polyfit(times[window], np.log(d).mean(axis=0), 1)[0]
        d_end = d[:, -1]
        ends = times[-1] + np.log(1.0 / d_end) / LYAPUNOV_LORENZ
        print(f"\nLorenz rtol={tol:g}: growth rate {rates[tol]:.3f} per time unit; "
              f"difference {d_end.min():.1e}..{d_end.max():.1e} at t = 20, O(1) (predictability ends) "
              f"near t = {ends.min():.0f}..{ends.max():.0f}")
        assert 0.6 < rates[tol] < 1.3, rates


# ---- the coupled pendulum next to its singularity -------------------------------------------
def near_pi_2(rng, system, n_nodes):
    """theta within 0.2 of +-pi/2 (many of these fall through the singularity), omega as the spec."""
    theta = (np.pi / 2 - rng.uniform(1e-6, 0.2, n_nodes)) * rng.choice([-1.0, 1.0], n_nodes)
    return np.stack([theta, rng.uniform(-0.5, 0.5, n_nodes)], axis=1)


def at_pi_2(rng, system, n_nodes):
    """theta just past the singularity: every trajectory must be refused."""
    theta = (np.pi / 2 - rng.uniform(0.0, 1e-7, n_nodes))
    return np.stack([theta, rng.uniform(2.0, 3.0, n_nodes)], axis=1)


def pendulum_scene(**kw):
    return replace(BUILTIN["coupled_pendulum"], **{"trajectories": 12, "horizon": 50, **kw})


def test_pendulum_near_singularity_redraws_and_saves_only_valid_states(tmp_path, monkeypatch):
    """Property: every saved state has |cos theta| >= 1e-6, and `redrawn` is the exact number of
    initial states that were thrown away (replayed from each trajectory's own seed)."""
    monkeypatch.setattr(simulate_module, "get_sampler", lambda *a: near_pi_2)
    scene = pendulum_scene()
    path = tmp_path / "p.h5"
    write_trajectories(path, generate(scene, workers=1, max_tries=50))
    t = read_trajectories(path)
    assert np.all(np.abs(np.cos(t.x[..., 0])) >= PENDULUM_COS_MIN)
    assert np.all(np.isfinite(t.x))
    f = make_rhs("coupled_pendulum", t.attrs, t.graphs[0])
    guard = SYSTEMS["coupled_pendulum"].guard
    replayed = 0
    for b in range(t.n_trajectories):
        rng = np.random.default_rng(np.random.SeedSequence(scene.seed, spawn_key=(b,)))
        while True:
            x0 = near_pi_2(rng, SYSTEMS["coupled_pendulum"], 2)
            if np.array_equal(x0, t.x[b, 0]):
                break
            with pytest.raises(NumericalError):  # a thrown-away state really fails
                integrate_switching(f, x0, t.horizon, t.dt, guard=guard)
            replayed += 1
            assert replayed <= t.attrs["redrawn"]
    assert replayed == t.attrs["redrawn"] > 0
    print(f"\npendulum near pi/2: {t.attrs['redrawn']} re-draws for {t.n_trajectories} trajectories, "
          f"min |cos theta| saved = {np.abs(np.cos(t.x[..., 0])).min():.2e}")


def test_pendulum_at_singularity_is_refused_and_nothing_is_written(tmp_path, monkeypatch):
    """Property: when no initial state works the generator stops with a clear error, no file."""
    monkeypatch.setattr(simulate_module, "get_sampler", lambda *a: at_pi_2)
    with pytest.raises(NumericalError, match="failed for 4 initial states"):
        generate(pendulum_scene(trajectories=2, horizon=20), workers=1, max_tries=4)
    out = tmp_path / "p.h5"
    r = CliRunner().invoke(main, ["generate", "coupled_pendulum", "-o", str(out), "-B", "2", "--workers", "1"])
    assert r.exit_code == 3, r.output
    assert "coupled_pendulum: trajectory 0 failed for 10 initial states" in r.stderr
    assert "Traceback" not in r.output and not out.exists() and list(tmp_path.iterdir()) == []


# ---- gene: large initial values, and the stiff side -------------------------------------------
def hundreds(rng, system, n_nodes):
    """Gene initial state uniform(100, 500) per node (the spec's sampler draws from (0, 50))."""
    return rng.uniform(100.0, 500.0, size=(n_nodes, 1))


def gene_run(b, B=3, T=50, **kw):
    graph = BUILTIN["gene16_ba"].graph.build()[0]
    params = dict(b=b, f=1.0, h=2.0)
    x, redraws, fallback = simulate("gene", params, [graph], np.zeros(B, int), hundreds, T, 0.05, 0,
                                    return_fallback=True, **kw)
    return x, redraws, fallback, make_rhs("gene", params, graph)


def test_gene_large_initial_values_are_not_stiff():
    """Property: with the spec's b = 1 large states only decay at rate 1: DOP853 keeps them, and
    the data match a tight Radau reference."""
    x, redraws, fallback, f = gene_run(1.0, workers=1)
    assert not fallback.any() and not redraws.any()
    for b in range(len(x)):
        ref = integrate(f, x[b, 0], 50, 0.05, "Radau", rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(x[b], ref, rtol=1e-7, atol=1e-7)


def test_gene_stiff_side_switches_to_radau_and_matches_a_tight_reference():
    """The stiff case: b = 1e4.  Each x_i decays at rate b (Jacobian diagonal -b f x^(f-1) = -1e4)
    while the saved states are dt = 0.05 apart, so the fast mode is 500 times faster than the
    sampling: an explicit method is held to steps of ~3.3/b by stability, not accuracy (DOP853
    needs ~47 000 RHS evaluations for T = 50, ~950 per saved step).  Radau takes the same
    trajectory in a few thousand (most of them finite-difference Jacobian columns).

    Property: the switch fires for every trajectory (budget 200 evaluations per saved step),
    the trajectory is integrated with Radau from the same initial state, and it matches a
    Radau rtol = atol = 1e-12 reference to 1e-8 absolute (the states fall from hundreds to ~0).
    """
    x, redraws, fallback, f = gene_run(1e4, B=2, workers=2)  # a trajectory for each worker
    assert fallback.all() and not redraws.any()
    x0 = x[0, 0]
    with pytest.raises(StiffnessDetected, match="more than"):
        integrate(f, x0, 50, 0.05, "DOP853", max_nfev=STIFF_NFEV_PER_STEP * 50)
    for b in range(len(x)):
        assert 100 <= x[b, 0].min() and x[b, 0].max() <= 500
        ref = integrate(f, x[b, 0], 50, 0.05, "Radau", rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(x[b], ref, rtol=0, atol=1e-8)
    # the switch is per trajectory and reproducible: same result with one worker, the same initial states
    x1, _, fallback1, _ = gene_run(1e4, B=2, workers=1)
    np.testing.assert_array_equal(x1, x)
    np.testing.assert_array_equal(fallback1, fallback)


def test_gene_stiff_scene_records_the_fallback_in_the_file(tmp_path):
    """Property: the file says which trajectories used which method, enough to re-integrate each."""
    scene = replace(BUILTIN["gene16_ba"], trajectories=3, horizon=20, params={"b": 1e4})
    path = tmp_path / "stiff.h5"
    write_trajectories(path, generate(scene, workers=1))
    t = read_trajectories(path)
    assert t.attrs["integrator"] == "DOP853" and t.attrs["fallback_integrator"] == FALLBACK_METHOD
    assert t.attrs["fallback_used"] == 3 and t.attrs["stiff_nfev_per_step"] == STIFF_NFEV_PER_STEP
    np.testing.assert_array_equal(t.aux["integrator_fallback"], [1, 1, 1])
    f = make_rhs("gene", {**t.attrs, **t.params}, t.graphs[0])
    for b in range(t.n_trajectories):
        method = t.attrs["fallback_integrator"] if t.aux["integrator_fallback"][b] else t.attrs["integrator"]
        again = integrate(f, t.x[b, 0], t.horizon, t.dt, method, t.attrs["rtol"], t.attrs["atol"])
        np.testing.assert_allclose(again, t.x[b], rtol=0, atol=1e-12)
    # the non-stiff default records that nobody needed the fallback
    plain = generate(replace(BUILTIN["gene16_ba"], trajectories=3, horizon=20), workers=1)
    assert plain.attrs["fallback_used"] == 0 and not plain.aux["integrator_fallback"].any()


def test_step_size_collapse_counts_as_stiffness():
    """Property: an explicit solver giving up (status -1, step-size collapse) triggers the switch;
    if the implicit method fails too the trajectory fails (NumericalError: it is re-drawn).

    y' = y^2, y(0) = 1 blows up at t = 1: every method's step size collapses there.
    """
    def blow_up(t, y):
        return y ** 2

    with pytest.raises(StiffnessDetected, match="gave up"):
        integrate(blow_up, [[1.0]], 40, 0.05, "DOP853", max_nfev=10**7)
    with pytest.raises(NumericalError) as e:
        integrate_switching(blow_up, [[1.0]], 40, 0.05, "DOP853")
    assert not isinstance(e.value, StiffnessDetected)  # the message is Radau's own failure
