"""The environment (issue 30, item 3): current, wind, waves, their composition and the sea-state presets.

Expected values are worked out here by hand or from closed forms (stated beside each), or by an independent
computation (numerical quadrature, finite differences of the public surface elevation), never read back from
the code under test. Statistical checks use seeded runs with tolerances from the sampling error computed here.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.integrate import quad

from agent.config import ConfigError, StrictModel, parse_mapping
from sim_bridge.current import Current, CurrentConfig
from sim_bridge.environment import SEA_STATES, Environment, EnvironmentConfig, SeaState, sea_state
from sim_bridge.waves import Waves, WavesConfig, pm_frequency, pm_spectrum, pm_variance
from sim_bridge.wind import Wind, WindConfig

OTTER = SimpleNamespace(length=2.0, beam=1.08, mass=80.0, frontal_area=0.4, lateral_area=0.8)


def rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


# --- current ---------------------------------------------------------------------------------------------

def test_uniform_current_is_exact_everywhere():
    # speed 0.5 towards atan2(3, 4): (0.5 * 4/5, 0.5 * 3/5) = (0.4, 0.3) at every point.
    current = Current(CurrentConfig(speed=0.5, direction=math.atan2(3.0, 4.0)), rng())
    x, y = np.array([0.0, -120.0, 3e4]), np.array([0.0, 55.5, -7e3])
    cx, cy = current.velocity(x, y)
    assert cx.shape == cy.shape == (3,)
    np.testing.assert_allclose(cx, 0.4, rtol=0, atol=1e-15)
    np.testing.assert_allclose(cy, 0.3, rtol=0, atol=1e-15)
    # Along x, with no noise at all: exactly (0.5, 0).
    cx, cy = Current(CurrentConfig(speed=0.5), rng()).velocity(x, y)
    assert np.all(cx == 0.5) and np.all(cy == 0.0)


def test_the_sheared_current_at_known_points():
    # 'gradient': 0.3 m/s along x, growing 0.01 s^-1 across the flow (along +y): c = (0.3 + 0.01 y, 0).
    current = Current(CurrentConfig(speed=0.3, shear=0.01), rng())
    x = np.array([0.0, 5.0, 0.0, 100.0, -40.0])
    y = np.array([0.0, 20.0, -30.0, -10.0, 7.5])
    cx, cy = current.velocity(x, y)
    np.testing.assert_allclose(cx, [0.3, 0.5, 0.0, 0.2, 0.375], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(cy, 0.0)
    # The same shear along the flow, about p_0 = (10, 10): c = (0.3 + 0.01 (x - 10), 0).
    along = Current(CurrentConfig(speed=0.3, shear=0.01, shear_direction=0.0, origin=(10.0, 10.0)), rng())
    cx, cy = along.velocity(np.array([10.0, 30.0, -20.0]), np.array([-3.0, 10.0, 99.0]))
    np.testing.assert_allclose(cx, [0.3, 0.5, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(cy, 0.0, rtol=0, atol=1e-15)


def ar1_autocorrelation_std(rho: float, lag: int, n: int) -> float:
    """Bartlett's large-sample standard deviation of the lag-L sample autocorrelation of an AR(1) series:
    var r_L = [(1 + rho^2)(1 - rho^(2L)) / (1 - rho^2) - 2 L rho^(2L)] / n."""
    r2l = rho ** (2 * lag)
    return math.sqrt(((1 + rho**2) * (1 - r2l) / (1 - rho**2) - 2 * lag * r2l) / n)


@pytest.mark.parametrize("seed", [3, 4])
def test_the_current_gauss_markov_part_has_its_stationary_variance_and_autocorrelation(seed):
    sigma, tau, dt, steps = 0.2, 5.0, 0.5, 50_000
    current = Current(CurrentConfig(variation=sigma, time_constant=tau), rng(seed))
    samples = np.empty((steps, 2))
    zero = np.zeros(1)
    for k in range(steps):
        current.advance(dt)
        cx, cy = current.velocity(zero, zero)
        samples[k] = cx[0], cy[0]
    rho = math.exp(-dt / tau)
    n = 2 * steps                                  # both components, independent
    # Sample variance of an AR(1): var(s^2) ~ 2 sigma^4 / n * (1 + rho^2) / (1 - rho^2).
    variance_std = sigma**2 * math.sqrt(2.0 / n * (1 + rho**2) / (1 - rho**2))
    assert abs(np.mean(samples**2) - sigma**2) < 4 * variance_std
    # Mean: var = sigma^2 / n * (1 + rho) / (1 - rho).
    assert abs(np.mean(samples)) < 4 * sigma * math.sqrt((1 + rho) / (1 - rho) / n)
    lag = round(tau / dt)
    r = np.mean(samples[:-lag] * samples[lag:]) / np.mean(samples**2)
    assert abs(r - math.exp(-1.0)) < 4 * ar1_autocorrelation_std(rho, lag, n)


# --- wind ------------------------------------------------------------------------------------------------

def test_wind_loads_against_a_hand_computed_relative_wind():
    # 8 m/s towards +x, no gust; heading 30 deg, u = 2, v = 0.5 (over ground).
    # Wind in body axes: (8 cos 30, -8 sin 30) = (4 sqrt 3, -4); apparent: u_rw = 4 sqrt 3 - 2 = 4.92820323,
    # v_rw = -4.5. Coefficients: c_x = 0.5 * 1.225 * 0.8 * 0.4 = 0.196, c_y = 0.5 * 1.225 * 0.8 * 0.8 = 0.392,
    # c_n = 0.5 * 1.225 * 0.1 * 0.8 * 2.0 = 0.098.
    wind = Wind(WindConfig(speed=8.0), rng())
    x, y, n = wind.loads(np.array([math.pi / 6]), np.array([2.0]), np.array([0.5]), OTTER)
    assert x[0] == pytest.approx(0.196 * 4.92820323**2, rel=1e-8)         # 4.76028867 N
    assert y[0] == pytest.approx(-0.392 * 20.25, rel=1e-12)              # -7.938 N
    assert n[0] == pytest.approx(-2 * 0.098 * 4.92820323 * -4.5, rel=1e-8)  # +4.34667525 N m
    assert (x[0], y[0], n[0]) == pytest.approx((4.76028867, -7.938, 4.34667525), abs=1e-7)


def test_wind_yaw_moment_vanishes_head_on_stern_on_and_beam_on_and_is_odd_in_the_heading():
    wind = Wind(WindConfig(speed=8.0, direction=0.3), rng())
    # Head-on: the bow into the wind (heading = direction + pi) at 3 m/s: u_rw = -(8 + 3), v_rw = 0.
    x, y, n = wind.loads(np.array([0.3 + math.pi]), np.array([3.0]), np.array([0.0]), OTTER)
    assert n[0] == pytest.approx(0.0, abs=1e-12) and y[0] == pytest.approx(0.0, abs=1e-12)
    assert x[0] == pytest.approx(-0.196 * 121.0, rel=1e-12)
    headings = 0.3 + np.array([0.0, math.pi / 2, -math.pi / 2])       # stern-on, beam-on both sides
    _, _, n = wind.loads(headings, np.zeros(3), np.zeros(3), OTTER)
    np.testing.assert_allclose(n, 0.0, atol=1e-12)
    # A hull at rest: N(direction + a) = -N(direction - a), largest on the quarters (|sin 2a| = 1).
    a = np.linspace(0.05, 3.0, 30)
    _, _, plus = wind.loads(0.3 + a, np.zeros(30), np.zeros(30), OTTER)
    _, _, minus = wind.loads(0.3 - a, np.zeros(30), np.zeros(30), OTTER)
    np.testing.assert_allclose(plus, -minus, rtol=1e-12, atol=1e-12)
    # -2 c_n u_rw v_rw = -2 c_n (8 cos a)(-8 sin a) = c_n 64 sin 2a.
    np.testing.assert_allclose(plus, 0.098 * 64 * np.sin(2 * a), rtol=1e-12, atol=1e-12)


def test_wind_gust_statistics():
    gain, tau, dt, steps = 2.0, 2.0, 0.2, 50_000
    wind = Wind(WindConfig(speed=8.0, gain=gain, time_constant=tau), rng(11))
    speeds = np.empty(steps)
    for k in range(steps):
        wind.advance(dt)
        speeds[k] = wind.speed
    rho = math.exp(-dt / tau)
    assert abs(speeds.mean() - 8.0) < 4 * gain * math.sqrt((1 + rho) / (1 - rho) / steps)
    gust = speeds - 8.0
    variance_std = gain**2 * math.sqrt(2.0 / steps * (1 + rho**2) / (1 - rho**2))
    assert abs(np.mean(gust**2) - gain**2) < 4 * variance_std
    lag = round(tau / dt)
    r = np.mean(gust[:-lag] * gust[lag:]) / np.mean(gust**2)
    assert abs(r - math.exp(-1.0)) < 4 * ar1_autocorrelation_std(rho, lag, steps)


# --- waves -----------------------------------------------------------------------------------------------

def test_pierson_moskowitz_variance_and_significant_height_against_the_closed_form():
    # m0 = K^2 alpha g^2 / (5 w_p^4); T_p = 5 s: w_p^4 = (2 pi / 5)^4 = 2.4936727; K = 0.3:
    # m0 = 0.09 * 0.0081 * 96.2361 / 12.4683636 = 0.00562670 m^2, H_s = 4 sqrt(m0) = 0.30004 m.
    assert pm_variance(5.0, 0.3) == pytest.approx(0.0056267, rel=1e-4)
    assert 4 * math.sqrt(pm_variance(5.0, 0.3)) == pytest.approx(0.30004, abs=1e-4)
    for period, gain in [(5.0, 0.3), (2.0, 2.0), (8.0, 1.0)]:
        integral, _ = quad(lambda w: float(pm_spectrum(w, period, gain)), 0.0, np.inf, limit=200)
        assert integral == pytest.approx(pm_variance(period, gain), rel=1e-7)


def test_the_components_split_the_spectrum_into_equal_energies():
    config = WavesConfig(gain=0.3, period=5.0, components=16)
    waves = Waves(config, rng())
    m0 = pm_variance(5.0, 0.3)
    assert np.sum(waves.amplitude**2 / 2) == pytest.approx(m0, rel=1e-12)
    # Component i sits where the spectrum below it holds (i + 1/2) / N of the energy (quadrature).
    for i, omega in enumerate(waves.omega):
        below, _ = quad(lambda w: float(pm_spectrum(w, 5.0, 0.3)), 0.0, omega, limit=200)
        assert below / m0 == pytest.approx((i + 0.5) / 16, abs=1e-8)
    np.testing.assert_allclose(waves.wavenumber, waves.omega**2 / 9.81, rtol=1e-14)   # deep water
    assert pm_frequency(np.array([math.exp(-1.25)]), 5.0)[0] == pytest.approx(2 * math.pi / 5, rel=1e-14)


def test_the_surface_elevation_has_the_spectrum_variance_over_a_long_record():
    waves = Waves(WavesConfig(gain=0.3, period=5.0, components=16, spread=0.0), rng(2))
    # Sampled every 0.37 s, below the top component's half period (pi / 3.14 rad/s = 1 s), commensurate with
    # none. Over T = 20,000 s a cross term a_i a_j cos(w_i t ...) cos(w_j t ...) averages to at most
    # a^2 / (T |w_i - w_j|); summed over the pairs, with the closest 0.055 rad/s apart, relative to
    # m0 = N a^2 / 2 the error is below (2 / N) N ln(N) / (T 0.055) = 0.5 %.
    assert np.diff(waves.omega).min() > 0.055
    t = np.arange(0.0, 20_000.0, 0.37)
    eta = np.array([waves.elevation(s, np.array([3.0]), np.array([-4.0]))[0] for s in t])
    assert np.var(eta) == pytest.approx(pm_variance(5.0, 0.3), rel=5e-3)


def test_the_wave_sinusoids_are_reproducible_from_the_seed():
    config = WavesConfig(gain=0.3, period=5.0)
    a, b, c = Waves(config, rng(7)), Waves(config, rng(7)), Waves(config, rng(8))
    assert np.array_equal(a.phase, b.phase) and np.array_equal(a.direction, b.direction)
    x, y = np.linspace(-30, 30, 7), np.linspace(5, -5, 7)
    assert np.array_equal(a.elevation(12.3, x, y), b.elevation(12.3, x, y))
    assert not np.array_equal(a.phase, c.phase)
    # Directions within +-spread of the mean; phases in [0, 2 pi).
    assert np.all(np.abs(a.direction) <= 0.4) and np.all((a.phase >= 0) & (a.phase < 2 * math.pi))


def box_average_loads(waves: Waves, t: float, centre, heading: float, hull, cells: int = 200):
    """-m g grad(eta) averaged over the L x B box by the midpoint rule, grad(eta) by central differences of
    the public elevation: an independent check of the closed-form box means."""
    s = (np.arange(cells) + 0.5) / cells - 0.5
    along, across = np.meshgrid(s * hull.length, s * hull.beam, indexing="ij")
    c, sn = math.cos(heading), math.sin(heading)
    px = centre[0] + along * c - across * sn
    py = centre[1] + along * sn + across * c
    h = 1e-5
    d_forward = (waves.elevation(t, (px + h * c).ravel(), (py + h * sn).ravel())
                 - waves.elevation(t, (px - h * c).ravel(), (py - h * sn).ravel())) / (2 * h)
    d_port = (waves.elevation(t, (px - h * sn).ravel(), (py + h * c).ravel())
              - waves.elevation(t, (px + h * sn).ravel(), (py - h * c).ravel())) / (2 * h)
    weight = hull.mass * 9.81
    fx, fy = -weight * d_forward, -weight * d_port
    moment = along.ravel() * fy - across.ravel() * fx
    return fx.mean(), fy.mean(), moment.mean()


@pytest.mark.parametrize("heading", [0.0, 0.7, 2.0, -2.6])
def test_wave_loads_equal_the_box_average_of_the_froude_krylov_force(heading):
    waves = Waves(WavesConfig(gain=2.0, period=2.0, components=12, spread=0.8), rng(5))
    hull = SimpleNamespace(length=4.9, beam=2.4, mass=180.0, frontal_area=1.0, lateral_area=2.0)
    for t in (0.0, 3.7):
        expected = box_average_loads(waves, t, (2.5, -1.0), heading, hull)
        x, y, n = waves.loads(t, np.array([2.5]), np.array([-1.0]), np.array([heading]), hull)
        scale = hull.mass * 9.81 * float(np.sum(waves.amplitude * waves.wavenumber))
        assert x[0] == pytest.approx(expected[0], abs=2e-4 * scale)
        assert y[0] == pytest.approx(expected[1], abs=2e-4 * scale)
        assert n[0] == pytest.approx(expected[2], abs=2e-4 * scale * hull.length)


def test_long_crested_waves_give_no_sway_nor_yaw_head_on_and_no_surge_nor_yaw_beam_on():
    waves = Waves(WavesConfig(gain=0.3, period=5.0, spread=0.0, direction=1.0), rng(1))
    x = np.linspace(-10, 10, 5)
    y = np.zeros(5)
    head = np.full(5, 1.0 + math.pi)
    fx, fy, n = waves.loads(4.0, x, y, head, OTTER)
    np.testing.assert_allclose(fy, 0.0, atol=1e-9)
    np.testing.assert_allclose(n, 0.0, atol=1e-9)
    assert np.max(np.abs(fx)) > 1.0                   # the surge force is there
    fx, fy, n = waves.loads(4.0, x, y, np.full(5, 1.0 + math.pi / 2), OTTER)
    np.testing.assert_allclose(fx, 0.0, atol=1e-9)
    np.testing.assert_allclose(n, 0.0, atol=1e-9)
    roll, pitch = waves.attitude(4.0, x, y, head)
    np.testing.assert_allclose(roll, 0.0, atol=1e-12)


def test_roll_and_pitch_follow_the_surface_slope_with_sname_signs():
    waves = Waves(WavesConfig(gain=2.0, period=2.0, spread=0.5), rng(9))
    t, h = 1.3, 1e-6
    px, py = np.array([0.0, 3.0, -7.0]), np.array([1.0, -2.0, 4.0])
    for heading in (0.0, 1.1, -2.5):
        c, s = math.cos(heading), math.sin(heading)
        ahead = waves.elevation(t, px + h * c, py + h * s)
        behind = waves.elevation(t, px - h * c, py - h * s)
        port = waves.elevation(t, px - h * s, py + h * c)
        starboard = waves.elevation(t, px + h * s, py - h * c)
        slope_forward, slope_port = (ahead - behind) / (2 * h), (port - starboard) / (2 * h)
        roll, pitch = waves.attitude(t, px, py, np.full(3, heading))
        # The deck's normal is the surface's: tan(pitch) = slope ahead (bow up positive),
        # sin(roll) = slope to port / |(slope_forward, slope_port, 1)| (port up = starboard down positive).
        np.testing.assert_allclose(np.tan(pitch), slope_forward, rtol=1e-6, atol=1e-9)
        norm = np.sqrt(1 + slope_forward**2 + slope_port**2)
        np.testing.assert_allclose(np.sin(roll), slope_port / norm, rtol=1e-6, atol=1e-9)
        assert np.max(np.abs(pitch)) > 1e-3


# --- the composed environment ----------------------------------------------------------------------------

def run_environment(seed: int, n: int, ticks: int = 50):
    env = Environment(sea_state("moderate"), rng(seed))
    x, y = np.linspace(-20, 20, n), np.linspace(10, -10, n)
    heading, u, v = np.linspace(-3, 3, n), np.full(n, 1.5), np.full(n, 0.1)
    out = []
    for k in range(1, ticks + 1):
        env.advance(0.01 * k)
        out.append((env.current(env.time, x, y), env.loads(env.time, x, y, heading, u, v, OTTER),
                    env.attitude(env.time, x, y, heading)))
    return out


def flatten(out) -> np.ndarray:
    return np.concatenate([np.ravel(part) for step in out for group in step for part in group])


def test_the_whole_environment_is_reproducible_from_its_seed():
    a, b, c = (flatten(run_environment(seed, 5)) for seed in (21, 21, 22))
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)


def test_the_draws_do_not_depend_on_the_fleet():
    # One environment answers for one vessel only, the other for a fleet of 40 as well, each substep: the
    # answers at the one vessel stay bit for bit the same.
    env_small = Environment(sea_state("moderate"), rng(21))
    env_large = Environment(sea_state("moderate"), rng(21))
    point = np.array([1.0]), np.array([2.0])
    for k in range(1, 200):
        env_small.advance(0.01 * k)
        env_large.advance(0.01 * k)
        fleet = np.linspace(-50, 50, 40)
        env_large.current(env_large.time, fleet, -fleet)                 # a per-call or per-vessel draw
        env_large.loads(env_large.time, fleet, fleet, fleet, np.ones(40), np.zeros(40), OTTER)   # would show
        env_large.attitude(env_large.time, fleet, fleet, fleet)
        assert env_small.current(0.0, *point) == env_large.current(0.0, *point)
        assert env_small.loads(0.0, *point, np.zeros(1), np.zeros(1), np.zeros(1), OTTER) == \
            env_large.loads(0.0, *point, np.zeros(1), np.zeros(1), np.zeros(1), OTTER)


def test_the_environment_leaves_the_callers_stream_alone():
    mine = rng(5)
    Environment(sea_state("moderate"), mine)
    assert mine.random() == rng(5).random()


def test_an_empty_environment_is_still_water_and_air():
    env = Environment(EnvironmentConfig(), rng())
    env.advance(1.0)
    x = np.arange(4.0)
    assert all(np.array_equal(part, np.zeros(4)) for part in env.current(1.0, x, x))
    assert all(np.array_equal(part, np.zeros(4)) for part in env.loads(1.0, x, x, x, x, x, OTTER))
    assert all(np.array_equal(part, np.zeros(4)) for part in env.attitude(1.0, x, x, x))


def test_the_environment_sums_wind_and_wave_loads_and_takes_per_vessel_windage():
    config = EnvironmentConfig(wind=WindConfig(speed=8.0, gain=2.0), waves=WavesConfig())
    configs = (config, EnvironmentConfig(wind=config.wind), EnvironmentConfig(waves=config.waves))
    env, wind_only, waves_only = (Environment(c, rng(3)) for c in configs)
    for e in (env, wind_only, waves_only):
        e.advance(0.5)
    hull = SimpleNamespace(length=np.array([2.0, 4.9]), beam=np.array([1.08, 2.4]),
                           mass=np.array([80.0, 180.0]), frontal_area=np.array([0.4, 1.2]),
                           lateral_area=np.array([0.8, 2.5]))
    args = (0.5, np.array([1.0, -3.0]), np.array([0.0, 2.0]), np.array([0.2, 2.2]), np.array([1.0, 2.0]),
            np.array([0.0, 0.3]))
    total = env.loads(*args, hull)
    parts = wind_only.loads(*args, hull), waves_only.loads(*args, hull)
    for k in range(3):
        np.testing.assert_allclose(total[k], parts[0][k] + parts[1][k], rtol=1e-14)
    # The second hull's own windage: the wind part matches a scalar windage for that hull alone.
    alone = SimpleNamespace(length=4.9, beam=2.4, mass=180.0, frontal_area=1.2, lateral_area=2.5)
    single = wind_only.loads(0.5, np.array([-3.0]), np.array([2.0]), np.array([2.2]), np.array([2.0]),
                             np.array([0.3]), alone)
    assert [p[0] for p in single] == pytest.approx([p[1] for p in parts[0]], rel=1e-14)


def test_advance_refuses_to_go_back_and_does_nothing_for_the_same_time():
    env = Environment(sea_state("moderate"), rng())
    env.advance(1.0)
    before = env.current(1.0, np.zeros(1), np.zeros(1))
    env.advance(1.0)
    assert env.current(1.0, np.zeros(1), np.zeros(1)) == before
    # A substep time summed to 0.30000000000000004 and the next tick's 0.3: a rounding error, not a step back.
    env.advance(1.0 - 1e-12)
    assert env.current(1.0, np.zeros(1), np.zeros(1)) == before and env.time == 1.0
    with pytest.raises(ValueError, match="back in time") as error:
        env.advance(0.99)
    assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match="back in time"):
        env.advance(math.nan)


# --- configs and presets ---------------------------------------------------------------------------------

@pytest.mark.parametrize("data, field", [
    ({"current": {"speed": -0.5}}, "current.speed"),
    ({"current": {"variation": -0.1}}, "current.variation"),
    ({"current": {"time_constant": 0.0}}, "current.time_constant"),
    ({"current": {"shear": math.inf}}, "current.shear"),
    ({"current": {"direction": math.nan}}, "current.direction"),
    ({"wind": {"speed": -8.0}}, "wind.speed"),
    ({"wind": {"gain": math.nan}}, "wind.gain"),
    ({"wind": {"time_constant": -2.0}}, "wind.time_constant"),
    ({"wind": {"cn": math.inf}}, "wind.cn"),
    ({"waves": {"gain": -0.3}}, "waves.gain"),
    ({"waves": {"period": math.inf}}, "waves.period"),
    ({"waves": {"period": 0.0}}, "waves.period"),
    ({"waves": {"components": 0}}, "waves.components"),
    ({"waves": {"spread": 4.0}}, "waves.spread"),
    ({"waves": {"hieght": 1.0}}, "waves.hieght"),
])
def test_bad_configs_are_refused_in_one_line(data, field):
    with pytest.raises(ConfigError) as error:
        parse_mapping(EnvironmentConfig, data, "sea.yaml")
    message = str(error.value)
    assert "\n" not in message and message.startswith("sea.yaml: field ") and f"'{field}'" in message


class _WithSea(StrictModel):
    sea: SeaState | None = None


def test_sea_states_are_named_presets_matching_the_issue():
    assert set(SEA_STATES) == {"calm", "current", "gradient", "wind", "waves", "moderate"}
    assert sea_state("calm") == EnvironmentConfig()
    assert sea_state("current").current == CurrentConfig(speed=0.5)
    gradient = sea_state("gradient").current
    assert (gradient.speed, gradient.shear) == (0.3, 0.01)
    wind = sea_state("wind").wind
    assert (wind.speed, wind.gain, wind.time_constant) == (8.0, 2.0, 2.0)
    waves = sea_state("waves").waves
    assert (waves.gain, waves.period) == (0.3, 5.0)
    moderate = sea_state("moderate")
    assert moderate.current == gradient and moderate.wind == wind and moderate.waves == waves
    # A config names one, or spells it out; an unknown name is one line.
    assert parse_mapping(_WithSea, {"sea": "moderate"}, "s.yaml").sea == moderate
    assert parse_mapping(_WithSea, {"sea": {"wind": {"speed": 3.0}}}, "s.yaml").sea.wind.speed == 3.0
    with pytest.raises(ConfigError) as error:
        parse_mapping(_WithSea, {"sea": "stormy"}, "s.yaml")
    assert "\n" not in str(error.value) and "unknown sea state 'stormy'" in str(error.value)
    with pytest.raises(ConfigError, match="unknown sea state 'stormy': one of calm, current"):
        sea_state("stormy")
