"""`usv-lab cluster-bench`: the same Monte Carlo campaign on this machine's process pool and on a local Dask
cluster with as many worker processes, in one run; what the scheduler costs per run. A benchmark, not a test.

The campaign is a scenario file's variants (Table II by default) with `--runs` runs each. Both engines get
the same job list and seeds (lab/experiments/scenarios.py `run_monte_carlo`), and the command checks that their
errors agree bit for bit before it writes anything. The cluster's start (its worker processes importing
the lab) is timed apart from the campaign; the overhead per run is the difference of the two campaigns'
wall times over the runs.

Then the client's memory: Experiment 1 (`usv-lab compare`, short runs) with N and 8N runs on a cluster started
as docs/lab.md starts one (`dask scheduler` and `dask worker` processes), the client's peak of traced Python
allocations (tracemalloc; the scheduler and the workers are other processes, as on real machines). Each run is
folded into running sums as it arrives and at most a window of runs is out at once, so the peak should not
grow with N.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from lab import arguments
from lab.experiments.comparison import ComparisonConfig, run_comparison
from lab.experiments.scenarios import DEFAULT_DIR, load, resolve, run_monte_carlo
from lab.harness.parallel import Engine, connect_client
from lab.report.markdown import invocation, machine, markdown_table
from sim_bridge.fleet import free_port

MEMORY_DURATION = 10.0   # simulated seconds of each run of the client-memory part


def _curve_bytes() -> int:
    """What one run's curves would take if held: error and NEES per estimator per epoch, float64."""
    config = ComparisonConfig(duration=MEMORY_DURATION)
    return 2 * len(config.estimators) * (round(MEMORY_DURATION / config.agent.dt) + 1) * 8


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="table2_estimators", help="scenario file stem (configs/scenarios)")
    parser.add_argument("--runs", type=arguments.positive_int, default=4, help="Monte Carlo runs of every variant")
    parser.add_argument("--workers", type=arguments.positive_int, default=os.cpu_count() or 1,
                        help="worker processes of the pool, and of the local Dask cluster")
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results"), help="where cluster_benchmark.md goes")
    parser.add_argument("--scenarios-dir", type=Path, default=DEFAULT_DIR, help="where the scenario files are")
    parser.add_argument("--memory-runs", type=arguments.positive_int, default=100,
                        help="N of the client-memory part: Experiment 1 with N and 8N runs")


def _campaign(files, engine: Engine) -> tuple[float, dict]:
    started = time.perf_counter()
    results = run_monte_carlo(files, engine)
    return time.perf_counter() - started, results


def _client_peak(engine: Engine, runs: int) -> tuple[float, float]:
    """Experiment 1 (one noise model, 10 s runs) on `engine`: the client's peak traced allocations (MB) and
    the wall time (s)."""
    config = ComparisonConfig(runs=runs, duration=MEMORY_DURATION)
    tracemalloc.start()
    started = time.perf_counter()
    try:
        run_comparison(config, "gmm", engine)
        return tracemalloc.get_traced_memory()[1] / 1e6, time.perf_counter() - started
    finally:
        tracemalloc.stop()


@contextlib.contextmanager
def _scheduler_and_workers(workers: int):
    """A Dask scheduler and `workers` worker processes (one thread each) on loopback, as `dask scheduler` and
    `dask worker` start them on lab machines; yields the scheduler's address."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    environment = dict(os.environ, DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED="False")
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "env": environment}
    processes = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                   "--port", str(port), "--dashboard-address", ":0"], **quiet)]
    try:
        processes.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address,
                                           "--nworkers", str(workers), "--nthreads", "1", "--no-dashboard"], **quiet))
        with connect_client(address, 60.0) as client:
            client.wait_for_workers(workers, timeout=120)
        yield address
    finally:
        for process in reversed(processes):
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def run(args: argparse.Namespace) -> int:
    (path,) = resolve([args.scenario], args.scenarios_dir)
    _, scenarios = load(path, args.runs)
    files = {path.stem: scenarios}
    runs = sum(s.runs for s in scenarios.values())
    print(f"cluster-bench: {runs} runs of {path.stem} on the process pool ({args.workers} workers)", file=sys.stderr)
    with Engine(workers=args.workers) as pool:
        pool_seconds, pool_results = _campaign(files, pool)
        pool_where = pool.where()
    print(f"cluster-bench: the same on a local Dask cluster of {args.workers} worker processes", file=sys.stderr)
    started = time.perf_counter()
    with Engine(cluster=f"local:{args.workers}") as cluster:
        # The workers are new interpreters (a pool's are forks of this one): their imports belong to the start.
        cluster.prepare("lab.experiments.scenarios")
        start_seconds = time.perf_counter() - started
        cluster_seconds, cluster_results = _campaign(files, cluster)
        cluster_where = cluster.where()
    print(f"cluster-bench: client memory, Experiment 1 with {args.memory_runs} and {8 * args.memory_runs} runs "
          f"on a scheduler and {args.workers} workers started as processes", file=sys.stderr)
    with _scheduler_and_workers(args.workers) as address, Engine(cluster=address) as remote:
        remote.prepare("lab.experiments.comparison")
        memory = [(n, *_client_peak(remote, n)) for n in (args.memory_runs, 8 * args.memory_runs)]
    ours, theirs = pool_results[path.stem], cluster_results[path.stem]
    same = all(np.array_equal(getattr(theirs[v], field), getattr(ours[v], field), equal_nan=True)
               for v in ours for field in ("error_mean", "error_std", "closest"))
    if not same:
        print("cluster-bench: the cluster's results differ from the pool's: report this", file=sys.stderr)
        return 1
    rows = [["process pool", pool_where, "-", f"{pool_seconds:.1f}", f"{pool_seconds / runs:.3f}", "-"],
            ["local Dask cluster", cluster_where, f"{start_seconds:.1f}", f"{cluster_seconds:.1f}",
             f"{cluster_seconds / runs:.3f}", f"{1e3 * (cluster_seconds - pool_seconds) / runs:+.0f}"]]
    text = "\n".join([
        "# Monte Carlo on a Dask cluster against the process pool", "",
        f"Command: `{invocation(args)}`", "",
        *[f"- {line}" for line in machine()], "",
        f"The same campaign, {runs} runs ({len(scenarios)} variants of `{path.name}` x {args.runs} runs, "
        f"{next(iter(scenarios.values())).duration:g} s simulated each), first on this machine's process pool "
        f"and then on a local Dask cluster with as many worker processes (lab/harness/parallel.py). The errors of every "
        "run are the same bit for bit on both (checked before this page is written). The cluster's start (its "
        "worker processes starting and importing the lab, which a pool's forked workers need not) is apart from "
        "the campaign's wall time; the overhead per run is the difference of the two wall times over the runs, "
        "what the scheduler and the transfer of jobs and results cost.", "",
        markdown_table(["engine", "where", "start (s)", "campaign wall time (s)", "per run (s)",
                        "overhead per run vs the pool (ms)"], rows), "",
        "## The client's memory", "",
        f"Experiment 1 (`usv-lab compare`'s runs: two vessels, six estimators, {MEMORY_DURATION:g} s simulated "
        f"each, GMM range noise) with N and 8N runs on a `dask scheduler` and `dask worker --nworkers "
        f"{args.workers} --nthreads 1` started as processes on this machine (as docs/lab.md starts them on lab "
        "machines); the client's peak of traced Python allocations over the campaign (tracemalloc: the command's "
        "own process; the scheduler and the runs are in others). "
        "Held whole, each run's error and NEES curves would add "
        f"{_curve_bytes() / 1e3:.1f} kB a run.", "",
        markdown_table(["runs", "client peak traced memory (MB)", "wall time (s)"],
                       [[n, f"{peak:.2f}", f"{seconds:.1f}"] for n, peak, seconds in memory]), "",
        "On two lab machines the same campaign splits over their cores: docs/lab.md says how to start a "
        "scheduler and workers and what speed-up to expect.", ""])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "cluster_benchmark.md").write_text(text, encoding="utf-8")
    print(text)
    return 0
