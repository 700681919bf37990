"""`usv-lab scenario` and `usv-lab fleet-bench` end to end on a tiny scenario (a few seconds in all).

No timing is asserted: tick times are reported, never checked.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from lab import scenario_cmd
from lab.cli import main

SCENARIOS_DIR = Path(__file__).resolve().parents[1] / "configs" / "scenarios"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

# Two vessels, one island between vessel 1 and the target (so some sight lines are blocked), two variants.
TINY = """\
name: tiny
description: Two vessels around a slow target, one island.
base:
  duration: 3.0
  runs: 2
  seed: 11
  world:
    vessels:
      - {id: "1", position: [-6.0, 0.0]}
      - {id: "2", position: [6.0, 0.5]}
    target: {kind: constant_velocity, position: [0.0, 0.0], velocity: [0.5, 0.0]}
    islands:
      - [[-4.0, -1.0], [-3.0, -1.0], [-3.0, 1.0], [-4.0, 1.0]]
  agent: {control: {radius: 5.0}}
variants:
  mckf:
    agent: {relative: {estimator: mckf}}
    paper: {table: II, mean_e_ij: 0.449, mean_e_io: 0.476, mean_e_c: 0.196, settling_time: 12.3,
            run_time_ms: 1.5}
  kf:
    agent: {relative: {estimator: kf}}
"""


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY, encoding="utf-8")
    return path


def test_scenario_writes_the_page_and_both_figures(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["scenario", str(tiny), "--out", str(out), "--workers", "1"]
    assert main(argv) == 0
    page = (out / "tiny.md").read_text(encoding="utf-8")
    for figure in ("tiny_trajectories.png", "tiny_errors.png"):
        assert (out / figure).read_bytes()[:8] == PNG_MAGIC
        assert f"]({figure})" in page
    assert "usv-lab " + " ".join(argv) in page
    assert "e_ij paper" in page and "run time paper (ms)" in page
    rows = {line.split("|")[1].strip(): line for line in page.splitlines() if line.startswith("| ")}
    assert "| 0.449 |" in rows["mckf"] and "| 12.30 |" in rows["mckf"]
    assert rows["kf"].count("| - |") == 5           # the paper gives nothing for this variant
    assert rows["mckf"].rstrip().endswith("/2 |")    # settled runs out of 2
    assert not (out / "README.md").exists()         # the index is written for 'all' only
    assert "mckf" in capsys.readouterr().out


def test_an_unknown_name_is_refused_with_the_known_ones(tmp_path, capsys):
    code = main(["scenario", "no_such_scenario", "--scenarios-dir", str(SCENARIOS_DIR),
                 "--out", str(tmp_path)])
    assert code == 2
    error = capsys.readouterr().err
    assert "no_such_scenario" in error and "table2_estimators" in error and "islands" in error
    assert not any(tmp_path.iterdir())


def test_results_do_not_depend_on_the_number_of_workers(tiny):
    _, scenarios = scenario_cmd.load(tiny)
    summaries = []
    for workers in (1, 2):
        results = scenario_cmd.run_monte_carlo({"tiny": scenarios}, workers)["tiny"]
        timing = scenario_cmd.TIMING_KEYS
        summaries.append({name: {k: v for k, v in result.summary().items() if k not in timing}
                          for name, result in results.items()})
    assert summaries[0] == summaries[1]
    assert all(math.isfinite(s["e_io"]) and s["runs"] == 2 for s in summaries[0].values())


def test_overrides_reach_every_variant(tiny):
    _, scenarios = scenario_cmd.load(tiny, runs=3, seed=5)
    assert {(s.runs, s.seed) for s in scenarios.values()} == {(3, 5)}


def test_fleet_bench_smoke(tiny, tmp_path):
    out = tmp_path / "bench"
    argv = ["fleet-bench", "--monte-carlo", str(tiny), "--runs", "1", "--workers", "1", "--sizes", "3",
            "--duration", "1", "--scenarios-dir", str(SCENARIOS_DIR), "--out", str(out)]
    assert main(argv) == 0
    document = (out / "fleet_benchmark.md").read_text(encoding="utf-8")
    assert "usv-lab " + " ".join(argv) in document
    assert "os.cpu_count()" in document and "numpy" in document
    assert "| 3 | 20 | drawn (seed 50) |" in document
