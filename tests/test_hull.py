"""The hull model (sim_bridge/hull.py) against closed forms worked out here from the presets' published numbers,
and the world with hull dynamics (WorldConfig.dynamics).

Hand values (docs/sea.md, "Hull dynamics"): the Otter's full thrust is 2 x 0.5 x 24.4 g N and its surge damping
24.4 g / U_max, so the straight-run balance is U_max = 6 kn = 3.0864 m/s; its surge time constant is
(m + 0.1 m_hull) / |X_u|, with m = 80 kg, m_hull = 55 kg. At u = 0 the yaw rate obeys
(m33 - m23^2/m22) r_dot = N - N_r r (sway and yaw share M's m23 = m x_g), a first-order lag of
T_r = (m33 - m23^2/m22) / N_r.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import fsolve

from agent.core.records import Command
from boat.presets import PRESETS, preset
from sim_bridge import hull
from sim_bridge.environment import Environment, sea_state
from sim_bridge.hull import CalmWater, HullFleet, Model, rk4, rk4_one
from sim_bridge.world import World, WorldConfig

G = 9.81
OTTER_UMAX = 6 * 0.5144


def run_thrust(model: Model, tau, steps: int, h: float = 0.02, state=None, current=(0.0, 0.0)):
    """Integrate one hull under a held tau = (X, Y, N); the states after each step, shape (steps, 6)."""
    state = np.zeros((6, 1)) if state is None else np.array(state, dtype=float).reshape(6, 1)
    tau = np.array(tau, dtype=float).reshape(3, 1)
    current = np.array(current, dtype=float).reshape(2, 1)
    out = np.empty((steps, 6))
    for k in range(steps):
        state = rk4(model, state, tau, current, h)
        out[k] = state[:, 0]
    return out


# ----- steady speed and time constants -----
def test_otter_steady_surge_speed_at_full_thrust_is_the_force_balance_and_the_published_speed():
    full = 2 * 0.5 * 24.4 * G                      # both propellers at bollard thrust (N)
    balance = full / (24.4 * G / OTTER_UMAX)       # X = |X_u| u (the Otter has no quadratic surge damping)
    model = Model.of(PRESETS["otter"].hull)
    u = run_thrust(model, (full, 0.0, 0.0), 1500)[-1, 3]   # 30 s, 27 time constants
    assert abs(u - balance) / balance < 0.02
    assert abs(u - 3.09) / 3.09 < 0.05
    assert u == pytest.approx(3.0864, rel=1e-4)    # the balance itself, to the integrator's accuracy


def test_wamv_steady_surge_speed_is_vrx_max_speed():
    # VRX sets each engine's thrust to (x_u + x_uu U) U / 2 at U = 7.71667 m/s: the balance is U.
    u_max = 7.71667
    thrust = (51.3 + 72.4 * u_max) * u_max
    u = run_thrust(Model.of(PRESETS["wamv"].hull), (thrust, 0.0, 0.0), 1500)[-1, 3]
    assert u == pytest.approx(u_max, rel=1e-4)


@pytest.mark.parametrize("name, expected", [
    ("otter", (80.0 + 0.1 * 55.0) / (24.4 * G / OTTER_UMAX)),   # 1.1025 s
    ("wamv", 180.0 / 51.3),                                     # 3.509 s, no added mass in VRX
])
def test_surge_step_response_is_first_order_with_the_hand_time_constant(name, expected):
    # The linear part (the WAM-V's quadratic drag removed: at low speed its surge lag is the linear one).
    model = Model.of(preset(name, {"hull": {"surge_damping_quadratic": 0.0}}).hull)
    h, force = 0.01, 1.0
    u = run_thrust(model, (force, 0.0, 0.0), int(10 * expected / h), h)[:, 3]
    t = h * np.arange(1, len(u) + 1)
    final = force / model.linear[0, 0]
    # Time at 63.2 % of the final value, interpolated: the time constant of a first-order lag.
    t63 = np.interp((1 - math.exp(-1)) * final, u, t)
    assert t63 == pytest.approx(expected, rel=5e-3)


@pytest.mark.parametrize("name", ["otter", "heron", "wamv"])
def test_yaw_step_response_is_first_order_with_the_hand_time_constant(name):
    hull = PRESETS[name].hull
    m, xg = hull.mass, hull.x_g
    m22, m23, m33 = m + hull.added_mass_sway, m * xg, hull.yaw_inertia + hull.added_mass_yaw
    expected = (m33 - m23 ** 2 / m22) / hull.yaw_damping      # Otter 0.982 s, Heron 1 s, WAM-V 1.115 s
    # The linear part alone (the quadratic yaw damping removed), at a small rate so sway stays negligible.
    model = Model.of(preset(name, {"hull": {"yaw_damping_quadratic": 0.0, "sway_damping_quadratic": 0.0}}).hull)
    moment, h = 0.01 * hull.yaw_damping, 0.01                  # final rate 0.01 rad/s
    r = run_thrust(model, (0.0, 0.0, moment), int(8 * expected / h), h)[:, 5]
    t = h * np.arange(1, len(r) + 1)
    assert r[-1] == pytest.approx(0.01, rel=1e-3)
    assert np.interp((1 - math.exp(-1)) * 0.01, r, t) == pytest.approx(expected, rel=5e-3)


def test_otter_steady_spin_rate_balances_linear_and_quadratic_yaw_damping():
    hull = PRESETS["otter"].hull
    moment = 0.395 * 0.5 * (24.4 + 13.6) * G                   # full differential thrust at u = 0: 73.6 N m
    a, b = hull.yaw_damping_quadratic, hull.yaw_damping
    expected = (-b + math.sqrt(b * b + 4 * a * moment)) / (2 * a)   # N = N_r r + N_rr r^2
    r = run_thrust(Model.of(hull), (0.0, 0.0, moment), 1000)[-1, 5]
    assert r == pytest.approx(expected, rel=1e-4)


# ----- a turning circle -----
def _steady_turn(hull, force: float, moment: float) -> np.ndarray:
    """(u, v, r) with tau = C(nu) nu + D(nu) nu, Fossen's 3-DOF terms written out here from his formulas."""
    m11 = hull.mass + hull.added_mass_surge
    m22 = hull.mass + hull.added_mass_sway
    m23 = hull.mass * hull.x_g

    def residual(nu):
        u, v, r = nu
        c = np.array([-(m22 * v + m23 * r) * r, m11 * u * r, (m22 * v + m23 * r) * u - m11 * u * v])
        d = np.array([(hull.surge_damping + hull.surge_damping_quadratic * abs(u)) * u,
                      (hull.sway_damping + hull.sway_damping_quadratic * abs(v)) * v,
                      (hull.yaw_damping + hull.yaw_damping_quadratic * abs(r)) * r])
        return np.array([force, 0.0, moment]) - c - d

    return fsolve(residual, [1.0, 0.0, 0.2], xtol=1e-13)


@pytest.mark.parametrize("name", ["otter", "heron", "wamv"])
def test_turning_circle_at_full_differential_thrust(name):
    boat = PRESETS[name]
    f, r_, b = boat.thrusters.max_forward, boat.thrusters.max_reverse, boat.thrusters.half_beam
    force, moment = f - r_, b * (f + r_)          # port full astern, starboard full ahead: a turn to port
    u, v, r = _steady_turn(boat.hull, force, moment)
    diameter = 2 * math.hypot(u, v) / abs(r)
    fleet = HullFleet(boat, 1, 0.02, 1)
    path = []
    for k in range(3000):                          # 60 s: the turn settles, then the last 20 s are fitted
        fleet.state = rk4(fleet.model, fleet.state, np.array([[force], [0.0], [moment]]), np.zeros((2, 1)), 0.02)
        path.append(fleet.state[:2, 0].copy())
    xy = np.array(path[-1000:])
    # Circle through the points by least squares: x^2 + y^2 = 2 a x + 2 b y + c.
    a_ = np.column_stack([2 * xy[:, 0], 2 * xy[:, 1], np.ones(len(xy))])
    (cx, cy, c), *_ = np.linalg.lstsq(a_, (xy ** 2).sum(axis=1), rcond=None)
    fitted = 2 * math.sqrt(c + cx * cx + cy * cy)
    assert fitted == pytest.approx(diameter, rel=1e-3)
    assert r > 0                                    # counter-clockwise: the starboard thruster pushes harder
    assert fleet.state[5, 0] == pytest.approx(r, rel=1e-4)


# ----- invariants -----
@pytest.mark.parametrize("name", ["otter", "heron", "wamv"])
def test_without_thrust_or_current_the_kinetic_energy_never_grows(name):
    model = Model.of(PRESETS[name].hull)
    rng = np.random.default_rng(30)               # seed 30; also checked with 31
    zero_tau, zero_c = np.zeros((3, 200)), np.zeros((2, 200))
    state = np.zeros((6, 200))
    state[2] = rng.uniform(-math.pi, math.pi, 200)
    state[3] = rng.uniform(-4.0, 8.0, 200)
    state[4] = rng.uniform(-3.0, 3.0, 200)
    state[5] = rng.uniform(-2.0, 2.0, 200)
    energy = start = model.energy(*state[3:])
    for _ in range(500):
        state = rk4(model, state, zero_tau, zero_c, 0.02)
        now = model.energy(*state[3:])
        assert np.all(now <= energy * (1 + 1e-12)), "the kinetic energy grew"
        energy = now
    assert np.all(np.isfinite(state)) and np.all(energy < start)     # and damping took some away


def test_the_mass_matrix_of_each_preset_is_symmetric_positive_definite():
    for boat in PRESETS.values():
        model = Model.of(boat.hull)
        matrix = np.linalg.inv(model.inverse)
        np.testing.assert_allclose(matrix, matrix.T, atol=1e-9)
        assert np.all(np.linalg.eigvalsh(matrix) > 0)


# ----- one hull in plain floats, many as arrays: the same numbers -----
@pytest.mark.parametrize("name", ["otter", "heron", "wamv"])
def test_rk4_one_in_plain_floats_equals_rk4_on_arrays(name):
    model = Model.of(PRESETS[name].hull)
    rng = np.random.default_rng(40)               # seed 40; also checked with 41
    n = 300
    state = np.vstack([rng.uniform(-50, 50, (2, n)), rng.uniform(-4, 4, (1, n)), rng.uniform(-3, 6, (1, n)),
                       rng.uniform(-2, 2, (1, n)), rng.uniform(-1, 1, (1, n))])
    tau = rng.uniform(-500, 500, (3, n))
    current = rng.uniform(-0.5, 0.5, (2, n))
    arrays = rk4(model, state, tau, current, 0.02)
    floats = [rk4_one(model, tuple(state[:, i].tolist()), tuple(tau[:, i].tolist()), tuple(current[:, i].tolist()),
                      0.02) for i in range(n)]
    np.testing.assert_array_equal(np.array(floats).T, arrays)


@pytest.mark.parametrize("sea", [None, "moderate"])
def test_a_small_fleet_in_plain_floats_moves_as_the_same_fleet_on_arrays(monkeypatch, sea):
    """HullFleet advances up to SMALL_FLEET hulls in plain floats: the same numbers as the arrays' path, in calm
    water and in a sea (current, wind, waves), through stale commands, saturation and a rejoin."""
    rng = np.random.default_rng(42)               # seed 42; also checked with 43
    commands = [(rng.uniform(-2, 5, 3), rng.uniform(-1, 1, 3), rng.choice([0.0, 0.05, 5.0])) for _ in range(60)]

    def advanced(small_fleet: int) -> HullFleet:
        monkeypatch.setattr(hull, "SMALL_FLEET", small_fleet)
        environment = None if sea is None else Environment(sea_state(sea), np.random.default_rng(7))
        fleet = HullFleet(PRESETS["otter"], 3, 0.02, 2, environment)
        for i, (x, y) in enumerate([(0.0, 0.0), (10.0, -3.0), (-4.0, 8.0)]):
            fleet.place(i, x, y, 0.3 * i)
        for k, (speed, rate, age) in enumerate(commands):
            if k == 30:
                fleet.place(1, 2.0, 2.0, 1.0)     # a vessel rejoins mid-run
            fleet.advance(0.1 * k, 0.1, speed, rate, 0.1 * k - age)   # 5 s old: stale, the thrust cut
        return fleet

    floats, arrays = advanced(3), advanced(0)
    assert floats.saturated_time.max() > 0       # the commands reached the thrust limit
    for field in ("state", "thrust", "demand", "current", "saturated_time"):
        np.testing.assert_array_equal(getattr(floats, field), getattr(arrays, field))
    for mine, theirs in zip(floats.loop, arrays.loop):
        np.testing.assert_array_equal(mine, theirs)


def test_a_hull_at_rest_in_the_water_moves_with_a_uniform_current():
    model = Model.of(PRESETS["otter"].hull)
    c = (0.3, -0.2)
    out = run_thrust(model, (0.0, 0.0, 0.0), 500, 0.02, state=(1.0, 2.0, 0.7, 0.0, 0.0, 0.0), current=c)
    t = 0.02 * np.arange(1, 501)
    np.testing.assert_allclose(out[:, 0], 1.0 + c[0] * t, atol=1e-9)
    np.testing.assert_allclose(out[:, 1], 2.0 + c[1] * t, atol=1e-9)
    np.testing.assert_allclose(out[:, 2:], np.tile([0.7, 0.0, 0.0, 0.0], (500, 1)), atol=1e-12)


def test_a_current_along_the_hull_carries_it_from_rest_to_the_current_velocity_with_the_surge_lag():
    # At rest over ground in a current c along its heading: u_r(0) = -c, then u_r = -c e^(-t/T), so the
    # speed over ground is c (1 - e^(-t/T)), T the surge time constant (the Otter's damping is linear in surge).
    model = Model.of(PRESETS["otter"].hull)
    heading, speed = 0.4, 0.5
    c = (speed * math.cos(heading), speed * math.sin(heading))
    out = run_thrust(model, (0.0, 0.0, 0.0), 1000, 0.01, state=(0, 0, heading, -speed, 0, 0), current=c)
    t = 0.01 * np.arange(1, 1001)
    tau = (80.0 + 5.5) / (24.4 * G / OTTER_UMAX)
    np.testing.assert_allclose(speed + out[:, 3], speed * (1 - np.exp(-t / tau)), atol=2e-6)
    assert speed + out[-1, 3] == pytest.approx(speed, abs=1e-4)   # 10 s: carried at the current's speed


# ----- the world with dynamics -----
def _config(**dynamics) -> WorldConfig:
    return WorldConfig(
        vessels=[{"id": "1", "position": (0.0, 0.0)}, {"id": "2", "position": (10.0, 0.0), "heading": 1.0}],
        target={"kind": "constant_velocity", "position": (50.0, 50.0), "velocity": (0.0, 0.0)},
        range_noise={"kind": "gaussian", "variance": 0.0}, bearing_variance=0.0, displacement_variance=0.0,
        dynamics={"preset": "otter", **dynamics})


class UniformCurrent:
    """A stand-in environment: a uniform current, no loads."""

    def __init__(self, cx: float, cy: float) -> None:
        self.c = (cx, cy)
        self.advanced: list[float] = []

    def advance(self, t):
        self.advanced.append(t)

    def current(self, t, x, y):
        return np.full_like(x, self.c[0]), np.full_like(x, self.c[1])

    def loads(self, t, x, y, heading, u, v, windage):
        assert windage.length == 2.0 and windage.mass == 80.0
        zero = np.zeros_like(x)
        return zero, zero, zero

    def attitude(self, t, x, y, heading):
        zero = np.zeros_like(x)
        return zero, zero


def test_the_dynamic_world_accelerates_with_the_surge_lag_and_reports_ground_velocity_and_odometry():
    world = World(_config(), np.random.default_rng(0))
    before = world.sense()["1"].odometry.position
    for _ in range(50):
        world.step({"1": Command(surge=1.0, yaw_rate=0.0), "2": Command(surge=0.0, yaw_rate=0.0)})
    truth = world.truth()
    # The inner loop ramps at 1 m/s^2 and holds 1 m/s through the water: after 5 s it is there.
    assert truth.velocities["1"][0] == pytest.approx(1.0, abs=0.02)
    assert truth.body_velocities["1"][0] == pytest.approx(1.0, abs=0.02)
    np.testing.assert_allclose(truth.velocities["2"], 0.0, atol=1e-9)
    # Odometry: the true displacement (its noise is zero here).
    moved = world.sense()["1"].odometry.position - before
    np.testing.assert_allclose(moved, truth.positions["1"] - np.array([0.0, 0.0]), atol=1e-12)
    assert truth.thrust_limit_time == {"1": 0.0, "2": 0.0}


def test_in_a_current_the_world_moves_a_stopped_vessel_with_it_and_calls_the_environment_every_substep():
    current = UniformCurrent(0.3, 0.1)
    world = World(_config(), np.random.default_rng(0), surroundings=current)
    stop = {"1": Command(surge=0.0, yaw_rate=0.0), "2": Command(surge=0.0, yaw_rate=0.0)}
    for _ in range(200):
        world.step(stop)
    truth = world.truth()
    for vessel in ("1", "2"):     # 20 s: the hull's speed through the water has died out
        np.testing.assert_allclose(truth.velocities[vessel], (0.3, 0.1), atol=5e-3)
    assert len(current.advanced) == 200 * 5 and current.advanced[:3] == pytest.approx([0.0, 0.02, 0.04])


def test_a_command_beyond_the_thrusters_counts_time_at_the_thrust_limit_and_bad_commands_are_counted():
    world = World(_config(), np.random.default_rng(0))
    for _ in range(30):
        world.step({"1": Command(surge=0.0, yaw_rate=1.0), "2": {"surge": math.nan}})
    truth = world.truth()
    assert world.bad_commands == 30
    assert truth.thrust_limit_time["1"] > 0.5           # the spin-up asks for more moment than there is
    assert truth.thrust_limit_time["2"] == 0.0
    assert all(np.isfinite(v).all() for v in truth.body_velocities.values())


def test_dynamics_config_rejects_a_bad_preset_and_steps_that_do_not_fit():
    with pytest.raises(ValueError, match="unknown hull preset"):
        _config(preset="titanic")
    with pytest.raises(ValueError, match="must divide"):
        _config(step_ms=40.0, inner_loop_hz=25.0)
    with pytest.raises(ValueError, match="whole number"):
        _config(inner_loop_hz=30.0)
    with pytest.raises(ValueError, match="greater than 0"):
        _config(overrides={"thrusters": {"time_constant": -1.0}})
    with pytest.raises(ValueError, match="needs hull dynamics"):
        World(_config().model_copy(update={"dynamics": None}), np.random.default_rng(0), surroundings=CalmWater())


def test_a_dynamic_world_is_reproducible_from_its_seed_and_draws_like_the_kinematic_one():
    noisy = {"displacement_variance": 1e-4, "heading_variance": 1e-4,
             "range_noise": {"kind": "gaussian", "variance": 0.1}}

    def fingerprint(dynamics, seed):
        config = _config().model_copy(update={"dynamics": None}).model_dump()
        config.update(noisy, dynamics=dynamics)
        world = World(WorldConfig(**config), np.random.default_rng(seed))
        rows = []
        for k in range(40):
            world.step({"1": Command(surge=1.0, yaw_rate=0.1 * math.sin(k)), "2": Command(surge=0.5, yaw_rate=-0.1)})
            reading = world.sense()["1"]
            rows.append([*world.truth().positions["1"], *reading.odometry.position, reading.ranges["2"]])
        return np.array(rows)

    first, again = fingerprint({"preset": "otter"}, 5), fingerprint({"preset": "otter"}, 5)
    np.testing.assert_array_equal(first, again)
    # The noise is drawn in the kinematic world's order: odometry minus truth is the same random walk.
    kinematic = fingerprint(None, 5)
    np.testing.assert_allclose((first[:, 2:4] - first[:, :2]), (kinematic[:, 2:4] - kinematic[:, :2]), atol=1e-12)
    assert not np.allclose(first[:, :2], kinematic[:, :2], atol=0.05)     # and the hull did lag the kinematics
