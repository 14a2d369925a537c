"""quadrotor_load (data_gen/quadrotor.py) against the quadrotor specification (docs/systems.md): statics, conservation
laws, free fall, the doorway controller and the generated files."""
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from data_gen import BUILTIN, generate
from data_gen import quadrotor as Q
from data_gen.graphs import GraphSpec
from data_gen.scenes import check_scene
from mpnode.base.errors import InputError
from mpnode.base.graph import Graph
from mpnode.data import read_trajectories, write_trajectories

TOL = dict(method="LSODA", rtol=1e-9, atol=1e-9)  # the scenes' integrator


@pytest.fixture(scope="module")
def physics():
    return Q.Physics()


def random_state(rng, n, spread=1.6):
    """Quadrotors scattered about a load, random unit quaternions, velocities and rates: (13 n + 6,)."""
    x = np.zeros((n, 13))
    x[:, 0:3] = rng.normal(0, spread, (n, 3))
    q = rng.normal(size=(n, 4))
    x[:, 3:7] = q / np.linalg.norm(q, axis=1, keepdims=True)
    x[:, 7:10] = rng.normal(0, 1, (n, 3))
    x[:, 10:13] = rng.normal(0, 2, (n, 3))
    return Q.pack(x, np.r_[rng.normal(0, 0.3, 3), rng.normal(0, 1, 3)])


# ---- physics by hand -----------------------------------------------------------------
def test_one_quadrotor_by_hand(physics):
    # load far below on a taut cable: l = 2, dl/dt = 0 -> s = 500 * 0.45 = 225 N straight down
    x = np.zeros((1, 13))
    x[0, 3] = 1.0
    y = Q.pack(x, [0, 0, -2.0, 0, 0, 0])
    F = np.array([[1.0, 2.0, 3.0, 4.0]])
    dy = physics.rhs(0.0, y, F)
    np.testing.assert_allclose(dy[7:10], [0, 0, -9.81 + (10.0 - 225.0) / 1.0], atol=1e-12)
    # tau = [L (F2 - F4), L (F3 - F1), k_m (F1 - F2 + F3 - F4)] / J
    tau = np.array([0.175 * -2.0, 0.175 * 2.0, 0.0245 * -2.0])
    np.testing.assert_allclose(dy[10:13], tau / np.array(Q.J_DIAG), rtol=1e-13)
    np.testing.assert_allclose(dy[13 + 3:13 + 6], [0, 0, -9.81 + 225.0 / 0.9], rtol=1e-13)
    # a cable shorter than d, or one being compressed fast, carries nothing (tension only)
    assert physics.tensions(Q.pack(x, [0, 0, -1.0, 0, 0, 0]), 1)[0] == 0.0
    assert physics.tensions(Q.pack(x, [0, 0, -1.56, 0, 0, 1.0]), 1)[0] == 0.0  # 5 - 10 < 0


def test_rotor_mixer_inverts():
    M = Q.mixer(0.175, 0.0245)
    F = np.array([1.0, 2.0, 3.0, 4.5])
    np.testing.assert_allclose(M @ F, [10.5, 0.175 * (2 - 4.5), 0.175 * (3 - 1), 0.0245 * (1 - 2 + 3 - 4.5)])
    np.testing.assert_allclose(np.linalg.solve(M, M @ F), F)


def test_attitude_gains_put_the_sampled_poles_where_asked(physics):
    # theta'' = a held over dt, a = -kp theta - kd omega sampled: both eigenvalues at att_pole
    dt = 0.1
    c = Q.Controller(3, None, physics, Q.CONTROL, dt)
    Phi, Gam = np.array([[1, dt], [0, 1]]), np.array([[dt * dt / 2], [dt]])
    A = Phi - Gam @ np.array([[c.kp_att, c.kd_att]])
    np.testing.assert_allclose(np.abs(np.linalg.eigvals(A)), Q.CONTROL["att_pole"], atol=1e-6)


# ---- statics -------------------------------------------------------------------------
@pytest.mark.parametrize("n", [3, 6])
def test_static_equilibrium_stays_put(physics, n):
    x0, load0, F, s = Q.static_equilibrium(n, [0.2, -0.1, 0.25], physics)
    a = math.asin(1.2 / 1.55)
    np.testing.assert_allclose(s, 0.9 * 9.81 / (n * math.cos(a)), rtol=1e-12)  # m_L g / (n cos a)
    l = np.linalg.norm(x0[:, 0:3] - load0[:3], axis=1)
    np.testing.assert_allclose(l, 1.55 + s / 500.0, rtol=1e-14)  # stretched by s / k_c
    np.testing.assert_allclose(x0[:, 2] - load0[2], (1.55 + s / 500) * math.cos(a), rtol=1e-14)
    assert np.all(F > 0) and np.all(F < 4.66)
    dy = physics.rhs(0.0, Q.pack(x0, load0), F)
    assert np.max(np.abs(dy)) < 1e-12
    x, load = Q.open_loop(physics, x0, load0, np.repeat(F[None], 50, axis=0), 0.1, **TOL)  # 5 s, constant thrusts
    assert np.max(np.abs(x - x0)) < 1e-6 and np.max(np.abs(load - load0)) < 1e-6
    np.testing.assert_allclose(np.linalg.norm(x[..., 3:7], axis=-1), 1.0, atol=1e-14)


def test_fan_statics_hold_too(physics):
    u = Q.fan_directions(3, 1.2, 1.55, 50.0)
    x0, load0, F, s = Q.static_equilibrium(3, [3, 0, 0.25], physics, directions=u)
    assert np.all(s > 0)
    assert np.max(np.abs(physics.rhs(0.0, Q.pack(x0, load0), F))) < 1e-12


# ---- conservation laws ---------------------------------------------------------------
def test_momentum_changes_only_by_gravity_and_thrust_pointwise(physics):
    rng = np.random.default_rng(0)
    for n in (1, 3, 6):
        for _ in range(20):
            y = random_state(rng, n)
            F = rng.uniform(0, 4.66, (n, 4))
            dy = physics.rhs(0.0, y, F)
            quads = dy[:13 * n].reshape(n, 13)
            dP = physics.m_q * quads[:, 7:10].sum(axis=0) + physics.m_L * dy[13 * n + 3:]
            np.testing.assert_allclose(dP, physics.external_force(y, F), rtol=0, atol=1e-10)


def test_momentum_changes_only_by_gravity_and_thrust_integrated(physics):
    # tumbling quadrotors on taut and slack cables, 0.5 s: P(t1) - P(t0) = integral of the external forces
    rng = np.random.default_rng(1)
    n = 3
    x0, load0, _, _ = Q.static_equilibrium(n, [0, 0, 0], physics)
    x0[:, 10:13] = rng.normal(0, 3, (n, 3))
    x0[:, 7:10] = rng.normal(0, 0.5, (n, 3))
    y0 = Q.pack(x0, load0)
    F = rng.uniform(1, 4.66, (n, 4))
    sol = solve_ivp(physics.rhs, (0, 0.5), y0, method="Radau", rtol=1e-11, atol=1e-11, args=(F,),
                    dense_output=True)
    assert sol.status == 0
    nodes, weights = np.polynomial.legendre.leggauss(40)
    impulse = np.zeros(3)
    for piece in range(50):  # composite Gauss-Legendre on 10 ms pieces
        a, b = piece * 0.01, (piece + 1) * 0.01
        for z, w in zip(nodes, weights):
            impulse += w * (b - a) / 2 * physics.external_force(sol.sol((a + b) / 2 + (b - a) / 2 * z), F)
    change = physics.momentum(sol.y[:, -1], n) - physics.momentum(y0, n)
    assert np.linalg.norm(change - (n * physics.m_q + physics.m_L) * physics.g * 0.5) > 1.0  # thrust matters
    np.testing.assert_allclose(change, impulse, rtol=0, atol=1e-7)


def test_free_fall_with_slack_cables_falls_at_g(physics):
    rng = np.random.default_rng(2)
    n = 3
    x0 = np.zeros((n, 13))
    x0[:, 0:3] = Q.circle_directions(n, 1.2, 1.55) * 1.2  # 1.2 m from the load: slack
    q = rng.normal(size=(n, 4))
    x0[:, 3:7] = q / np.linalg.norm(q, axis=1, keepdims=True)
    v0 = np.array([0.3, -0.2, 1.0])
    x0[:, 7:10] = v0
    x0[:, 10:13] = rng.normal(0, 1, (n, 3))
    load0 = np.r_[0.0, 0.0, 0.0, v0]
    x, load = Q.open_loop(physics, x0, load0, np.zeros((10, n, 4)), 0.1, **TOL)
    t = 0.1 * np.arange(11)
    fall = v0 * t[:, None] + 0.5 * np.array([0, 0, -9.81]) * t[:, None] ** 2
    np.testing.assert_allclose(x[:, :, 0:3], x0[None, :, 0:3] + fall[:, None], rtol=0, atol=1e-8)
    np.testing.assert_allclose(load[:, :3], fall, rtol=0, atol=1e-8)
    np.testing.assert_allclose(x[:, :, 7:10], np.broadcast_to(v0 + np.outer(t, [0, 0, -9.81])[:, None], x[..., 7:10].shape),
                               atol=1e-8)
    assert all(np.all(physics.tensions(Q.pack(x[k], load[k]), n) == 0) for k in range(11))
    np.testing.assert_allclose(np.linalg.norm(x[..., 3:7], axis=-1), 1.0, atol=1e-14)


# ---- the generated data --------------------------------------------------------------
def test_quad3_file_validates_and_its_controls_reproduce_it(tmp_path, physics):
    scene = replace(BUILTIN["quad3"], trajectories=3, horizon=12)
    traj = generate(scene, workers=1)
    path = tmp_path / "q3.h5"
    write_trajectories(path, traj)
    t = read_trajectories(path)
    B, T, n = 3, 12, 3
    assert t.system == "quadrotor_load" and t.dt == 0.1
    assert t.x.shape == (B, T + 1, n, 13) and t.u.shape == (B, T, n, 4) and t.aux["load"].shape == (B, T + 1, 6)
    assert t.graphs[0].equals(Graph.complete(n))
    a = t.attrs
    for name in ("m_q", "L", "k_m", "m_L", "d", "k_c", "c_c", "seed", "integrator", "rtol", "atol", "controller_rate"):
        assert name in a
    assert (a["k_c"], a["c_c"], a["integrator"]) == (500.0, 10.0, "LSODA")
    np.testing.assert_allclose(t.params["J"], np.diag([0.0023, 0.0023, 0.004]))
    np.testing.assert_allclose(t.params["g"], [0, 0, -9.81])
    assert np.all(t.u >= 0) and np.all(t.u <= 4.66)
    np.testing.assert_allclose(np.linalg.norm(t.x[..., 3:7], axis=-1), 1.0, atol=1e-12)
    # initial state: the static equilibrium at the drawn load start
    x0, load0, _, _ = Q.static_equilibrium(n, t.aux["load_start"][1], physics)
    np.testing.assert_allclose(t.x[1, 0], x0, atol=1e-15)
    np.testing.assert_allclose(t.aux["load"][1, 0], load0, atol=1e-15)
    # every saved step is the file's own control held over dt (ZOH), from the saved state
    p = Q.Physics({**a, **t.params})
    for b in range(B):
        for k in range(T):
            y1 = Q.step(p, Q.pack(t.x[b, k], t.aux["load"][b, k]), t.u[b, k], k * t.dt, t.dt, "Radau", 1e-11, 1e-11)
            np.testing.assert_allclose(y1, Q.pack(t.x[b, k + 1], t.aux["load"][b, k + 1]), rtol=0, atol=1e-6)
            assert np.all(p.tensions(y1, n) >= 0)
    # trajectory b depends on its own seed only: a 2-trajectory file made by 2 workers agrees
    again = generate(replace(scene, trajectories=2), workers=2)
    np.testing.assert_array_equal(again.x, traj.x[:2])
    np.testing.assert_array_equal(again.u, traj.u[:2])


def test_thrust_excitation_is_a_collective_offset_and_a_torque_doublet_per_pair_of_steps(physics):
    """Thrust excitation: each thrust is the controller's at the saved state plus, per quadrotor and pair of
    steps, one collective offset (the same on its four rotors in both steps) and a zero-sum doublet (torques:
    a pattern across the rotors, then its negative): thrusts that the state does not decide."""
    c = {**Q.CONTROL, "thrust_noise": 0.0, "thrust_excitation": 0.4}
    r = Q.closed_loop(np.random.default_rng(5), 3, 6, 0.1, physics, c, **TOL)
    control = Q.Controller(3, Q.Reference(3, r["start"], r["goal"], physics, c), physics, c, 0.1, r["gain_scale"])
    assert np.all((r["u"] > 0) & (r["u"] < physics.F_max))  # nothing clipped: the offsets are what is left
    offsets = np.array([r["u"][k] - control(k * 0.1, r["x"][k])[0] for k in range(6)])  # (T, n, 4)
    collective = offsets.mean(axis=-1)
    doublet = offsets - collective[..., None]
    np.testing.assert_allclose(collective[1::2], collective[0::2], atol=1e-12)
    np.testing.assert_allclose(doublet[1::2], -doublet[0::2], atol=1e-12)
    assert 0.1 < np.std(collective[0::2]) < 1.0 and not np.allclose(collective[0], collective[2])
    assert 0.01 < np.std(doublet) < np.std(collective[0::2])


@pytest.mark.parametrize("excitation", [0.0, 0.4])
def test_the_scenes_controllers_draw_the_excitation_as_generate_does(excitation):
    """From the file's own states, the scene's controllers (which drive a learned model) give the file's thrusts."""
    scene = replace(BUILTIN["quad3"], trajectories=2, horizon=4, excitation=excitation)
    t = generate(scene, workers=1)
    assert t.attrs["ctrl_thrust_excitation"] == excitation
    x0, controls = Q.controllers(scene)
    np.testing.assert_array_equal(x0, t.x[:, 0])
    for k in range(4):
        np.testing.assert_allclose(controls(k, t.x[:, k]), t.u[:, k], rtol=0, atol=1e-12)
    if excitation:
        plain = generate(replace(scene, excitation=0.0), workers=1)
        assert np.max(np.abs(plain.u[:, 0] - t.u[:, 0])) > 0.05


def test_quadrotor_scene_needs_the_equilibrium_start():
    check_scene(BUILTIN["quad6"], "quad6")
    with pytest.raises(InputError, match="initial"):
        check_scene(replace(BUILTIN["quad3"], initial="uniform"), "quad3")
    with pytest.raises(InputError, match="graph"):
        generate(replace(BUILTIN["quad3"], graph=GraphSpec("edges", 3, edges=((0, 1),))), workers=1)


@pytest.mark.parametrize("name, B", [("quad3", 3), ("quad6", 2)])
def test_full_horizon_transport_reaches_the_goal(name, B):
    t = generate(replace(BUILTIN[name], trajectories=B, horizon=100), workers=1)
    load = t.aux["load"]
    err = np.linalg.norm(load[:, -1, :3] - t.aux["load_goal"], axis=1)
    assert np.all(err < 0.3), err
    # it went through the doorway: at t = 5 s the load is at [3, 0, 0.25] within 0.3 m
    assert np.all(np.linalg.norm(load[:, 50, :3] - [3.0, 0.0, 0.25], axis=1) < 0.3)
    assert t.attrs["min_tension"] >= 0 and t.attrs["redrawn"] == 0


def test_a_learned_model_runs_in_the_scenes_closed_loop(tmp_path):
    """`mpnode simulate MODEL quadN`: the scene's controllers choose the thrusts from the model's state,
    drawing as generate draws: the same start, and at step 0 (same state) the same thrusts."""
    from click.testing import CliRunner

    from cli.main import main
    from mpnode.model import Model

    model = Model.create(13, 4, dt=0.1, message_dim=2, hidden=4, seed=3)
    model.x_mean, model.x_std = np.r_[0, 0, 1, 1, np.zeros(9)], np.full(13, 0.5)
    model.save(tmp_path / "m.h5")
    res = CliRunner().invoke(main, ["simulate", str(tmp_path / "m.h5"), "quad4", "-o", str(tmp_path / "s.h5"),
                                    "-B", "2", "-T", "3", "--seed", "11"])
    assert res.exit_code == 0, res.output
    sim = read_trajectories(tmp_path / "s.h5")
    ref = generate(replace(BUILTIN["quad4"], trajectories=2, horizon=1, seed=11), workers=1)
    np.testing.assert_allclose(sim.x[:, 0], ref.x[:, 0], atol=1e-6)  # float32 model states
    np.testing.assert_allclose(sim.u[:, 0], ref.u[:, 0], atol=1e-4)
    # given the thrusts the loop chose, the open-loop rollout is the closed loop, bit for bit
    from data_gen import closed_loop_start
    from mpnode.evaluation.evaluate import closed_loop_rollout

    x0, graphs, gi, controls = closed_loop_start(replace(BUILTIN["quad4"], trajectories=2, seed=11))
    x, u = closed_loop_rollout(model, x0, graphs, gi, 3, controls)
    np.testing.assert_array_equal(model.rollout(x0, graphs[0], u), x)
    np.testing.assert_array_equal(x, sim.x)
    other = Model.create(13, 0, dt=0.1, hidden=4)
    other.save(tmp_path / "n.h5")
    res = CliRunner().invoke(main, ["simulate", str(tmp_path / "n.h5"), "quad4", "-o", str(tmp_path / "t.h5"), "-B", "1"])
    assert res.exit_code == 2 and "controls" in res.output
