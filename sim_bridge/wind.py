"""The wind after VRX's USVWind: a mean speed plus a Gauss-Markov gust along a fixed direction, and its loads.

Wind over ground V_w(t) = (U + g(t)) (cos beta_w, sin beta_w), g a first-order Gauss-Markov gust of standard
deviation K (VRX's gain) and time constant tau (`gauss_markov.py`). The apparent wind in the body frame
(x forward, y to port) is (u_rw, v_rw) = R(psi)^T V_w - (u, v), u, v the hull's velocity over ground, and

    X_w = c_x u_rw |u_rw|,  Y_w = c_y v_rw |v_rw|,  N_w = -2 c_n u_rw v_rw        (VRX, USVWind.cc)
    c_x = rho_a C_X A_F / 2,  c_y = rho_a C_Y A_L / 2,  c_n = rho_a C_N A_L L / 2   (the hull's windage)

so the yaw moment is zero head-on, stern-on and beam-on and largest on the quarters (Fossen 2021, Sec. 10.1).
VRX itself applies the law to the wind in body axes without the hull's velocity; we use the apparent wind.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from agent.config import NonNegativeFloat, PositiveFloat, StrictModel
from sim_bridge.gauss_markov import GaussMarkov
from sim_bridge.targets import FiniteFloat


class WindConfig(StrictModel):
    speed: NonNegativeFloat = Field(0.0, description="U, mean speed (m/s; VRX 2023 worlds: 0, 3 or 8)")
    direction: FiniteFloat = Field(0.0, description="beta_w, the way the wind blows, from the x axis (rad)")
    gain: NonNegativeFloat = Field(0.0, description="K, the gust's standard deviation (m/s; VRX gain 0-4)")
    time_constant: PositiveFloat = Field(2.0, description="tau, the gust's time constant (s; VRX 2)")
    air_density: PositiveFloat = Field(1.225, description="rho_a (kg/m^3, ISA sea level)")
    cx: NonNegativeFloat = Field(0.8, description="C_X, on the frontal area (VRX's drag of a box-like body)")
    cy: NonNegativeFloat = Field(0.8, description="C_Y, on the lateral area (VRX's drag of a box-like body)")
    cn: NonNegativeFloat = Field(
        0.1, description="C_N, on lateral area x length (from VRX's WAM-V coefficients' ratio, 0.108)")


class Wind:
    """The wind of a `WindConfig`; `advance(dt)` moves its gust on."""

    def __init__(self, config: WindConfig, rng: np.random.Generator) -> None:
        self.config = config
        self._direction = (math.cos(config.direction), math.sin(config.direction))
        self._gust = GaussMarkov(config.gain, config.time_constant, 1, rng)

    def advance(self, dt: float) -> None:
        self._gust.advance(dt)

    @property
    def speed(self) -> float:
        """U + g(t), the wind's speed along its direction now (m/s)."""
        return self.config.speed + float(self._gust.state[0])

    def velocity(self) -> tuple[float, float]:
        """V_w, the wind over ground now (m/s)."""
        speed = self.speed
        return speed * self._direction[0], speed * self._direction[1]

    def loads(self, heading: np.ndarray, u: np.ndarray, v: np.ndarray, windage) -> tuple[np.ndarray, ...]:
        """(X_w, Y_w, N_w) in the body frame (N, N, N m), hulls at `heading` (rad) moving at (u, v) (m/s)."""
        wx, wy = self.velocity()
        c, s = np.cos(heading), np.sin(heading)
        u_rw = c * wx + s * wy - u
        v_rw = -s * wx + c * wy - v
        half_rho = 0.5 * self.config.air_density
        lateral = np.asarray(windage.lateral_area, dtype=float)
        x = half_rho * self.config.cx * np.asarray(windage.frontal_area, dtype=float) * u_rw * np.abs(u_rw)
        y = half_rho * self.config.cy * lateral * v_rw * np.abs(v_rw)
        n = -2.0 * half_rho * self.config.cn * lateral * np.asarray(windage.length, dtype=float) * u_rw * v_rw
        return x, y, n
