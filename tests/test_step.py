"""The tick as a step function: a state saved after any tick and read back continues exactly as the original."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import orjson
import pytest

import lab.harness.runner as runner
from agent.config import updated
from agent.core.build import InitialEstimates, initial_state
from agent.core.params import AgentParams
from agent.core.records import OdometryReading, Share, TickInputs
from agent.core.snapshot import state_from_json, state_to_json
from agent.core.step import step
from sim_bridge.scenario import select_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "configs" / "scenarios"


def _through_json(state, params):
    return state_from_json(orjson.loads(orjson.dumps(state_to_json(state), option=orjson.OPT_SERIALIZE_NUMPY)),
                           params)


def _assert_same_run(again, original):
    for name in ("commands", "estimates", "relative", "positions"):
        np.testing.assert_array_equal(getattr(again, name), getattr(original, name), err_msg=name)


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["mckf", "kf", "akf", "rls", "huber_rls"])
def test_a_fleet_whose_states_are_saved_and_read_back_mid_run_runs_on_bit_for_bit(monkeypatch, variant):
    _, scenario = select_scenario(SCENARIOS / "table2_estimators.yaml", variant)
    scenario = scenario.model_copy(update={"duration": 12.0})
    original = runner.run(scenario, 5)
    round_trips = []

    def step_with_a_round_trip(params, state, inputs):
        if abs(inputs.time - 6.0) < 1e-9:     # every vessel's state goes through JSON after 60 ticks
            round_trips.append(state.vessel)
            state = _through_json(state, params)
        return step(params, state, inputs)

    monkeypatch.setattr(runner, "step", step_with_a_round_trip)
    again = runner.run(scenario, 5)
    _assert_same_run(again, original)
    assert sorted(round_trips) == ["1", "2", "3", "4"]


@pytest.mark.slow
def test_a_joining_fleet_round_trips_with_priors_pending_and_tracks_starting(monkeypatch):
    """The join scenario: at the save, the joiner's pair filters have not all started (priors pending)."""
    _, scenario = select_scenario(SCENARIOS / "dropout_join.yaml")
    scenario = scenario.model_copy(update={"duration": 50.0})
    original = runner.run(scenario, 2)
    saved = []

    def step_with_round_trips(params, state, inputs):
        if round(inputs.time * 10) % 37 == 0:       # every 3.7 s, in the middle of joins and leaves
            saved.append(len(state.tracks))
            state = _through_json(state, params)
        return step(params, state, inputs)

    monkeypatch.setattr(runner, "step", step_with_round_trips)
    again = runner.run(scenario, 2)
    _assert_same_run(again, original)
    assert len(saved) > 20


def test_the_snapshot_is_a_fixed_point_of_writing_and_reading():
    params = AgentParams()
    state = initial_state("1", params, InitialEstimates(target=(5.0, 0.0, 0.1, 0.0), neighbours={"2": (3.0, 1.0)}))
    for k in range(5):
        t = 0.1 * k
        state, _ = step(params, state, TickInputs(time=t, odometry=OdometryReading(t, np.array([0.1 * k, 0.0]), 0.0),
                                                  bearing=np.array([1.0, 0.0])))
    data = orjson.loads(orjson.dumps(state_to_json(state), option=orjson.OPT_SERIALIZE_NUMPY))
    again = orjson.loads(orjson.dumps(state_to_json(state_from_json(data, params)),
                                      option=orjson.OPT_SERIALIZE_NUMPY))
    assert again == data
    assert data["priors"]["2"]["position"] == [3.0, 1.0]       # not started: j has not shared yet
    assert data["tracker"]["predictions"] == 4


def test_a_snapshot_of_another_version_is_refused():
    params = AgentParams()
    data = state_to_json(initial_state("1", params, InitialEstimates()))
    data["version"] = 99
    with pytest.raises(ValueError, match="version 99"):
        state_from_json(data, params)


def test_read_back_with_another_estimator_the_pair_keeps_its_estimate():
    """Replay with `--set relative.estimator=...` from a snapshot: the new filter starts where the old was."""
    _, scenario = select_scenario(SCENARIOS / "table2_estimators.yaml", "akf")
    params = scenario.agent_params()
    states = {}

    def keep(p, state, inputs):
        states[state.vessel] = state
        return step(p, state, inputs)

    runner_step = runner.step
    try:
        runner.step = keep
        runner.run(scenario.model_copy(update={"duration": 3.0}), 1)
    finally:
        runner.step = runner_step
    saved = state_to_json(states["1"])
    as_kf = state_from_json(saved, updated(params, relative=updated(params.relative, estimator="kf")))
    for j, track in as_kf.tracks.items():
        before = states["1"].tracks[j].estimator
        assert track.estimator.name == "kf" and before.name == "akf"
        np.testing.assert_array_equal(track.estimator.position, before.position)
        np.testing.assert_array_equal(track.estimator.covariance, before.covariance)


@pytest.mark.parametrize("measured, localised", [(5.0, True), (5.0 + 1.9, True), (5.0 + 2.1, False), (1.0, False)])
def test_a_sure_pair_estimate_that_the_ranges_contradict_steers_nothing(measured, localised):
    """Regression (a restart test, MCKF): both vessels of a pair sure of 5.3 m while they were 0.2-1.6 m
    apart crept together. A neighbour is localised only if |p^_ij| is within 2 m of the median of its last
    five ranges; otherwise it is judged by its ranges (and steers nothing)."""
    params = AgentParams(relative={"estimator": "mckf"})   # the MCKF keeps its prior: |p^_ij| stays 5 m
    state = initial_state("1", params, InitialEstimates(target=(5.0, 0.0, 0.0, 0.0), neighbours={"2": (5.0, 0.0)},
                                                        neighbour_variance=0.04))
    out = None
    for k in range(8):
        t = 0.1 * k
        share = Share("2", OdometryReading(t - 0.1, np.zeros(2), 0.0), np.zeros(2), 0.0)
        state, out = step(params, state, TickInputs(time=t, odometry=OdometryReading(t, np.zeros(2), 0.0),
                                                    ranges={"2": measured}, shares={"2": share} if k else {},
                                                    bearing=np.array([1.0, 0.0])))
    record = out.record.neighbours["2"]
    assert abs(np.hypot(*record.position) - 5.0) < 0.05 and np.trace(record.covariance) < 0.1
    assert record.localised is localised
