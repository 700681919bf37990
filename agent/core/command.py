"""The control law of one tick: formation, target tracking and avoidance velocities, (30), (31), (32), (33),
(34), (35), to a command."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.angles import wrap_angle
from agent.core.control.avoidance import avoidance_velocity, safety_filter
from agent.core.control.formation import (
    desired_offset,
    desired_offsets,
    desired_velocity,
    formation_velocity,
    lag_compensated_rate,
    neighbour_gain,
    saturate,
    surge_and_yaw_rate,
    tracking_velocity,
)
from agent.core.params import ControlParams
from agent.core.records import Command

# Up to this many neighbours their desired offsets (27) are computed one by one in floats, above it in numpy.
FLOAT_OFFSETS = 8


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
                    estimates: dict[str, tuple[float, float] | None], neighbour_phases: dict[str, float],
                    obstacles: np.ndarray | None, yaw_rate_estimate: float = 0.0,
                    sway: float = 0.0, along: float = 0.0) -> tuple[Command, VelocityTerms, dict[str, bool]]:
    """The command for this tick: the desired offsets (27), (29) and their errors (30), (31), (32) pull
    towards the neighbours and the target, (33) adds the target's estimated velocity, (34) the avoidance,
    (35) sums and saturates; then the safety filter after (35), then (surge, yaw rate). Returns (command,
    its velocity terms, which limits saturated). With `c.yaw_lag` > 0 the yaw rate is the lag-compensated
    heading loop's, from the boat's rate as the agent models it (`yaw_rate_estimate`); with
    `c.boat_max_yaw_rate` it is clipped to the boat's turn-rate limit, with `c.boat_max_astern` the surge to
    its astern limit."""
    ox, oy = desired_offset(c.radius, phase)
    usable = [j for j, estimate in estimates.items() if estimate is not None and j in neighbour_phases]
    gain = neighbour_gain(len(usable), c.gain_neighbour, c.neighbour_gain_cap)
    # (30), (33): kappa_ij (p*_ij - p^_ij) with p*_ij = p*_io - p*_jo, then the target's term.
    terms = []
    if usable:
        # A few offsets in floats, many in one numpy call: the same numbers (tests/test_core_kernels.py).
        theirs = ([desired_offset(c.radius, neighbour_phases[j]) for j in usable] if len(usable) <= FLOAT_OFFSETS
                  else desired_offsets(c.radius, np.array([neighbour_phases[j] for j in usable])).tolist())
        for (dx, dy), j in zip(theirs, usable):
            px, py = estimates[j]      # p^_ij at now (x, y)
            terms.append((gain, (ox - dx) - px, (oy - dy) - py))
    tracking = np.zeros(2)
    if target_state is not None:
        t0, t1, t2, t3 = np.asarray(target_state, dtype=float).tolist()
        terms.append((c.gain_target, ox - t0, oy - t1))
        vx, vy = np.asarray(own_velocity, dtype=float).tolist()
        # v^_o = v_i - v^_io
        tracking = np.array(tracking_velocity((vx - t2, vy - t3), desired_velocity(c.radius, phase, next_phase, dt),
                                              c.max_target_speed))
    formation = np.array(formation_velocity(terms))
    avoidance = avoidance_velocity(obstacles, c.safety_distance, c.avoidance_gain, c.avoidance_spread)
    formation_bounded = saturate(c.max_formation_speed, formation)
    avoidance_bounded = saturate(c.max_avoidance_speed, avoidance)
    command_velocity = formation_bounded + tracking + avoidance_bounded        # (35)
    if sway != 0.0:
        # The hull goes along its heading at the surge asked and across it at the sway the wind gives it
        # (leeway): ask for the velocity less that sway, so that the sum is the velocity wanted.
        command_velocity = command_velocity - sway * np.array([-math.sin(heading), math.cos(heading)])
    if along != 0.0:
        # And a current's set along the heading, which the surge through the water does not include.
        command_velocity = command_velocity - along * np.array([math.cos(heading), math.sin(heading)])
    filtered, unfiltered = False, command_velocity
    if c.safety_filter:
        command_velocity, filtered = safety_filter(command_velocity, obstacles, c.min_clearance, c.clearance_rate)
    surge, yaw_rate, yaw_saturated = surge_and_yaw_rate(
        command_velocity, heading, c.yaw_rate, dt, c.max_correction_yaw_rate, c.max_speed, c.heading_gain)
    if c.yaw_lag > 0.0:
        vx, vy = command_velocity.tolist()
        error = 0.0 if vx == 0.0 and vy == 0.0 else wrap_angle(math.atan2(vy, vx) - heading)
        yaw_rate = lag_compensated_rate(error, yaw_rate_estimate, c.yaw_rate, c.yaw_lag, c.heading_bandwidth,
                                        c.heading_damping)
        correction = yaw_rate - c.yaw_rate
        yaw_saturated = abs(correction) > c.max_correction_yaw_rate
        yaw_rate = c.yaw_rate + min(max(correction, -c.max_correction_yaw_rate), c.max_correction_yaw_rate)
    if c.boat_max_yaw_rate is not None and abs(yaw_rate) > c.boat_max_yaw_rate:
        yaw_rate, yaw_saturated = math.copysign(c.boat_max_yaw_rate, yaw_rate), True
    # Before the separation guard, whose interval always holds 0: clipping here never undoes it.
    astern = c.boat_max_astern is not None and surge < -c.boat_max_astern
    if astern:
        surge = -c.boat_max_astern
    saturated = {
        "formation": formation_bounded is not formation,
        "avoidance": avoidance_bounded is not avoidance,
        "yaw_rate": yaw_saturated,
        "speed": abs(surge) >= c.max_speed or astern,
        "safety_filter": filtered,
    }
    terms = VelocityTerms(formation, tracking, avoidance, command_velocity - unfiltered, command_velocity)
    return Command(surge, yaw_rate), terms, saturated
