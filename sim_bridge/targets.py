"""How the simulated target moves: its configuration (a tagged union on `kind`) and one small class per model.

Every model has `position` and `velocity` ((2,) arrays, the current state) and `step(dt, rng)`, which moves
it on by one sampling period drawing any randomness from the caller's generator. A drifting target moves
with the water: `make_target(spec, current)` hands it the environment's `current(t, x, y)`; the other
models ignore that argument.
"""

from __future__ import annotations

import math
from typing import Annotated, Callable, Literal, Protocol

import numpy as np
from pydantic import Field, model_validator

from agent.config import NonNegativeFloat, PositiveFloat, StrictModel

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Point = tuple[FiniteFloat, FiniteFloat]


class ConstantVelocitySpec(StrictModel):
    kind: Literal["constant_velocity"] = "constant_velocity"
    position: Point = Field(description="start position (m)")
    velocity: Point = Field(description="velocity (m/s)")


class SinusoidSpec(StrictModel):
    """Constant speed along y' = A sin(2 pi x' / wavelength), in a frame at `position` rotated by `direction`."""

    kind: Literal["sinusoid"] = "sinusoid"
    position: Point = Field(description="start position (m), where x' = y' = 0")
    speed: PositiveFloat = Field(description="speed along the path (m/s)")
    amplitude: NonNegativeFloat = Field(description="A, lateral amplitude (m)")
    wavelength: PositiveFloat = Field(description="lambda, along-track period (m)")
    direction: FiniteFloat = Field(0.0, description="mean direction of travel, the x' axis (rad)")


class RandomWalkSpec(StrictModel):
    """The noise-driven double integrator (3), (4), its speed kept at or below `max_speed`."""

    kind: Literal["random_walk"] = "random_walk"
    position: Point = Field(description="start position (m)")
    velocity: Point = Field((0.0, 0.0), description="start velocity (m/s)")
    process_noise: NonNegativeFloat = Field(0.01, description="q: w ~ N(0, q I_4) per step (Table I Q_o)")
    max_speed: PositiveFloat = Field(0.5, description="U_vo, bound on the target's speed (Table I)")

    @model_validator(mode="after")
    def _start_within_bound(self) -> RandomWalkSpec:
        if math.hypot(*self.velocity) > self.max_speed:
            raise ValueError("the start velocity is faster than max_speed")
        return self


class MooredSpec(StrictModel):
    """A buoy swinging round its mooring: a circle of `radius` about the anchor, once every `period`."""

    kind: Literal["moored"] = "moored"
    anchor: Point = Field(description="the anchor, the circle's centre (m)")
    radius: NonNegativeFloat = Field(2.0, description="the swing's radius (m; a few metres of slack chain)")
    period: PositiveFloat = Field(120.0, description="time for one turn of the circle (s)")
    phase: FiniteFloat = Field(0.0, description="start angle on the circle, from the x axis (rad)")
    clockwise: bool = Field(False, description="turn clockwise instead of counter-clockwise")


class DriftingSpec(StrictModel):
    """A free-floating object carried by the current at its position (still when there is no current)."""

    kind: Literal["drifting"] = "drifting"
    position: Point = Field(description="start position (m)")


TargetSpec = Annotated[
    ConstantVelocitySpec | SinusoidSpec | RandomWalkSpec | MooredSpec | DriftingSpec,
    Field(discriminator="kind"),
]

# The environment's current(t, x, y) -> (cx, cy): ground-frame velocity (m/s) at positions, arrays in and out.
CurrentField = Callable[[float, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


class Target(Protocol):
    position: np.ndarray
    velocity: np.ndarray

    def step(self, dt: float, rng: np.random.Generator) -> None: ...


class ConstantVelocityTarget:
    """(3), (4) without process noise (w = 0): the constant-velocity target of Sec. VI-B."""

    def __init__(self, spec: ConstantVelocitySpec) -> None:
        self.position = np.array(spec.position, dtype=float)
        self.velocity = np.array(spec.velocity, dtype=float)

    def step(self, dt: float, rng: np.random.Generator) -> None:
        self.position = self.position + self.velocity * dt


class SinusoidTarget:
    """Constant speed along a sinusoid.

    The state is the along-track coordinate x'. Each step moves the target to the next point of the curve
    whose straight-line distance from the current point is exactly speed * dt, so the target never leaves
    the curve and covers the same distance every step. That chord differs from a step along the local
    tangent (x' += speed dt cos(slope angle)) only by the curvature, O(kappa (speed dt)^2), but does not
    drift off the path over a long run.
    """

    def __init__(self, spec: SinusoidSpec) -> None:
        self._start = np.array(spec.position, dtype=float)
        self._speed = spec.speed
        self._amplitude = spec.amplitude
        self._wavenumber = 2.0 * math.pi / spec.wavelength
        c, s = math.cos(spec.direction), math.sin(spec.direction)
        self._rotation = np.array([[c, -s], [s, c]])
        self._along = 0.0
        self._update_state()

    def _lateral(self, along: float) -> float:
        return self._amplitude * math.sin(self._wavenumber * along)

    def _update_state(self) -> None:
        along = self._along
        self.position = self._start + self._rotation @ np.array([along, self._lateral(along)])
        slope = self._amplitude * self._wavenumber * math.cos(self._wavenumber * along)
        self.velocity = self._speed * (self._rotation @ np.array([1.0, slope])) / math.hypot(1.0, slope)

    def step(self, dt: float, rng: np.random.Generator) -> None:
        length = self._speed * dt
        along = self._along
        if self._amplitude == 0.0:
            advance = length
        else:
            here = self._lateral(along)

            def excess(delta: float) -> float:
                return delta**2 + (self._lateral(along + delta) - here) ** 2 - length**2

            # Imported here: scipy.optimize adds 0.4 s to the start of every sim bridge, few of which need it.
            from scipy.optimize import brentq

            # excess(0) < 0 <= excess(length): a chord of the right length ends in (0, length].
            advance = brentq(excess, 0.0, length, xtol=1e-14, rtol=4 * np.finfo(float).eps)
        self._along = along + advance
        self._update_state()


class RandomWalkTarget:
    """(3), (4): x_o,k = A x_o,k-1 + w_o,k-1, A = [[I, dt I], [0, I]], w ~ N(0, q I_4); |v_o| <= U_vo."""

    def __init__(self, spec: RandomWalkSpec) -> None:
        self.position = np.array(spec.position, dtype=float)
        self.velocity = np.array(spec.velocity, dtype=float)
        self._noise_std = math.sqrt(spec.process_noise)
        self._max_speed = spec.max_speed

    def step(self, dt: float, rng: np.random.Generator) -> None:
        w = rng.normal(0.0, self._noise_std, size=4)
        self.position = self.position + dt * self.velocity + w[:2]
        velocity = self.velocity + w[2:]
        speed = math.hypot(*velocity)
        if speed > self._max_speed:
            # The paper assumes a bounded target speed; scale back rather than redraw, to keep the stream fixed.
            velocity = velocity * (self._max_speed / speed)
        self.velocity = velocity


class MooredTarget:
    """p(t) = anchor + R (cos a(t), sin a(t)), a(t) = phase +- 2 pi t / T: on its circle at every step."""

    def __init__(self, spec: MooredSpec) -> None:
        self._anchor = np.array(spec.anchor, dtype=float)
        self._radius = spec.radius
        self._rate = (-1.0 if spec.clockwise else 1.0) * 2.0 * math.pi / spec.period
        self._phase = spec.phase
        self._time = 0.0
        self._update_state()

    def _update_state(self) -> None:
        angle = self._phase + self._rate * self._time
        c, s = math.cos(angle), math.sin(angle)
        self.position = self._anchor + self._radius * np.array([c, s])
        self.velocity = self._radius * self._rate * np.array([-s, c])

    def step(self, dt: float, rng: np.random.Generator) -> None:
        self._time += dt
        self._update_state()


class DriftingTarget:
    """dp/dt = c(t, p): carried by the current, by the midpoint rule (exact for a uniform current and for a
    shear across the flow, whose gradient squares to zero); velocity = c at the new position."""

    def __init__(self, spec: DriftingSpec, current: CurrentField | None) -> None:
        self._current = current
        self._time = 0.0
        self.position = np.array(spec.position, dtype=float)
        self.velocity = self._water(self._time, self.position)

    def _water(self, t: float, p: np.ndarray) -> np.ndarray:
        if self._current is None:
            return np.zeros(2)
        cx, cy = self._current(t, p[:1], p[1:])
        return np.array([float(cx[0]), float(cy[0])])

    def step(self, dt: float, rng: np.random.Generator) -> None:
        t = self._time
        middle = self.position + 0.5 * dt * self._water(t, self.position)
        self.position = self.position + dt * self._water(t + 0.5 * dt, middle)
        self._time = t + dt
        self.velocity = self._water(self._time, self.position)


def make_target(spec: ConstantVelocitySpec | SinusoidSpec | RandomWalkSpec | MooredSpec | DriftingSpec,
                current: CurrentField | None = None) -> Target:
    """The moving target a spec describes, at its start state; `current` moves a drifting one."""
    if isinstance(spec, MooredSpec):
        return MooredTarget(spec)
    if isinstance(spec, DriftingSpec):
        return DriftingTarget(spec, current)
    if isinstance(spec, ConstantVelocitySpec):
        return ConstantVelocityTarget(spec)
    if isinstance(spec, SinusoidSpec):
        return SinusoidTarget(spec)
    if isinstance(spec, RandomWalkSpec):
        return RandomWalkTarget(spec)
    raise TypeError(f"unknown target spec {type(spec).__name__}")
