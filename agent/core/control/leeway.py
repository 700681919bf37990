"""A leeway model for a hull in a steady wind, estimated from the odometry alone (no anemometer, no GNSS).

A steady wind W (over ground) pushes the hull sideways until the air's cross force, quadratic in the wind
across the hull W . n, balances the water's, quadratic in the sway v: v = kappa W . n with kappa =
1 / (1 + sqrt(d_v / c_y)) (sim_bridge/wind.py; docs/sea.md, "Wind"), n = (-sin psi, cos psi) the hull's port
side. So the sway over ground is w . n(psi) for one unknown vector w = kappa W, whatever the heading.
`leeway_update` moves w towards the sway the odometry showed (normalised least mean squares on one sample:
a heading only tells w . n); `leeway_sway` is the sway the model expects at a heading, which the command
steers against (agent/core/command.py).
A current c adds c . n to the sway, which w takes, and c . t along the heading, which it does not: with a
DVL the surge over ground less the surge through the water (the agent's lagged command) is c . t(psi), and
`set_update` / `set_along` fit and give it the same way (control.set_time_constant; docs/sea.md).
"""

from __future__ import annotations

import math

import numpy as np


def leeway_update(w: np.ndarray, velocity: np.ndarray, heading: float, gain: float) -> np.ndarray:
    """w + gain (s - w . n) n with s = velocity . n the measured sway over ground, 0 <= gain <= 1; w itself
    where that is not finite (a bad sample must not stop the model for good)."""
    nx, ny = -math.sin(heading), math.cos(heading)
    error = float(velocity[0]) * nx + float(velocity[1]) * ny - (float(w[0]) * nx + float(w[1]) * ny)
    updated = np.array([w[0] + gain * error * nx, w[1] + gain * error * ny])
    return updated if np.all(np.isfinite(updated)) else np.array(w, dtype=float)


def leeway_sway(w: np.ndarray, heading: float) -> float:
    """w . n(heading): the sway (m/s, to port) the model expects at this heading."""
    return -math.sin(heading) * float(w[0]) + math.cos(heading) * float(w[1])


def set_update(c: np.ndarray, velocity: np.ndarray, heading: float, surge: float, gain: float) -> np.ndarray:
    """c + gain (s - c . t) t, s = velocity . t - surge: the velocity over ground along the heading less the
    surge through the water, t = (cos psi, sin psi); c itself where that is not finite."""
    tx, ty = math.cos(heading), math.sin(heading)
    error = float(velocity[0]) * tx + float(velocity[1]) * ty - surge - (float(c[0]) * tx + float(c[1]) * ty)
    updated = np.array([c[0] + gain * error * tx, c[1] + gain * error * ty])
    return updated if np.all(np.isfinite(updated)) else np.array(c, dtype=float)


def set_along(c: np.ndarray, heading: float) -> float:
    """c . t(heading): the drift along the heading (m/s) the model expects."""
    return math.cos(heading) * float(c[0]) + math.sin(heading) * float(c[1])
