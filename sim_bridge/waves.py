"""Long-crested deep-water waves: a sum of sinusoids from a Pierson-Moskowitz spectrum, their first-order
(Froude-Krylov) surge, sway and yaw loads on a hull, and the roll and pitch of a hull following the surface.

Spectrum as VRX's PMS wavefield: S(w) = alpha g^2 w^-5 exp(-5/4 (w_p/w)^4), alpha = 0.0081, w_p = 2 pi / T_p,
the amplitudes scaled by VRX's gain K (so the spectrum by K^2): variance m0 = K^2 alpha g^2 / (5 w_p^4),
H_s = 4 sqrt(m0). Its cumulative energy is exp(-5/4 (w_p/w)^4), so N equal-energy bins have closed-form edges;
component i sits at its bin's energy midpoint with a_i = sqrt(2 m0 / N), k_i = w_i^2 / g, a seeded phase and
a direction within +-spread of the mean:  eta(p, t) = sum_i a_i cos(k_i d_i . p - w_i t + phi_i).
Loads: -m g grad(eta) spread over an L x B box (the water's acceleration on the displaced mass), averaged in
closed form over the box; attitude: the tilt of the surface's normal at the point (SNAME signs: roll positive
starboard down, pitch positive bow up). Equations in docs/sea_environment.md.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from agent.config import NonNegativeFloat, PositiveFloat, StrictModel
from sim_bridge.targets import FiniteFloat

GRAVITY = 9.81        # m/s^2, as VRX's wavefield
PHILLIPS = 0.0081     # alpha, the Pierson-Moskowitz (Phillips) constant, as VRX's wavefield


class WavesConfig(StrictModel):
    gain: NonNegativeFloat = Field(
        0.3, description="K, VRX's multiplier of the PM amplitudes (VRX default 0.3; hard tasks 2.0)")
    period: PositiveFloat = Field(5.0, description="T_p, peak period (s; VRX default 5, hard tasks 2)")
    direction: FiniteFloat = Field(0.0, description="the way the waves travel, from the x axis (rad)")
    spread: float = Field(
        0.4, ge=0.0, le=math.pi, description="half-width of the components' directions (rad; VRX angle 0.4)")
    components: int = Field(16, ge=1, le=256, description="N, sinusoids in the sum (VRX uses 3)")


def pm_spectrum(omega: np.ndarray, period: float, gain: float = 1.0) -> np.ndarray:
    """K^2 S(w): VRX's Pierson-Moskowitz spectrum (m^2 s) at angular frequencies w > 0 (rad/s)."""
    omega = np.asarray(omega, dtype=float)
    omega_p = 2.0 * math.pi / period
    return gain**2 * PHILLIPS * GRAVITY**2 / omega**5 * np.exp(-1.25 * (omega_p / omega) ** 4)


def pm_variance(period: float, gain: float = 1.0) -> float:
    """m0 = K^2 alpha g^2 / (5 w_p^4), the integral of K^2 S(w) over w > 0 (m^2)."""
    omega_p = 2.0 * math.pi / period
    return gain**2 * PHILLIPS * GRAVITY**2 / (5.0 * omega_p**4)


def pm_frequency(energy: np.ndarray, period: float) -> np.ndarray:
    """The w whose share of the spectrum below it is `energy` in (0, 1): w_p (5 / (4 (-ln F)))^(1/4)."""
    return 2.0 * math.pi / period * (1.25 / -np.log(np.asarray(energy, dtype=float))) ** 0.25


def _box_means(z: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Over s in [-h, h]: the means of cos(z s / h), sin z / z, and s sin(z s / h), h (sin z / z - cos z) / z.
    Near z = 0 the second loses digits, but its absolute error stays below 1e-8 h; at z = 0 both are exact."""
    safe = np.where(z == 0.0, 1e-300, z)     # head and beam seas give exact zeros
    sinc = np.sin(safe) / safe
    return sinc, half * (sinc - np.cos(safe)) / safe


class Waves:
    """The sea surface of a `WavesConfig`, its components drawn once from `rng` (phases, then directions)."""

    def __init__(self, config: WavesConfig, rng: np.random.Generator) -> None:
        self.config = config
        n = config.components
        self.variance = pm_variance(config.period, config.gain)
        self.omega = pm_frequency((np.arange(n) + 0.5) / n, config.period)
        self.wavenumber = self.omega**2 / GRAVITY
        self.amplitude = np.full(n, math.sqrt(2.0 * self.variance / n))
        self.phase = rng.uniform(0.0, 2.0 * math.pi, n)
        self.direction = config.direction + config.spread * rng.uniform(-1.0, 1.0, n)
        self._kx = self.wavenumber * np.cos(self.direction)
        self._ky = self.wavenumber * np.sin(self.direction)

    def _phase(self, t: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """theta_i at each position: shape (n vessels, N components)."""
        x, y = np.asarray(x, dtype=float)[..., None], np.asarray(y, dtype=float)[..., None]
        return self._kx * x + self._ky * y - self.omega * t + self.phase

    def elevation(self, t: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """eta (m) at each position."""
        return np.cos(self._phase(t, x, y)) @ self.amplitude

    def _body_wavenumbers(self, heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(k_i cos(beta_i - psi), k_i sin(beta_i - psi)): the components' wave vectors in each body frame."""
        heading = np.asarray(heading, dtype=float)[..., None]
        c, s = np.cos(heading), np.sin(heading)
        return c * self._kx + s * self._ky, c * self._ky - s * self._kx

    def slopes(self, t: float, x: np.ndarray, y: np.ndarray, heading: np.ndarray) -> tuple[np.ndarray, ...]:
        """(d eta / dx_b, d eta / dy_b) at each position, in the body frame (x forward, y to port)."""
        kx, ky = self._body_wavenumbers(heading)
        weighted = -self.amplitude * np.sin(self._phase(t, x, y))
        return (weighted * kx).sum(axis=-1), (weighted * ky).sum(axis=-1)

    def attitude(self, t: float, x: np.ndarray, y: np.ndarray, heading: np.ndarray) -> tuple[np.ndarray, ...]:
        """(roll, pitch) (rad) of a hull whose deck follows the surface's normal at its position."""
        sx, sy = self.slopes(t, x, y, heading)
        return np.arcsin(sy / np.sqrt(1.0 + sx**2 + sy**2)), np.arctan(sx)

    def loads(self, t: float, x: np.ndarray, y: np.ndarray, heading: np.ndarray, windage
              ) -> tuple[np.ndarray, ...]:
        """(X, Y, N) (N, N, N m): -m g grad(eta) over an L x B box, and its moment about the centre."""
        kx, ky = self._body_wavenumbers(heading)
        theta = self._phase(t, x, y)
        half_l = np.asarray(windage.length, dtype=float)[..., None] / 2.0
        half_b = np.asarray(windage.beam, dtype=float)[..., None] / 2.0
        along, lever_l = _box_means(kx * half_l, half_l)
        across, lever_b = _box_means(ky * half_b, half_b)
        weight = np.asarray(windage.mass, dtype=float) * GRAVITY
        sine = self.amplitude * np.sin(theta) * along * across
        x_force = weight * (sine * kx).sum(axis=-1)
        y_force = weight * (sine * ky).sum(axis=-1)
        arms = ky * lever_l * across - kx * lever_b * along
        moment = weight * (self.amplitude * np.cos(theta) * arms).sum(axis=-1)
        return x_force, y_force, moment
