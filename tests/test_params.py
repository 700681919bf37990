"""Configuration: Table I defaults, YAML loading, and one clear message for a bad file."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from agent.config import ConfigError, load_yaml
from agent.core.params import AgentParams

REPO = Path(__file__).resolve().parents[1]


def test_defaults_are_table_one():
    p = AgentParams()
    assert p.dt == 0.1
    c = p.control
    assert c.yaw_rate == pytest.approx(math.pi / 30) and c.safety_distance == 3.0
    assert (c.max_correction_yaw_rate, c.max_speed, c.max_target_speed) == (pytest.approx(math.pi / 3), 5, 0.5)
    assert (c.max_formation_speed, c.max_avoidance_speed) == (1.5, 0.7)
    assert (c.gain_neighbour, c.gain_target, c.avoidance_gain, c.avoidance_spread) == (1.5, 0.9, 1.7, 0.5)
    t = p.target
    assert (t.bearing_variance, t.initial_covariance) == (1e-4, 1.0)
    # The one deliberate departure from Table I (0.01): see docs/estimation.md, "the target tracker".
    assert t.process_noise == 1e-5 and t.gain_bearing == "predicted"
    r = p.relative
    assert (r.displacement_variance, r.initial_covariance) == (1e-6, 25.0)
    mckf = r.params_of("mckf")
    assert mckf.bandwidths == (9999, 9999, 0.8)
    assert (mckf.tolerance, mckf.max_iterations) == (1e-6, 10)


def test_shipped_agent_config_is_table_one():
    assert load_yaml(AgentParams, REPO / "configs" / "agent.yaml") == AgentParams()


def test_partial_yaml_overrides_only_what_it_names(tmp_path):
    path = tmp_path / "a.yaml"
    path.write_text("relative:\n  estimator: {name: mckf, max_iterations: 4}\n")
    p = load_yaml(AgentParams, path)
    assert p.relative.estimator.name == "mckf" and p.relative.estimator.max_iterations == 4
    assert p.relative.estimator.tolerance == 1e-6 and p.control == AgentParams().control


@pytest.mark.parametrize("text, field, words", [
    ("relative:\n  estimator: {name: mckf, max_iteration: 4}\n", "relative.estimator",
     "'max_iteration' is not a parameter of mckf; mckf's parameters: bandwidths, tolerance, max_iterations"),
    ("control:\n  radius: -5\n", "control.radius", "greater than 0"),
    ("relative:\n  estimator: ukf\n", "relative.estimator",
     "unknown estimator 'ukf'; the estimators are rls, huber_rls, kf, akf, mckf, raw_range"),
    ("target:\n  process_noise: .nan\n", "target.process_noise", "finite"),
    ("relative:\n  estimator: {name: mckf, bandwidths: [1, 2]}\n", "relative.estimator",
     "mckf parameter 'bandwidths.2': Field required"),
])
def test_bad_values_name_the_field_and_the_file(tmp_path, text, field, words):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        load_yaml(AgentParams, path)
    message = str(caught.value)
    assert str(path) in message and f"'{field}" in message and words in message
    assert "\n" not in message


def test_broken_yaml_names_the_line(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("relative:\n  estimator: [kf\n")
    with pytest.raises(ConfigError, match=r"broken.yaml: line \d+, column \d+"):
        load_yaml(AgentParams, path)


def test_missing_file_and_non_mapping(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_yaml(AgentParams, tmp_path / "nope.yaml")
    path = tmp_path / "list.yaml"
    path.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_yaml(AgentParams, path)


def test_empty_file_gives_defaults(tmp_path):
    path = tmp_path / "empty.yaml"
    path.write_text("")
    assert load_yaml(AgentParams, path) == AgentParams()
