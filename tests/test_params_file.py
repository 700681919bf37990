"""One parameter-file shape: an AgentParams file (configs/agent.yaml, configs/uwb/*.yaml, what `fit-noise`
writes) is taken as it is by `usv-agent --params`, by the settings' `agent:`, by a scenario's `base.agent` and
by the inventory's `agent:`, through the command lines a user runs; a fault in it is one line naming it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from agent.config import load_yaml
from agent.core.params import AgentParams

REPO = Path(__file__).resolve().parents[1]
CALIBRATED = REPO / "configs" / "uwb" / "murp.yaml"   # a fit-noise output, as committed
AGENT = [sys.executable, "-m", "agent"]
WORLD = {"vessels": [{"id": "1", "position": [0.0, 0.0]}],
         "target": {"kind": "constant_velocity", "position": [1.0, 1.0], "velocity": [0.0, 0.0]}}


def run(command: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, cwd=cwd, timeout=120)


def printed_params(result: subprocess.CompletedProcess) -> AgentParams:
    """The `agent` section of what `--print-config` printed, as AgentParams."""
    assert result.returncode == 0, result.stderr
    return AgentParams.model_validate(yaml.safe_load(result.stdout)["agent"])


def calibrated(tmp_path: Path) -> Path:
    path = tmp_path / "calibrated" / "my_uwb.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(CALIBRATED.read_text(encoding="utf-8"), encoding="utf-8")
    return path


@pytest.mark.slow   # runs the command line in a process of its own
def test_usv_agent_takes_a_parameter_file_as_it_is(tmp_path):
    expected = load_yaml(AgentParams, CALIBRATED)
    assert expected != AgentParams()                          # the file changes something: the check can fail
    assert printed_params(run([*AGENT, "--vessel", "1", "--params", str(CALIBRATED), "--print-config"],
                              tmp_path)) == expected
    # The Table I file itself, as generated: the defaults.
    assert printed_params(run([*AGENT, "--vessel", "1", "--params", str(REPO / "configs" / "agent.yaml"),
                               "--print-config"], tmp_path)) == AgentParams()


@pytest.mark.slow   # runs the command line in a process of its own
def test_the_settings_agent_may_name_the_file_relative_to_the_settings(tmp_path):
    params = calibrated(tmp_path)
    settings = tmp_path / "calibrated" / "node.yaml"
    settings.write_text(f"clock: sim\nagent: {params.name}\n", encoding="utf-8")
    result = run([*AGENT, "--vessel", "1", "--config", str(settings), "--print-config"], tmp_path)
    assert printed_params(result) == load_yaml(AgentParams, CALIBRATED)
    assert yaml.safe_load(result.stdout)["clock"] == "sim"
    # --params takes the place of the settings' own parameters.
    settings.write_text("clock: sim\nagent: {control: {radius: 9.0}}\n", encoding="utf-8")
    result = run([*AGENT, "--vessel", "1", "--config", str(settings), "--params", str(params), "--print-config"],
                 tmp_path)
    assert printed_params(result) == load_yaml(AgentParams, CALIBRATED)


@pytest.mark.slow   # runs the command line in a process of its own
@pytest.mark.parametrize("how", ["--params", "settings"])
def test_a_fault_in_a_parameter_file_is_one_line_naming_that_file(tmp_path, how):
    bad = tmp_path / "bad.yaml"
    bad.write_text("control:\n  radiuss: 6.0\n", encoding="utf-8")
    if how == "--params":
        result = run([*AGENT, "--vessel", "1", "--params", str(bad), "--print-config"], tmp_path)
    else:
        (tmp_path / "node.yaml").write_text("agent: bad.yaml\n", encoding="utf-8")
        result = run([*AGENT, "--vessel", "1", "--config", "node.yaml", "--print-config"], tmp_path)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.strip().splitlines() == [
        f"usv-agent: {bad if how == '--params' else 'bad.yaml'}: field 'control.radiuss': "
        "unknown key"]


def test_a_scenario_base_may_name_the_file_and_its_variants_go_over_it(tmp_path):
    from sim_bridge.scenario import load_scenarios

    params = calibrated(tmp_path)
    scenario = tmp_path / "mine.yaml"
    scenario.write_text(yaml.safe_dump({
        "name": "mine", "base": {"world": WORLD, "agent": f"calibrated/{params.name}"},
        "variants": {"as_calibrated": {}, "mckf": {"agent": {"relative": {"estimator": "mckf"}}}}}))
    _, variants = load_scenarios(scenario)
    expected = load_yaml(AgentParams, CALIBRATED)
    assert variants["as_calibrated"].agent == expected
    assert variants["mckf"].agent.relative.estimator.name == "mckf"
    # The file beneath it: what the variant does not name stays the calibrated file's.
    assert variants["mckf"].agent.relative.range_variance == expected.relative.range_variance
    assert variants["mckf"].agent.model_dump(exclude={"relative"}) == expected.model_dump(exclude={"relative"})
    # The same shape inline gives the same scenario.
    inline = tmp_path / "inline.yaml"
    inline.write_text(yaml.safe_dump({"name": "inline", "base": {"world": WORLD,
                                                                 "agent": yaml.safe_load(CALIBRATED.read_text())}}))
    assert load_scenarios(inline)[1]["inline"].agent == expected


INVENTORY = """fleet: trial
vessels:
  - {id: "1", address: 10.0.0.11}
  - {id: "2", address: 10.0.0.12, agent: {control: {max_speed: 1.2}}}
agent: AGENT
"""


def render(tmp_path: Path, agent: str, vessel: str = "1") -> subprocess.CompletedProcess:
    inventory = tmp_path / "fleet.yaml"
    inventory.write_text(INVENTORY.replace("AGENT", agent), encoding="utf-8")
    return run([sys.executable, "-m", "usv_deploy", "render", str(inventory), "--vessel", vessel, "--out",
                str(tmp_path / "out")], tmp_path)


def rendered_params(tmp_path: Path) -> AgentParams:
    return AgentParams.model_validate(yaml.safe_load((tmp_path / "out" / "agent.yaml").read_text())["agent"])


@pytest.mark.slow   # runs the command line in a process of its own
def test_the_inventory_takes_the_file_as_the_fleets_parameters_under_each_vessels_own(tmp_path):
    params = calibrated(tmp_path)
    expected = load_yaml(AgentParams, CALIBRATED)
    assert render(tmp_path, f"calibrated/{params.name}", "2").returncode == 0
    rendered = rendered_params(tmp_path)
    assert rendered.relative == expected.relative and rendered.control.max_speed == 1.2
    assert render(tmp_path, f"calibrated/{params.name}", "1").returncode == 0
    assert rendered_params(tmp_path) == expected


@pytest.mark.slow   # runs the command line in a process of its own
def test_a_typo_in_any_vessels_parameters_refuses_the_inventory_in_one_line(tmp_path):
    """Before: rendering vessel 1 went through with a typo in vessel 2's parameters (an untyped dict)."""
    inventory = INVENTORY.replace("max_speed", "max_sped")
    (tmp_path / "fleet.yaml").write_text(inventory.replace("AGENT", "{control: {radius: 20.0}}"), encoding="utf-8")
    result = run([sys.executable, "-m", "usv_deploy", "render", "fleet.yaml", "--vessel", "1", "--out", "out"],
                 tmp_path)
    assert result.returncode == 2 and not (tmp_path / "out").exists()
    assert result.stderr.strip().splitlines() == [
        "usv-deploy: fleet.yaml: field 'vessels.1.agent.control.max_sped': unknown key"]
