"""Monte Carlo on a real local Dask cluster (lab/harness/parallel.py): the same results bit for bit as this machine's
process pool, a worker killed mid-campaign, a run that raises."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from test_range_replay import circle_scenario, write_csv
from test_scenario_cmd import TINY

from agent.core.params import AgentParams
from lab.experiments import scenarios as scenario_cmd
from lab.experiments.comparison import ComparisonConfig, run_comparison
from lab.experiments.replay import RangeLog, replay
from lab.harness.parallel import Engine

pytest.importorskip("dask.distributed")
pytestmark = pytest.mark.slow   # worker processes of a Dask cluster

CLUSTER = "local:2"


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY.replace("runs: 2", "runs: 6"))
    return path


def _arrays(results) -> dict:
    return {name: (np.stack([v.error_mean, v.error_std]), v.closest, [m.settling_time for m in v.metrics])
            for name, v in results.items()}


def test_scenario_and_compare_give_the_same_numbers_on_the_cluster_as_on_the_pool(tiny):
    _, scenarios = scenario_cmd.load(tiny)
    config = ComparisonConfig(runs=6, duration=6.0, estimators=("kf", "mckf", "raw_range"))
    log = RangeLog("walk", *circle_scenario(seed=3, range_std=0.1, duration=8.0))
    outcomes = {}
    for name, engine in (("pool", Engine(workers=2)), ("cluster", Engine(cluster=CLUSTER))):
        with engine:
            outcomes[name] = (_arrays(scenario_cmd.run_monte_carlo({"tiny": scenarios}, engine)["tiny"]),
                              run_comparison(config, "gmm", engine), engine.where(),
                              replay(log, AgentParams(), runs=5, seed=3, engine=engine))
    (pool_runs, pool_compare, pool_where, pool_replay), (runs, compare, where, replayed) = outcomes.values()
    assert pool_where == "this machine, 2 worker process(es)"
    assert where.startswith("Dask scheduler tcp://") and "2 worker(s), 2 thread(s)" in where
    assert pool_runs.keys() == runs.keys()
    for name in runs:
        np.testing.assert_array_equal(runs[name][0], pool_runs[name][0])     # bit for bit
        np.testing.assert_array_equal(runs[name][1], pool_runs[name][1])
        assert runs[name][2] == pool_runs[name][2]
    for estimator in config.estimators:
        for summary in ("rmse", "spread"):
            np.testing.assert_array_equal(getattr(compare, summary)(estimator), getattr(pool_compare, summary)(estimator))
        np.testing.assert_array_equal(compare.nees[estimator].mean, pool_compare.nees[estimator].mean)
        assert compare.worst_late == pool_compare.worst_late
    # every run of every variant is in
    assert all(len(v[1]) == 6 for v in runs.values())
    assert replayed.runs == pool_replay.runs == 5
    for estimator in replayed.moments:
        np.testing.assert_array_equal(replayed.rmse(estimator), pool_replay.rmse(estimator))
        np.testing.assert_array_equal(replayed.spread(estimator), pool_replay.spread(estimator))
    # ... and the same as one process, run after run
    alone = replay(log, AgentParams(), runs=5, seed=3)
    np.testing.assert_array_equal(alone.rmse("raw_range"), replayed.rmse("raw_range"))


def test_a_worker_killed_mid_campaign_loses_nothing(tiny):
    _, scenarios = scenario_cmd.load(tiny)
    with Engine(workers=2) as pool:
        expected = _arrays(scenario_cmd.run_monte_carlo({"tiny": scenarios}, pool)["tiny"])
    with Engine(cluster=CLUSTER) as engine:
        pids = engine._client.run(os.getpid)     # {worker address: pid}
        victim = sorted(pids.values())[0]
        done = []

        def progress(n: int) -> None:
            done.append(n)
            if len(done) == 1:          # the first run is in: the others are on the workers now
                os.kill(victim, signal.SIGKILL)

        results = _arrays(scenario_cmd.run_monte_carlo({"tiny": scenarios}, engine, progress)["tiny"])
        retried = engine.retried
    assert sum(done) == 6 * len(scenarios) and not engine.failures
    assert retried >= 1, "the killed worker's runs were not run again"
    for name in expected:
        np.testing.assert_array_equal(results[name][0], expected[name][0])


def _raise_on_three(job: int) -> int:
    if job == 3:
        raise ValueError("run three is cursed")
    return job * job


@pytest.mark.parametrize("engine", [Engine(workers=2), Engine(cluster=CLUSTER)], ids=["pool", "cluster"])
def test_a_run_that_raises_is_named_and_the_others_finish(engine):
    with engine:
        results = engine.map(_raise_on_three, list(range(6)), describe=lambda n: f"variant v run {n} (seed 7)")
    assert results == [0, 1, 4, None, 16, 25]
    (failure,) = engine.failures
    assert failure.run == "variant v run 3 (seed 7)" and failure.error.startswith("ValueError: run three is cursed")


def _tables(page: str) -> list[list[str]]:
    """The page's table rows, cell by cell, without the columns of compute times (which differ run to run)."""
    rows, timed = [], set()
    for line in page.splitlines():
        if not line.startswith("|"):
            timed = set()
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if not timed and not rows or line.startswith("| variant") or line.startswith("| estimator"):
            timed = {n for n, cell in enumerate(cells) if "tick" in cell or "run time" in cell}
        rows.append([cell for n, cell in enumerate(cells) if n not in timed])
    return rows


def test_the_commands_take_a_cluster_and_their_pages_say_where_they_ran(tiny, tmp_path):
    from lab.cli import main

    out, pool = tmp_path / "out", tmp_path / "pool"
    assert main(["scenario", str(tiny), "--out", str(out), "--cluster", CLUSTER]) == 0
    page = (out / "tiny.md").read_text(encoding="utf-8")
    assert "ran on Dask scheduler tcp://" in page and "(a local cluster the command started): 2 worker(s)" in page
    assert main(["compare", "--runs", "4", "--out", str(out), "--no-diagnosis", "--cluster", CLUSTER]) == 0
    compared = (out / "estimator_comparison.md").read_text(encoding="utf-8")
    assert "ran on Dask scheduler tcp://" in compared
    # The pool's pages have the same tables, digit for digit.
    assert main(["scenario", str(tiny), "--out", str(pool), "--workers", "2"]) == 0
    assert main(["compare", "--runs", "4", "--out", str(pool), "--no-diagnosis", "--workers", "2"]) == 0
    for name, cluster_page in (("tiny.md", page), ("estimator_comparison.md", compared)):
        pool_tables = _tables((pool / name).read_text(encoding="utf-8"))
        assert len(pool_tables) >= 6 and _tables(cluster_page) == pool_tables, name
    csv_path = write_csv(tmp_path / "walk.csv", *circle_scenario(seed=3, range_std=0.1, duration=15.0))
    assert main(["replay", str(csv_path), "--runs", "3", "--out", str(out), "--cluster", CLUSTER]) == 0
    page = (out / "replay_walk.md").read_text(encoding="utf-8")
    assert "runs: 3 of 3" in page and "ran on Dask scheduler tcp://" in page
    assert main(["scenario", str(tiny), "--out", str(out), "--cluster", "local:zero"]) == 2
