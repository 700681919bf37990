"""The world with its hulls in the water: the environment of a scenario (`world.environment`) moves the hulls
and a drifting target, and the odometry of `world.sensors` reads what those hulls do (issue 30's pieces,
joined in sim_bridge/world.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.config import ConfigError, parse_mapping, parse_yaml
from agent.core.records import Command
from sim_bridge.world import World, WorldConfig

TARGET = {"kind": "constant_velocity", "position": (30.0, 0.0), "velocity": (0.0, 0.0)}
QUIET = {"range_noise": {"kind": "gaussian", "variance": 0.0}, "bearing_variance": 0.0,
         "displacement_variance": 0.0, "heading_variance": 0.0}
CURRENT = 0.5     # m/s, the `current` sea state, along +x


def world(seed: int = 0, **changes) -> World:
    data = {"vessels": [{"id": "a", "position": (0.0, 0.0), "heading": 1.0}], "target": TARGET, **QUIET,
            "dynamics": {"preset": "otter"}, **changes}
    return World(WorldConfig.model_validate(data), np.random.default_rng(seed))


def drift(w: World, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(true displacement, odometry displacement) of vessel a, left without thrust (a zero command)."""
    start, odometry = w.truth().positions["a"].copy(), w.sense()["a"].odometry.position.copy()
    for _ in range(round(seconds / w.config.dt)):
        w.step({"a": Command(0.0, 0.0)})
    return w.truth().positions["a"] - start, w.sense()["a"].odometry.position - odometry


def test_a_hull_without_thrust_is_carried_by_the_current_and_a_speed_log_does_not_see_it():
    """Water-referenced odometry drifts from the truth by the integral of the current (sea-physics.md §4). A
    hull is placed at rest in the water, so it moves with the current from the start; a perfect speed log
    reads its motion through the water: none."""
    seconds = 60.0
    moved, odometry = drift(world(environment="current", sensors={"odometry": {"kind": "water_log_compass"}}),
                            seconds)
    assert moved == pytest.approx([CURRENT * seconds, 0.0], abs=1e-6)
    assert odometry == pytest.approx([0.0, 0.0], abs=1e-9)


def test_in_still_water_the_speed_log_reads_the_track_except_the_sideslip_of_a_turn():
    """Straight ahead the log's dead reckoning is the truth; turning, the hull slips sideways (sway v, about
    0.2 m/s for the Otter at 1 m/s and 0.1 rad/s) and a log, which measures along the hull, misses it."""
    def run(rate: float) -> tuple[np.ndarray, np.ndarray]:
        w = world(sensors={"odometry": {"kind": "water_log_compass"}})
        start, odometry = w.truth().positions["a"].copy(), w.sense()["a"].odometry.position.copy()
        slip = np.zeros(2)
        for _ in range(200):
            heading = w.truth().headings["a"]
            w.step({"a": Command(1.0, rate)})
            v = w.truth().body_velocities["a"][1]
            mean = heading + 0.5 * float(np.angle(np.exp(1j * (w.truth().headings["a"] - heading))))
            slip += w.config.dt * v * np.array([-math.sin(mean), math.cos(mean)])
        moved = w.truth().positions["a"] - start
        return moved - (w.sense()["a"].odometry.position - odometry), slip

    straight, _ = run(0.0)
    assert straight == pytest.approx([0.0, 0.0], abs=1e-9)
    missed, slip = run(0.1)
    assert np.linalg.norm(slip) > 1.0                        # the effect is there, metres of it
    assert np.linalg.norm(missed - slip) < 0.1 * np.linalg.norm(slip)


def test_a_drifting_target_moves_with_the_scenarios_current():
    w = world(environment="current", target={"kind": "drifting", "position": (30.0, 0.0)})
    start = w.truth().target_position.copy()
    for _ in range(100):
        w.step({"a": Command(0.0, 0.0)})
    assert w.truth().target_position - start == pytest.approx([CURRENT * 10.0, 0.0], abs=1e-9)


def test_the_environment_is_drawn_from_the_worlds_seed():
    def positions(seed: int) -> np.ndarray:
        w = world(seed, environment="moderate")
        for _ in range(100):
            w.step({"a": Command(1.0, 0.2)})
        return w.truth().positions["a"]

    assert np.array_equal(positions(3), positions(3))
    assert not np.array_equal(positions(3), positions(4))


def read(text: str) -> WorldConfig:
    text = "vessels: [{id: a, position: [0, 0]}]\ntarget: {kind: constant_velocity, position: [5, 0], " \
           "velocity: [0, 0]}\n" + text
    return parse_mapping(WorldConfig, parse_yaml(text, "world.yaml"), "world.yaml")


def test_an_environment_without_hulls_or_with_an_unknown_name_is_one_line():
    with pytest.raises(ConfigError) as error:
        read("environment: moderate\n")
    assert "world.dynamics" in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(ConfigError) as error:
        read("dynamics: {preset: otter}\nenvironment: stormy\n")
    assert "moderate" in str(error.value) and "\n" not in str(error.value)


def test_a_kinematic_world_with_sensors_has_no_environment():
    w = World(WorldConfig.model_validate({"vessels": [{"id": "a", "position": (0.0, 0.0)}], "target": TARGET}),
              np.random.default_rng(0))
    assert w.environment is None and math.isfinite(w.truth().positions["a"][0])


@pytest.mark.slow
def test_every_share_the_core_makes_at_sea_is_one_the_wire_carries(tmp_path):
    """At sea pairs lose their fix and start again from no prior (1e12 m^2): such an estimate is left out of
    the share, which the contract would otherwise refuse whole (the agent process then sent no share at all,
    and the fleet of processes parted from the in-process runner). Checked over every share of a run on the
    Otter's hull with the realistic sensors, where pairs lose their fixes."""
    from agent.contract import MAX_VARIANCE, encode
    from agent.core import step as core_step
    from agent.shell.translate import message_from_share
    from lab.harness import runner
    from sim_bridge.scenario import SCENARIOS_DIR, select_scenario, with_duration

    assert core_step.MAX_SHARED_VARIANCE == MAX_VARIANCE
    seen: list = []

    def stepping(params, state, inputs):
        state, output = core_step.step(params, state, inputs)
        seen.append(output.share)
        return state, output

    _, scenario = select_scenario(with_duration(SCENARIOS_DIR / "sea_states.yaml", tmp_path, 20.0), "moderate")
    original = runner.step
    runner.step = stepping
    try:
        runner.run(scenario, 0)
    finally:
        runner.step = original
    assert len(seen) == 4 * 201
    for n, share in enumerate(seen):
        encode(message_from_share(share, n))        # raises if the contract refuses it
    # The run does meet pairs without a fix: an estimate the share leaves out.
    assert any(len(share.neighbours) < 3 for share in seen)

