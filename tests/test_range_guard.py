"""The range guard (agent/core/step.py `_range_allowances`, agent/core/control/separation.py
`range_allowance`): a neighbour without a pair estimate is kept apart by a low order statistic of its last
raw ranges, whatever the ranges' outliers (docs/equations.md D18)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.config import updated
from agent.core.build import InitialEstimates, initial_state
from agent.core.control.separation import range_allowance
from agent.core.params import AgentParams
from agent.core.range_noise import GaussianMixtureNoise
from agent.core.records import OdometryReading, TickInputs
from agent.core.step import step

TABLE_II_NOISE = GaussianMixtureNoise(outlier_fraction=0.2, variance=0.4, outlier_variance=10.0)


def test_the_allowance_is_the_rate_times_the_order_statistic_beyond_the_guard_distance():
    assert range_allowance([6.0, 0.1, 13.0, 5.0, 5.5], 1, 3.5, 0.4) == 0.4 * (5.0 - 3.5)   # 0.1 m alone: voted out
    assert range_allowance([0.2, 0.1, 13.0, 5.0, 5.5], 1, 3.5, 0.4) == 0.0                 # two short: stop
    assert range_allowance([4.5], 1, 3.5, 0.4) == 0.4 * (4.5 - 3.5)                          # one range: itself
    assert range_allowance([4.5, 2.0], 3, 3.5, 0.4) == 0.0                                   # fewer: the smallest


def _chase(rng: np.random.Generator, count: int, ticks: int) -> float:
    """`count` vessels placed at random at least 4 m apart, each started without estimates and hearing no
    share, each seeing the next one as its target (bearings): each drives at its neighbour with nothing but
    the ranges, Table II's noise, to keep it off. Returns the closest approach (m) of any two."""
    params = AgentParams()
    params = updated(params, control=updated(params.control, radius=0.5))
    dt = params.dt
    while True:
        positions = rng.uniform(-8.0, 8.0, size=(count, 2))
        gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1)[np.triu_indices(count, 1)]
        if gaps.min() >= 4.0:
            break
    headings = rng.uniform(-math.pi, math.pi, size=count)
    ids = [str(i + 1) for i in range(count)]
    states = [initial_state(v, params, InitialEstimates()) for v in ids]
    odometry = positions.copy()
    closest = math.inf
    for k in range(ticks):
        distances = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
        closest = min(closest, float(distances[np.triu_indices(count, 1)].min()))
        commands = []
        for i, v in enumerate(ids):
            away = positions[i] - positions[(i + 1) % count]       # the bearing: from the 'target' to i
            bearing = away / np.linalg.norm(away)
            noise = TABLE_II_NOISE.sample(rng, count)
            ranges = {w: max(float(distances[i, m] + noise[m]), 0.0) for m, w in enumerate(ids) if m != i}
            states[i], output = step(params, states[i], TickInputs(
                time=k * dt, odometry=OdometryReading(k * dt, odometry[i].copy(), float(headings[i])),
                ranges=ranges, shares={}, bearing=bearing))
            commands.append(output.command)
        for i, command in enumerate(commands):
            surge = min(max(command.surge, -params.control.max_speed), params.control.max_speed)
            step_vector = surge * dt * np.array([math.cos(headings[i]), math.sin(headings[i])])
            positions[i] += step_vector
            odometry[i] += step_vector
            headings[i] = math.remainder(headings[i] + command.yaw_rate * dt, 2 * math.pi)
    return closest


@pytest.mark.slow   # an in-process fleet run of seconds: the full suite's, not test-fast's
def test_vessels_chasing_each_other_with_no_estimates_never_come_inside_the_safety_distance():
    """30 fleets of 2-5 vessels placed at random, each driving at the next with no estimate of any
    neighbour, its ranges drawn with Table II's heavy-tailed noise: no two ever closer than min_separation.
    (Before the range guard, the raw-range stop alone: down to 0.00 m, seed 36.)"""
    rng = np.random.default_rng(36)
    limit = AgentParams().control.min_separation
    worst = min(_chase(rng, int(rng.integers(2, 6)), 200) for _ in range(30))
    assert worst >= limit, f"closest approach {worst:.2f} m"
