"""The target's sea motions (issue 30, item 3): moored (a circle round its anchor) and drifting (with the
current), and that the other targets ignore the current handed to `make_target`. Expected values are closed
forms worked out here."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.config import ConfigError, parse_mapping
from agent.core.records import Command
from sim_bridge.current import CurrentConfig
from sim_bridge.environment import Environment, EnvironmentConfig
from sim_bridge.targets import DriftingSpec, MooredSpec, RandomWalkSpec, SinusoidSpec, make_target
from sim_bridge.world import World, WorldConfig


def environment(**current) -> Environment:
    return Environment(EnvironmentConfig(current=CurrentConfig(**current)), np.random.default_rng(0))


@pytest.mark.parametrize("clockwise", [False, True])
def test_a_moored_target_stays_on_its_circle_and_turns_once_a_period(clockwise):
    spec = MooredSpec(anchor=(10.0, -5.0), radius=3.0, period=60.0, phase=0.5, clockwise=clockwise)
    target = make_target(spec)
    rng = np.random.default_rng(0)
    start = target.position.copy()
    np.testing.assert_allclose(start, (10.0 + 3 * math.cos(0.5), -5.0 + 3 * math.sin(0.5)), atol=1e-12)
    for k in range(1, 1201):                                   # 120 s, two turns, at dt = 0.1 s
        target.step(0.1, rng)
        assert math.hypot(*(target.position - (10.0, -5.0))) == pytest.approx(3.0, abs=1e-9)
        # Speed 2 pi R / T = 0.31416 m/s, along the tangent.
        assert math.hypot(*target.velocity) == pytest.approx(2 * math.pi * 3.0 / 60.0, rel=1e-12)
        assert float(np.dot(target.velocity, target.position - (10.0, -5.0))) == pytest.approx(0.0, abs=1e-9)
        if k == 150:                                           # 15 s, a quarter turn: 0.5 +- pi / 2
            angle = 0.5 + (-1 if clockwise else 1) * math.pi / 2
            np.testing.assert_allclose(target.position, (10.0 + 3 * math.cos(angle), -5.0 + 3 * math.sin(angle)),
                                       atol=1e-9)
    np.testing.assert_allclose(target.position, start, atol=1e-9)
    assert rng.random() == np.random.default_rng(0).random()   # no draws


def test_a_drifting_target_moves_with_a_uniform_current():
    # 0.5 m/s towards atan2(3, 4): velocity (0.4, 0.3); after 500 steps of 0.1 s, 50 s: (20, 15) further on.
    env = environment(speed=0.5, direction=math.atan2(3.0, 4.0))
    target = make_target(DriftingSpec(position=(1.0, 2.0)), current=env.current)
    np.testing.assert_allclose(target.velocity, (0.4, 0.3), atol=1e-15)
    for _ in range(500):
        target.step(0.1, np.random.default_rng(0))
    np.testing.assert_allclose(target.position, (21.0, 17.0), atol=1e-11)
    np.testing.assert_allclose(target.velocity, (0.4, 0.3), atol=1e-15)


def test_a_drifting_target_follows_the_sheared_current_in_closed_form():
    # Across the flow: c = (0.3 + 0.01 y, 0). From (0, 20) the target keeps y = 20 and moves at 0.5 m/s.
    env = environment(speed=0.3, shear=0.01)
    target = make_target(DriftingSpec(position=(0.0, 20.0)), current=env.current)
    for _ in range(1000):
        target.step(0.1, np.random.default_rng(0))
    np.testing.assert_allclose(target.position, (50.0, 20.0), atol=1e-10)
    # Along the flow: dx/dt = 0.3 + 0.01 x, x(t) = (x0 + 30) e^(0.01 t) - 30; from x0 = 0 over 100 s:
    # 30 (e - 1) = 51.5484549. The midpoint rule multiplies x + 30 by 1 + h + h^2 / 2 (h = 0.01 dt) each step:
    # 30 (1.0010005^1000 - 1) = 51.5484413, 1.36e-5 m short, its O(dt^2) error (30 e h^3 / 6 per step).
    env = environment(speed=0.3, shear=0.01, shear_direction=0.0)
    target = make_target(DriftingSpec(position=(0.0, 4.0)), current=env.current)
    for _ in range(1000):
        target.step(0.1, np.random.default_rng(0))
    assert target.position[0] == pytest.approx(30.0 * (1.0010005**1000 - 1.0), abs=1e-9)
    assert target.position[0] == pytest.approx(30.0 * (math.e - 1.0), abs=2e-5)
    assert target.position[1] == pytest.approx(4.0, abs=1e-12)
    assert target.velocity[0] == pytest.approx(0.3 + 0.01 * target.position[0], rel=1e-12)


def test_a_drifting_target_without_a_current_stays_where_it_is():
    target = make_target(DriftingSpec(position=(3.0, -4.0)))
    for _ in range(10):
        target.step(0.1, np.random.default_rng(0))
    np.testing.assert_array_equal(target.position, (3.0, -4.0))
    np.testing.assert_array_equal(target.velocity, (0.0, 0.0))


def test_the_other_targets_ignore_the_current_bit_for_bit():
    env = environment(speed=0.5)
    for spec in (RandomWalkSpec(position=(1.0, 1.0)),
                 SinusoidSpec(position=(0.0, 0.0), speed=0.4, amplitude=2.0, wavelength=20.0)):
        plain, given = make_target(spec), make_target(spec, current=env.current)
        a, b = np.random.default_rng(4), np.random.default_rng(4)
        for _ in range(50):
            plain.step(0.1, a)
            given.step(0.1, b)
            assert np.array_equal(plain.position, given.position)
            assert np.array_equal(plain.velocity, given.velocity)


def test_the_world_takes_the_new_targets_from_its_config():
    vessels = [{"id": "a", "position": (5.0, 0.0)}]
    world = World(WorldConfig.model_validate({"vessels": vessels, "target": {
        "kind": "moored", "anchor": (0.0, 0.0), "radius": 2.0, "period": 40.0}}), np.random.default_rng(0))
    for _ in range(100):
        world.step({"a": Command(surge=0.0, yaw_rate=0.0)})
    # 10 s of a 40 s turn: a quarter, from (2, 0) to (0, 2).
    np.testing.assert_allclose(world.truth().target_position, (0.0, 2.0), atol=1e-9)
    world = World(WorldConfig.model_validate({"vessels": vessels, "target": {
        "kind": "drifting", "position": (1.0, 1.0)}}), np.random.default_rng(0))
    world.step({"a": Command(surge=0.0, yaw_rate=0.0)})
    np.testing.assert_array_equal(world.truth().target_position, (1.0, 1.0))   # no current in the world yet


@pytest.mark.parametrize("target, field", [
    ({"kind": "moored", "anchor": (0.0, 0.0), "radius": -1.0}, "radius"),
    ({"kind": "moored", "anchor": (0.0, 0.0), "period": 0.0}, "period"),
    ({"kind": "moored", "anchor": (0.0, math.nan)}, "anchor"),
    ({"kind": "drifting", "position": (math.inf, 0.0)}, "position"),
    ({"kind": "drifting"}, "position"),
])
def test_bad_target_configs_are_refused_in_one_line(target, field):
    with pytest.raises(ConfigError) as error:
        parse_mapping(WorldConfig, {"vessels": [{"id": "a", "position": (0.0, 0.0)}], "target": target}, "w.yaml")
    message = str(error.value)
    assert "\n" not in message and f"target.{target['kind']}.{field}" in message
