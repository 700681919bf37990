"""The first-order Gauss-Markov process the current's slow part and the wind's gusts share.

dx = -x/tau dt + sigma sqrt(2/tau) dW: stationary standard deviation sigma, autocorrelation exp(-|lag|/tau)
(Fossen 2021, Sec. 10.3; VRX's USVWind gust, whose gain K is sigma). `advance(dt)` uses the exact
discretisation x+ = a x + sigma sqrt(1 - a^2) w, a = exp(-dt/tau): its statistics do not depend on the step.
The state starts in the stationary distribution: the sea was already in this state before the run began.
"""

from __future__ import annotations

import math

import numpy as np


class GaussMarkov:
    """`size` independent components, each with standard deviation `std` and time constant `tau` (s)."""

    def __init__(self, std: float, tau: float, size: int, rng: np.random.Generator) -> None:
        self.std = float(std)
        self.tau = float(tau)
        self._rng = rng
        self._dt = math.nan          # the last step's dt, whose decay and noise factors are cached
        self._decay = self._noise = 0.0
        self.state = rng.standard_normal(size) * self.std if self.std > 0 else np.zeros(size)

    def advance(self, dt: float) -> None:
        """Move the state on by dt >= 0 seconds (no draw for dt = 0, nor when std = 0)."""
        if dt <= 0.0 or self.std == 0.0:
            return
        if dt != self._dt:
            self._dt = dt
            self._decay = math.exp(-dt / self.tau)
            self._noise = self.std * math.sqrt(-math.expm1(-2.0 * dt / self.tau))
        self.state = self._decay * self.state + self._noise * self._rng.standard_normal(self.state.shape[0])
