"""A scenario's cold start (`initial.cold`): who starts with no estimates, in the runner and the launcher,
and that the warm vessels keep the draws they get in the warm scenario."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agent.config import ConfigError, updated
from agent.core.build import InitialEstimates
from agent.core.estimators import estimator_names
from lab.harness import runner
from sim_bridge.fleet import agent_configs
from sim_bridge.scenario import Scenario, initial_estimates, load_scenarios, select_scenario
from sim_bridge.world import World, streams

SCENARIOS = Path(__file__).resolve().parents[1] / "configs" / "scenarios"
SEED = 7


def table_two(cold: str | list[str]) -> Scenario:
    """Two ticks of Table II with the MCKF, with `cold` starting cold."""
    _, scenario = select_scenario(SCENARIOS / "table2_estimators.yaml", "mckf")
    return updated(scenario, duration=0.1, initial=updated(scenario.initial, cold=cold))


def run_and_watch_starts(monkeypatch, scenario: Scenario
                         ) -> tuple[dict[str, InitialEstimates], runner.RunTrace]:
    """What each of the runner's agents was built from, and the run's trace."""
    starts: dict[str, InitialEstimates] = {}
    build = runner.initial_state

    def watched(vessel, params, initial):
        starts.setdefault(vessel, initial)
        return build(vessel, params, initial)

    monkeypatch.setattr(runner, "initial_state", watched)
    return starts, runner.run(scenario, SEED)


def test_cold_vessels_start_with_nothing_and_the_others_with_their_warm_draws(monkeypatch):
    warm, warm_trace = run_and_watch_starts(monkeypatch, table_two([]))
    cold, cold_trace = run_and_watch_starts(monkeypatch, table_two(["2", "3"]))
    assert sorted(warm) == sorted(cold) == ["1", "2", "3", "4"]
    assert cold["2"] == cold["3"] == InitialEstimates()
    assert cold["1"] == warm["1"] and cold["4"] == warm["4"]   # the cold ones' draws are made all the same
    assert warm["2"].target is not None and sorted(warm["2"].neighbours) == ["1", "3", "4"]
    # At the second tick (the first holds no pair estimates yet) a cold vessel has no estimate of any
    # neighbour; a warm one has all three.
    assert np.isnan(cold_trace.relative[1, 1]).all() and np.isnan(cold_trace.relative[1, 2]).all()
    assert np.isfinite(cold_trace.relative[1, 0, [1, 2, 3]]).all()
    assert np.isfinite(warm_trace.relative[1, 1, [0, 2, 3]]).all()


def test_a_warm_fleet_starts_from_the_scenarios_own_draws(monkeypatch):
    """The runner's agents get what `initial_estimates` draws from the seed's initial stream, as before
    cold starts existed, and the launcher gives the agent processes the same."""
    scenario = table_two([])
    random = streams(SEED)
    expected = initial_estimates(scenario, World(scenario.world, random.world).truth(), random.initial)
    starts, _ = run_and_watch_starts(monkeypatch, scenario)
    assert starts == expected
    configs = agent_configs(scenario, SEED, Path("unused"), lambda vessel: {})
    assert {v: c["initial"] for v, c in configs.items()} == {v: s.model_dump(mode="json")
                                                              for v, s in starts.items()}


def test_a_fleet_cold_all_through_has_no_initial_section_for_any_agent():
    scenario = table_two("all")
    random = streams(SEED)
    assert initial_estimates(scenario, World(scenario.world, random.world).truth(), random.initial) == {}
    configs = agent_configs(scenario, SEED, Path("unused"), lambda vessel: {})
    assert {v: c["initial"] for v, c in configs.items()} == {v: {} for v in ("1", "2", "3", "4")}
    partly = agent_configs(table_two(["4"]), SEED, Path("unused"), lambda vessel: {})
    assert partly["4"]["initial"] == {} and partly["1"]["initial"]["neighbours"]


def test_a_cold_vessel_the_world_does_not_have_is_refused(tmp_path):
    text = (SCENARIOS / "table2_estimators.yaml").read_text()
    path = tmp_path / "typo.yaml"
    path.write_text(text.replace("target_variance: 1.0}", "target_variance: 1.0, cold: ['9']}"))
    with pytest.raises(ConfigError, match="9"):
        load_scenarios(path)


def test_the_cold_start_file_is_table_two_cold_with_one_variant_per_estimator():
    _, cold = load_scenarios(SCENARIOS / "cold_start.yaml")
    _, table2 = load_scenarios(SCENARIOS / "table2_estimators.yaml")
    assert list(cold) == list(estimator_names())
    for name, scenario in cold.items():
        assert scenario.initial.cold == "all"
        assert (scenario.runs, scenario.duration, scenario.seed) == (20, 90.0, 2)
        assert scenario.world == table2[name].world
        assert scenario.agent == table2[name].agent
        assert scenario.agent.relative.estimator.name == name
        assert not scenario.paper.table


@pytest.mark.slow
def test_a_cold_fleet_whose_target_filter_was_pushed_through_a_vessel_recovers():
    # Seed 3 of the cold-start scenario: vessel 1's first bearings pushed its target estimate through the
    # vessel onto the target's point reflection, where the pseudo-linear filter stayed (e_io 18-38 m for the
    # whole run). The bearing's side now restarts the filter, and every vessel's estimate of the target
    # ends within a few centimetres.
    _, scenario = select_scenario(SCENARIOS / "cold_start.yaml", "raw_range")
    trace = runner.run(updated(scenario, duration=40.0), 3)
    late = trace.time >= 30.0
    truth = trace.positions - trace.target[:, None, :]
    e_io = np.hypot(*(trace.estimates[late, :, :2] - truth[late]).transpose(2, 0, 1))
    assert np.nanmax(e_io) < 0.3
    assert trace.metrics.settling_time is not None
