"""The target's range along the bearing from the neighbours' target estimates and the ranges to them
(agent/core/target_range.py, docs/equations.md D20): the fit against geometry worked by hand, its variance
against (R2) and against seeded noise, the cases it must refuse, and what it mends in a fleet: a vessel that
joins or restarts without estimates (the paper's MCKF, which does not localise from ranges, as in the
paper's Figs. 12-15)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agent.core.build import InitialEstimates, initial_state
from agent.core.membership import receive_shares, store_ranges
from agent.core.params import AgentParams
from agent.core.records import OdometryReading, Share
from agent.core.target import range_from_neighbours, target_filter
from agent.core.target_range import MEDIAN_EFFICIENCY, RangeWitness, range_along_bearing
from lab.harness import runner
from sim_bridge.scenario import select_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "configs" / "scenarios"
RANGE_VARIANCE = 2.32
DT = 0.1


def witness(target_range: float, direction, pair, count: int = 10, covariance=None, moves=None,
            distances=None) -> RangeWitness:
    """A neighbour at p_ij = `pair` when our target lies `target_range` along `direction`: its target
    estimate is p_jo = s u - p_ij (R1); the ranges are exact unless given."""
    u, pair = np.asarray(direction, float), np.asarray(pair, float)
    moves = np.zeros((count, 2)) if moves is None else np.asarray(moves, float)
    if distances is None:
        distances = np.hypot(*(pair + moves).T)
    return RangeWitness(target_range * u - pair, np.zeros((2, 2)) if covariance is None else np.asarray(covariance),
                        np.asarray(distances, float), moves, RANGE_VARIANCE)


def test_exact_ranges_give_the_range_and_the_variance_of_r2():
    u = np.array([math.cos(0.7), math.sin(0.7)])
    pairs = [(3.0, -4.0), (-6.0, 1.0), (2.0, 5.0)]
    witnesses = [witness(7.0, u, p, count=20) for p in pairs]
    s, variance, ranges_only = range_along_bearing(u, witnesses, 0.1)
    assert s == pytest.approx(7.0, abs=1e-9)
    # (R2) by hand: c_j = u . p_ij / |p_ij|, sigma_j^2 = (pi/2) 2.32 / 20 (exact estimates of p_jo).
    sigma2 = MEDIAN_EFFICIENCY * RANGE_VARIANCE / 20
    information = sum((u @ np.array(p) / math.hypot(*p)) ** 2 / sigma2 for p in pairs)
    assert variance == pytest.approx(1.0 / information, rel=1e-9) and ranges_only == pytest.approx(variance, rel=1e-9)


def test_a_neighbours_own_target_error_counts_in_the_variance_but_not_in_the_ranges_alone():
    u = np.array([1.0, 0.0])
    pairs = [(3.0, -4.0), (-6.0, 1.0)]
    sure = [witness(7.0, u, p, count=20) for p in pairs]
    unsure = [witness(7.0, u, p, count=20, covariance=0.3 * np.eye(2)) for p in pairs]
    _, variance, ranges_only = range_along_bearing(u, sure, 0.1)
    _, wider, same = range_along_bearing(u, unsure, 0.1)
    assert same == pytest.approx(ranges_only, rel=1e-9)
    # sigma_j^2 gains along^T (0.3 I) along = 0.3 for each.
    sigma2 = MEDIAN_EFFICIENCY * RANGE_VARIANCE / 20 + 0.3
    assert wider == pytest.approx(1.0 / sum((p[0] / math.hypot(*p)) ** 2 / sigma2 for p in pairs), rel=1e-9)
    assert wider > variance


def test_ranges_taken_while_the_pair_moved_are_carried_by_the_odometry():
    """Two neighbours closing and opening along their lines of sight at 1 m/s over the last 3 s: each range
    is |p_ij + move_k|, carried back to the share's time by the odometry. Fitted as if all were taken at that
    time, the ranges' median (1.5 s old) misses by 1.5 m and the fit is off or refused."""
    u = np.array([0.0, 1.0])
    times = np.linspace(-3.0, 0.0, 31)
    moves = np.outer(times, [0.0, 1.0])
    witnesses = [witness(6.0, u, (1.0, -4.0), moves=moves), witness(6.0, u, (-1.5, 5.0), moves=moves)]
    s, _, _ = range_along_bearing(u, witnesses, 0.1)
    assert s == pytest.approx(6.0, abs=1e-9)
    still = [RangeWitness(w.target, w.target_covariance, w.distances, np.zeros_like(w.moves), RANGE_VARIANCE)
             for w in witnesses]
    fit = range_along_bearing(u, still, 0.1)
    assert fit is None or abs(fit[0] - 6.0) > 0.5, fit


def test_one_neighbour_cannot_say_which_root():
    u = np.array([1.0, 0.0])
    assert range_along_bearing(u, [witness(7.0, u, (3.0, -4.0))], 0.1) is None
    assert range_along_bearing(u, [], 0.1) is None


def test_two_neighbours_in_line_with_our_bearing_cannot_either():
    """Both neighbours have u . p_ij = 2, so both circles cut our line of sight at s and at s - 4 (both
    roots 2 u.p_jo - s = s - 4): two fits fit equally well."""
    u = np.array([1.0, 0.0])
    witnesses = [witness(9.0, u, (2.0, 4.0)), witness(9.0, u, (2.0, -5.0))]
    assert range_along_bearing(u, witnesses, 0.1) is None
    # The second root behind the vessel (s - 4 < least range) leaves one.
    close = [witness(3.0, u, (2.0, 4.0)), witness(3.0, u, (2.0, -5.0))]
    assert range_along_bearing(u, close, 0.1)[0] == pytest.approx(3.0, abs=1e-9)


def test_a_neighbour_whose_ranges_contradict_the_others_refuses_the_fit():
    u = np.array([1.0, 0.0])
    good = [witness(7.0, u, (3.0, -4.0), count=20), witness(7.0, u, (-6.0, 1.0), count=20)]
    wrong = witness(7.0, u, (0.0, 6.0), count=20)
    off = RangeWitness(wrong.target, wrong.target_covariance, wrong.distances + 3.0, wrong.moves, RANGE_VARIANCE)
    assert range_along_bearing(u, good + [wrong], 0.1) is not None
    assert range_along_bearing(u, good + [off], 0.1) is None


def test_the_variance_covers_the_error_over_seeded_noise():
    """Gaussian ranges (variance 2.32 m^2, 30 per neighbour), three neighbours at random around a target at a
    random range: the normalised squared error (s - s_true)^2 / var has the mean of chi-square with one
    degree of freedom, 1, within what 400 draws allow (its standard error is 0.07); seed 11."""
    rng = np.random.default_rng(11)
    normalised = []
    for _ in range(400):
        angle, s_true = rng.uniform(0, 2 * math.pi), rng.uniform(4.0, 25.0)
        u = np.array([math.cos(angle), math.sin(angle)])
        witnesses = []
        for _ in range(3):
            pair = rng.uniform(4.0, 12.0) * np.array([math.cos(b := rng.uniform(0, 2 * math.pi)), math.sin(b)])
            exact = np.full(30, math.hypot(*pair))
            witnesses.append(witness(s_true, u, pair, count=30,
                                     distances=exact + rng.normal(0.0, math.sqrt(RANGE_VARIANCE), 30)))
        fit = range_along_bearing(u, witnesses, 0.1)
        if fit is not None:
            normalised.append((fit[0] - s_true) ** 2 / fit[1])
    assert len(normalised) >= 300
    assert 0.8 <= float(np.mean(normalised)) <= 1.25, np.mean(normalised)


@pytest.mark.slow   # an in-process fleet run of seconds: the full suite's, not test-fast's
@pytest.mark.parametrize("seed", [0, 1])
def test_a_vessel_that_joins_with_the_papers_mckf_localises_its_neighbours(seed):
    """dropout_join's join (the paper's Figs. 12-15: vessel 5 joins at 50 s, MCKF): over the last 20 s the worst
    pair error e_ij stays under 1 m. Before its target filter took its range from the neighbours, the joiner's
    pairs waited on target routes that waited on that range, then started from a range alone, and the MCKF
    never localised them: e_ij 11.6 and 9.9 m on these seeds."""
    _, scenario = select_scenario(SCENARIOS / "dropout_join.yaml", "join")
    trace = runner.run(scenario, np.random.SeedSequence(scenario.seed).spawn(seed + 1)[seed])
    last = trace.e_ij[trace.time >= trace.time[-1] - 20.0]
    assert np.nanmax(last) < 1.0, np.nanmax(last)


def _restarted_vessel_two(neighbours: dict, ticks: int = 50):
    """Vessel 2 at (15, 0) from a target at the origin, still, its target filter restarted (range unobserved).
    Each neighbour (id -> (position, v^_o it shares, that velocity's covariance)) shares an exact target
    position with 0.01 m^2 per axis and is ranged exactly every tick."""
    params = AgentParams()
    here = np.array([15.0, 0.0])
    state = initial_state("2", params, InitialEstimates())
    for k in range(ticks):
        now = k * DT
        state.own.put(now, (0.0, 0.0))
        shares = {}
        for j, (p, velocity, covariance) in neighbours.items():
            shared_covariance = np.zeros((4, 4))
            shared_covariance[:2, :2] = 0.01 * np.eye(2)
            shared_covariance[2:, 2:] = covariance
            shares[j] = Share(j, OdometryReading(now, np.asarray(p) + 100.0, 0.0), np.zeros(2), 0.0,
                              target=np.array([*p, *velocity]), target_covariance=shared_covariance)
        receive_shares(params, state, shares, now)
        store_ranges(params, state, {j: float(np.hypot(*(here - p))) for j, (p, _, _) in neighbours.items()}, now)
    return params, state, (ticks - 1) * DT


def test_a_range_taken_from_the_neighbours_takes_their_target_velocity_too():
    """The restarted filter sits at 10 m for 15 with a velocity 2 m/s off and sure of it (as the bearings at a
    wrong range leave it: dropout_join seed 1, 2.6 m/s off across the line of sight at 0.006 (m/s)^2). Taking
    the range, it takes v_io = v_i - v_o with v_o the neighbours' shared v^_o fused with equal weights, and P_vv
    theirs; by hand, per axis (the covariances are diagonal): information (1/0.2 + 1/0.05) / 2 = 12.5 on both,
    so P_vv = 0.08 I and v_o = 0.08 (5 * 0.5 + 20 * 0.3) / 2 = 0.34 along x, 0.08 (20 * 0.1 - 5 * 0.1) / 2 =
    0.06 along y; v_i = (0.3, -0.4). Before, the filter kept its own v and P_vv, and its range drifted 5.5 m
    in 4 s (docs/equations.md D20)."""
    neighbours = {"1": ((0.0, 5.0), (0.5, 0.1), np.diag([0.2, 0.05])),
                  "3": ((-5.0, 0.0), (0.3, -0.1), np.diag([0.05, 0.2]))}
    params, state, now = _restarted_vessel_two(neighbours)
    wrong = np.diag([4.0, 4.0, 0.005, 0.005])
    wrong[0, 2] = wrong[2, 0] = 0.1
    state.tracker = target_filter(params.target, np.array([10.0, 0.0, -1.7, 1.0]), wrong, DT, range_unobserved=True)
    state.motion.velocity = np.array([0.3, -0.4])
    assert range_from_neighbours(params, state, np.array([1.0, 0.0]), now)
    x, P = state.tracker.state, state.tracker.covariance
    np.testing.assert_allclose(x[:2], [15.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(x[2:], [0.3 - 0.34, -0.4 - 0.06], atol=1e-12)
    np.testing.assert_allclose(P[2:, 2:], 0.08 * np.eye(2), atol=1e-12)
    np.testing.assert_array_equal(P[:2, 2:], np.zeros((2, 2)))
    assert state.health.target_ranges_fixed == 1
