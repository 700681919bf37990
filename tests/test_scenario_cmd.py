"""`usv-lab scenario` and `usv-lab fleet-bench` end to end on a tiny scenario (a few seconds in all).

No timing is asserted: tick times are reported, never checked.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agent.config import updated
from lab.cli import main
from lab.experiments import scenarios as scenario_cmd
from lab.harness.parallel import Engine, hand_off_lines
from lab.harness.run_cost import costed_run
from lab.harness.runner import run as run_scenario
from mission_log.metrics import RunMetrics, nan_mean
from sim_bridge.scenario import Scenario, ScenarioFile

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


@pytest.mark.slow
def test_scenario_writes_the_page_and_both_figures(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["scenario", str(tiny), "--out", str(out), "--workers", "1"]
    assert main(argv) == 0
    page = (out / "tiny.md").read_text(encoding="utf-8")
    for figure in ("tiny_trajectories.png", "tiny_errors.png"):
        assert (out / figure).read_bytes()[:8] == PNG_MAGIC
        assert f"]({figure})" in page
    assert "usv-lab " + " ".join(argv) in page
    paper, settling = page.split("## Whole run and after settling")
    assert "e_ij paper" in paper and "run time paper (ms)" in paper
    rows = {line.split("|")[1].strip(): line for line in paper.splitlines() if line.startswith("| ")}
    assert "| 0.449 |" in rows["mckf"] and "| 12.30 |" in rows["mckf"]
    assert rows["kf"].count("| - |") == 5           # the paper gives nothing for this variant
    assert rows["mckf"].rstrip().endswith("/2 |")    # settled runs out of 2
    header = next(line for line in settling.splitlines() if line.startswith("| variant"))
    for column in ("e_c whole run (m)", "e_c after settling (m)", "e_ij after settling (m)",
                   "e_io after settling (m)", "closest approach (m)", "settled runs"):
        assert f"| {column} |" in header
    rows = {line.split("|")[1].strip(): line for line in settling.splitlines() if line.startswith("| ")}
    assert {"mckf", "kf"} <= set(rows)
    assert "initial estimates: drawn around the truth, P_ij,0 = 0.04 I" in page
    assert not (out / "README.md").exists()         # the index is written for 'all' only
    assert "mckf" in capsys.readouterr().out


def hand_made(scenario: Scenario, curves: list[list[float]], settling: list[float | None]
              ) -> scenario_cmd.VariantResult:
    """A variant's result from given e_c curves (one per run, 1 s apart; e_ij and e_io twice and three
    times e_c) and settling times, without running anything."""
    e_c = np.array(curves)
    errors = np.stack([2 * e_c, 3 * e_c, e_c], axis=1)             # (runs, ERRORS, K)
    metrics = [RunMetrics(nan_mean(2 * c), nan_mean(3 * c), math.nan, nan_mean(c), t, 0.5, 0.9)
               for c, t in zip(e_c, settling)]
    runs = scenario_cmd.RunsGathered(np.arange(e_c.shape[1]) * 1.0)
    for curves_of_run, m, closest in zip(errors, metrics, [4.0, 3.0, 5.0]):
        runs.add(m, curves_of_run, closest)
    return runs.result(scenario.name, scenario)


def test_runs_reduced_as_they_come_give_the_mean_and_spread_of_all_of_them():
    """The running mean and std per tick (Welford's update, NaN ticks left out) against numpy's over the
    stacked runs."""
    rng = np.random.default_rng(4)
    errors = rng.gamma(2.0, 0.5, size=(7, 3, 40))
    errors[rng.random(errors.shape) < 0.2] = np.nan
    errors[:, :, :3] = np.nan                            # ticks no run has
    runs = scenario_cmd.RunsGathered(np.arange(40) * 0.1)
    for curves in errors:
        runs.add(RunMetrics(1.0, 1.0, 1.0, 1.0, None, 0.5, 0.9), curves, 3.0)
    result = runs.result("v", None)
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning):
        expected_mean, expected_std = np.nanmean(errors, axis=0), np.nanstd(errors, axis=0)
    np.testing.assert_allclose(result.error_mean, expected_mean, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(result.error_std, expected_std, rtol=1e-10, atol=1e-14)
    assert np.all(np.isnan(result.error_mean[:, :3])) and np.all(np.isnan(result.error_std[:, :3]))


def test_the_mean_after_settling_starts_at_each_runs_own_settling_time(tiny):
    nan = math.nan
    curves = [[5, 5, 5, 5, 1, 1, 1, 1, 1, 3],           # settles at 4 s: mean after 8/6
              [4, 4, 4, 4, 4, 4, 0.5, nan, 0.5, 0.5],   # settles at 6 s: 0.5, the tick with no value left out
              [0.1] * 10]                               # never settles: no mean after settling
    result = hand_made(scenario_cmd.load(tiny)[1]["kf"], curves, [4.0, 6.0, None])
    np.testing.assert_allclose(result.after_settling("e_c"), [8 / 6, 0.5], rtol=1e-12)
    np.testing.assert_allclose(result.after_settling("e_io"), [3 * 8 / 6, 1.5], rtol=1e-12)
    summary = result.summary()
    assert summary["e_c_settled"] == pytest.approx((8 / 6 + 0.5) / 2, rel=1e-12)
    assert summary["e_c_settled_std"] == pytest.approx((8 / 6 - 0.5) / 2, rel=1e-12)
    assert summary["e_c"] == pytest.approx((2.8 + 25.5 / 9 + 0.1) / 3, rel=1e-12)   # whole run, every run
    assert (summary["closest"], summary["closest_min"], summary["settled"]) == (4.0, 3.0, 2.0)
    assert scenario_cmd.mean_after(np.arange(4.0), np.array([9.0, nan, 1.0, 2.0]), 1.0) == pytest.approx(1.5)


def test_a_cold_file_without_paper_numbers_has_no_paper_columns(tiny):
    kf = scenario_cmd.load(tiny)[1]["kf"]
    cold = updated(kf, initial=updated(kf.initial, cold="all"))
    variants = {"kf": hand_made(cold, [[1.0, 0.5, 0.5]] * 3, [1.0, 1.0, None])}
    tables = (scenario_cmd.comparison_table(variants), scenario_cmd.settling_table(variants))
    assert "paper" not in tables[0] and "| 2/3 |" in tables[0]
    assert "| 0.500 ± 0.000 |" in tables[1]            # e_c after settling
    spec = ScenarioFile(name="cold", base={})
    page = scenario_cmd.render_page(tiny, spec, variants, tables, "usv-lab scenario cold", 1.0, 1,
                                    ("t.png", "e.png"))
    assert "## Ours (the paper gives no numbers)" in page
    assert "initial estimates: none, every vessel starts cold" in page


def test_an_unknown_name_is_refused_with_the_known_ones(tmp_path, capsys):
    code = main(["scenario", "no_such_scenario", "--scenarios-dir", str(SCENARIOS_DIR),
                 "--out", str(tmp_path)])
    assert code == 2
    error = capsys.readouterr().err
    assert "no_such_scenario" in error and "table2_estimators" in error and "islands" in error
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
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
    argv = ["fleet-bench", "--monte-carlo", str(tiny), "--runs", "1", "--workers", "1", "--sizes", "3", "4",
            "--duration", "1", "--scenarios-dir", str(SCENARIOS_DIR), "--out", str(out)]
    assert main(argv) == 0
    document = (out / "fleet_benchmark.md").read_text(encoding="utf-8")
    assert "usv-lab " + " ".join(argv) in document
    assert "os.cpu_count()" in document and "numpy" in document
    # One row per pair estimator, each fleet on that estimator (the paper's and the agent's by default).
    assert "| mckf | 3 | 20 | drawn (seed 50) |" in document
    assert "| raw_range | 3 | 20 | drawn (seed 50) |" in document
    # The campaign's time beyond the runs' CPU: one worker runs them in this process, with no hand-off.
    assert "- The runs took " in document and "in this process" in document and "hand-off" not in document
    # What a neighbour adds, split into its pair filter's own work and the rest, per estimator (n = 3 to 4).
    for name in ("mckf", "raw_range"):
        assert f"- {name}: an extra neighbour adds " in document and "(n = 3 to 4), of which its pair" in document


def test_the_hand_off_is_the_workers_time_beyond_the_runs_cpu():
    # 2 workers for 10 s had 20 s; runs of 18 s of CPU leave 2 s, 500 ms for each of 4 runs.
    (line,) = hand_off_lines(Engine(workers=2), wall=10.0, cpu=18.0, runs=4)
    assert "had 20.0 s (10.0 s of wall time each)" in line and "18.0 s of CPU in them (90%)" in line
    assert "The rest, 2.0 s (500 ms a run)" in line
    # One worker runs them in this process: no hand-off, the rest is the campaign's own.
    (line,) = hand_off_lines(Engine(workers=1), wall=10.0, cpu=9.0, runs=4)
    assert "9.0 s of CPU in 10.0 s of wall time, in this process (90%); the rest, 1.0 s" in line
    assert hand_off_lines(Engine(workers=2, cluster="tcp://elsewhere:8786"), 10.0, 18.0, 4) == []


def test_a_costed_run_is_the_same_run_and_its_parts_fit_in_it(tiny):
    _, scenarios = scenario_cmd.load(tiny)
    scenario = next(iter(scenarios.values()))
    seed = np.random.SeedSequence(scenario.seed).spawn(1)[0]
    trace, cost = costed_run(scenario, seed)
    plain = run_scenario(scenario, np.random.SeedSequence(scenario.seed).spawn(1)[0])
    for name in ("positions", "estimates", "relative", "commands", "e_ij", "e_io", "e_c"):
        np.testing.assert_array_equal(getattr(trace, name), getattr(plain, name))
    assert cost.world > 0.0 and cost.agents > 0.0 and cost.rest >= 0.0
    assert cost.world + cost.agents + cost.rest == pytest.approx(cost.whole)


def test_fleet_bench_times_every_call_of_the_pair_filters_and_puts_the_factory_back():
    from agent.core import neighbours
    from lab.benchmarks.fleet import FilterClock, fleet_scenarios
    from lab.harness.runner import run

    spec, variants = scenario_cmd.load(SCENARIOS_DIR / "table4_scale.yaml")
    ((_, scenario, _, _),) = fleet_scenarios(spec.base, variants, [4], 3.0, 50, "mckf")
    original, made = neighbours.make_relative_estimator, []
    clock = FilterClock()
    clock.calibrate(calls=1000)
    with clock.timing():
        timed = neighbours.make_relative_estimator
        assert timed is not original
        neighbours.make_relative_estimator = lambda *args, **kwargs: made.append(timed(*args, **kwargs)) or made[-1]
        try:
            run(scenario)
        finally:
            neighbours.make_relative_estimator = timed
    assert neighbours.make_relative_estimator is original
    # Every predict and update counts one of these three (base.py: refused ones in `rejected`).
    diagnostics = [e.diagnostics for e in made]
    calls = sum(d.predictions + d.updates + d.rejected for d in diagnostics)
    assert len(made) == 12 and sum(d.updates for d in diagnostics) > 0
    assert clock.calls == calls
    assert 0.0 < clock.overhead and 0.0 < clock.seconds < clock.raw


def test_fleet_bench_puts_every_vessel_on_the_estimator_asked_for(tiny):
    from lab.benchmarks.fleet import fleet_scenarios

    spec, variants = scenario_cmd.load(SCENARIOS_DIR / "table4_scale.yaml")
    for name in ("kf", "raw_range"):
        built = fleet_scenarios(spec.base, variants, [4, 5], 1.0, 50, name)
        assert [n for n, *_ in built] == [4, 5]
        assert {s.agent_params().relative.estimator.name for _, s, _, _ in built} == {name}
