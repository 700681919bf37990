"""Estimators as components: the registry derived from the classes, the tagged union `relative.estimator`
read by the real config loader, and a new estimator added the documented way (docs/architecture.md §5)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
from pydantic import Field

from agent.config import ConfigError, PositiveFloat, deep_merge, load_yaml
from agent.core.estimators import (
    KF,
    EstimatorParams,
    RawRange,
    RelativePositionEstimator,
    UpdateOutcome,
    estimator_class,
    estimator_names,
    make_relative_estimator,
    register,
    registry,
)
from agent.core.estimators.pseudolinear_estimator import PseudoLinearEstimator
from agent.core.params import AgentParams
from lab.harness import runner
from mission_log.replay import parse_assignments, recorded_agent
from sim_bridge.scenario import load_scenarios

REPO = Path(__file__).resolve().parents[1]
TABLE_II_ORDER = ("rls", "huber_rls", "kf", "akf", "mckf", "raw_range")


def load(tmp_path: Path, text: str) -> AgentParams:
    path = tmp_path / "agent.yaml"
    path.write_text(text)
    return load_yaml(AgentParams, path)


# ----- the registry -----
def test_the_names_come_from_the_classes_in_table_order():
    assert estimator_names() == TABLE_II_ORDER
    for name in TABLE_II_ORDER:
        cls = estimator_class(name)
        assert cls.name == name and cls.Params().name == name


def test_the_five_pseudo_linear_estimators_share_the_update_and_raw_range_does_not():
    pseudo = [name for name in estimator_names() if issubclass(estimator_class(name), PseudoLinearEstimator)]
    assert pseudo == ["rls", "huber_rls", "kf", "akf", "mckf"]
    assert not issubclass(RawRange, PseudoLinearEstimator) and not hasattr(RawRange, "_correct")


def test_a_class_without_its_own_parameters_is_refused():
    with pytest.raises(TypeError, match="declares its own `name` and `Params`"):
        register(type("Nameless", (KF,), {}))


# ----- the tagged union through the config loader -----
def test_a_name_alone_selects_the_estimator_with_its_defaults(tmp_path):
    params = load(tmp_path, "relative:\n  estimator: mckf\n")
    assert params.relative.estimator == estimator_class("mckf").Params()
    assert load(tmp_path, "relative:\n  estimator: {name: mckf}\n") == params


def test_an_estimators_own_fields_go_with_its_name(tmp_path):
    params = load(tmp_path, "relative:\n  estimator:\n    name: raw_range\n    window: 100\n"
                            "    bias_variance: 0.01\n")
    own = params.relative.estimator
    assert (own.name, own.window, own.bias_variance, own.min_ranges) == ("raw_range", 100, 0.01, 20)
    estimator = make_relative_estimator(params.relative, (3.0, 4.0))
    assert isinstance(estimator, RawRange) and estimator.params is own


@pytest.mark.parametrize("text, message", [
    ("relative:\n  estimator: ukf\n",
     "field 'relative.estimator': unknown estimator 'ukf'; the estimators are rls, huber_rls, kf, akf, mckf, "
     "raw_range (got 'ukf')"),
    ("relative:\n  estimator: {name: mckf, window: 100}\n",
     "field 'relative.estimator': 'window' is not a parameter of mckf (it is raw_range's); mckf's "
     "parameters: bandwidths, tolerance, max_iterations"),
    ("relative:\n  estimator: {name: kf, forgetting_factor: 0.9}\n",
     "field 'relative.estimator': 'forgetting_factor' is not a parameter of kf (it is rls and huber_rls's); "
     "kf's parameters: none"),
    ("relative:\n  estimator: {window: 100}\n",
     "field 'relative.estimator': expected an estimator's name or {name: ..., its parameters}; the "
     "estimators are rls, huber_rls, kf, akf, mckf, raw_range"),
    ("relative:\n  estimator: {name: akf, min_scale: 2.0, max_scale: 1.0}\n",
     "field 'relative.estimator': akf's parameters: min_scale must be below max_scale"),
    ("relative:\n  estimator: raw_range\n  raw_range: {window: 100}\n",
     "field 'relative': 'raw_range' is an estimator: its parameters go under estimator, as estimator: "
     "{name: raw_range, ...}"),
])
def test_a_wrong_estimator_or_field_is_one_line_listing_the_valid_ones(tmp_path, text, message):
    with pytest.raises(ConfigError) as caught:
        load(tmp_path, text)
    assert str(caught.value).startswith(f"{tmp_path / 'agent.yaml'}: {message}")
    assert "\n" not in str(caught.value)


@pytest.mark.slow
def test_usv_agent_meets_the_error_as_one_line(tmp_path):
    path = tmp_path / "node.yaml"
    path.write_text("agent:\n  relative:\n    estimator: {name: mckf, window: 100}\n")
    shown = subprocess.run(
        [sys.executable, "-m", "agent", "--vessel", "1", "--config", str(path), "--print-config"],
        capture_output=True, text=True, timeout=60, cwd=REPO)
    assert shown.returncode == 2 and shown.stdout == ""
    assert shown.stderr.splitlines() == [
        f"usv-agent: {path}: field 'agent.relative.estimator': 'window' is not a parameter of mckf (it is "
        "raw_range's); mckf's parameters: bandwidths, tolerance, max_iterations"]


def test_every_shipped_config_still_loads_with_the_estimator_it_named():
    for path in sorted((REPO / "configs" / "uwb").glob("*.yaml")):
        own = load_yaml(AgentParams, path).relative.estimator
        assert own.name == "raw_range" and own.bias_variance > 0.0
    assert load_yaml(AgentParams, REPO / "configs" / "agent.yaml") == AgentParams()
    _, variants = load_scenarios(REPO / "configs" / "scenarios" / "table2_estimators.yaml")
    assert [v.agent.relative.estimator.name for v in variants.values()][:6] == list(TABLE_II_ORDER)


def test_a_log_recorded_before_the_union_replays_with_its_estimators_block():
    old = AgentParams().model_dump()
    old["relative"] = {key: value for key, value in old["relative"].items() if key != "estimator"}
    old["relative"].update(estimator="huber_rls", mckf={"bandwidths": [1.0, 1.0, 1.0]}, akf={},
                           rls={"forgetting_factor": 0.95}, huber_rls={"threshold": 2.0, "scale_window": 20},
                           raw_range={"window": 100})
    relative = AgentParams.model_validate(recorded_agent(old)).relative
    assert relative.estimator == estimator_class("huber_rls").Params(
        threshold=2.0, scale_window=20, forgetting_factor=0.95)
    assert recorded_agent(AgentParams().model_dump()) == AgentParams().model_dump()


# ----- a new estimator, added the documented way -----
class RadialParams(EstimatorParams):
    name: Literal["radial"] = "radial"
    gain: PositiveFloat = Field(1.0, le=1.0, description="share of the range residual taken on the bearing")


class Radial(RelativePositionEstimator):
    """Moves p along its bearing by `gain` times the range residual: |p+| = |p-| + gain (r - |p-|)."""

    name = "radial"
    Params = RadialParams

    def update(self, range_prev: float, range_now: float) -> UpdateOutcome:
        if not (math.isfinite(range_now) and 0.0 <= range_now <= self.relative.max_range):
            self._diag.rejected += 1
            return self._record(UpdateOutcome(accepted=False, reason="bad range"))
        saved = (self._px, self._py, self._p11, self._p12, self._p22)
        distance = math.hypot(self._px, self._py)
        if distance > 0.0:
            scale = 1.0 + self.params.gain * (range_now / distance - 1.0)
            self._px, self._py = self._px * scale, self._py * scale
        return self._settle(saved, UpdateOutcome(accepted=True, innovation=range_now - distance))


@pytest.fixture
def radial(monkeypatch):
    """Radial registered for one test (the registry as it was afterwards)."""
    monkeypatch.setattr(registry, "_classes", dict(registry._classes))
    return register(Radial)


def test_a_new_estimator_is_listed_configured_and_ticked(tmp_path, monkeypatch, radial):
    assert estimator_names() == (*TABLE_II_ORDER, "radial")
    # A config names it (through the loader a user's `usv-agent --config` goes through) ...
    params = load(tmp_path, "relative:\n  estimator: {name: radial, gain: 1.0}\n")
    assert params.relative.estimator == RadialParams(gain=1.0)
    with pytest.raises(ConfigError, match="'bandwidths' is not a parameter of radial \\(it is mckf's\\); "
                                          "radial's parameters: gain"):
        load(tmp_path, "relative:\n  estimator: {name: radial, bandwidths: [1, 1, 1]}\n")
    # ... and the core ticks with it: a 3 s fleet run of the short scenario, every vessel on Radial.
    _, scenarios = load_scenarios(REPO / "tests" / "data" / "short_scenario.yaml")
    scenario = next(iter(scenarios.values()))
    data = scenario.model_dump()
    data["duration"], data["agent"]["relative"] = 3.0, params.relative.model_dump()
    scenario = type(scenario).model_validate(data)
    checked = []
    real_step = runner.step

    def step_and_look(agent_params, state, inputs):
        state, output = real_step(agent_params, state, inputs)
        for j, neighbour in (output.record.neighbours if output.record is not None else {}).items():
            estimator = state.tracks[j].estimator
            assert isinstance(estimator, Radial)
            accepted = [(r, outcome) for _, r, outcome in neighbour.outcomes if outcome.accepted]
            if accepted:
                # gain 1: after its last update the estimate lies on the circle of the range it used.
                assert math.hypot(*estimator.position) == pytest.approx(accepted[-1][0], rel=1e-12)
                checked.append(j)
        return state, output

    monkeypatch.setattr(runner, "step", step_and_look)
    trace = runner.run(scenario, 0)
    assert len(checked) > 50 and np.all(np.isfinite(trace.commands))


def test_a_change_naming_another_estimator_replaces_the_estimators_block():
    """`usv-log replay --set relative.estimator=...` and scenario variants merge into a recorded config: a new
    name replaces the old estimator's parameters instead of mixing them."""
    recorded = AgentParams(relative={"estimator": {"name": "raw_range", "window": 100}}).model_dump()
    for text in ("relative.estimator=mckf", "relative.estimator={name: mckf, bandwidths: [9999, 9999, 1.5]}"):
        merged = deep_merge(recorded, parse_assignments([text]))
        own = AgentParams.model_validate(merged).relative.estimator
        assert own.name == "mckf" and own.max_iterations == 10
    same = deep_merge(recorded, parse_assignments(["relative.estimator.min_ranges=30"]))
    own = AgentParams.model_validate(same).relative.estimator
    assert (own.name, own.window, own.min_ranges) == ("raw_range", 100, 30)
