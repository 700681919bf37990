"""The sea around the vessels: current, wind and waves composed behind one small interface, and sea states.

`Environment(config, rng)` answers, for arrays of n vessels (t the world time in s):
    current(t, x, y) -> (cx, cy)                         ground-frame current velocity (m/s)
    loads(t, x, y, heading, u, v, windage) -> (X, Y, N)  wind + wave loads in the body frame (N, N, N m)
    attitude(t, x, y, heading) -> (roll, pitch)          rad, SNAME signs (starboard down, bow up positive)
    advance(t)                                           moves the slow random processes on to time t
`windage` has length, beam, mass, frontal_area, lateral_area (m, m, kg, m^2, m^2; floats or (n,) arrays);
u, v are the hull's velocity over ground in its body frame. Each process draws from its own child of `rng`
(spawned, so the caller's own stream is untouched), and only per process, never per vessel or per call:
the same seed and calls give the same numbers whatever the fleet. `SEA_STATES` names the issue's presets;
a config field typed `SeaState` takes either a preset's name (`moderate`) or a whole mapping.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BeforeValidator

from agent.config import ConfigError, StrictModel
from sim_bridge.current import Current, CurrentConfig
from sim_bridge.waves import Waves, WavesConfig
from sim_bridge.wind import Wind, WindConfig

_ROUNDING = 1e-9   # s: a time this much before the last one counts as the same (sums of substeps vs products)


class EnvironmentConfig(StrictModel):
    """Each part optional: a missing one is still water, still air or a flat sea."""

    current: CurrentConfig | None = None
    wind: WindConfig | None = None
    waves: WavesConfig | None = None


class Environment:
    def __init__(self, config: EnvironmentConfig, rng: np.random.Generator) -> None:
        self.config = config
        current_rng, wind_rng, waves_rng = rng.spawn(3)
        self._current = Current(config.current, current_rng) if config.current else None
        self._wind = Wind(config.wind, wind_rng) if config.wind else None
        self._waves = Waves(config.waves, waves_rng) if config.waves else None
        self.time = 0.0

    def advance(self, t: float) -> None:
        """Move the current's Gauss-Markov part and the wind's gust on from the last time to t (s)."""
        dt = t - self.time
        if not dt >= -_ROUNDING:
            raise ValueError(f"the environment cannot go back in time (from {self.time} s to {t} s)")
        if dt <= 0.0:     # the same time, or a rounding error's worth before it (t computed two ways)
            return
        self.time = t
        if self._current is not None:
            self._current.advance(dt)
        if self._wind is not None:
            self._wind.advance(dt)

    def current(self, t: float, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._current is None:
            zero = np.zeros(np.broadcast(np.asarray(x), np.asarray(y)).shape)
            return zero, zero.copy()
        return self._current.velocity(x, y)

    def loads(self, t: float, x: np.ndarray, y: np.ndarray, heading: np.ndarray, u: np.ndarray,
              v: np.ndarray, windage) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._wind is None and self._waves is None:
            zero = np.zeros(np.broadcast(np.asarray(x), np.asarray(y), np.asarray(heading)).shape)
            return zero, zero.copy(), zero.copy()
        if self._waves is None:
            return self._wind.loads(heading, u, v, windage)
        wave = self._waves.loads(t, x, y, heading, windage)
        if self._wind is None:
            return wave
        wind = self._wind.loads(heading, u, v, windage)
        return wind[0] + wave[0], wind[1] + wave[1], wind[2] + wave[2]

    def attitude(self, t: float, x: np.ndarray, y: np.ndarray, heading: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        if self._waves is None:
            zero = np.zeros(np.broadcast(np.asarray(x), np.asarray(y), np.asarray(heading)).shape)
            return zero, zero.copy()
        return self._waves.attitude(t, x, y, heading)


_CURRENT = CurrentConfig(speed=0.5)
_GRADIENT = CurrentConfig(speed=0.3, shear=0.01)
_WIND = WindConfig(speed=8.0, gain=2.0, time_constant=2.0)
_WAVES = WavesConfig(gain=0.3, period=5.0)

# The sea states (#30, item 6), the water only: the hull and the sensors are the scenario's.
SEA_STATES: dict[str, EnvironmentConfig] = {
    "calm": EnvironmentConfig(),
    "current": EnvironmentConfig(current=_CURRENT),
    "gradient": EnvironmentConfig(current=_GRADIENT),
    "wind": EnvironmentConfig(wind=_WIND),
    "waves": EnvironmentConfig(waves=_WAVES),
    "moderate": EnvironmentConfig(current=_GRADIENT, wind=_WIND, waves=_WAVES),
}


def sea_state(name: str) -> EnvironmentConfig:
    """The environment of a named sea state; a ConfigError naming the known ones otherwise."""
    try:
        return SEA_STATES[name]
    except KeyError:
        raise ConfigError(f"unknown sea state {name!r}: one of {', '.join(SEA_STATES)}") from None


def _named(value: object) -> object:
    if isinstance(value, str):
        if value not in SEA_STATES:
            raise ValueError(f"unknown sea state {value!r}: one of {', '.join(SEA_STATES)}")
        return SEA_STATES[value]
    return value


# A config field for the sea: a preset's name from SEA_STATES or an EnvironmentConfig mapping.
SeaState = Annotated[EnvironmentConfig, BeforeValidator(_named)]
