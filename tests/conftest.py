"""Shared fixtures: one short real fleet run (separate processes over Zenoh) for every test of its logs."""

from __future__ import annotations

import pytest

SCENARIO = """
name: short
base:
  duration: 12.0
  seed: 5
  world:
    vessels:
      - {id: "1", position: [-6.0, -7.0]}
      - {id: "2", position: [6.0, 6.0]}
      - {id: "3", position: [-10.0, 3.0]}
    target: {kind: constant_velocity, position: [1.0, 1.0], velocity: [0.5, 0.0]}
    islands: [[[20.0, -3.0], [24.0, -3.0], [22.0, 1.0]]]
  agent: {control: {radius: 5.0}}
"""


@pytest.fixture
def short_scenario(tmp_path):
    """A scenario file: three vessels, 12 s, an island out of the way."""
    path = tmp_path / "short.yaml"
    path.write_text(SCENARIO)
    return path


@pytest.fixture(scope="session")
def fleet_run(tmp_path_factory):
    """(run folder, scenario file) of a lockstep run of the short scenario, made once for all tests."""
    pytest.importorskip("zenoh")
    from sim_bridge.fleet import Fleet

    folder = tmp_path_factory.mktemp("fleet")
    scenario = folder / "short.yaml"
    scenario.write_text(SCENARIO)
    fleet = Fleet(scenario, None, folder / "runs")
    return fleet.run(timeout=240), scenario
