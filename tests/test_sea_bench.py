"""The sea mode against the ideal simulation over real processes (`usv-lab sea-bench`), one seed.

The benchmark's page (docs/results/sea_mode.md) carries the issue's figure: the mean e_ij over several seeds
within 10 % of the ideal mode's. One run's ratio varies with the seed and with the run (wall-clock timing):
0.94 to 1.21 over seeds 2-6. So this test, which runs one seed, holds a single run to 1.35: what it catches
is the sea mode's failures this product had, e_ij 1.5 to 2.2 times the ideal's (shared pair estimates carried
with a commanded velocity and fed back into the filters; one range set kept per tick).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from lab.cli import main as lab_main

SEA_TRIAL = Path(__file__).resolve().parents[1] / "configs" / "scenarios" / "sea_trial.yaml"
SINGLE_RUN_BOUND = 1.35


@pytest.mark.slow
def test_a_sea_mode_fleet_settles_with_e_ij_close_to_the_ideal_simulations(tmp_path, capsys):
    spec = yaml.safe_load(SEA_TRIAL.read_text())
    spec["base"]["duration"] = 30.0
    scenario = tmp_path / "sea_trial.yaml"
    scenario.write_text(yaml.safe_dump(spec))
    page = tmp_path / "sea_mode.md"
    assert lab_main(["sea-bench", "--scenario", str(scenario), "--seeds", "2", "--out", str(page),
                     "--runs", str(tmp_path / "runs")]) == 0
    text = page.read_text()
    row = re.search(r"^\| sea \| ([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \| (yes|no) \| (\d)/1 \|$", text, re.M)
    assert row, text
    ideal, sea, ratio, _, settled = row.groups()
    print(f"seed 2, 30 s: ideal e_ij {ideal} m, sea {sea} m, ratio {ratio}")
    assert settled == "1", text
    assert 0.0 < float(ratio) <= SINGLE_RUN_BOUND, text
    assert "usv-lab sea-bench --scenario" in text          # the page says how it was made
    assert len(list((tmp_path / "runs").iterdir())) == 2   # one ideal run and one sea run, over real processes
