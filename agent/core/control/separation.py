"""The separation guard between vessels (not in the paper): a bound on the surge that no desired velocity,
r*, omega* or oscillator phase can lift.

The vessel does not steer a free velocity: over one sampling period it moves s dt along a heading that turns
from theta by at most omega dt (surge s and yaw rate omega of (31); the simulation holds the heading over the
period, a boat turns during it). With p_ij = p_i - p_j, d = |p_ij| and u = -p_ij / d the direction towards j,
the distance after the period is at least d minus what i moves along u minus what j moves along -u (the
length of a vector is at least its component on p_ij). Vessel i's part is at most
    s dt max cos(psi - beta)   over the headings psi the period sweeps, beta the bearing of u
(for s >= 0; astern the same with the opposite heading). The guard limits that part to
    lambda (d - D)^+,   lambda = rate dt <= 1/2,
with D the guard's distance. Both vessels of a pair run the same guard, so the pair closes by at most
2 lambda (d - D) in one period and (d - D) shrinks by at most the factor 1 - 2 lambda: a pair outside D
never crosses it, and one inside D (a start too close, an estimate that moved) only opens. Whatever the
formation asks, surge 0 always keeps the bound, so the allowed surges are an interval around 0 and the
guard clips the commanded surge into it; the yaw rate is left alone, so a vessel stopped facing its
neighbour turns away and goes on.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

TWO_PI = 2.0 * math.pi


def sweep_max_cos(start: float, sweep: float) -> float:
    """max cos(start + a) over a between 0 and `sweep` (either sign): the largest share of a unit step
    along a heading that turns from `start` by `sweep` radians can have along angle 0."""
    if abs(sweep) >= TWO_PI:
        return 1.0
    low, high = min(start, start + sweep), max(start, start + sweep)
    if TWO_PI * math.ceil(low / TWO_PI) <= high:
        return 1.0       # the sweep passes through the direction itself
    return max(math.cos(start), math.cos(start + sweep))


def surge_interval(heading: float, turn: float, neighbours: Iterable[tuple[float, float]],
                   guard_distance: float, rate: float) -> tuple[float, float]:
    """The surges (low <= 0 <= high, m/s) that move this vessel towards no neighbour faster than
    rate (d - D)^+ (m/s) over a period in which its heading turns from `heading` by `turn` (rad).
    `neighbours` are the p_ij = p_i - p_j (m) of the neighbours to keep apart from; D is `guard_distance`."""
    low, high = -math.inf, math.inf
    for px, py in neighbours:
        d = math.hypot(px, py)
        allowed = rate * max(d - guard_distance, 0.0)      # closing speed allowed towards j
        if d == 0.0:
            return 0.0, 0.0     # no direction to judge by: do not move
        if allowed >= high and allowed >= -low:
            # Its bounds, allowed / ahead and -allowed / astern (shares at most 1), cannot be tighter than
            # those kept: skip the angles. Most of a large fleet is this far, where the sweeps cost 3 us each.
            continue
        beta = math.atan2(-py, -px)                         # bearing of j from i
        ahead = sweep_max_cos(heading - beta, turn)         # at most this share of s goes towards j ...
        astern = sweep_max_cos(heading - beta + math.pi, turn)   # ... and of -s, going astern
        if ahead > 0.0:
            high = min(high, allowed / ahead)
        if astern > 0.0:
            low = max(low, -allowed / astern)
    return low, high


def guarded_surge(surge: float, heading: float, yaw_rate: float, dt: float,
                  neighbours: Iterable[tuple[float, float]], guard_distance: float, rate: float) -> float:
    """The commanded surge clipped into `surge_interval` for a tick that commands `yaw_rate`: the same
    float when it is within it."""
    low, high = surge_interval(heading, yaw_rate * dt, neighbours, guard_distance, rate)
    if surge > high:
        return high
    if surge < low:
        return low
    return surge


def coasting_distance(speed: float, surge_lag: float) -> float:
    """How far a boat at `speed` (m/s) whose surge follows the command with a first-order lag of time
    constant `surge_lag` (s) runs after a stop command: int_0^inf |u| e^{-t/tau} dt = |u| tau (m)."""
    return abs(speed) * surge_lag


def range_allowance(ranges: list[float], rank: int, guard_distance: float, rate: float) -> float:
    """The surge (m/s, either way) allowed near a neighbour known by its ranges alone: rate (q - D)^+,
    q the `rank`-th smallest (0: the smallest) of its last `ranges`, or their smallest if there are fewer."""
    ordered = sorted(ranges)
    return rate * max((ordered[rank] if len(ordered) > rank else ordered[0]) - guard_distance, 0.0)
