"""The control law of one tick: formation, target tracking and avoidance velocities, (30), (31), (32), (33),
(34), (35), to a command."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.core.control.avoidance import avoidance_velocity, safety_filter
from agent.core.control.formation import (
    desired_offsets,
    neighbour_gain,
    saturate,
    saturate_floats,
    surge_and_yaw_rate,
)
from agent.core.params import ControlParams
from agent.core.records import Command


@dataclass(frozen=True)
class VelocityTerms:
    """The parts of the commanded velocity (35), for the record."""

    formation: np.ndarray
    tracking: np.ndarray
    avoidance: np.ndarray
    safety_correction: np.ndarray   # what the safety filter added to (35)
    command: np.ndarray


def control_command(c: ControlParams, dt: float, phase: float, next_phase: float, heading: float,
                    target_state: np.ndarray | None, own_velocity: np.ndarray,
                    estimates: dict[str, np.ndarray | None], neighbour_phases: dict[str, float],
                    obstacles: np.ndarray | None) -> tuple[Command, VelocityTerms, dict[str, bool]]:
    """The command for this tick: the desired offsets (27), (29) and their errors (30), (31), (32) pull
    towards the neighbours and the target, (33) adds the target's estimated velocity, (34) the avoidance,
    (35) sums and saturates; then the safety filter after (35), then (surge, yaw rate). Returns (command,
    its velocity terms, which limits saturated)."""
    # The 2-vector algebra of (27), (29), (30), (33) in plain floats, element by element as numpy did it (the
    # same operations in the same order: the same numbers); numpy's per-call overhead was most of the cost.
    # The neighbours' offsets keep numpy's cos and sin, as before.
    ox, oy = c.radius * math.cos(phase), c.radius * math.sin(phase)             # (27): desired_offset
    usable = [j for j, estimate in estimates.items() if estimate is not None and j in neighbour_phases]
    gain = neighbour_gain(len(usable), c.gain_neighbour, c.neighbour_gain_cap)
    # (30), (33): p*_ij - p^_ij = (p*_io - p*_jo) - p^_ij, then the target's offset error, summed in order.
    fx = fy = 0.0
    if usable:
        theirs = desired_offsets(c.radius, np.array([neighbour_phases[j] for j in usable])).tolist()
        for (dx, dy), j in zip(theirs, usable):
            px, py = np.asarray(estimates[j], dtype=float).tolist()
            fx, fy = fx + gain * ((ox - dx) - px), fy + gain * ((oy - dy) - py)
    tracking = np.zeros(2)
    if target_state is not None:
        t0, t1, t2, t3 = np.asarray(target_state, dtype=float).tolist()
        fx, fy = fx + c.gain_target * (ox - t0), fy + c.gain_target * (oy - t1)
        vx, vy = np.asarray(own_velocity, dtype=float).tolist()
        nx, ny = c.radius * math.cos(next_phase), c.radius * math.sin(next_phase)
        # (29): v*_io = (p*_io,k+1 - p*_io,k) / dt; (33): v^t = sat(U_vo, v^_o) + v*_io, v^_o = v_i - v^_io.
        sx, sy = saturate_floats(c.max_target_speed, vx - t2, vy - t3)
        tracking = np.array([sx + (nx - ox) / dt, sy + (ny - oy) / dt])
    # formation_velocity's np.zeros(2) + sum: 0.0 + the sum.
    formation = np.array([0.0 + fx, 0.0 + fy])
    avoidance = avoidance_velocity(obstacles, c.safety_distance, c.avoidance_gain, c.avoidance_spread)
    formation_bounded = saturate(c.max_formation_speed, formation)
    avoidance_bounded = saturate(c.max_avoidance_speed, avoidance)
    command_velocity = formation_bounded + tracking + avoidance_bounded        # (35)
    filtered, unfiltered = False, command_velocity
    if c.safety_filter:
        command_velocity, filtered = safety_filter(command_velocity, obstacles, c.min_clearance, c.clearance_rate)
    surge, yaw_rate, yaw_saturated = surge_and_yaw_rate(
        command_velocity, heading, c.yaw_rate, dt, c.max_correction_yaw_rate, c.max_speed)
    saturated = {
        "formation": formation_bounded is not formation,
        "avoidance": avoidance_bounded is not avoidance,
        "yaw_rate": yaw_saturated,
        "speed": abs(surge) >= c.max_speed,
        "safety_filter": filtered,
    }
    terms = VelocityTerms(formation, tracking, avoidance, command_velocity - unfiltered, command_velocity)
    return Command(surge, yaw_rate), terms, saturated
