"""UWB antennas off the hull's centre (agent/core/antenna.py): the range between two lever arms, the raw-range
filter's model of it, the share's `antenna` field, and the pair track that feeds the filter the offsets.

Reference values: ranges worked out by hand for chosen headings and arms, and the simulator's own antenna
positions (sim_bridge/sensors.py, written separately) on random geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from agent.contract import ReceivedShare, ShareMessage, encode
from agent.core.antenna import antenna_offset, antenna_range, arm_vector
from agent.core.checks import checked_share
from agent.core.estimators import RawRange, make_relative_estimator
from agent.core.neighbours import History, NeighbourPrior, NeighbourTrack, PairTiming, stamp_key
from agent.core.params import AgentParams, FleetParams, RelativeEstimationParams
from agent.core.records import OdometryReading, Share, share_from_json, share_to_json
from agent.shell.translate import message_from_share, share_from_message
from sim_bridge.sensors import antenna_positions

DT = 0.1
NO_PRIOR = 1e12 * np.eye(2)


def offset(psi_i, arm_i, psi_j, arm_j):
    return antenna_offset(arm_vector(psi_i, arm_i), arm_vector(psi_j, arm_j))


# ----- the geometry -----

def test_two_aft_antennas_facing_each_other_are_further_apart_by_both_arms():
    # i at the origin heading east, j 10 m east heading west, each antenna 0.3 m aft: the antennas are at
    # (-0.3, 0) and (10.3, 0), 10.6 m apart. p_ij = p_i - p_j = (-10, 0).
    delta = offset(0.0, (-0.3, 0.0), math.pi, (-0.3, 0.0))
    assert delta == pytest.approx((-0.6, 0.0), abs=1e-15)
    assert antenna_range((-10.0, 0.0), delta) == pytest.approx(10.6, abs=1e-12)


def test_a_range_between_arms_at_right_angles_by_hand():
    # i at the origin heading east, antenna (-0.3 forward, 0.2 left): at (-0.3, 0.2). j at (0, 10) heading
    # north, the same arm: R(90 deg)(-0.3, 0.2) = (-0.2, -0.3), at (-0.2, 9.7). Range sqrt(0.1^2 + 9.5^2).
    assert arm_vector(math.pi / 2, (-0.3, 0.2)) == pytest.approx((-0.2, -0.3), abs=1e-15)
    delta = offset(0.0, (-0.3, 0.2), math.pi / 2, (-0.3, 0.2))
    assert antenna_range((0.0, -10.0), delta) == pytest.approx(math.sqrt(0.01 + 90.25), abs=1e-12)
    # Centre to centre it would be 10 m: the arms take 0.5 m off this range.
    assert antenna_range((0.0, -10.0), (0.0, 0.0)) == 10.0


def test_the_range_between_antennas_is_the_simulators_on_random_geometry():
    rng = np.random.default_rng(7)
    for _ in range(200):
        centres = rng.uniform(-30.0, 30.0, (2, 2))
        headings = rng.uniform(-math.pi, math.pi, 2)
        arms = np.column_stack([rng.uniform(-2.0, 2.0, (2, 2)), np.zeros(2)])
        antennas = antenna_positions(centres, headings, arms)
        delta = offset(headings[0], tuple(arms[0, :2]), headings[1], tuple(arms[1, :2]))
        relative = tuple(centres[0] - centres[1])
        assert antenna_range(relative, delta) == pytest.approx(np.linalg.norm(antennas[0] - antennas[1]),
                                                               abs=1e-12)


# ----- the filter -----

def _pair(seconds=60.0, rate=0.1, seed=0, arm=(1.0, 0.5)):
    """p_ij on a 15 m circle; i heads along its own slow turn, j holds north. Antenna ranges with N(0, 0.3^2)
    noise. Returns (path (K+1, 2), offsets (K+1, 2), ranges (K+1,))."""
    t = np.arange(round(seconds / DT) + 1) * DT
    path = 15.0 * np.column_stack([np.cos(rate * t), np.sin(rate * t)])
    psi_i, psi_j = 0.02 * t, np.full_like(t, math.pi / 2)
    offsets = np.array([offset(a, arm, b, arm) for a, b in zip(psi_i, psi_j)])
    ranges = np.linalg.norm(path + offsets, axis=1) + np.random.default_rng(seed).normal(0.0, 0.3, len(t))
    return path, offsets, ranges


def _relative(**raw) -> RelativeEstimationParams:
    return RelativeEstimationParams(estimator={"name": "raw_range",
                                               "noise_components": ((1.0, 0.0, 0.09),), **raw})


def _filtered(path, offsets, ranges, corrected: bool) -> np.ndarray:
    """The estimator's p^_ij at every epoch, fed the ranges with (`update_between`) or without the offsets."""
    estimator = RawRange(_relative(), (0.0, 0.0), NO_PRIOR)
    estimator.mark_range_epoch()
    estimates = [estimator.position]
    for k in range(1, len(path)):
        estimator.predict(path[k] - path[k - 1])
        if corrected:
            estimator.update_between(ranges[k - 1], ranges[k], tuple(offsets[k - 1]), tuple(offsets[k]))
        else:
            estimator.update(ranges[k - 1], ranges[k])
        estimates.append(estimator.position)
    return np.array(estimates)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_arms_bias_the_centre_estimate_and_the_corrected_filter_does_not(seed):
    path, offsets, ranges = _pair(seed=seed)
    last = slice(-200, None)       # the last 20 s
    plain = np.linalg.norm(_filtered(path, offsets, ranges, False)[last] - path[last], axis=1).mean()
    corrected = np.linalg.norm(_filtered(path, offsets, ranges, True)[last] - path[last], axis=1).mean()
    # The offset is 0.7-1.6 m, mostly along the range on this geometry: the centre filter misses by a
    # good part of it. 600 ranges of 0.3 m noise put the corrected one within a few centimetres.
    assert plain > 0.4
    assert corrected < 0.1


def test_noise_free_antenna_ranges_give_the_centres_exactly():
    path, offsets, _ = _pair(seconds=30.0)
    ranges = np.linalg.norm(path + offsets, axis=1)
    estimator = RawRange(RelativeEstimationParams(
        estimator={"name": "raw_range", "noise_components": ((1.0, 0.0, 1e-6),), "tolerance": 1e-12},
        displacement_variance=1e-12), (0.0, 0.0), NO_PRIOR)
    estimator.mark_range_epoch()
    for k in range(1, len(path)):
        estimator.predict(path[k] - path[k - 1])
        estimator.update_between(ranges[k - 1], ranges[k], tuple(offsets[k - 1]), tuple(offsets[k]))
    assert estimator.fixed
    assert np.linalg.norm(estimator.position - path[-1]) < 1e-4


def test_zero_offsets_are_the_centre_model_bit_for_bit():
    path, _, ranges = _pair(seconds=40.0)
    zeros = np.zeros((len(path), 2))
    assert np.array_equal(_filtered(path, zeros, ranges, True), _filtered(path, zeros, ranges, False))


def test_a_non_finite_offset_is_refused_and_leaves_the_state():
    estimator = RawRange(_relative(), (10.0, 0.0), np.eye(2))
    estimator.mark_range_epoch()
    before = estimator.moments()
    outcome = estimator.update_between(10.0, 10.1, (0.0, 0.0), (math.nan, 0.0))
    assert not outcome.accepted and estimator.moments() == before and estimator.diagnostics.rejected == 1


@pytest.mark.parametrize("name", ["mckf", "kf"])
def test_the_papers_filters_ignore_the_offsets(name):
    relative = RelativeEstimationParams(estimator=name)
    a = make_relative_estimator(relative, (10.0, 1.0), np.eye(2))
    b = make_relative_estimator(relative, (10.0, 1.0), np.eye(2))
    for e in (a, b):
        e.mark_range_epoch()
        e.predict((0.1, 0.2))
    a.update(10.0, 10.3)
    b.update_between(10.0, 10.3, (0.5, 0.5), (0.4, -0.2))
    assert a.moments() == b.moments()


# ----- the share's field -----

BASE = dict(stamp_ns=1, seq=0, sender="2", position=(0.0, 0.0), heading=0.0, velocity=(0.0, 0.0), phase=0.0)


@pytest.mark.parametrize("bad", [[math.nan, 0.0], [0.0, math.inf], [25.0, 0.0], [1.0], [1.0, 2.0, 3.0],
                                 "aft"])
def test_a_share_with_a_bad_antenna_is_refused(bad):
    assert ShareMessage.model_validate({**BASE, "antenna": [-0.3, 0.0]}).antenna == (-0.3, 0.0)
    with pytest.raises(ValidationError):
        ShareMessage.model_validate({**BASE, "antenna": bad})


def test_an_absent_antenna_is_none_and_is_not_written():
    message = ShareMessage.model_validate(BASE)
    assert message.antenna is None and b"antenna" not in encode(message)
    # What a receiver that predates the field decodes: the same bytes as before it existed.
    assert ReceivedShare.model_validate_json(encode(message)).antenna is None
    given = ShareMessage.model_validate({**BASE, "antenna": [-0.3, 0.1]})
    assert ReceivedShare.model_validate_json(encode(given)).antenna == (-0.3, 0.1)


def _share(antenna=None, heading=0.5, stamp=0.0, position=(0.0, 0.0)) -> Share:
    return Share(sender="2", odometry=OdometryReading(stamp, np.array(position), heading),
                 velocity=np.zeros(2), phase=0.0, antenna=antenna)


def test_the_share_record_round_trips_with_and_without_an_antenna():
    for antenna in (None, (-0.3, 0.0)):
        share = _share(antenna)
        assert share_from_json(share_to_json(share)).antenna == antenna
        assert share_from_message(message_from_share(share, 0)).antenna == antenna
    assert "antenna" not in share_to_json(_share())


@pytest.mark.parametrize("antenna,heading", [((math.nan, 0.0), 0.5), ((30.0, 0.0), 0.5), ((0.1,), 0.5),
                                             ((-0.3, 0.0), math.nan)])
def test_the_core_refuses_a_share_with_a_bad_antenna_and_counts_it(antenna, heading):
    from agent.core.build import initial_state
    from agent.core.membership import receive_shares
    assert checked_share(_share(antenna, heading), "1") is None
    assert checked_share(_share((-0.3, 0.0), heading=0.5), "1") is not None
    params = AgentParams()
    state = initial_state("1", params, __import__("agent.core.build", fromlist=["x"]).InitialEstimates())
    receive_shares(params, state, {"2": _share(antenna, heading)}, 0.0)
    assert state.health.bad_shares == 1 and not state.tracks


def test_the_agents_own_antenna_is_checked_and_defaults_to_the_centre():
    assert RelativeEstimationParams().antenna == (0.0, 0.0)
    for bad in ((math.nan, 0.0), (21.0, 0.0)):
        with pytest.raises(ValidationError):
            RelativeEstimationParams(antenna=bad)


# ----- the pair track -----

def _track_run(share_antenna, own_antenna, seed=0, seconds=60.0):
    """A NeighbourTrack fed i's odometry (and antenna arm vectors if `own_antenna`), j's shares (with
    `share_antenna`) and the antenna ranges of `_pair`; returns the mean |p^_ij - p_ij| over the last 20 s."""
    arm = (1.0, 0.5)
    path, _, ranges = _pair(seconds=seconds, seed=seed, arm=arm)
    t = np.arange(len(path)) * DT
    psi_i, psi_j = 0.02 * t, np.full_like(t, math.pi / 2)
    relative = _relative()
    track = NeighbourTrack("2", relative, DT, 50, PairTiming.of(FleetParams()))
    own, own_arms = History(50), History(50)
    errors = []
    for k in range(len(path)):
        key = stamp_key(t[k])
        own.put(t[k], (float(path[k, 0]), float(path[k, 1])))     # j stays at its origin: p_ij = p_i
        if own_antenna:
            own_arms.put(t[k], arm_vector(psi_i[k], arm))
        share = _share(arm if share_antenna else None, float(psi_j[k]), float(t[k]))
        track.receive(share, t[k], checked_share(share, "1"))
        track.ranges.put_key(key, float(ranges[k]))
        if k == 0:
            assert track.start(NeighbourPrior(np.zeros(2), NO_PRIOR, 0.0), own, own_arms) == "started"
        track.advance(own, key, __import__("collections").Counter(), own_arms)
        if t[k] >= seconds - 20.0:
            errors.append(np.linalg.norm(track.estimate_at(own, key) - path[k]))
    return float(np.mean(errors))


def test_the_track_corrects_with_both_arms_from_the_histories_and_the_share():
    corrected = _track_run(share_antenna=True, own_antenna=True)
    assert corrected < 0.1
    # Without the neighbour's antenna in its share (an older sender: zero) or the own, the arms bias it.
    assert _track_run(share_antenna=False, own_antenna=True) > 0.3
    assert _track_run(share_antenna=True, own_antenna=False) > 0.3
    assert _track_run(share_antenna=False, own_antenna=False) > 0.3


# ----- the whole tick -----

def test_with_antennas_a_saved_and_restored_fleet_runs_on_bit_for_bit(monkeypatch):
    """Table II's fleet with its UWB antennas off the centres, in the world and in the agents' parameters: a
    JSON round trip of every vessel's state mid-run (the arm histories and the last offset with it) changes
    nothing, and the shares carry the arms."""
    from pathlib import Path

    import orjson

    from agent.config import updated
    from agent.core.snapshot import state_from_json, state_to_json
    from agent.core.step import step
    from lab.harness import runner
    from sim_bridge.scenario import select_scenario
    from sim_bridge.sensors import SensorsConfig, Uwb

    scenarios = Path(__file__).resolve().parents[1] / "configs" / "scenarios"
    _, scenario = select_scenario(scenarios / "table2_estimators.yaml", "raw_range")
    agent = updated(scenario.agent, relative=updated(scenario.agent.relative, antenna=(-0.3, 0.2)))
    world = updated(scenario.world, sensors=SensorsConfig(uwb=Uwb(antenna=(-0.3, 0.2, 0.0))))
    scenario = scenario.model_copy(update={"duration": 8.0, "agent": agent, "world": world})
    original = runner.run(scenario, 5)
    saved, arms = [], []

    def step_with_a_round_trip(params, state, inputs):
        if abs(inputs.time - 3.0) < 1e-9:
            saved.append(state.vessel)
            arms.append(len(state.own_arms.keys()) + sum(len(t.arms.keys()) for t in state.tracks.values()))
            state = state_from_json(orjson.loads(orjson.dumps(state_to_json(state),
                                                              option=orjson.OPT_SERIALIZE_NUMPY)), params)
        state, output = step(params, state, inputs)
        assert output.share is None or output.share.antenna == (-0.3, 0.2)
        return state, output

    monkeypatch.setattr(runner, "step", step_with_a_round_trip)
    again = runner.run(scenario, 5)
    for name in ("commands", "estimates", "relative", "positions"):
        np.testing.assert_array_equal(getattr(again, name), getattr(original, name), err_msg=name)
    assert sorted(saved) == ["1", "2", "3", "4"] and min(arms) > 0
