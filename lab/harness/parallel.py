"""Monte Carlo runs over this machine's cores or a Dask cluster, results in job order whatever ran them.

`Engine(workers=N)` is today's process pool on this machine; `Engine(cluster="tcp://host:8786")` sends the
runs to a Dask scheduler (`dask scheduler`, `dask worker` on each machine: docs/lab.md) and
`Engine(cluster="local:N")` starts a Dask cluster of N worker processes here. Dask is imported only then
(the `lab-cluster` extra). Either way each run draws from its own child seed, so the results are the same
bit for bit whatever ran them, in whatever order.

A scheduler's first answer has a deadline (`FIRST_ANSWER_SECONDS`, 20 s by default; `--cluster-timeout`): an
address where something accepts the connection but never answers as a Dask scheduler (another service, a
scheduler stuck, a firewall that swallows the traffic) is one clear error within it, not a command that
hangs without a word (Dask's own `timeout` does not cover a handshake that never comes).

A run that raises does not stop the campaign: its result is None and `Engine.failures` says which run and
what it raised, so the command still writes what finished. On a Dask cluster, a worker that dies takes its
runs to another worker (the scheduler's own retry); `Engine.retried` counts them.
"""

from __future__ import annotations

import importlib
import os
import sys
import threading
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from functools import partial
from typing import TypeVar

from agent.config import ConfigError
from lab import arguments

J = TypeVar("J")
R = TypeVar("R")
FIRST_ANSWER_SECONDS = 20.0   # default deadline on a remote scheduler's first answer (--cluster-timeout)
CHUNKS_PER_WORKER = 16      # the pool's runs go out in about this many chunks per worker process
RELEASE_BATCH = 64          # finished runs whose results a cluster is told to forget at once
WINDOW_PER_THREAD = 8       # runs out on a cluster at once, per worker thread
LOW_LEVEL_LOG = 50          # Dask's debugging logs of recent messages and transitions, in entries


@dataclass(frozen=True)
class Failure:
    """A run that raised: which one (the caller's words: variant, run, seed) and what it raised."""

    run: str
    error: str


def _guarded(function: Callable[[J], R], job: J) -> tuple[bool, R | str]:
    """(True, result), or (False, the exception in a line and its last frame) if `function(job)` raised."""
    try:
        return True, function(job)
    except Exception as error:  # noqa: BLE001  (one run's failure is reported, the campaign goes on)
        where = traceback.extract_tb(error.__traceback__)[-1]
        return False, f"{type(error).__name__}: {error} ({os.path.basename(where.filename)}:{where.lineno})"


class Engine:
    """Where a campaign's runs go; a context manager (a Dask client lives from enter to exit)."""

    def __init__(self, workers: int = 1, cluster: str | None = None,
                 first_answer_seconds: float = FIRST_ANSWER_SECONDS) -> None:
        self.workers, self.cluster = workers, cluster
        self.first_answer_seconds = first_answer_seconds
        self.failures: list[Failure] = []
        self.retried = 0
        self._client = self._local = None

    def __enter__(self) -> Engine:
        if self.cluster is None:
            return self
        try:
            import dask
            from dask.distributed import Client, LocalCluster
        except ImportError:
            raise ConfigError("--cluster needs Dask: pip install 'usv-circumnav[lab-cluster]'") from None
        # The workers' sampling profiler wakes every 10 ms and takes the GIL from runs that are pure Python:
        # off in the workers started here (docs/lab.md says how to turn it off on a cluster's own).
        dask.config.set({"distributed.worker.profile.enabled": False,
                         # Dask keeps the last this-many messages (each run's task, pickled) and transitions
                         # for debugging; at its default of 1000 that is megabytes on the client of a long
                         # campaign, and in the scheduler of a local cluster.
                         "distributed.admin.low-level-log-length": LOW_LEVEL_LOG})
        if self.cluster.startswith("local:"):
            count = self.cluster.partition(":")[2]
            if not count.isdigit() or int(count) < 1:
                raise ConfigError(f"--cluster {self.cluster}: give local:N with N worker processes, e.g. local:2")
            self._local = LocalCluster(n_workers=int(count), threads_per_worker=1, processes=True,
                                       dashboard_address=None)
            self._client = Client(self._local)
        else:
            self._client = connect_client(self.cluster, self.first_answer_seconds)
        return self

    def __exit__(self, *exc) -> None:
        if self._client is not None:
            self._client.close()
        if self._local is not None:
            self._local.close()

    def prepare(self, module: str) -> None:
        """Import `module` in every worker of the cluster now (nothing to do for the pool, whose workers
        are forks of this process)."""
        if self._client is not None:
            self._client.run(importlib.import_module, module)

    def where(self) -> str:
        """Where the runs went, in words, for a results page."""
        if self._client is None:
            return f"this machine, {self.workers} worker process(es)"
        workers = self._client.scheduler_info().get("workers", {})
        threads = sum(w.get("nthreads", 0) for w in workers.values())
        hosts = sorted({w.get("host", "?") for w in workers.values()})
        started = " (a local cluster the command started)" if self._local is not None else ""
        return (f"Dask scheduler {self._client.scheduler.address}{started}: {len(workers)} worker(s), {threads} "
                f"thread(s), on {', '.join(hosts)}")

    def map(self, function: Callable[[J], R], jobs: Sequence[J], progress: Callable[[int], None] | None = None,
            describe: Callable[[int], str] | None = None,
            consume: Callable[[int, R | None], None] | None = None) -> list[R | None] | None:
        """`function` over `jobs`, results in job order; a run that raised gives None and a `Failure` named
        by `describe(index)`. `progress(1)` is called as each run finishes. With `consume`, each result is
        handed to `consume(index, result)` in job order as soon as those before it are in, and not kept:
        a campaign then holds only the results that came early (None is returned)."""
        guarded = partial(_guarded, function)
        kept: list[R | None] = []
        for index, (ok, value) in self._outcomes(guarded, jobs, progress):
            if not ok:
                self.failures.append(Failure(describe(index) if describe else f"run {index}", value))
            result = value if ok else None
            if consume is None:
                kept.append(result)
            else:
                consume(index, result)
        return kept if consume is None else None

    def _outcomes(self, guarded, jobs: Sequence[J], progress) -> Iterator[tuple[int, tuple[bool, object]]]:
        """(index, outcome) of every job, in job order."""
        if self._client is not None:
            yield from self._dask_outcomes(guarded, jobs, progress)
        elif self.workers > 1 and len(jobs) > 1:
            # Chunks of a few runs: few round trips, yet the last chunks are short, so that one worker does not
            # finish a long chunk alone (runs of different variants differ twice in cost).
            chunk = max(1, len(jobs) // (CHUNKS_PER_WORKER * self.workers))
            with ProcessPoolExecutor(max_workers=min(self.workers, len(jobs))) as pool:
                for index, outcome in enumerate(pool.map(guarded, jobs, chunksize=chunk)):
                    if progress:
                        progress(1)
                    yield index, outcome
        else:
            for index, job in enumerate(jobs):
                outcome = guarded(job)
                if progress:
                    progress(1)
                yield index, outcome

    def _dask_outcomes(self, guarded, jobs: Sequence[J], progress) -> Iterator[tuple[int, tuple[bool, object]]]:
        """Outcomes of `jobs` on the cluster. At most `_window()` runs are out at once, more sent as they
        finish, so the client holds a bounded number of futures and early results however long the campaign."""
        from dask.distributed import as_completed

        index: dict = {}
        pending = as_completed()
        sent = 0

        def send() -> None:
            nonlocal sent
            future = self._client.submit(guarded, jobs[sent], pure=False)
            index[future.key] = sent
            pending.add(future)
            sent += 1

        for _ in range(min(self._window(), len(jobs))):
            send()
        early: dict[int, tuple[bool, object]] = {}   # results that came before an earlier job's
        done: list = []
        following = 0
        for future in pending:
            early[index.pop(future.key)] = future.result()
            done.append(future)
            if sent < len(jobs):
                send()
            if progress:
                progress(1)
            if len(done) >= RELEASE_BATCH:
                self._release(done)
            while following in early:
                yield following, early.pop(following)
                following += 1
        self._release(done)

    def _window(self) -> int:
        """Runs out on the cluster at once: enough to keep every worker thread busy with a queue behind it."""
        threads = sum(w.get("nthreads", 0) for w in self._client.scheduler_info().get("workers", {}).values())
        return max(WINDOW_PER_THREAD * threads, RELEASE_BATCH)

    def _release(self, futures: list) -> None:
        """Count how many of `futures` ran again after their worker died (the scheduler's `suspicious`), then
        let the cluster forget them and their results."""
        if futures:
            self.retried += self._client.run_on_scheduler(_suspicious, [f.key for f in futures])
            self._client.cancel(futures)
            futures.clear()


def connect_client(address: str, deadline: float = FIRST_ANSWER_SECONDS):
    """A Dask client of the scheduler at `address`, or ConfigError (one line) if it does not answer within
    `deadline` seconds: nothing listening, or something that accepts the connection and never answers.

    Dask's client waits for the scheduler's handshake without its own timeout, so the client is made in a
    thread that is given up after the deadline; should it connect later after all, it closes itself."""
    from dask.distributed import Client

    outcome: dict = {}
    given_up = threading.Event()

    def connect() -> None:
        try:
            client = Client(address, timeout=f"{deadline}s")
        except BaseException as error:  # noqa: BLE001  (handed to the caller's thread)
            outcome["error"] = error
            return
        outcome["client"] = client
        if given_up.is_set():
            client.close()

    # A daemon thread: one still waiting for an answer must not keep the process alive after the error.
    thread = threading.Thread(target=connect, name="dask-connect", daemon=True)
    thread.start()
    thread.join(deadline)
    given_up.set()
    if "client" in outcome:
        return outcome["client"]
    error = outcome.get("error")
    if error is None:
        raise ConfigError(f"--cluster {address}: the scheduler did not answer within {deadline:g} s "
                          "(something accepts the connection there but does not answer as a Dask scheduler; "
                          "--cluster-timeout waits longer)")
    if isinstance(error, (OSError, TimeoutError)):
        raise ConfigError(f"--cluster {address}: no Dask scheduler answers there "
                          f"({' '.join(str(error).split())[:300]})") from None
    raise error


def _suspicious(keys: list, dask_scheduler=None) -> int:
    """On the scheduler: how many times the tasks `keys` were lost with a worker and run again."""
    return sum(dask_scheduler.tasks[k].suspicious for k in keys if k in dask_scheduler.tasks)


def add_engine_arguments(parser) -> None:
    """--workers and --cluster, the same on every command that runs Monte Carlo."""
    parser.add_argument("--workers", type=arguments.positive_int, default=os.cpu_count() or 1,
                        help="processes of this machine to use (without --cluster)")
    parser.add_argument("--cluster", default=None, metavar="ADDRESS",
                        help="run on a Dask cluster: a scheduler's address (tcp://host:8786), or local:N to start "
                             "one of N worker processes here (needs the lab-cluster extra; docs/lab.md)")
    parser.add_argument("--cluster-timeout", type=arguments.positive_float, default=FIRST_ANSWER_SECONDS,
                        metavar="SECONDS", help="give up on a --cluster scheduler that has not answered in this "
                                                f"many seconds (default {FIRST_ANSWER_SECONDS:g})")


def engine_from(args) -> Engine:
    return Engine(workers=args.workers, cluster=args.cluster, first_answer_seconds=args.cluster_timeout)


def campaign_notes(engine: Engine) -> list[str]:
    """Lines a results page adds when the campaign was not plain: runs retried after a worker died, runs
    that raised (left out of the figures)."""
    notes = []
    if engine.retried:
        notes.append(f"- {engine.retried} run(s) were run again on another worker after theirs died; their "
                     "results are the same as any run's (each run draws from its own seed)")
    if engine.failures:
        notes.append(f"- **{len(engine.failures)} run(s) raised and are left out**: "
                     + "; ".join(f"{f.run}: {f.error}" for f in engine.failures[:10])
                     + (" ..." if len(engine.failures) > 10 else ""))
    return notes


def hand_off_lines(engine: Engine, wall: float, cpu: float, runs: int) -> list[str]:
    """What the campaign's processes spent beyond its runs' CPU (`cpu`, s, as the workers measured it): the
    pool's workers had `wall` x workers seconds. Nothing for a cluster, whose workers are elsewhere and their
    time not ours to count."""
    if engine.cluster is not None or runs < 1 or wall <= 0.0:
        return []
    if engine.workers == 1 or runs == 1:
        return [f"- The runs took {cpu:.1f} s of CPU in {wall:.1f} s of wall time, in this process "
                f"({cpu / wall:.0%}); the rest, {wall - cpu:.1f} s, is the campaign's own work between runs "
                "and whatever else the machine ran."]
    had = wall * engine.workers
    return [f"- The {engine.workers} worker(s) had {had:.1f} s ({wall:.1f} s of wall time each); the runs took "
            f"{cpu:.1f} s of CPU in them ({cpu / had:.0%}). The rest, {had - cpu:.1f} s "
            f"({(had - cpu) / runs * 1e3:.0f} ms a run), is the hand-off between the processes (each job and its "
            "result pickled and sent), the pool's start, the idle tail of the last runs, and whatever else "
            "the machine ran."]


def report_failures(engine: Engine) -> int:
    """Say on stderr which runs raised; the command's exit code (1 if any did)."""
    for failure in engine.failures:
        print(f"usv-lab: {failure.run} raised {failure.error}", file=sys.stderr)
    return 1 if engine.failures else 0
