"""The simulated world: vessels, target, islands and every sensor, advanced one sampling period at a time.

The paper's world and sensor models (Sec. II): surge-yaw kinematics (1), (2); the target (3), (4) and its
other motions in `targets.py`; odometry (5); ranges (6) with the noise of (7) or (8) (agent/core/range_noise.py); bearings
(9). docs/equations.md says where the simulation departs from them (ranges clipped at 0, unit bearings).

Pure code: no clock, no I/O. All randomness comes from the generator given to `World`, drawn in the same
order every tick whatever the caller does, so a run is reproducible bit for bit from its seed:

1. in `step`: for each live vessel in config order its displacement and heading noise, then the target;
2. whenever a tick begins (at construction and at the end of every `step`): each joining vessel's heading
   noise, then the readings of the tick (for each live vessel in config order: its ranges to the others,
   then its bearing noise).

The error models of `WorldConfig.sensors` (`sensors.py`; the paper's by default) draw from their own stream,
spawned from that generator only when one is on, in the order `sensors.py` states, so the draws above stay.
Readings are drawn eagerly when a tick begins and cached, so `sense()` is free of side effects: calling it
twice, or not at all, changes nothing.

The sea mode (`WorldConfig.sea`, off by default; `SeaSensors`) measures like vessels at sea instead: each
vessel has its own clock (offset and drift), each sensor its own period, phase and latency, and the driver
stamps a message when it arrives. The sim bridge then steps the world in short steps (`sea_world`), and the
measurements are taken from its state interpolated between two steps (`Frame`), with their own random
stream (`Streams.sea`). Without a `sea` section nothing here changes: the same seed gives the same world.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from agent.angles import wrap_angle
from agent.config import NonNegativeFloat, PositiveFloat, StrictModel
from agent.contract import nanoseconds, seconds
from agent.core.range_noise import GaussianMixtureNoise, RangeNoise
from agent.core.records import Command, OdometryReading
from boat.presets import BoatPreset, preset
from boat.sway import SwayModel
from sim_bridge.environment import Environment, SeaState
from sim_bridge.geometry import (
    is_simple_polygon,
    sample_boundary,
    segment_intersects_polygon,
)
from sim_bridge.hull import HullFleet
from sim_bridge.noise import IsotropicGaussianNoise
from sim_bridge.sensors import (
    SensorsConfig,
    advance_odometry,
    antenna_positions,
    expand_preset,
    rotate,
    start_odometry,
    tilted_azimuth,
    uwb_faults,
)
from sim_bridge.targets import FiniteFloat, Point, TargetSpec, make_target

TIME_TOLERANCE = 1e-9   # s; join and leave times this close to a tick count as reached


class VesselSpec(StrictModel):
    id: str = Field(min_length=1)
    position: Point = Field(description="true start position (m)")
    heading: FiniteFloat = Field(0.0, description="true start heading (rad)")
    join_time: NonNegativeFloat = Field(0.0, description="when the vessel appears (s); 0: from the start")
    leave_time: NonNegativeFloat | None = Field(None, description="when it leaves for good (s); None: never")

    @model_validator(mode="after")
    def _leaves_after_joining(self) -> VesselSpec:
        if self.leave_time is not None and self.leave_time <= self.join_time:
            raise ValueError("leave_time must be after join_time")
        return self


class SensorTiming(StrictModel):
    """When one kind of sensor measures, and how late its messages reach the vessel's driver (sea mode)."""

    period_ms: PositiveFloat | None = Field(None, description="time between two measurements (ms); None: dt")
    # None: drawn for each vessel, uniform in [0, period).
    phase_ms: NonNegativeFloat | None = Field(
        None, description="time of the first measurement after the start (ms), less than the period")
    latency_ms: NonNegativeFloat = Field(0.0, description="mean time from the measurement to the driver (ms)")
    jitter_ms: NonNegativeFloat = Field(
        0.0, description="each latency is uniform in [latency - jitter, latency + jitter] (ms)")

    @model_validator(mode="after")
    def _consistent(self) -> SensorTiming:
        if self.jitter_ms > self.latency_ms:
            raise ValueError("jitter_ms must not exceed latency_ms (a message cannot arrive before it is measured)")
        if self.phase_ms is not None and self.period_ms is not None and self.phase_ms >= self.period_ms:
            raise ValueError("phase_ms must be less than period_ms")
        return self


class SeaConfig(StrictModel):
    """The sea mode: vessels with their own clocks, sensors with their own times and latencies, and drivers
    that stamp what they receive. Its presence switches it on (the sim bridge's real-time mode only)."""

    offset_ms: NonNegativeFloat = Field(
        0.0, description="each vessel's clock offset is drawn uniform in [-offset_ms, offset_ms]")
    drift_ppm: NonNegativeFloat = Field(
        0.0, description="each vessel's clock drift is drawn uniform in [-drift_ppm, drift_ppm]")
    offsets_ms: dict[str, FiniteFloat] = Field(default_factory=dict, description="vessel id -> offset, not drawn")
    drifts_ppm: dict[str, FiniteFloat] = Field(default_factory=dict, description="vessel id -> drift, not drawn")
    # An NTP step or an operator's date -s, for the vessel's driver and agent alike.
    steps: dict[str, list[tuple[NonNegativeFloat, FiniteFloat]]] = Field(
        default_factory=dict,
        description="vessel id -> [(sim time s, step ms)]: its clock steps by that much then")
    # A driver on a computer of its own; the vessel's sensors are stamped in that clock.
    driver_offsets_ms: dict[str, FiniteFloat] = Field(
        default_factory=dict,
        description="vessel id -> how far its driver's clock runs from its computer's (ms)")
    odometry: SensorTiming = Field(SensorTiming(), description="odometry (with the sonar, which rides along)")
    uwb: SensorTiming = SensorTiming()
    camera: SensorTiming = SensorTiming()
    # 'arrival' is the driver's clock at measurement + latency.
    stamps: Literal["arrival", "measurement"] = Field(
        "arrival", description="'arrival': a driver stamps a message when it receives it; 'measurement': when "
                               "measured")
    # As boats wait for the go: deployment estimates stamped within it stay true.
    hold_ms: NonNegativeFloat = Field(
        0.0, description="the vessels are held still (zero command) for this long at the start (ms)")
    # So a command acts within step_ms of its arrival.
    step_ms: PositiveFloat = Field(
        10.0, description="the world moves in steps this long, each with the latest command (ms; dt a multiple)")


class DynamicsConfig(StrictModel):
    """Hull dynamics (`sim_bridge/hull.py`: Fossen's 3-DOF model, thrusters, inner loop) for every vessel,
    instead of the paper's kinematics (1), (2)."""

    preset: str = Field(description="hull preset of boat/presets.py: otter, heron or wamv")
    overrides: dict[str, Any] = Field(
        default_factory=dict, description="changes deep-merged onto the preset, e.g. {thrusters: {time_constant: 0.2}}")
    step_ms: PositiveFloat = Field(20.0, description="integration step (ms), dividing the world's step")
    inner_loop_hz: PositiveFloat = Field(50.0, description="rate of the inner loop; its period a whole number of steps")

    @model_validator(mode="after")
    def _consistent(self) -> DynamicsConfig:
        self.boat()   # a bad preset name or override is reported with the world config
        every = 1e3 / (self.inner_loop_hz * self.step_ms)
        if abs(every - round(every)) > 1e-9 or round(every) < 1:
            raise ValueError(f"dynamics: the inner loop's period (1/{self.inner_loop_hz:g} s) must be a whole "
                             f"number of steps of {self.step_ms:g} ms")
        return self

    def boat(self) -> BoatPreset:
        return preset(self.preset, self.overrides)

    def loop_every(self) -> int:
        return round(1e3 / (self.inner_loop_hz * self.step_ms))


class WorldConfig(StrictModel):
    dt: PositiveFloat = Field(0.1, description="sampling period (s)")
    vessels: list[VesselSpec] = Field(min_length=1)
    target: TargetSpec
    range_noise: RangeNoise = Field(
        GaussianMixtureNoise(outlier_fraction=0.2, variance=0.4, outlier_variance=10.0),
        description="noise of one range measurement (Table II mixture by default)",
    )
    bearing_variance: NonNegativeFloat = Field(1e-4, description="R_b of (9), per axis")
    displacement_variance: NonNegativeFloat = Field(1e-6, description="R_delta of (5), per axis per step")
    heading_variance: NonNegativeFloat = Field(0.0, description="compass noise of each heading reading (rad^2)")
    islands: list[Annotated[list[Point], Field(min_length=3)]] = Field(
        default_factory=list, description="obstacles as simple polygons (m)"
    )
    sonar_range: PositiveFloat = Field(6.0, description="island points closer than this are seen (m)")
    sonar_spacing: PositiveFloat = Field(0.25, description="distance between sampled island points (m)")
    packet_loss: float = Field(0.0, ge=0, lt=1, description="probability that one inter-vessel message is lost")
    max_speed: PositiveFloat = Field(5.0, description="U_v, bound on the commanded surge speed (m/s)")
    max_yaw_rate: PositiveFloat = Field(
        math.pi / 3 + math.pi / 30, description="bound on the commanded yaw rate (rad/s)"
    )
    sea: SeaConfig | None = Field(None, description="the sea mode (sim bridge, real time); None: ideal sensors")
    sensors: SensorsConfig = Field(
        SensorsConfig(), description="sensor error models (sim_bridge/sensors.py), or a preset: 'realistic'; "
                                     "default: the paper's (5)-(9)")
    dynamics: DynamicsConfig | None = Field(None, description="hull dynamics; None: the paper's kinematics (1), (2)")
    environment: SeaState | None = Field(
        None, description="current, wind and waves: a sea state's name (moderate, ...) or its settings; needs dynamics")

    @field_validator("sensors", mode="before")
    @classmethod
    def _preset(cls, value):
        return expand_preset(value)

    @field_validator("islands")
    @classmethod
    def _simple_polygons(cls, islands: list[list[tuple[float, float]]]) -> list[list[tuple[float, float]]]:
        for index, polygon in enumerate(islands):
            if not is_simple_polygon(polygon):
                raise ValueError(f"island {index} is not a simple polygon (edges cross, overlap or vanish)")
        return islands

    @model_validator(mode="after")
    def _unique_ids(self) -> WorldConfig:
        ids = [vessel.id for vessel in self.vessels]
        repeated = sorted({i for i in ids if ids.count(i) > 1})
        if repeated:
            raise ValueError(f"vessel ids must be unique, repeated: {repeated}")
        if self.sea is not None:
            unknown = sorted((set(self.sea.offsets_ms) | set(self.sea.drifts_ppm) | set(self.sea.steps)
                              | set(self.sea.driver_offsets_ms)) - set(ids))
            if unknown:
                raise ValueError(f"sea: clocks of unknown vessels {unknown}")
            steps = self.dt / (self.sea.step_ms * 1e-3)
            if abs(steps - round(steps)) > 1e-9 or round(steps) < 1:
                raise ValueError(f"sea: step_ms ({self.sea.step_ms}) must divide dt ({self.dt} s)")
            if self.sensors.uwb is not None or self.sensors.camera is not None:
                raise ValueError("sensors: the sea mode's measurements lack the uwb and camera models")
        unknown = sorted(self.sensors.named_vessels() - set(ids))
        if unknown:
            raise ValueError(f"sensors: values for unknown vessels {unknown}")
        if self.environment is not None and self.dynamics is None:
            raise ValueError("environment: the water and the wind act on hulls: give world.dynamics too")
        if getattr(self.sensors.odometry, "sway", "none") == "hull":
            if self.dynamics is None:
                raise ValueError("sensors: odometry sway 'hull' takes the hull model of world.dynamics: "
                                 "give it")
            SwayModel.of(self.dynamics.boat().hull)   # a hull without sway damping is refused here
        if self.dynamics is not None:
            period = self.dt if self.sea is None else self.sea.step_ms * 1e-3
            steps = period / (self.dynamics.step_ms * 1e-3)
            if abs(steps - round(steps)) > 1e-9 or round(steps) < 1:
                raise ValueError(f"dynamics: step_ms ({self.dynamics.step_ms}) must divide the world's step "
                                 f"({period} s)")
        return self


@dataclass(frozen=True)
class Reading:
    """What one vessel's sensors report at one tick (arrays are read-only)."""

    odometry: OdometryReading
    ranges: dict[str, float]          # neighbour id -> measured range (m), (6)
    bearing: np.ndarray | None        # (2,) noisy target -> vessel unit vector (9); None when not visible
    obstacle_points: np.ndarray       # (M, 2) island points within sonar range, relative to the vessel
    occluded: bool                    # an island blocks the line of sight to the target


@dataclass(frozen=True)
class Truth:
    """The true state at `time`, for metrics; vessel entries cover the live vessels only."""

    time: float
    positions: dict[str, np.ndarray]
    headings: dict[str, float]
    velocities: dict[str, np.ndarray]     # velocity (2) used over the last step; zero before the first
    target_position: np.ndarray
    target_velocity: np.ndarray
    # With hull dynamics only (empty otherwise): (u, v, r) over ground in the body frame now (the velocities
    # above are then the velocity over ground now), and the seconds each vessel's thrust demand has spent
    # beyond what its thrusters can give.
    body_velocities: dict[str, np.ndarray] = field(default_factory=dict)
    thrust_limit_time: dict[str, float] = field(default_factory=dict)


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=float)
    array.setflags(write=False)
    return array


# What the sonar sees of a world without islands, every tick: one read-only array shared by every reading.
_NO_POINTS = _frozen(np.zeros((0, 2)))


def _fixed(x: float, y: float) -> np.ndarray:
    """A new read-only 2-vector. A vessel's arrays are replaced every step, never changed in place, and read-only,
    so the readings and the truth can hand them out without a copy."""
    array = np.array([x, y])
    array.setflags(write=False)
    return array


class _Vessel:
    """Mutable true and dead-reckoned state of one vessel while it is live."""

    def __init__(self, spec: VesselSpec) -> None:
        self.position = _frozen(spec.position)
        self.heading = float(wrap_angle(spec.heading))
        self.velocity = _fixed(0.0, 0.0)
        self.odometry_position = _fixed(0.0, 0.0)
        self.odometry_heading = self.heading
        # The velocity through water (2, world frame) over the last step, set by the motion where there is a
        # current; None: the velocity over ground. Read by the water-referenced odometry.
        self.water_velocity: np.ndarray | None = None
        self.odometry_state = None      # sensors.OdometryState of a non-paper odometry model


class World:
    """Vessels following (1), (2), a target (3), (4), islands, and sensors (5), (6), (7), (8), (9), stepped by
    `step(commands)`. With `config.dynamics` the vessels are hulls instead (`sim_bridge/hull.py`: Fossen's
    3-DOF model behind thrusters and an inner loop), moving in the `surroundings` given (calm water if None);
    the randomness is drawn in the same order, and without `dynamics` nothing here changes."""

    def __init__(self, config: WorldConfig, rng: np.random.Generator, surroundings: Any = None,
                 attitude: Callable[[float, float, float, float], tuple[float, float]] | None = None) -> None:
        """`surroundings`: the environment (current, wind and wave loads, attitude; `sim_bridge/hull.py`
        `CalmWater` shows the interface) the hulls move in; None: calm water. Needs `config.dynamics`.
        `attitude(t, x, y, heading) -> (roll, pitch)` (rad) tilts the UWB antennas and the camera of
        `config.sensors`; None: the surroundings' attitude if they have one, else level."""
        self.config = config
        self.time = 0.0
        self.time_ns = 0
        self.tick = 0
        self.bad_commands = 0
        self._rng = rng
        self._vessels: dict[str, _Vessel] = {}
        self._live: list[str] = []         # ids of the live vessels in config order, set when a tick begins
        self._departed: set[str] = set()
        self._islands = _islands(config)
        self._boundary = _boundary(config, self._islands)
        self._displacement_noise = IsotropicGaussianNoise(variance=config.displacement_variance)
        self._bearing_noise = IsotropicGaussianNoise(variance=config.bearing_variance)
        self._heading_std = math.sqrt(config.heading_variance)
        self._sensors = config.sensors
        self._odometry_model = None if config.sensors.odometry.kind == "paper" else config.sensors.odometry
        self._sway = (SwayModel.of(config.dynamics.boat().hull)
                      if getattr(self._odometry_model, "sway", "none") == "hull" else None)
        # The new sensor models draw from a stream of their own, spawned (the world's draws stay as they were)
        # only when one is on: the paper's world takes nothing more from the generator. The environment's
        # stream is spawned after it, so the sensors draw the same with or without one.
        self._sensor_rng = None if config.sensors.is_paper else rng.spawn(1)[0]
        if surroundings is None and config.environment is not None:
            surroundings = Environment(config.environment, rng.spawn(1)[0])
        self.environment = surroundings
        if attitude is None and surroundings is not None:
            attitude = getattr(surroundings, "attitude", None)
        self.attitude = attitude
        self._target = make_target(config.target, current=None if surroundings is None else surroundings.current)
        self._attitudes: dict[str, tuple[float, float]] = {}
        self._hulls: HullFleet | None = None
        if config.dynamics is not None:
            dynamics = config.dynamics
            self._hulls = HullFleet(dynamics.boat(), len(config.vessels), dynamics.step_ms * 1e-3,
                                    dynamics.loop_every(), surroundings)
            self._index = {spec.id: n for n, spec in enumerate(config.vessels)}
        elif surroundings is not None:
            raise ValueError("an environment needs hull dynamics (world.dynamics)")
        self._begin_tick()

    def live(self) -> list[str]:
        """Ids of the vessels present now, in config order."""
        return list(self._live)

    def sense(self) -> dict[str, Reading]:
        """Every live vessel's readings at the current time (drawn once per tick; repeat calls agree)."""
        return dict(self._readings)

    def step(self, commands: Mapping[str, Command]) -> None:
        """Apply each live vessel's command for one period dt, move the target, and start the next tick:
        the kinematics (1), (2), the odometry (5) and the target's model ((3), (4) for the random walk).

        A missing or non-finite command stops that vessel for the period and is counted in `bad_commands`.
        With hull dynamics (`config.dynamics`) the commands go to the hulls' inner loops instead (`_move_hulls`).
        """
        config = self.config
        dt = config.dt
        if self._hulls is not None:
            self._move_hulls(commands)
        for vessel_id in self._live if self._hulls is None else ():
            vessel = self._vessels[vessel_id]
            surge, yaw_rate = self._checked(commands.get(vessel_id))
            surge = min(max(surge, -config.max_speed), config.max_speed)
            yaw_rate = min(max(yaw_rate, -config.max_yaw_rate), config.max_yaw_rate)
            # (1), (2): move along the heading held over the period, then turn. In plain floats, the same
            # element-wise operations numpy would do on these 2-vectors (its per-call overhead is the cost).
            vx, vy = surge * math.cos(vessel.heading), surge * math.sin(vessel.heading)
            vessel.velocity = _fixed(vx, vy)
            dx, dy = vx * dt, vy * dt
            (x, y), (ox, oy) = vessel.position.tolist(), vessel.odometry_position.tolist()
            held = vessel.heading
            vessel.position = _fixed(x + dx, y + dy)
            vessel.heading = float(wrap_angle(vessel.heading + yaw_rate * dt))
            self._odometry(vessel, ox, oy, dx, dy, held, yaw_rate * dt)
        self._target.step(dt, self._rng)
        self.tick += 1
        # The clock counts whole nanoseconds, as every stamp on the wire does, so the in-process runner and
        # the agents behind the sim bridge see the very same times; a product, so it does not drift.
        self.time_ns = nanoseconds(self.tick * dt)
        self.time = seconds(self.time_ns)
        self._begin_tick()

    def truth(self) -> Truth:
        live = self.live()
        body: dict[str, np.ndarray] = {}
        limit: dict[str, float] = {}
        if self._hulls is not None:
            u, v, r = self._hulls.body_velocity()
            for i in live:
                n = self._index[i]
                body[i] = _frozen((u[n], v[n], r[n]))
                limit[i] = float(self._hulls.saturated_time[n])
        return Truth(
            time=self.time,
            positions={i: self._vessels[i].position for i in live},        # read-only (`_fixed`)
            headings={i: self._vessels[i].heading for i in live},
            velocities={i: self._vessels[i].velocity for i in live},
            target_position=_frozen(self._target.position),
            target_velocity=_frozen(self._target.velocity),
            body_velocities=body,
            thrust_limit_time=limit,
        )

    def _move_hulls(self, commands: Mapping[str, Command]) -> None:
        """Advance the hulls by dt under the live vessels' commands (a vessel not live, or a bad command:
        a stop, (0, 0), for its inner loop), then read each live vessel's new state and its odometry, as in the
        kinematic world."""
        config, hulls = self.config, self._hulls
        speed, rate = np.zeros(len(config.vessels)), np.zeros(len(config.vessels))
        for vessel_id in self._live:
            surge, yaw_rate = self._checked(commands.get(vessel_id))
            n = self._index[vessel_id]
            speed[n] = min(max(surge, -config.max_speed), config.max_speed)
            rate[n] = min(max(yaw_rate, -config.max_yaw_rate), config.max_yaw_rate)
        hulls.advance(self.time, config.dt, speed, rate, self.time)
        hulls.state[2] = wrap_angle(hulls.state[2])
        xs, ys, headings = (row.tolist() for row in hulls.state[:3])
        vxs, vys = (row.tolist() for row in hulls.ground_velocity())
        cxs, cys = (row.tolist() for row in hulls.current)
        dt = config.dt
        for vessel_id in self._live:
            vessel, n = self._vessels[vessel_id], self._index[vessel_id]
            (x, y), (ox, oy) = vessel.position.tolist(), vessel.odometry_position.tolist()
            dx, dy = xs[n] - x, ys[n] - y
            held = vessel.heading
            vessel.position = _fixed(xs[n], ys[n])
            vessel.velocity = _fixed(vxs[n], vys[n])
            vessel.heading = headings[n]
            # Through the water: the step's mean velocity over ground less the current at its end.
            vessel.water_velocity = (dx / dt - cxs[n], dy / dt - cys[n])
            self._odometry(vessel, ox, oy, dx, dy, held, float(wrap_angle(headings[n] - held)))

    # --- inside a tick -----------------------------------------------------------------------------------

    def _checked(self, command: Command | None) -> tuple[float, float]:
        try:
            surge, yaw_rate = float(command.surge), float(command.yaw_rate)  # type: ignore[union-attr]
        except (AttributeError, TypeError, ValueError):
            surge = yaw_rate = math.nan
        if math.isfinite(surge) and math.isfinite(yaw_rate):
            return surge, yaw_rate
        self.bad_commands += 1
        return 0.0, 0.0

    def _noisy_heading(self, heading: float) -> float:
        return float(wrap_angle(heading + self._rng.normal(0.0, self._heading_std)))

    def _odometry(self, vessel: _Vessel, ox: float, oy: float, dx: float, dy: float, held: float, turn: float
                  ) -> None:
        """The odometry over the step just made, from (ox, oy) (its position before it): (5), the true
        displacement (dx, dy) plus its per-step noise; or `config.sensors`' model, with `held` the heading held
        over the step, `turn` the heading's change (rad) and the vessel's water velocity (ground's if None).
        The paper's noises are drawn either way, in the same order: the world's stream stays the paper's."""
        nx, ny = self._displacement_noise.sample(self._rng).tolist()
        heading = self._noisy_heading(vessel.heading)
        if self._odometry_model is None:
            vessel.odometry_position = _fixed((ox + dx) + nx, (oy + dy) + ny)
            vessel.odometry_heading = heading
            return
        dt = self.config.dt
        ground = (dx / dt, dy / dt)
        water = ground if vessel.water_velocity is None else vessel.water_velocity
        state = advance_odometry(self._odometry_model, vessel.odometry_state, ground, water, held, turn, dt,
                                 self._sensor_rng, self._sway)
        vessel.odometry_state = state
        vessel.odometry_position = _fixed(*state.position)
        vessel.odometry_heading = state.heading

    def _begin_tick(self) -> None:
        """Let vessels leave and join at the new time, then draw this tick's readings."""
        now = self.time + TIME_TOLERANCE
        for spec in self.config.vessels:
            if spec.id in self._vessels and spec.leave_time is not None and spec.leave_time <= now:
                del self._vessels[spec.id]
                self._departed.add(spec.id)
            elif spec.id not in self._vessels and spec.id not in self._departed and spec.join_time <= now:
                if spec.leave_time is not None and spec.leave_time <= now:
                    self._departed.add(spec.id)      # its whole stay fell between two ticks
                    continue
                vessel = _Vessel(spec)
                vessel.odometry_heading = self._noisy_heading(vessel.heading)
                if self._odometry_model is not None:
                    vessel.odometry_state = start_odometry(self._odometry_model, spec.id, vessel.heading,
                                                           self._sensor_rng)
                    vessel.odometry_heading = vessel.odometry_state.heading
                self._vessels[spec.id] = vessel
                if self._hulls is not None:
                    x, y = vessel.position.tolist()
                    self._hulls.place(self._index[spec.id], x, y, vessel.heading)
        self._live = [spec.id for spec in self.config.vessels if spec.id in self._vessels]
        if self.attitude is not None and (self._sensors.uwb is not None or self._sensors.camera is not None):
            here = {v: self._vessels[v] for v in self._live}
            self._attitudes = {v: tuple(map(float, self.attitude(self.time, *h.position.tolist(), h.heading)))
                               for v, h in here.items()}
        # Every true range of the tick at once: row i holds |p_j - p_i| for each j, the element-wise
        # operations of a norm along axis 1 (rounded as one vessel's row alone would be).
        positions = np.array([self._vessels[v].position for v in self._live]).reshape(-1, 2)
        if self._sensors.uwb is not None:   # the ranges are between the antennas
            positions = self._antennas(positions)
        differences = positions[None, :, :] - positions[:, None, :]
        distances = np.sqrt(np.add.reduce(differences * differences, axis=2))
        count = len(self._live)
        # Row n without its diagonal entry: vessel n's true ranges to the others, in live order.
        others = distances[~np.eye(count, dtype=bool)].reshape(count, count - 1)
        self._readings = {vessel_id: self._read(n, vessel_id, others[n]) for n, vessel_id in enumerate(self._live)}

    def _read(self, index: int, vessel_id: str, true_ranges: np.ndarray) -> Reading:
        """One vessel's readings at this tick: ranges (6) with the range noise (7) or (8), the bearing (9),
        its cumulative odometry (5) and the sonar's island points (the obstacle points of (34)). The vessel
        is `index` in `_live`; `true_ranges` its true distances to the other live vessels, in live order."""
        vessel = self._vessels[vessel_id]
        here = vessel.position
        live = self._live
        others = live[:index] + live[index + 1:]
        # (6): each ordered pair gets its own draw, as each vessel ranges on its own.
        noise = self.config.range_noise.sample(self._rng, len(others))
        # A UWB module never reports a negative range.
        measured = np.maximum(true_ranges + noise, 0.0)
        if self._sensors.uwb is None:
            ranges = dict(zip(others, measured.tolist()))
        else:
            measured, kept = uwb_faults(self._sensors.uwb, true_ranges, measured, self._sensor_rng)
            ranges = {j: r for j, r, k in zip(others, measured.tolist(), kept.tolist()) if k}
        # (9): drawn even when unused, so the stream does not depend on the geometry.
        bearing_noise = self._bearing_noise.sample(self._rng)
        bearing, occluded = _bearing(here, self._target.position, bearing_noise, self._islands)
        if bearing is not None and self._sensors.camera is not None:
            bearing = self._camera(vessel_id, vessel, bearing)
        odometry = OdometryReading(
            stamp=self.time, position=vessel.odometry_position, heading=vessel.odometry_heading
        )
        return Reading(
            odometry=odometry,
            ranges=ranges,
            bearing=bearing,
            obstacle_points=_sonar(self._boundary, here, self.config.sonar_range) if len(self._boundary)
            else _NO_POINTS,
            occluded=occluded,
        )

    def _antennas(self, centres: np.ndarray) -> np.ndarray:
        """The live vessels' UWB antenna positions (N, 2), from their centres, headings and attitudes."""
        uwb, live = self._sensors.uwb, self._live
        levels = [self._attitudes.get(v, (0.0, 0.0)) for v in live]
        return antenna_positions(centres, np.array([self._vessels[v].heading for v in live]),
                                 np.array([uwb.lever_arm(v) for v in live]).reshape(-1, 3),
                                 np.array([a[0] for a in levels]), np.array([a[1] for a in levels]))

    def _camera(self, vessel_id: str, vessel: _Vessel, bearing: np.ndarray) -> np.ndarray:
        """The bearing turned by the camera's tilt error and, if it is referred to the vessel's own heading
        reading, by that reading's error (sensors.tilted_azimuth)."""
        camera = self._sensors.camera
        roll, pitch = self._attitudes.get(vessel_id, (0.0, 0.0))
        sight = self._target.position - vessel.position
        azimuth = math.atan2(-bearing[1], -bearing[0]) - vessel.heading
        elevation = -math.atan2(camera.height, math.sqrt(sight.dot(sight)))
        turn = float(tilted_azimuth(azimuth, elevation, roll, pitch)) - azimuth
        if camera.heading_reference == "odometry":
            turn += vessel.odometry_heading - vessel.heading
        return _frozen(rotate(bearing, turn))


def _islands(config: WorldConfig) -> list[np.ndarray]:
    return [np.array(polygon, dtype=float) for polygon in config.islands]


def _boundary(config: WorldConfig, islands: list[np.ndarray]) -> np.ndarray:
    """Every island's outline sampled every `sonar_spacing` metres: what the sonar can see."""
    boundary = [sample_boundary(polygon, config.sonar_spacing) for polygon in islands]
    return np.concatenate(boundary, axis=0) if boundary else np.zeros((0, 2))


def _bearing(here: np.ndarray, target: np.ndarray, noise: np.ndarray, islands: list[np.ndarray]
             ) -> tuple[np.ndarray | None, bool]:
    """(9): the noisy unit vector from the target to the vessel, None when an island blocks the line of sight
    or the vessel is on the target; and whether it is blocked."""
    offset = here - target
    # sqrt(x . x): numpy.linalg.norm's own computation of a vector's norm, without its checks.
    distance = math.sqrt(offset.dot(offset))
    occluded = any(segment_intersects_polygon(here, target, island) for island in islands)
    if occluded or distance == 0.0:
        return None, occluded
    # (9) is a direction plus noise; the camera reports it as a unit vector (the contract's form).
    noisy = offset / distance + noise
    return _frozen(noisy / math.sqrt(noisy.dot(noisy))), occluded


def _sonar(boundary: np.ndarray, here: np.ndarray, sonar_range: float) -> np.ndarray:
    """The island points within `sonar_range` of the vessel, relative to it."""
    relative = boundary - here
    near = np.einsum("ij,ij->i", relative, relative) <= sonar_range**2
    return _frozen(relative[near].reshape(-1, 2))


# --- the sea mode ------------------------------------------------------------------------------------------

SEA_SENSORS = ("odometry", "uwb", "camera")


@dataclass(frozen=True)
class VesselClock:
    """One vessel's own clock: c(t) = t + offset + drift * t (s from the run's epoch) at true time t (s of sim
    time), plus every step taken by t. A driver's stamp is epoch_ns + c(t) in whole nanoseconds. The agent of
    the vessel reads the same clock (agent/shell/wall_clock.py `SimulatedVesselClock`)."""

    offset: float   # s
    drift: float    # s per s (1 ppm = 1e-6)
    steps: tuple[tuple[float, float], ...] = ()   # (true time s, step s)

    def read(self, t: float) -> float:
        return t + self.offset + self.drift * t + sum(step for at, step in self.steps if at <= t)

    def stamp_ns(self, t: float, epoch_ns: int = 0) -> int:
        return epoch_ns + nanoseconds(self.read(t))


@dataclass(frozen=True)
class Frame:
    """The world at one tick, as much as the sea mode's sensors need of it."""

    time_ns: int
    positions: dict[str, np.ndarray]       # true positions of the live vessels
    target: np.ndarray
    odometry: dict[str, OdometryReading]   # each live vessel's odometry reading of the tick

    @classmethod
    def of(cls, world: World) -> Frame:
        truth = world.truth()
        return cls(world.time_ns, truth.positions, truth.target_position,
                   {vessel: reading.odometry for vessel, reading in world.sense().items()})


@dataclass(frozen=True)
class Measurement:
    """One message of the sea mode's sensors, as the vessel's driver sends it on."""

    vessel: str
    sensor: str       # one of SEA_SENSORS; the odometry carries the sonar's points
    measured: float   # true time of the measurement (s of sim time)
    arrival: float    # true time it reaches the driver: measured + latency (s)
    stamp_ns: int     # the driver's stamp in the vessel's clock, from the run's epoch (add the epoch's ns)
    values: dict      # odometry: position, heading, points; uwb: ranges; camera: bearing (None: not seen)


def sea_steps(config: WorldConfig) -> int:
    """How many steps of the sea mode's world make one tick: m = dt / step."""
    return round(config.dt / (config.sea.step_ms * 1e-3))


def sea_world(config: WorldConfig) -> WorldConfig:
    """The world of the sea mode: the same world stepped every step = dt / m, with its per-step noises scaled
    so that their variance over a tick is as before: R_delta' = R_delta / m for the odometry's random walk
    (5), q' = q / m for a random-walk target (3), (4). A heading reading's noise is per reading: unchanged."""
    m = sea_steps(config)
    changes: dict = {"dt": config.dt / m, "displacement_variance": config.displacement_variance / m}
    if getattr(config.target, "kind", None) == "random_walk":
        changes["target"] = config.target.model_copy(update={"process_noise": config.target.process_noise / m})
    return config.model_copy(update=changes)


class SeaSensors:
    """The sensors of the sea mode (`WorldConfig.sea`): own clocks, own measurement times, latencies.

    Construction draws from `rng`, for each vessel in config order: its clock offset o ~ U(-offset, offset),
    its drift d ~ U(-drift, drift) (1e-6 per ppm), then one phase per sensor of SEA_SENSORS, U(0, period).
    Each is drawn even where the config gives the value, so naming one vessel leaves the others as they were.

    A sensor of period T and phase p measures at t_n = p + n T (n = 0, 1, ...). `measure(a, b)` gives every
    measurement of the period [t_a, t_b) between two ticks, from the world interpolated on a straight line,
    x(t) = x_a + (t - t_a) / (t_b - t_a) (x_b - x_a): exact for the vessels, which move straight over a period
    ((1): the heading is held, then turns at the period's end), and for a constant-velocity target. The
    heading reading is the tick's before (held, as the heading is). The latency of a message is
    L = latency + jitter u, u ~ U(-1, 1); it reaches the driver at t + L, and is stamped c(t + L) when stamps
    are taken at arrival, c(t) when at measurement.

    Draws per period: for each vessel live at both ticks, in config order, each sensor in SEA_SENSORS order,
    each measurement in time order: its latency u, then its noise (uwb: one range noise per peer, (6) with
    (7) or (8); camera: the bearing noise of (9), drawn even when the target is hidden). The odometry draws no
    noise: the world's odometry, noisy per step (5), is interpolated.
    """

    def __init__(self, config: WorldConfig, rng: np.random.Generator) -> None:
        if config.sea is None:
            raise ValueError("the world config has no sea section")
        self.config = config
        self.sea = sea = config.sea
        self._rng = rng
        self._islands = _islands(config)
        self._boundary = _boundary(config, self._islands)
        self._bearing_noise = IsotropicGaussianNoise(variance=config.bearing_variance)
        self.clocks: dict[str, VesselClock] = {}
        self.lag = 0.0   # s from the epoch the vessels' clocks count from to the run's (`stamp_ns`)
        self.phases_ns: dict[tuple[str, str], int] = {}
        for spec in config.vessels:
            offset = rng.uniform(-1.0, 1.0) * sea.offset_ms
            drift = rng.uniform(-1.0, 1.0) * sea.drift_ppm
            self.clocks[spec.id] = VesselClock(sea.offsets_ms.get(spec.id, offset) * 1e-3,
                                               sea.drifts_ppm.get(spec.id, drift) * 1e-6,
                                               tuple((at, step * 1e-3) for at, step in
                                                     sea.steps.get(spec.id, [])))
            for sensor in SEA_SENSORS:
                timing = self.timing(sensor)
                drawn = rng.uniform(0.0, 1.0) * self.period_ns(sensor)
                given = None if timing.phase_ms is None else nanoseconds(timing.phase_ms * 1e-3)
                self.phases_ns[spec.id, sensor] = int(drawn) if given is None else given

    def timing(self, sensor: str) -> SensorTiming:
        return getattr(self.sea, sensor)

    def stamp_ns(self, vessel: str, t: float, epoch_ns: int = 0, driver: bool = True) -> int:
        """The stamp `vessel`'s driver (`driver`; else its computer) takes at true time t (s from the run's
        epoch): its vessel's clock, plus the driver's own offset if it has one. The clocks count from the
        epoch the agents were given, `lag` s before the run's (a run that started late): so a step comes at
        the same moment for the driver and the agent."""
        offset = self.sea.driver_offsets_ms.get(vessel, 0.0) * 1e-3 if driver else 0.0
        clock = self.clocks[vessel]
        return clock.stamp_ns(t + self.lag, epoch_ns) - nanoseconds(self.lag) + nanoseconds(offset)

    def period_ns(self, sensor: str) -> int:
        period_ms = self.timing(sensor).period_ms
        return nanoseconds(self.config.dt if period_ms is None else period_ms * 1e-3)

    def times_ns(self, vessel: str, sensor: str, start_ns: int, end_ns: int) -> list[int]:
        """The measurement times t_n = p + n T of `sensor` on `vessel` in [start_ns, end_ns), in whole ns."""
        phase, period = self.phases_ns[vessel, sensor], self.period_ns(sensor)
        first = max(0, -(-(start_ns - phase) // period))   # the smallest n with p + n T >= start
        return list(range(phase + first * period, end_ns, period))

    def measure(self, before: Frame, after: Frame) -> list[Measurement]:
        """Every measurement made in [before.time, after.time), the period between two consecutive ticks."""
        live = [v.id for v in self.config.vessels if v.id in before.positions and v.id in after.positions]
        span = after.time_ns - before.time_ns
        found = []
        for vessel in live:
            for sensor in SEA_SENSORS:
                timing = self.timing(sensor)
                for t_ns in self.times_ns(vessel, sensor, before.time_ns, after.time_ns):
                    t = seconds(t_ns)
                    latency = (timing.latency_ms + timing.jitter_ms * self._rng.uniform(-1.0, 1.0)) * 1e-3
                    w = (t_ns - before.time_ns) / span
                    here = _lerp(before.positions[vessel], after.positions[vessel], w)
                    if sensor == "odometry":
                        values = {"position": _lerp(before.odometry[vessel].position,
                                                    after.odometry[vessel].position, w),
                                  "heading": before.odometry[vessel].heading,
                                  "points": _sonar(self._boundary, here, self.config.sonar_range)}
                    elif sensor == "uwb":
                        peers = [j for j in live if j != vessel]
                        noise = self.config.range_noise.sample(self._rng, len(peers))
                        there = np.array([_lerp(before.positions[j], after.positions[j], w) for j in peers])
                        measured = np.maximum(np.linalg.norm(there.reshape(-1, 2) - here, axis=1) + noise, 0.0)
                        values = {"ranges": dict(zip(peers, measured.tolist()))}
                    else:
                        noise = self._bearing_noise.sample(self._rng)
                        bearing, _ = _bearing(here, _lerp(before.target, after.target, w), noise, self._islands)
                        values = {"bearing": bearing}
                    stamped = t + latency if self.sea.stamps == "arrival" else t
                    found.append(Measurement(vessel, sensor, t, t + latency, self.stamp_ns(vessel, stamped),
                                             values))
        return found


def _lerp(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """The point a fraction w of the way from a to b: a + w (b - a)."""
    return a + w * (b - a)


def message_lost(seed: int, sender: str, receiver: str, tick: int, probability: float) -> bool:
    """Whether the message `sender` sends `receiver` at `tick` is lost, the same in every process.

    A keyed hash of the fields (not Python's salted `hash`) gives a uniform number in [0, 1); the message is
    lost when it falls below `probability`.
    """
    if not 0.0 <= probability <= 1.0:
        raise ValueError(f"probability must be in [0, 1], got {probability}")
    # JSON keeps the fields apart unambiguously, whatever characters the ids contain.
    key = json.dumps([int(seed), str(sender), str(receiver), int(tick)]).encode()
    digest = hashlib.blake2b(key, digest_size=8, person=b"usv-msg-loss").digest()
    uniform = (int.from_bytes(digest, "big") >> 11) / 2.0**53   # 53 bits: exact in a float, never 1.0
    return uniform < probability


def lost_shares(seed: int, senders: list[str], receivers: list[str], joined: set[str], tick: int,
                probability: float) -> list[tuple[str, str]]:
    """The shares sent at `tick` - 1 that do not reach their receivers at `tick`, as (sender, receiver).

    `senders` shared at the tick before and are still here; `receivers` are live now, and those in `joined`
    were not yet listening when the shares went out. Every other share is lost with `probability`
    (`message_lost`). The in-process runner and the sim bridge both use this, so they lose the same shares.
    """
    if not 0.0 <= probability <= 1.0:
        raise ValueError(f"probability must be in [0, 1], got {probability}")
    # With no loss no hash is needed: every share of a listening receiver arrives (a uniform is never < 0).
    if probability == 0.0 and not joined:
        return []
    return [(j, i) for j in senders for i in receivers
            if j != i and (i in joined or (probability > 0.0 and message_lost(seed, j, i, tick, probability)))]


@dataclass(frozen=True)
class Streams:
    """The random streams of one run, all from its seed: the world's, the initial estimates', the key of the
    packet-loss hash, and the sea mode's (clocks, phases, latencies and the noise of its measurements). The
    in-process runner, the sim bridge and the fleet launcher derive them the same way."""

    world: np.random.Generator
    initial: np.random.Generator
    loss_seed: int
    sea: np.random.Generator


def streams(seed: np.random.SeedSequence | int) -> Streams:
    sequence = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    # A third child leaves the first two as they were: spawned children depend only on their index.
    world_seed, initial_seed, sea_seed = sequence.spawn(3)
    return Streams(np.random.default_rng(world_seed), np.random.default_rng(initial_seed),
                   int(sequence.generate_state(1)[0]), np.random.default_rng(sea_seed))
