"""The shells in process (lab/benchmarks/shell.py): the sim bridge and agent nodes are the processes' own, handing
each other the bytes a lockstep fleet sends, so what they command must be what the cores command in the
in-process runner."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lab.benchmarks.shell import AGENT_SECTIONS, run_shells
from lab.harness.runner import run
from sim_bridge.scenario import select_scenario, with_duration

SCENARIOS = Path(__file__).resolve().parents[1] / "configs" / "scenarios"


@pytest.mark.slow
def test_the_shells_command_what_the_cores_command_and_every_section_is_timed(tmp_path):
    _, scenario = select_scenario(with_duration(SCENARIOS / "table2_estimators.yaml", tmp_path, 5.0), "mckf")
    shell = run_shells(scenario, tmp_path / "logs")
    core = run(scenario)
    assert shell.commands.shape == core.commands.shape == (51, 4, 2)
    np.testing.assert_allclose(shell.commands, core.commands, rtol=0, atol=1e-9)
    assert all(shell.per_tick_ms(section) > 0 for section in (*AGENT_SECTIONS, "bridge"))
    assert sorted(p.name for p in (tmp_path / "logs").glob("*.mcap")) == [*(f"agent-{v}.mcap" for v in "1234"), "sim.mcap"]
