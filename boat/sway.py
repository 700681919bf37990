"""The hull's sway velocity through the water, estimated from what a boat measures; the dead-reckoning step.

Fossen's sway row (sim_bridge/hull.py, with nu_r = (u, v, r) through the water):
    m22 v_dot + m23 r_dot + m11 u r + (d22 + d22q |v|) v = tau_Y
An open-loop observer integrates it with tau_Y = 0 from the speed log's surge u and a yaw rate r (a gyro, or
successive compass headings): in the momentum w = m22 v + m23 r the r_dot term is exact, w_dot = -m11 u r -
D(v) v, so a step needs the change of r over it, never a differentiated (noisy) rate. The damping is taken
at the step's end, linearly implicit: stable for any dt, and a steady (u, r) gives the exact steady value
d22 v + d22q |v| v = -m11 u r (`steady`). Arrays of shape (n,), one entry per vessel, like inner_loop.py.

Neglected: every sway force but the hull's own (wind, waves, a fender), the current's gradient across the
hull (the model is in the water's frame, exact for a uniform current), and the speed log's own errors (its
scale error and dead band enter u as they are). A non-finite input gives a non-finite v: the caller
refuses it.

`arc_step` is the dead reckoning both users share (the sim's water_log_compass with `sway: hull`, the driver
bridge's odometry): a body-frame displacement (surge, sway) made while the heading turns steadily.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.config import ConfigError
from boat.presets import Hull


@dataclass(frozen=True)
class SwayModel:
    """The sway row's coefficients (Fossen's M and D) of one hull."""

    m11: float   # m - X_udot (kg)
    m22: float   # m - Y_vdot (kg)
    m23: float   # m x_g (kg m)
    linear: float      # d22 = -Y_v (N s/m)
    quadratic: float   # d22q = -Y_|v|v (N s^2/m^2)

    @classmethod
    def of(cls, hull: Hull) -> SwayModel:
        if hull.sway_damping <= 0 and hull.sway_damping_quadratic <= 0:
            raise ConfigError("the hull has no sway damping: its sideslip has no steady value to estimate")
        return cls(hull.mass + hull.added_mass_surge, hull.mass + hull.added_mass_sway, hull.mass * hull.x_g,
                   hull.sway_damping, hull.sway_damping_quadratic)


def steady(model: SwayModel, u, r):
    """v with d22 v + d22q |v| v = -m11 u r: the sway of a steady turn (a quadratic in |v|)."""
    force = -model.m11 * np.asarray(u, dtype=float) * np.asarray(r, dtype=float)
    if model.quadratic == 0:
        return force / model.linear
    a, b = model.quadratic, model.linear
    return np.sign(force) * (-b + np.sqrt(b * b + 4 * a * np.abs(force))) / (2 * a)


def step(model: SwayModel, v, u, r, r_change, dt: float):
    """v after a step of dt in which the surge is u and the yaw rate r (the step's values) and r changed by
    r_change: w' = w - dt (m11 u r + D(|v|) v'), w = m22 v + m23 r, v' = (w' - m23 r_end) / m22."""
    v, u, r, r_change = (np.asarray(a, dtype=float) for a in (v, u, r, r_change))
    damping = model.linear + model.quadratic * np.abs(v)
    # m22 (v' - v) + m23 r_change = -dt (m11 u r + damping v')
    return (model.m22 * v - model.m23 * r_change - dt * model.m11 * u * r) / (model.m22 + dt * damping)


def arc_step(x: float, y: float, heading: float, turn: float, surge: float, sway: float
             ) -> tuple[float, float]:
    """(x, y) after a body-frame displacement (surge forward, sway to port, m) made while the heading turned
    steadily from `heading` by `turn` (rad): the chord, sinc(turn / 2) R(heading + turn / 2) (surge, sway).
    Exact for a steady turn at a steady velocity; with sway 0, the chord along the mean heading."""
    half = 0.5 * turn
    factor = math.sin(half) / half if abs(half) > 1e-9 else 1.0 - half * half / 6.0
    along, across = surge * factor, sway * factor
    direction = heading + half
    c, s = math.cos(direction), math.sin(direction)
    return x + along * c - across * s, y + along * s + across * c
