"""Shared fixtures: one short real fleet run (separate processes over Zenoh) for every test of its logs."""

from __future__ import annotations

from pathlib import Path

import pytest

SCENARIO = (Path(__file__).parent / "data" / "short_scenario.yaml").read_text()


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
