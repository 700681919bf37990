"""The water's current: a uniform flow, a slow Gauss-Markov part and an optional linear shear across the area.

c(p, t) = (V_c + G s) (cos beta_c, sin beta_c) + g(t),  s = (p - p_0) . (cos beta_G, sin beta_G),
with g a 2-D first-order Gauss-Markov process (`gauss_markov.py`), uniform in space. Velocities are ground
frame (m/s), directions the way the water flows, counter-clockwise from the x axis (rad). The shear G (s^-1)
grows the speed along beta_G, by default across the flow to its left (beta_c + pi/2), where the field has no
divergence. The vessels feel it through their relative velocity (Fossen 2021, Sec. 10.3; sea-physics.md, 3).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from agent.config import NonNegativeFloat, PositiveFloat, StrictModel
from sim_bridge.gauss_markov import GaussMarkov
from sim_bridge.targets import FiniteFloat, Point


class CurrentConfig(StrictModel):
    speed: NonNegativeFloat = Field(0.0, description="V_c, uniform speed (m/s; 0.1-0.5 typical)")
    direction: FiniteFloat = Field(0.0, description="beta_c, the way the water flows, from the x axis (rad)")
    variation: NonNegativeFloat = Field(
        0.0, description="std of each ground component of the Gauss-Markov part (m/s)")
    time_constant: PositiveFloat = Field(300.0, description="tau of the Gauss-Markov part (s; slow: minutes)")
    shear: FiniteFloat = Field(
        0.0, description="G, growth of the speed along shear_direction (s^-1; 0.01 in 'gradient')")
    shear_direction: FiniteFloat | None = Field(
        None, description="beta_G, where the speed grows (rad); None: across the flow, beta_c + pi/2")
    origin: Point = Field((0.0, 0.0), description="p_0, where the shear part is zero (m)")


class Current:
    """The field of a `CurrentConfig`; `advance(dt)` moves its Gauss-Markov part on."""

    def __init__(self, config: CurrentConfig, rng: np.random.Generator) -> None:
        self.config = config
        self._flow = (math.cos(config.direction), math.sin(config.direction))
        across = config.direction + math.pi / 2 if config.shear_direction is None else config.shear_direction
        self._across = (math.cos(across), math.sin(across))
        self._slow = GaussMarkov(config.variation, config.time_constant, 2, rng)

    def advance(self, dt: float) -> None:
        self._slow.advance(dt)

    def velocity(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(cx, cy) at positions (x, y) (m/s, ground frame), arrays of their broadcast shape."""
        config = self.config
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        gx, gy = self._slow.state
        if config.shear == 0.0:
            shape = np.broadcast_shapes(x.shape, y.shape)
            speed = config.speed
            return np.full(shape, speed * self._flow[0] + gx), np.full(shape, speed * self._flow[1] + gy)
        s = (x - config.origin[0]) * self._across[0] + (y - config.origin[1]) * self._across[1]
        speed = config.speed + config.shear * s
        cx = speed * self._flow[0] + gx
        cy = speed * self._flow[1] + gy
        return cx, cy
