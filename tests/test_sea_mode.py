"""The sea mode (sim_bridge/world.py `SeaSensors`, sim_bridge/bridge.py `_run_sea`): each vessel's own clock,
sensors measuring at their own times with latency, drivers stamping on arrival.

Unit tests check the model against values worked out by hand from its stated formulas; one checks that a
world without `sea` is the world it was before the mode existed; the slow ones run a short wall-clock fleet
in the sea mode as separate processes (the launcher cannot yet, see `start_sea_fleet`) and read its logs.
"""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import ValidationError

from agent.config import ConfigError
from agent.core.records import Command
from mission_log.reader import read_log
from sim_bridge.bridge import BridgeSettings, SimBridge
from sim_bridge.fleet import AGENT_LISTEN, agent_configs, at_sea, free_port
from sim_bridge.scenario import Scenario, select_scenario
from sim_bridge.world import Frame, SeaSensors, VesselClock, World, WorldConfig, sea_steps, sea_world, streams

REPO = Path(__file__).resolve().parents[1]
SEA_TRIAL = REPO / "configs" / "scenarios" / "sea_trial.yaml"
TABLE2 = REPO / "configs" / "scenarios" / "table2_estimators.yaml"
QUIET = {"range_noise": {"kind": "gaussian", "variance": 0.0}, "bearing_variance": 0.0,
         "displacement_variance": 0.0, "heading_variance": 0.0}
STILL_TARGET = {"kind": "constant_velocity", "position": (0.0, 5.0), "velocity": (0.0, 0.0)}


def config(sea: dict, vessels=None, **changes) -> WorldConfig:
    vessels = vessels or [{"id": "a", "position": (0.0, 0.0)}, {"id": "b", "position": (10.0, 0.0)}]
    return WorldConfig.model_validate({"vessels": vessels, "target": STILL_TARGET, **QUIET, "sea": sea, **changes})


# --- the clock model ---------------------------------------------------------------------------------------

def test_a_vessel_clock_reads_true_time_plus_offset_plus_drift():
    clock = VesselClock(offset=0.05, drift=20e-6)
    # c(100 s) = 100 + 0.05 + 20e-6 * 100 = 100.052 s
    assert clock.read(100.0) == pytest.approx(100.052, abs=1e-12)
    assert clock.stamp_ns(100.0, epoch_ns=1_700_000_000_000_000_000) == 1_700_000_000_000_000_000 + 100_052_000_000
    assert VesselClock(offset=-0.03, drift=0.0).stamp_ns(0.0) == -30_000_000


def test_clocks_and_phases_are_drawn_from_the_seed_in_the_stated_order():
    sea = {"offset_ms": 50.0, "drift_ppm": 20.0, "uwb": {"period_ms": 125.0}}
    sensors = SeaSensors(config(sea), np.random.default_rng(7))
    # By hand from the docstring's order: per vessel, offset, drift, then a phase per odometry, uwb, camera.
    rng = np.random.default_rng(7)
    for vessel in ("a", "b"):
        offset, drift = rng.uniform(-1, 1) * 50.0, rng.uniform(-1, 1) * 20.0
        phases = [rng.uniform(0, 1) * period for period in (100e6, 125e6, 100e6)]
        assert sensors.clocks[vessel] == VesselClock(offset * 1e-3, drift * 1e-6)
        assert [sensors.phases_ns[vessel, s] for s in ("odometry", "uwb", "camera")] == [int(p) for p in phases]
        assert abs(sensors.clocks[vessel].offset) <= 0.05 and abs(sensors.clocks[vessel].drift) <= 20e-6
    # A listed clock wins, and the other vessel's draws stay as they were.
    listed = SeaSensors(config({**sea, "offsets_ms": {"a": 10.0}, "drifts_ppm": {"a": -3.0}}),
                        np.random.default_rng(7))
    assert listed.clocks["a"] == VesselClock(0.01, -3e-6)
    assert listed.clocks["b"] == sensors.clocks["b"] and listed.phases_ns == sensors.phases_ns


def test_ranging_rounds_at_8_hz_fall_between_the_ticks():
    sensors = SeaSensors(config({"uwb": {"period_ms": 125.0, "phase_ms": 30.0}}), np.random.default_rng(0))
    # t_n = 30 ms + n 125 ms: 30, 155, 280, 405 ms in the first half second; none on a 100 ms tick.
    assert sensors.times_ns("a", "uwb", 0, 500_000_000) == [30_000_000, 155_000_000, 280_000_000, 405_000_000]
    per_tick = [sensors.times_ns("a", "uwb", k * 100_000_000, (k + 1) * 100_000_000) for k in range(10)]
    # 30, 155, 280, -, 405, 530, 655, 780, -, 905 ms: 8 rounds a second over 10 ticks, two without one.
    assert [len(times) for times in per_tick] == [1, 1, 1, 0, 1, 1, 1, 1, 0, 1]
    assert [t for times in per_tick for t in times] == sensors.times_ns("a", "uwb", 0, 1_000_000_000)   # once each
    # The default period is the world's dt; a phase of 0 puts the measurements on the ticks.
    on_ticks = SeaSensors(config({"odometry": {"phase_ms": 0.0}}), np.random.default_rng(0))
    assert on_ticks.times_ns("a", "odometry", 200_000_000, 300_000_000) == [200_000_000]


def quiet_pair(sea: dict) -> tuple[World, SeaSensors]:
    """Vessel a from (0, 0) along x at 2 m/s, b still at (10, 0), the target still at (0, 5); exact sensors."""
    world_config = config(sea)
    return World(world_config, np.random.default_rng(1)), SeaSensors(world_config, np.random.default_rng(2))


def first_period(world: World, sensors: SeaSensors):
    before = Frame.of(world)
    world.step({"a": Command(2.0, 0.0), "b": Command(0.0, 0.0)})
    return {(m.vessel, m.sensor): m for m in sensors.measure(before, Frame.of(world))}


def test_measurements_between_ticks_see_the_world_at_their_own_time():
    world, sensors = quiet_pair({"odometry": {"phase_ms": 50.0}, "uwb": {"phase_ms": 30.0},
                                 "camera": {"phase_ms": 70.0}})
    found = first_period(world, sensors)
    # At t = 30 ms, a is at (0.06, 0): the range to b is 9.94 m (not 10 m at the tick, nor 9.8 m at the next).
    assert found["a", "uwb"].measured == pytest.approx(0.03)
    assert found["a", "uwb"].values["ranges"] == {"b": pytest.approx(9.94, abs=1e-12)}
    # At t = 50 ms a's odometry has moved 0.1 m; the heading reading is the tick's.
    np.testing.assert_allclose(found["a", "odometry"].values["position"], [0.1, 0.0], atol=1e-12)
    assert found["a", "odometry"].values["heading"] == 0.0
    # At t = 70 ms a is at (0.14, 0): the bearing from the target (0, 5) to it.
    np.testing.assert_allclose(found["a", "camera"].values["bearing"], np.array([0.14, -5.0]) / math.hypot(0.14, 5.0),
                               atol=1e-12)


def test_stamps_at_arrival_and_at_measurement_in_the_vessels_clock():
    sea = {"offsets_ms": {"a": 40.0}, "drifts_ppm": {"a": 100.0},
           "uwb": {"phase_ms": 30.0, "latency_ms": 20.0}, "stamps": "arrival"}
    found = first_period(*quiet_pair(sea))["a", "uwb"]
    # Measured at 30 ms, at the driver 20 ms later; stamped c(0.05) = 0.05 + 0.04 + 100e-6 * 0.05 s.
    assert (found.measured, found.arrival) == (pytest.approx(0.03), pytest.approx(0.05))
    assert found.stamp_ns == 90_005_000
    at_measurement = first_period(*quiet_pair({**sea, "stamps": "measurement"}))["a", "uwb"]
    assert at_measurement.arrival == pytest.approx(0.05)          # it still arrives late ...
    assert at_measurement.stamp_ns == 70_003_000                  # ... but carries c(0.03) = 0.03 + 0.04 + 3e-6


def test_latency_jitter_stays_within_its_bounds_around_its_mean():
    world, sensors = quiet_pair({"uwb": {"latency_ms": 30.0, "jitter_ms": 10.0}})
    latencies = []
    for _ in range(300):
        before = Frame.of(world)
        world.step({})
        latencies += [m.arrival - m.measured for m in sensors.measure(before, Frame.of(world)) if m.sensor == "uwb"]
    latencies = np.array(latencies)
    assert len(latencies) == 600                                   # two vessels, one round per tick
    assert latencies.min() >= 0.020 - 1e-12 and latencies.max() <= 0.040 + 1e-12
    assert latencies.min() < 0.021 and latencies.max() > 0.039     # the whole band is used, uniform
    assert latencies.mean() == pytest.approx(0.030, abs=0.001)     # 3 sigma of the mean: 10 ms / sqrt(3 * 600)


def test_the_sea_world_moves_in_short_steps_with_the_noise_of_a_tick_unchanged():
    walk = {"kind": "random_walk", "position": (0.0, 0.0), "process_noise": 0.01}
    world = config({"step_ms": 20.0}, target=walk, displacement_variance=1e-6, heading_variance=0.01)
    fine = sea_world(world)
    assert sea_steps(world) == 5 and fine.dt == pytest.approx(0.02)
    # Variances per step: R_delta / 5 and q / 5, so five steps add up to one tick's; a heading reading's stays.
    assert fine.displacement_variance == pytest.approx(2e-7) and fine.target.process_noise == pytest.approx(0.002)
    assert fine.heading_variance == 0.01 and fine.vessels == world.vessels and fine.sea == world.sea
    # A command acts from the step after it arrives: 2 m/s for the last 3 of 5 steps moves 0.12 m in the tick.
    moving = World(sea_world(config({"step_ms": 20.0})), np.random.default_rng(0))
    for step in range(5):
        moving.step({"a": Command(2.0 if step >= 2 else 0.0, 0.0), "b": Command(0.0, 0.0)})
    assert moving.time_ns == 100_000_000
    np.testing.assert_allclose(moving.truth().positions["a"], [0.12, 0.0], atol=1e-12)


@pytest.mark.parametrize(("sea", "words"), [
    ({"step_ms": 30.0}, "must divide"),
    ({"uwb": {"latency_ms": 5.0, "jitter_ms": 6.0}}, "jitter_ms"),
    ({"uwb": {"period_ms": 125.0, "phase_ms": 125.0}}, "phase_ms"),
    ({"offsets_ms": {"z": 1.0}}, "unknown vessels"),
    ({"offset_ms": -1.0}, "offset_ms"),
    ({"stamps": "whenever"}, "stamps"),
])
def test_a_bad_sea_section_is_refused(sea, words):
    with pytest.raises(ValidationError, match=words):
        config(sea)


def test_the_sea_mode_is_refused_in_lockstep():
    _, scenario = select_scenario(SEA_TRIAL, "sea")
    with pytest.raises(ConfigError, match="real-time"):
        SimBridge(scenario, BridgeSettings(mode="lockstep"))


# --- the ideal mode is unchanged ----------------------------------------------------------------------------

def fingerprint(world: World, ticks: int = 50) -> np.ndarray:
    """Every value the world's sensors give over `ticks` steps of a fixed command, in order."""
    values: list[float] = []
    for _ in range(ticks):
        for reading in world.sense().values():
            values.extend(np.asarray(reading.odometry.position, dtype=float))
            values.append(float(reading.odometry.heading))
            values.extend(float(r) for r in reading.ranges.values())
            if reading.bearing is not None:
                values.extend(np.asarray(reading.bearing, dtype=float))
        world.step({v: Command(1.0, 0.1) for v in world.live()})
    return np.array(values)


# Recorded with the code before the sea mode existed (commit adc83fe): Table II, MCKF, its seed 2. Compared
# within 1e-12 relative: OpenBLAS picks its kernels by processor and they round differently in the last bit
# (on an AVX-512 EPYC, 39 of the 1600 values differ from the Haswell kernels' by one ulp, 3.5e-16), while a
# change of the model or of a random draw moves these values by millimetres.
BEFORE_SEA = np.load(Path(__file__).parent / "data" / "world_before_sea.npy")


def test_a_world_without_sea_is_the_world_it_was_before():
    _, scenario = select_scenario(TABLE2, "mckf")
    assert scenario.world.sea is None
    random = streams(scenario.seed)
    assert random.loss_seed == 2834126987
    assert random.initial.normal(size=2).tolist() == [0.2928247151363088, -1.6237030300648838]
    without_sea = fingerprint(World(scenario.world, random.world))
    np.testing.assert_allclose(without_sea, BEFORE_SEA, rtol=1e-12, atol=0.0)
    # The sea section leaves the world's own stream alone: its measurements draw from streams().sea. Both
    # worlds are computed here, on the same kernels, so they must agree bit for bit.
    _, sea = select_scenario(SEA_TRIAL, "sea")
    np.testing.assert_array_equal(fingerprint(World(sea.world, streams(scenario.seed).world)), without_sea)


# --- a wall-clock fleet in the sea mode, as processes ----------------------------------------------------------

def start_sea_fleet(scenario_path: Path, variant: str | None, folder: Path, duration: float | None = None,
                    seed: int | None = None, lead: float = 6.0) -> tuple[subprocess.Popen, dict, int]:
    """What `usv-fleet run` does for a sea scenario, with the duration and lead chosen: the sim bridge in real
    time with an epoch `lead` s ahead, and one agent per vessel on the wall clock read through its vessel's
    clock (`at_sea`). Returns (bridge, {vessel: agent}, epoch_ns)."""
    name, scenario = select_scenario(scenario_path, variant)
    if duration is not None:
        data = scenario.model_dump(mode="json")
        data["duration"] = duration
        scenario_path = folder / "scenario.yaml"
        scenario_path.write_text(yaml.safe_dump({"name": name, "base": data}))
        scenario = Scenario.model_validate(data)
        variant = None
    port = free_port()
    epoch_ns = time.time_ns() + int(lead * 1e9)
    (folder / "bridge.yaml").write_text(yaml.safe_dump({
        "mode": "realtime", "epoch_ns": epoch_ns, "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
        "log": str(folder / "sim.mcap")}))
    agents = {}
    configs = agent_configs(scenario, seed, folder, lambda v: {
        "listen": [AGENT_LISTEN], "connect": [f"tcp/127.0.0.1:{port}"]})
    at_sea(scenario, seed, epoch_ns, configs)
    for vessel, settings in configs.items():
        (folder / f"agent-{vessel}.yaml").write_text(yaml.safe_dump(settings))
    command = [sys.executable, "-m", "sim_bridge", "--scenario", str(scenario_path), "--config",
               str(folder / "bridge.yaml")]
    command += ["--variant", variant] if variant else []
    command += ["--seed", str(seed)] if seed is not None else []
    bridge = subprocess.Popen(command, stdout=(folder / "bridge.log").open("w"), stderr=subprocess.STDOUT)
    for vessel in configs:
        agents[vessel] = subprocess.Popen(
            [sys.executable, "-m", "agent", "--vessel", vessel, "--config", str(folder / f"agent-{vessel}.yaml")],
            stdout=(folder / f"agent-{vessel}.log").open("w"), stderr=subprocess.STDOUT)
    return bridge, agents, epoch_ns


def finish_sea_fleet(bridge: subprocess.Popen, agents: dict, timeout: float) -> None:
    """Wait for the bridge to end the mission, then stop the agents as the launcher does (SIGTERM)."""
    try:
        bridge.wait(timeout=timeout)
    finally:
        for process in [*agents.values(), bridge]:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for process in [*agents.values(), bridge]:
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()


def true_times(stamps_ns: np.ndarray, clock: VesselClock, epoch_ns: int) -> np.ndarray:
    """Invert c(t) = t + o + d t: the true time (s from the epoch) a stamp of this clock was taken at."""
    return ((stamps_ns - epoch_ns) * 1e-9 - clock.offset) / (1.0 + clock.drift)


@pytest.mark.slow
def test_a_wall_clock_fleet_in_the_sea_mode_gets_ranges_stamped_off_the_ticks(tmp_path):
    variant = "uwb_8hz"
    _, scenario = select_scenario(SEA_TRIAL, variant)
    bridge, agents, epoch_ns = start_sea_fleet(SEA_TRIAL, variant, tmp_path, duration=8.0)
    finish_sea_fleet(bridge, agents, timeout=60)
    bridge_log = (tmp_path / "bridge.log").read_text()
    assert bridge.returncode == 0, bridge_log
    assert "81 ticks" in bridge_log and "0 refused" in bridge_log, bridge_log
    sea = read_log(tmp_path / "sim.mcap").messages("/bridge/sea")
    assert sea and sea[0][1]["epoch_ns"] == epoch_ns        # the agents were ready before the epoch
    sensors = SeaSensors(scenario.world, streams(scenario.seed).sea)
    timing = scenario.world.sea
    for vessel, clock in sensors.clocks.items():
        log = read_log(tmp_path / f"agent-{vessel}.mcap")
        inputs = [m for _, m in log.messages(f"/{vessel}/inputs")]
        ranged = [m for m in inputs if m["ranges"]]
        # Ranges at 8 Hz and ticks at 10 Hz: most ticks have a range pair, each with its own stamp.
        assert len(ranged) > 40, f"vessel {vessel}: {len(ranged)} ticks with ranges"
        stamps = np.array([m["range_stamp"] for m in ranged if m["range_stamp"] is not None])
        ticks = np.array([m["time"] for m in ranged if m["range_stamp"] is not None])
        assert len(stamps) == len(ranged)                     # never the tick's own time
        assert np.all(np.abs(stamps - ticks) > 1e-6)
        # Mapped back through the vessel's clock, each range stamp is a round (phase + n 125 ms) plus the
        # UWB latency (20 +- 10 ms): the bridge stamped in this vessel's clock, at arrival.
        rounds = true_times(np.round(stamps * 1e9), clock, epoch_ns) - sensors.phases_ns[vessel, "uwb"] * 1e-9
        late = rounds - np.round(rounds / 0.125) * 0.125
        assert np.all(np.abs(late - timing.uwb.latency_ms * 1e-3) <= timing.uwb.jitter_ms * 1e-3 + 1e-5), late
        # The odometry (the tick's time) likewise: phase + n 100 ms, plus 10 +- 5 ms.
        odometry = true_times(np.round(np.array([m["time"] for m in inputs if m["odometry"]]) * 1e9), clock,
                              epoch_ns) - sensors.phases_ns[vessel, "odometry"] * 1e-9
        late = odometry - np.round(odometry / 0.1) * 0.1
        assert np.all(np.abs(late - 0.010) <= 0.005 + 1e-5), late
        # The agent refused nothing for its age: the stamps are within milliseconds of its own clock.
        refused = log.messages(f"/{vessel}/summary")[-1][1]["refused"]
        assert not {"stale", "future"} & {reason for reason, count in refused.items() if count}, refused
