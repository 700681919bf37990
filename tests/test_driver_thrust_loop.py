"""The driver bridge's inner loop (driver_bridge/thrust_loop.py), in process: the driver's loop closed around
the sim's hull (sim_bridge/hull.py) gives the sim bridge's own thrusts, the boat reaches what it is told,
the yaw rate it measures, and its invariants over random inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from boat.presets import PRESETS
from driver_bridge.odometry import OdometrySettings
from driver_bridge.thrust_loop import LoopSettings, LoopThrusters, Measurements
from lab.experiments.hull import rise_overshoot, step_response
from sim_bridge.hull import HullFleet

DT = 0.02   # 50 Hz: the loop's default rate, and lab.experiments.hull.step_response's step


def _driver(name: str, **settings) -> LoopThrusters:
    """The driver's loop fed the hull's true (u_r, r): a yaw-rate input, counter-clockwise, no filter."""
    return LoopThrusters(LoopSettings(preset=name, rate_filter=0.0, **settings),
                         OdometrySettings(yaw_input="yaw_rate"))


def _closed(name: str, phases: list[tuple[float, float | None, float]], cruise: float = 0.0) -> dict:
    """The sim's hull (its own loop running, as in the sim bridge) with the driver's loop beside it on the
    same measurements and commands: `phases` of (seconds, surge or None for no command, yaw rate). Returns
    each tick's driver demand, the sim's demand, the $THR pair, the hull's (u_r, r) after the tick, and t."""
    fleet, driver = HullFleet(PRESETS[name], 1, DT, 1), _driver(name)
    out = {key: [] for key in ("driver", "sim", "thr", "u", "r", "t")}
    t, commanded_at, k = 0.0, 0.0, 0
    for seconds, surge, rate in phases:
        for _ in range(round(seconds / DT)):
            t = k * DT
            driver.measure(t, fleet.state[3, 0], fleet.state[5, 0])
            if surge is not None:
                driver.command(surge, rate, t)
                commanded_at, command = t, (surge, rate)
            thr = driver.output(t)
            fleet.advance(t, DT, np.array([command[0]]), np.array([command[1]]), commanded_at)
            out["driver"].append(driver.demand)
            out["sim"].append(fleet.demand[:, 0].copy())
            out["thr"].append((thr.left, thr.right))
            out["u"].append(fleet.state[3, 0])
            out["r"].append(fleet.state[5, 0])
            out["t"].append(t + DT)
            k += 1
    return {key: np.array(values) for key, values in out.items()}


@pytest.mark.parametrize("name", ["otter", "heron", "wamv"])
def test_the_driver_loop_around_the_sim_hull_gives_the_sim_bridges_thrusts_and_reaches_the_command(name):
    run = _closed(name, [(10.0, 1.0, 0.0), (10.0, 1.0, 0.2), (10.0, -0.5, -0.1), (2.0, None, 0.0)])
    assert np.abs(run["driver"] - run["sim"]).max() <= 1e-12           # the same code on the same inputs
    tr = PRESETS[name].thrusters
    limit = np.where(run["driver"] >= 0, tr.max_forward, tr.max_reverse)
    assert np.array_equal(run["thr"], run["driver"] / limit)            # each by its own limit that way
    assert np.abs(run["thr"]).max() <= 1.0 and (run["thr"] < 0).any()
    t = run["t"]

    def at(seconds: float) -> int:
        return round(seconds / DT) - 1   # the tick that ends at `seconds`

    assert run["u"][at(10)] == pytest.approx(1.0, rel=0.02)
    assert run["u"][at(20)] == pytest.approx(1.0, rel=0.02)
    assert run["r"][at(20)] == pytest.approx(0.2, rel=0.02)
    assert run["u"][at(30)] == pytest.approx(-0.5, rel=0.02)
    assert run["r"][at(30)] == pytest.approx(-0.1, rel=0.02)
    # The commands stop at 30 s: the thrust holds until the preset's 0.5 s timeout, then is zero.
    timeout = PRESETS[name].inner_loop.timeout
    last = 30.0 - DT
    held, after = (t - DT > 30.0) & (t - DT - last <= timeout - 1e-9), t - DT - last > timeout + 1e-9
    assert (np.abs(run["driver"][held]).max(axis=1) > 0).all()
    assert (run["driver"][after] == 0).all() and (run["thr"][after] == 0).all() and after.sum() >= 70


@pytest.mark.parametrize("name", ["otter", "heron", "wamv"])
def test_the_driver_loops_step_responses_are_the_presets(name):
    """The speed step 0 -> 1 m/s from rest and the turn-rate step 0 -> 0.2 rad/s at 1 m/s, closed by the
    driver's loop: the same trace as the lab's step_response (the sim's own loop), within the bounds of
    tests/test_inner_loop.py (docs/sea.md, "Inner loop": otter 0.72 s, 8.7 % and 0.21 s, 13.4 %)."""
    speed = _closed(name, [(10.0, 1.0, 0.0)])
    t, u = step_response(name, "speed", 1.0, 0.0)
    assert np.abs(speed["u"] - u).max() <= 1e-12
    rise, overshoot = rise_overshoot(speed["t"], speed["u"], 1.0)
    assert rise <= 1.0 and overshoot <= 0.15 and speed["u"][-1] == pytest.approx(1.0, rel=0.02)
    turn = _closed(name, [(20.0, 1.0, 0.0), (10.0, 1.0, 0.2)])
    rate, times = turn["r"][-500:], turn["t"][-500:] - 20.0
    _, r = step_response(name, "rate", 0.2, 1.0)
    assert np.abs(rate - r).max() <= 1e-9     # after 20 s of cruise commanded every 0.02 s, not every 0.1 s
    rise, overshoot = rise_overshoot(times, rate, 0.2)
    assert rise <= 0.4 and overshoot <= 0.35 and rate[-1] == pytest.approx(0.2, rel=0.02)
    if name == "otter":
        assert (rise, overshoot) == (pytest.approx(0.21, abs=0.01), pytest.approx(0.134, abs=0.002))


def _measured(settings: dict, samples) -> Measurements:
    m = Measurements(OdometrySettings(**settings), LoopSettings(preset="otter", rate_filter=0.2))
    for now, speed, yaw in samples:
        assert m.update(now, speed, yaw) == ""
    return m


def test_the_yaw_rate_is_the_differenced_heading_low_passed_and_the_rate_input_is_taken_as_it_comes():
    """A compass heading (clockwise, yaw_sign -1) across north at 2 deg per 0.1 s: a clockwise turn of
    -20 deg/s. Headings held, then the turn: r_k = w (1 - (1 - a)^k), a = dt / (dt + 0.2) = 1/3."""
    held = [(0.1 * k, 1.0, math.radians(350.0)) for k in range(4)]
    turning = [(0.1 * (4 + k), 1.0, math.radians((350.0 + 2 * (k + 1)) % 360.0)) for k in range(10)]
    m = _measured({"yaw_sign": -1}, held + turning)
    w = -math.radians(20.0)
    assert m.r == pytest.approx(w * (1 - (2 / 3) ** 10), rel=1e-9) and m.u == 1.0 and m.fresh(1.3)
    # A first sample gives no rate yet; after a gap beyond measurement_timeout the filter starts again.
    m = _measured({"yaw_sign": -1}, [(0.0, 1.0, 0.1)])
    assert not m.fresh(0.0)
    m = _measured({"yaw_sign": -1}, held + [(2.0, 1.0, 0.0), (2.1, 1.0, math.radians(2.0))])
    assert m.r == pytest.approx(w, rel=1e-9)
    # A yaw-rate input: taken with its sign, the first sample unfiltered.
    m = _measured({"yaw_input": "yaw_rate", "yaw_sign": -1}, [(0.0, 0.5, 0.3)])
    assert m.r == -0.3 and m.fresh(0.5) and not m.fresh(0.51)


SPECIALS = np.array([np.nan, np.inf, -np.inf, 1e308, -1e308, 0.0])


@pytest.mark.parametrize("seed", [3, 4])
def test_any_input_gives_finite_thrust_in_range_and_zero_after_either_timeout(seed):
    """Random commands, speed-log samples and times (Cauchy values with NaN, +-inf and +-1e308 mixed in,
    times jittered backwards, gaps of up to 2 s, a silent speed log): every $THR value finite and in [-1, 1];
    zero whenever the newest command or the newest sample came longer ago than its timeout."""
    rng = np.random.default_rng(seed)

    def value(scale: float) -> float:
        return float(rng.choice(SPECIALS)) if rng.random() < 0.1 else float(rng.standard_cauchy() * scale)

    driving = stopped_by_command = stopped_by_measurement = 0
    for episode in range(12):
        name = ["otter", "heron", "wamv"][episode % 3]
        yaw_input = "yaw" if episode % 2 else "yaw_rate"
        driver = LoopThrusters(LoopSettings(preset=name, rate_filter=float(rng.uniform(0, 0.3)),
                                            measurement_timeout=float(rng.uniform(0.1, 1.0))),
                               OdometrySettings(yaw_input=yaw_input))
        timeout, measurement_timeout = driver.boat.inner_loop.timeout, driver.settings.measurement_timeout
        now, last_command, last_sample = 0.0, -math.inf, -math.inf
        for tick in range(400):
            now += float(rng.uniform(0.0, 0.05)) if rng.random() > 0.02 else float(rng.uniform(0.5, 2.0))
            if rng.random() < 0.5:
                at = now - float(rng.uniform(0, 0.1)) if rng.random() > 0.05 else math.nan
                driver.command(value(1.0), value(0.3), at)
                last_command = max(last_command, at) if math.isfinite(at) else last_command
            if rng.random() < 0.7 and not 200 <= tick < 250:     # and a silent speed log for 50 ticks
                at = now - float(rng.uniform(0, 0.05)) if rng.random() > 0.05 else math.nan
                yaw = value(0.3) if yaw_input == "yaw_rate" else float(rng.uniform(0, 2 * math.pi))
                driver.measure(at, value(1.0), yaw)
                last_sample = max(last_sample, at) if math.isfinite(at) else last_sample
            thrust = driver.output(now if rng.random() > 0.01 else math.nan)
            pair = np.array([thrust.left, thrust.right])
            assert np.isfinite(pair).all() and (np.abs(pair) <= 1.0).all(), pair
            if now - last_command > timeout:
                assert (pair == 0).all()
                stopped_by_command += 1
            elif now - last_sample > measurement_timeout:
                assert (pair == 0).all()
                stopped_by_measurement += 1
            driving += bool(pair.any())
    assert min(driving, stopped_by_command, stopped_by_measurement) >= 50   # each case met, none vacuous


def test_a_stop_is_said_once_and_counted():
    said: list[str] = []
    driver = LoopThrusters(LoopSettings(preset="otter"), OdometrySettings(yaw_input="yaw_rate"), said.append)
    now = 0.0
    for k in range(100):                         # 2 s of commands and samples, then the samples stop
        now = k * DT
        driver.command(1.0, 0.0, now)
        if k < 50:
            driver.measure(now, 0.5, 0.0)
        driver.output(now)
    assert driver.events["measurement_stop"] == 1 and len(said) == 1, said
    assert said[0].startswith("thrusters stopped: no speed-log or yaw sample for 0.5")
    for k in range(100, 150):                    # the commands stop too: one more line, for the command
        driver.output(k * DT)
    driver.measure(150 * DT, 0.5, 0.0)
    driver.output(150 * DT)
    assert driver.events["watchdog_stop"] == 1 and len(said) == 2 and "no fresh command" in said[1], said


@pytest.mark.parametrize("thrusters, odometry, says", [
    ({"control": "inner_loop"}, True, "control 'inner_loop' needs inner_loop"),
    ({"control": "inner_loop", "inner_loop": {"preset": "cat"}}, True, "unknown hull preset 'cat'"),
    ({"control": "inner_loop", "inner_loop": {"preset": "otter"}}, False, "it needs the odometry port"),
    ({"control": "inner_loop", "inner_loop": {"preset": "otter"}, "baud": 9600}, True,
     "9600 baud cannot carry 50 thrust lines a second"),
    ({}, True, "control 'mix' needs hull"),
])
def test_a_driver_config_that_cannot_close_the_loop_is_a_clear_error(thrusters, odometry, says):
    from agent.config import ConfigError, parse_mapping
    from driver_bridge.node import DriverSettings

    config = {"thrusters": {"device": "/dev/null", **thrusters}}
    if odometry:
        config["odometry"] = {"device": "/dev/null"}
    with pytest.raises(ConfigError, match=says):
        parse_mapping(DriverSettings, config, "driver.yaml")
    config["thrusters"] = {"device": "/dev/null", "control": "inner_loop", "inner_loop": {"preset": "otter"}}
    config["odometry"] = {"device": "/dev/null"}
    assert parse_mapping(DriverSettings, config, "driver.yaml").thrusters.lines_per_second() == 50.0


def test_the_loop_on_a_10_hz_compass_turns_the_hull_as_told():
    """lab/experiments/driver_loop.py: its hull under the driver's thrust is the sim's (fed the exact rate,
    the lab's step_response trace); fed a VHW compass heading at 10 Hz, rounded to 0.1 degree and
    differenced, the turn-rate step rises within the inner loop's bounds (tests/test_inner_loop.py) and
    settles on the command."""
    from lab.experiments import driver_loop

    _, rate, _ = driver_loop.turn("otter", None, 0.0)
    _, expected = step_response("otter", "rate", 0.2, 1.0)
    assert np.abs(rate[:len(expected)] - expected).max() <= 1e-9
    t, rate, thr = driver_loop.turn("otter", 10, 0.05)
    rise, overshoot = rise_overshoot(t, rate, 0.2)
    assert rise <= 0.4 and overshoot <= 0.35 and rate[-50:].mean() == pytest.approx(0.2, rel=0.02)
    assert (thr[:, 0] < thr[:, 1]).all()   # turning counter-clockwise: the starboard thruster pushes harder
