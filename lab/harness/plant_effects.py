"""The boat and the water around today's kinematic world, in process: a wrapper around `World` for the lab.

`with_effects(world, effects, rng)` returns the same world with its methods wrapped so that it adds:
- a boat between the command and the kinematics (1), (2): per vessel, the commanded surge u_c and yaw rate
  r_c are clipped to the rate limits, then pass a first-order lag x_{k+1} = x_k + (1 - e^{-dt/tau})(u_c - x_k)
  whose change per step is clipped to the acceleration limit times dt; the world moves with x_{k+1};
- a per-vessel compass bias b_i: the odometry heading reads theta + b_i and the dead-reckoned position,
  which starts at 0, reads R(b_i) times the true one, as displacements measured with a biased compass sum
  to; with `bias_bearings` the camera's bearing turns by b_i as well (its direction is the hull's plus the
  compass heading);
- a uniform current c: each vessel moves by c dt more over ground per step, its water-referenced odometry
  does not see it.
Nothing is drawn from the world's generator (the biases come from `rng`), so with no effect the world is
the kinematic world bit for bit. A `PlantEffects` of zeros wraps nothing.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from agent.angles import wrap_angle
from agent.core.records import Command
from sim_bridge.world import World, WorldConfig


@dataclass(frozen=True)
class PlantEffects:
    surge_lag: float = 0.0  # tau_u (s); 0: none
    yaw_lag: float = 0.0  # tau_r (s); 0: none
    max_surge: float | None = None  # |u| at most this (m/s)
    max_yaw_rate: float | None = None  # |r| at most this (rad/s)
    max_acceleration: float | None = None  # |du/dt| at most this (m/s^2)
    max_yaw_acceleration: float | None = None  # |dr/dt| at most this (rad/s^2)
    compass_bias_std: float = 0.0  # each vessel's bias b_i ~ N(0, this^2) (rad)
    compass_biases: tuple[float, ...] | None = None  # the biases themselves, in config order (rad)
    bias_bearings: bool = True  # the camera's bearing turns with the compass bias
    current: tuple[float, float] = (0.0, 0.0)  # c over ground (m/s)

    @property
    def boat(self) -> bool:
        return any(
            (
                self.surge_lag,
                self.yaw_lag,
                self.max_surge,
                self.max_yaw_rate,
                self.max_acceleration,
                self.max_yaw_acceleration,
            )
        )


def lag_step(
    state: float, command: float, dt: float, tau: float, limit: float | None, acceleration: float | None
) -> float:
    """One step of the boat's response: the command clipped to +-limit, a first-order lag of time constant
    tau (exact for a command held over dt; tau 0: the command itself), the change clipped to
    acceleration dt."""
    if limit is not None:
        command = min(max(command, -limit), limit)
    target = command if tau <= 0.0 else state + (1.0 - math.exp(-dt / tau)) * (command - state)
    if acceleration is not None:
        change = acceleration * dt
        target = min(max(target, state - change), state + change)
    return target


def rotate(x: float, y: float, angle: float) -> tuple[float, float]:
    c, s = math.cos(angle), math.sin(angle)
    return c * x - s * y, s * x + c * y


def draw_biases(effects: PlantEffects, config: WorldConfig, rng: np.random.Generator) -> dict[str, float]:
    ids = [v.id for v in config.vessels]
    if effects.compass_biases is not None:
        if len(effects.compass_biases) != len(ids):
            raise ValueError(f"compass_biases: {len(ids)} vessels, {len(effects.compass_biases)} biases")
        return dict(zip(ids, map(float, effects.compass_biases)))
    if effects.compass_bias_std == 0.0:
        return {}
    return dict(zip(ids, rng.normal(0.0, effects.compass_bias_std, len(ids)).tolist()))


def with_effects(world: World, effects: PlantEffects, rng: np.random.Generator) -> World:
    """`world` with `effects` (wrapped in place and returned). Its first tick's readings, drawn at
    construction, are already biased and the current acts from the first step."""
    config = world.config
    dt = config.dt
    biases = draw_biases(effects, config, rng)
    world.biases = biases  # for the lab's figures
    if effects.boat:
        response: dict[str, tuple[float, float]] = {}  # each vessel's (u, r) as it moves now
        world.responses = response
        inner_step = world.step

        def step(commands: Mapping[str, Command]) -> None:
            moved = {}
            for vessel in world.live():
                command = commands.get(vessel)
                try:
                    surge, yaw_rate = float(command.surge), float(command.yaw_rate)  # type: ignore[union-attr]
                except (AttributeError, TypeError, ValueError):
                    moved[vessel] = command  # the world counts it and stops the vessel
                    continue
                if not (math.isfinite(surge) and math.isfinite(yaw_rate)):
                    moved[vessel] = command
                    continue
                u, r = response.get(vessel, (0.0, 0.0))
                u = lag_step(u, surge, dt, effects.surge_lag, effects.max_surge, effects.max_acceleration)
                r = lag_step(
                    r, yaw_rate, dt, effects.yaw_lag, effects.max_yaw_rate, effects.max_yaw_acceleration
                )
                response[vessel] = (u, r)
                moved[vessel] = Command(u, r)
            inner_step(moved)

        world.step = step
    if effects.current != (0.0, 0.0):
        cx, cy = effects.current
        inner_begin = world._begin_tick

        def begin_tick() -> None:
            # Called by `step` after the kinematics and before the tick's readings are drawn.
            for vessel in world._vessels.values():
                (x, y), (vx, vy) = vessel.position.tolist(), vessel.velocity.tolist()
                vessel.position = _fixed(x + cx * dt, y + cy * dt)
                vessel.velocity = _fixed(vx + cx, vy + cy)
            inner_begin()

        world._begin_tick = begin_tick
    if biases:
        inner_sense = world.sense

        def sense():
            readings = inner_sense()
            return {
                i: _biased(reading, biases.get(i, 0.0), effects.bias_bearings)
                for i, reading in readings.items()
            }

        world.sense = sense
    return world


def _fixed(x: float, y: float) -> np.ndarray:
    array = np.array([x, y])
    array.setflags(write=False)
    return array


def _biased(reading, bias: float, bearings: bool):
    if bias == 0.0:
        return reading
    odometry = reading.odometry
    x, y = np.asarray(odometry.position, dtype=float).tolist()
    odometry = dataclasses.replace(
        odometry, position=_fixed(*rotate(x, y, bias)), heading=float(wrap_angle(odometry.heading + bias))
    )
    bearing = reading.bearing
    if bearings and bearing is not None:
        bearing = _fixed(*rotate(*np.asarray(bearing, dtype=float).tolist(), bias))
    return dataclasses.replace(reading, odometry=odometry, bearing=bearing)


def world_factory(effects: PlantEffects, seed: int):
    """A `make_world` for lab/runner.py's `run`: the kinematic world with `effects`, the biases drawn from a
    generator of its own seeded by (seed, 30), so the world's stream is the kinematic run's."""

    def make(config: WorldConfig, rng: np.random.Generator) -> World:
        return with_effects(World(config, rng), effects, np.random.default_rng([seed, 30]))

    return make
