"""Covariance intersection and the two cooperative fusions built on it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agent.config import deep_merge
from agent.core.build import InitialEstimates, initial_state
from agent.core.estimators import make_relative_estimator
from agent.core.estimators.plkf import PLKF
from agent.core.fusion import covariance_intersection, covariance_intersection_many
from agent.core.params import AgentParams, RelativeEstimationParams, TargetEstimationParams
from agent.core.records import OdometryReading, Share, TickInputs
from agent.core.step import step
from lab.harness.runner import run
from sim_bridge.scenario import Scenario, load_scenarios

DT = AgentParams().dt
SCENARIOS = Path(__file__).resolve().parents[1] / "configs" / "scenarios"


def test_intersection_of_equal_covariances_is_the_mean_and_keeps_the_covariance():
    A = np.array([[2.0, 0.5], [0.5, 1.0]])
    x, P = covariance_intersection(np.array([1.0, 2.0]), A, np.array([3.0, -2.0]), A)
    np.testing.assert_allclose(x, [2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(P, A, atol=1e-12)  # no confidence is invented from correlated inputs


def test_intersection_hand_value_for_crossing_ellipses():
    # A long in x, B long in y: information 0.5 diag(1/4, 1) + 0.5 diag(1, 1/4) = diag(5/8, 5/8).
    A, B = np.diag([4.0, 1.0]), np.diag([1.0, 4.0])
    x, P = covariance_intersection(np.array([4.0, 0.0]), A, np.array([0.0, 4.0]), B)
    np.testing.assert_allclose(P, np.eye(2) * 1.6, atol=1e-12)
    # x = P (0.5 A^-1 a + 0.5 B^-1 b) = 1.6 * (0.5 * [1, 0] + 0.5 * [0, 1]) = [0.8, 0.8]
    np.testing.assert_allclose(x, [0.8, 0.8], atol=1e-12)
    x_many, P_many = covariance_intersection_many([(np.array([4.0, 0.0]), A), (np.array([0.0, 4.0]), B)])
    np.testing.assert_allclose(x_many, x, atol=1e-12)
    np.testing.assert_allclose(P_many, P, atol=1e-12)


def test_pairwise_fusion_makes_the_two_estimates_exactly_opposite():
    """What removes the 'chase': i fuses (p_ij, -p_ji), j fuses (p_ji, -p_ij), and they end opposite."""
    a, A = np.array([3.0, 1.0]), np.array([[0.5, 0.1], [0.1, 0.3]])
    b, B = np.array([-2.6, -1.3]), np.array([[0.2, -0.05], [-0.05, 0.4]])
    x_i, P_i = covariance_intersection(a, A, -b, B)
    x_j, P_j = covariance_intersection(b, B, -a, A)
    np.testing.assert_allclose(x_i, -x_j, atol=1e-12)
    np.testing.assert_allclose(P_i, P_j, atol=1e-12)


def test_assimilate_refuses_a_bad_estimate():
    est = make_relative_estimator(RelativeEstimationParams(), (1.0, 2.0), name="mckf")
    assert not est.assimilate((np.nan, 0.0), np.eye(2))
    assert not est.assimilate((0.0, 0.0), np.array([[1.0, 2.0], [2.0, 1.0]]))
    np.testing.assert_array_equal(est.position, [1.0, 2.0])
    assert est.diagnostics.rejected == 2
    tracker = PLKF(TargetEstimationParams(), np.zeros(4))
    assert not tracker.assimilate(np.zeros(4), -np.eye(4)) and tracker.rejected == 1


def test_a_faulty_neighbour_target_estimate_is_gated_out():
    params = AgentParams()
    state = initial_state("1", params, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0), target_variance=0.01,
                                                        neighbours={"2": (3.0, 0.0)}, neighbour_variance=0.04))
    for k in range(3):
        t = 0.1 * k
        liar = Share("2", OdometryReading(t, np.zeros(2), 0.0), np.zeros(2), 0.0,
                     target=np.array([500.0, 300.0, 0.0, 0.0]), target_covariance=0.01 * np.eye(4))
        state, out = step(params, state, TickInputs(time=t, odometry=OdometryReading(t, np.zeros(2), 0.0),
                                                    ranges={"2": 3.0}, shares={"2": liar},
                                                    bearing=np.array([1.0, 0.0])))
    assert out.record.health["target_estimates_gated"] >= 1
    assert np.linalg.norm(out.record.target_state[:2] - [5.0, 0.0]) < 0.5


@pytest.mark.slow
def test_cooperative_fusion_improves_the_fleet_over_the_paper_architecture():
    """Table II's MCKF fleet over 30 s, same seeds: with both fusions the estimates are better."""
    _, variants = load_scenarios(SCENARIOS / "table2_estimators.yaml")
    base = variants["mckf"].model_dump()
    fused = Scenario.model_validate(deep_merge(base, {"duration": 30.0}))
    paper = Scenario.model_validate(deep_merge(base, {"duration": 30.0, "agent": {"fleet": {
        "fuse_shared_estimates": False, "fuse_target_estimates": False}}}))
    with_fusion = [run(fused, seed).metrics for seed in range(3)]
    without = [run(paper, seed).metrics for seed in range(3)]
    assert np.mean([m.mean_e_io for m in with_fusion]) < 0.8 * np.mean([m.mean_e_io for m in without])
    assert np.mean([m.mean_e_ij for m in with_fusion]) < np.mean([m.mean_e_ij for m in without])
    assert all(m.settling_time is not None for m in with_fusion)


@pytest.mark.parametrize("bad", [
    {"target": np.array([1.0, 2.0])},                                         # wrong shape
    {"target": np.zeros(4), "target_covariance": np.full((4, 4), np.nan)},    # NaN covariance
    {"target": np.zeros(4)},                                                  # a target without covariance
    {"target": np.zeros(4), "target_covariance": np.eye(3)},                  # wrong shape
    {"target": np.zeros(4), "target_covariance": np.full((4, 4), "x", dtype=object)},    # not numbers
    {"neighbours": {"1": (np.array([np.inf, 0.0]), np.eye(2), 0.0)}},        # inf estimate
    {"neighbours": {"1": (np.zeros(2), np.eye(2), math.nan)}},               # NaN stamp
])
def test_malformed_shares_are_counted_and_ignored(bad):
    params = AgentParams()
    state = initial_state("1", params, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0)))
    fields = {"target": None, "target_covariance": None, "neighbours": {}} | bad
    share = Share("2", OdometryReading(0.0, np.zeros(2), 0.0), np.zeros(2), 0.0, **fields)
    state, out = step(params, state, TickInputs(time=0.0, odometry=OdometryReading(0.0, np.zeros(2), 0.0),
                                                shares={"2": share}, bearing=np.array([1.0, 0.0])))
    assert out.record.health["bad_shares"] == 1 and "2" not in state.tracks
    assert np.isfinite(out.command.surge) and np.isfinite(out.command.yaw_rate)


@pytest.mark.parametrize("delay_to_2", [1, 3])
def test_two_held_vessels_that_command_motion_keep_their_pair_estimates(delay_to_2):
    """Regression (the sea mode's hold at the start): the vessels are still, but their agents command motion
    and share that velocity. A shared estimate carried on with the neighbour's commanded velocity was fused
    into the receiver's filter, which shared it back: the pair estimates walked off by ~0.1 m a tick while
    nothing moved. A shared estimate now refers to the sender's filter epoch, where both vessels' odometry
    was measured, and the fusion is not fed back: with nothing moving each filter keeps its prior and the two
    vessels' fused estimates are the same (CI of the two priors: their mean, the covariances being equal)."""
    # The MCKF: with nothing moving its pseudo-linear update carries no information, so each filter keeps its
    # prior exactly and the fused estimate has a closed form (the raw-range filter would use the ranges).
    params = AgentParams(relative={"estimator": "mckf"})
    truth = np.array([-12.0, -13.0])                          # p_12 = p_1 - p_2, constant
    starts = {"1": InitialEstimates(target=(8.0, 3.0, 0.0, 0.0), neighbours={"2": tuple(truth + [0.1, 0.0])},
                                    neighbour_variance=0.04),
              "2": InitialEstimates(target=(-4.0, -10.0, 0.0, 0.0), neighbours={"1": tuple(-truth + [0.0, 0.1])},
                                    neighbour_variance=0.04)}
    states = {v: initial_state(v, params, s) for v, s in starts.items()}
    sent: dict[str, Share] = {}
    outbox: list[Share] = []    # vessel 1's shares on their way to vessel 2, which get there `delay_to_2` ticks late
    worst, speeds = 0.0, []
    for k in range(40):
        now = k * DT
        outputs = {}
        for v, other in (("1", "2"), ("2", "1")):
            held = OdometryReading(now, np.zeros(2), 0.0)         # never moves
            states[v], outputs[v] = step(params, states[v], TickInputs(
                time=now, odometry=held, ranges={other: float(np.hypot(*truth))},
                shares={other: sent[other]} if other in sent else {}))
        outbox.append(outputs["1"].share)
        sent = {"2": outputs["2"].share}                          # delivered at the next tick ...
        if len(outbox) >= delay_to_2:
            sent["1"] = outbox[-delay_to_2]                       # ... or later: the order must not matter
        speeds.append(np.hypot(*outputs["1"].share.velocity))
        for v, sign in (("1", 1.0), ("2", -1.0)):
            track = states[v].tracks.get("1" if v == "2" else "2")
            if track is not None and track.estimator is not None:
                worst = max(worst, float(np.hypot(*(track.best()[0] - sign * truth))))
    assert np.mean(speeds) > 0.1             # the agents do command motion (turning towards the circle)
    assert worst <= 0.1 + 1e-9              # never further from the truth than the worse prior
    p12 = states["1"].tracks["2"].best()[0]
    p21 = states["2"].tracks["1"].best()[0]
    np.testing.assert_allclose(p12, -p21, atol=1e-9)             # the two vessels agree ...
    np.testing.assert_allclose(p12, truth + [0.05, -0.05], atol=1e-9)   # ... on the mean of the two priors
