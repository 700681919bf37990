"""Pinning processes to CPUs, for the runtime benchmark's agent on a core of its own (as on a boat's computer).

Linux only (os.sched_setaffinity). A process's threads each have their own CPU set and a new thread takes
its creator's, so `pin` sets every thread there is now: a process pinned before it starts its threads (an
agent just started is still importing) keeps all of them on the set.
"""

from __future__ import annotations

import contextlib
import os
import platform
from pathlib import Path


class AffinityUnsupported(RuntimeError):
    """This system cannot pin a process to CPUs."""


def _check() -> None:
    if not hasattr(os, "sched_setaffinity") or not Path("/proc/self/task").is_dir():
        raise AffinityUnsupported(f"pinning a process to a CPU needs os.sched_setaffinity and /proc (Linux); "
                                  f"this is {platform.system()}")


def usable_cpus() -> list[int]:
    """The CPUs this process may run on, in order."""
    _check()
    return sorted(os.sched_getaffinity(0))


def threads(pid: int) -> list[int]:
    """The thread ids of process `pid` now (ProcessLookupError if it has gone)."""
    try:
        return sorted(int(task.name) for task in Path(f"/proc/{pid}/task").iterdir())
    except FileNotFoundError:
        raise ProcessLookupError(f"no process {pid}") from None


def pin(pid: int, cpus: set[int]) -> None:
    """Every thread of process `pid` onto `cpus` (0: this process); the threads it starts later inherit them."""
    _check()
    for tid in threads(pid or os.getpid()):
        with contextlib.suppress(ProcessLookupError):   # a thread that ended meanwhile
            os.sched_setaffinity(tid, cpus)


def affinities(pid: int) -> dict[int, set[int]]:
    """Each thread of process `pid` and the CPUs it may run on, read back from the kernel."""
    _check()
    found = {}
    for tid in threads(pid):
        with contextlib.suppress(ProcessLookupError):
            found[tid] = os.sched_getaffinity(tid)
    return found


@contextlib.contextmanager
def pinned(cpus: set[int]):
    """This process (every thread, and the processes it starts meanwhile) on `cpus`; put back as it was after."""
    _check()
    before = os.sched_getaffinity(0)
    pin(0, cpus)
    try:
        yield
    finally:
        pin(0, before)
