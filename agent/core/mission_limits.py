"""What an operator's `set` may ask of the fleet: a circle it can fly, reached at a bounded rate.

A circle of radius r* with n vessels evenly spaced on it puts neighbours 2 r* sin(pi / n) apart (the chord);
it must leave room for the separation guard's distance (min_separation + separation_margin,
agent/core/control/separation.py) and for the formation's own error. Flying it takes |omega*| r* of speed
on top of the target's (up to U_vo), and the formation needs some of U_v left to correct with. A `set` that
asks for less is refused with one line that says why (`infeasible`). An accepted one is not jumped to: r*
and omega* move towards it tick by tick (`toward`), at most RADIUS_RATE and CIRCLE_ACCELERATION, so that the
formation follows the circle rather than chasing it, and a change of direction slows the fleet down to
turn it round instead of reversing it in one tick. docs/operator.md states these limits for the operator.
"""

from __future__ import annotations

import math

from agent.core.params import ControlParams

FORMATION_MARGIN = 1.0     # m between neighbours beyond the guard's distance, for the formation's error
SPEED_SHARE = 0.8          # of U_v for the circle and the target's motion; the rest corrects the formation
RADIUS_RATE = 1.0          # m/s: the most r* moves per second (under U_vf = 1.5 m/s: the formation keeps up)
CIRCLE_ACCELERATION = 0.5  # m/s^2: the most the speed on the circle, |omega*| r*, changes per second
NEAR_ZERO = 1e-9           # rad/s: where omega* passes through 0 (which circles nowhere) on its way round


def chord(radius: float, vessels: int) -> float:
    """2 r sin(pi / n): the distance between neighbours evenly spaced on a circle; infinite for one vessel."""
    return math.inf if vessels < 2 else 2.0 * radius * math.sin(math.pi / vessels)


def needed_chord(control: ControlParams) -> float:
    """The least distance between neighbours on the circle that a `set` may ask for (m)."""
    return control.min_separation + control.separation_margin + FORMATION_MARGIN


def circle_speed_room(control: ControlParams) -> float:
    """The most speed on the circle, |omega*| r*, that a `set` may ask for (m/s)."""
    return SPEED_SHARE * control.max_speed - control.max_target_speed


def infeasible(radius: float, yaw_rate: float, vessels: int, control: ControlParams) -> str | None:
    """Why a fleet of `vessels` (this one included) cannot fly the circle (radius, yaw_rate) with the limits
    of `control`, in one line; None when it can."""
    spacing, needed = chord(radius, vessels), needed_chord(control)
    if spacing < needed:
        return (f"radius {radius:g} m: neighbours {spacing:.2f} m apart on the circle of {vessels} vessels, "
                f"under the {needed:g} m they need (safety distance {control.min_separation:g} m, "
                f"{control.separation_margin:g} m for the estimates, "
                f"{FORMATION_MARGIN:g} m for the formation)")
    speed, room = abs(yaw_rate) * radius, circle_speed_room(control)
    if speed > room:
        return (f"yaw rate {abs(yaw_rate):g} rad/s: {speed:.2f} m/s on the circle of {radius:g} m, over the "
                f"{room:g} m/s the vessels can give it ({SPEED_SHARE:.0%} of their speed limit "
                f"{control.max_speed:g} m/s less the target's {control.max_target_speed:g} m/s)")
    return None


def _move(value: float, goal: float, most: float) -> float:
    return goal if abs(goal - value) <= most else value + math.copysign(most, goal - value)


def toward(radius: float, yaw_rate: float, goal: tuple[float, float], dt: float, control: ControlParams
           ) -> tuple[float, float]:
    """(r*, omega*) one tick of `dt` nearer the `goal` (r*, omega*): r* by at most RADIUS_RATE dt, omega*
    by at most CIRCLE_ACCELERATION dt / r*, skipping 0. Neither move may take the speed on the circle above
    the room for it (or above what it is, if more): the one that would waits for the other (a circle that
    grows while it slows down grows once it is slow enough)."""
    goal_radius, goal_rate = goal
    new_radius = _move(radius, goal_radius, RADIUS_RATE * dt)
    new_rate = _move(yaw_rate, goal_rate, CIRCLE_ACCELERATION * dt / radius)
    if new_rate == 0.0:
        new_rate = math.copysign(NEAR_ZERO, goal_rate)
    allowed = max(circle_speed_room(control), abs(yaw_rate) * radius)
    if abs(new_rate) * new_radius > allowed:
        if abs(new_rate) * radius <= allowed:
            new_radius = radius
        elif abs(yaw_rate) * new_radius <= allowed:
            new_rate = yaw_rate
    return new_radius, new_rate
