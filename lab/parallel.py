"""Monte Carlo jobs over the machine's cores, results in job order whatever the number of workers."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import TypeVar

J = TypeVar("J")
R = TypeVar("R")


def map_in_order(function: Callable[[J], R], jobs: Sequence[J], workers: int,
                 progress: Callable[[int], None] | None = None) -> list[R]:
    """`function` over `jobs` in `workers` processes (in this one when 1), calling `progress(1)` per job."""
    results: list[R] = []
    if workers > 1 and len(jobs) > 1:
        # A few chunks per worker: few round trips, yet a slow chunk at the end does not idle the others.
        chunk = max(1, len(jobs) // (4 * workers))
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
            for result in pool.map(function, jobs, chunksize=chunk):
                results.append(result)
                if progress:
                    progress(1)
    else:
        for job in jobs:
            results.append(function(job))
            if progress:
                progress(1)
    return results
