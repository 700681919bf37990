"""(g) of `usv-lab runtime-bench`: one agent on a core of its own, as on a boat's computer.

A real-time fleet whose first vessel's agent is pinned to one CPU and the sim bridge, the other agents and the
launcher to another (lab/benchmarks/pinning.py), so that the agent's sensor-to-command latency is what its
own computer would give it, apart from whatever else the machine runs on that CPU. Beside it, from the same
run of the benchmark: the same agent in the unpinned fleet, and the bare Zenoh round trip between two
processes pinned the same way (the hop the pinned agent makes, from one core to the other).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lab.benchmarks.pinning import affinities, pin
from lab.report.markdown import markdown_table
from sim_bridge.fleet import Fleet

CHECK_AT = 5.0     # sim s (= wall s) into the run when the launcher reads back the processes' CPUs
END_BEFORE = 2.0   # sim s before the end of the run when it reads the scheduler's times a second time


class PinnedFleet(Fleet):
    """A fleet whose agent of `vessel` (by default the first vessel's) is pinned to `cpus` as it starts; every
    other process runs where the launcher does (a child takes its parent's CPUs), so the caller pins the
    launcher first."""

    def __init__(self, *args, cpus: set[int], vessel: str | None = None, others_nice: int = 0, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.pinned_vessel = vessel or self.scenario.world.vessels[0].id
        self.pinned_cpus = set(cpus)
        # The other vessels' agents at this niceness: 19 stands for agents that run on computers of their own
        # (on a boat nothing else shares its bridge's CPU); the bridge and the launcher keep theirs.
        self.others_nice = others_nice
        self.seen: dict[str, dict[int, set[int]]] = {}   # "agent", "bridge" -> each thread's CPUs, read back
        # (sim s, the agent's and the bridge's scheduler times, the agent's CPU's times), twice
        self.snapshots: list[tuple] = []

    def start_agent(self, vessel: str) -> None:
        super().start_agent(vessel)
        if vessel == self.pinned_vessel:
            # Just started, it is still importing: its Zenoh threads, started later, take this set too.
            pin(self.agents[vessel].pid, self.pinned_cpus)
        elif self.others_nice:
            # Niceness is per thread on Linux too, and a new thread takes its creator's: set it as it starts.
            os.setpriority(os.PRIO_PROCESS, self.agents[vessel].pid, self.others_nice)

    def look(self, fleet: Fleet, sim_seconds: float) -> None:
        """`on_time`: well into the run, each thread's CPUs of the pinned agent and of the bridge; then and
        near the end, the agent's scheduler times and its CPU's (`waits`)."""
        try:
            if not self.seen and sim_seconds >= CHECK_AT:
                self.seen = {"agent": affinities(self.agents[self.pinned_vessel].pid),
                             "bridge": affinities(self.bridge.pid)}
                self.snapshots.append(self._snapshot(sim_seconds))
            elif len(self.snapshots) == 1 and sim_seconds >= self.scenario.duration - END_BEFORE:
                self.snapshots.append(self._snapshot(sim_seconds))
        except OSError:   # a process that has gone (ProcessLookupError, FileNotFoundError)
            self.seen = self.seen or {"agent": {}, "bridge": {}}

    def _snapshot(self, sim_seconds: float) -> tuple:
        return (sim_seconds, scheduler_times(self.agents[self.pinned_vessel].pid), scheduler_times(self.bridge.pid),
                cpu_times(min(self.pinned_cpus)))

    def waits(self) -> dict[str, float] | None:
        """Between the two snapshots, per tick (ms): the agent's and the bridge's time on a CPU and waiting,
        runnable, for one (every thread); and the share of the agent's CPU's time that went to other processes
        and to the hypervisor (steal). None if the run ended before the second."""
        if len(self.snapshots) < 2:
            return None
        (t0, agent0, bridge0, cpu0), (t1, agent1, bridge1, cpu1) = self.snapshots
        ticks = (t1 - t0) / self.scenario.world.dt
        total = sum(cpu1.values()) - sum(cpu0.values())
        busy = cpu1["busy"] - cpu0["busy"]
        ran = (agent1[0] - agent0[0]) * 1e-9
        return {"run_ms": 1e3 * ran / ticks, "wait_ms": (agent1[1] - agent0[1]) * 1e-6 / ticks,
                "bridge_run_ms": (bridge1[0] - bridge0[0]) * 1e-6 / ticks,
                "bridge_wait_ms": (bridge1[1] - bridge0[1]) * 1e-6 / ticks,
                "others": max(0.0, busy - ran) / total if total else float("nan"),
                "steal": (cpu1["steal"] - cpu0["steal"]) / total if total else float("nan")}

    def threads_on(self, who: str, cpus: set[int]) -> str:
        """"k/n": of the n threads of `who` read back, k may run on `cpus` alone."""
        seen = self.seen.get(who, {})
        return f"{sum(found == cpus for found in seen.values())}/{len(seen)}"


def scheduler_times(pid: int) -> tuple[int, int]:
    """Nanoseconds the threads of `pid` have run, and waited runnable for a CPU (/proc/<pid>/task/*/schedstat):
    the sums over the threads there now (an agent's and the bridge's last the whole run)."""
    run = wait = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            fields = (task / "schedstat").read_text().split()
        except OSError:       # a thread that ended meanwhile
            continue
        run, wait = run + int(fields[0]), wait + int(fields[1])
    return run, wait


def cpu_times(cpu: int) -> dict[str, float]:
    """Seconds CPU `cpu` has spent busy, idle (with I/O wait) and stolen by the hypervisor (/proc/stat)."""
    tick = os.sysconf("SC_CLK_TCK")
    for line in Path("/proc/stat").read_text().splitlines():
        if line.startswith(f"cpu{cpu} "):
            user, nice, system, idle, iowait, irq, softirq, steal = (int(v) / tick for v in line.split()[1:9])
            return {"busy": user + nice + system + irq + softirq, "idle": idle + iowait, "steal": steal}
    raise ProcessLookupError(f"no cpu{cpu} in /proc/stat")


def percentiles(values: list[float]) -> tuple[float, float, float]:
    """p50, p99 and max (ms); NaN for none."""
    if not values:
        return (float("nan"),) * 3
    return float(np.percentile(values, 50)), float(np.percentile(values, 99)), float(np.max(values))


def row(size: int, vessel: str, pinned: list[float], unpinned: list[float] | None, bare: dict,
        others: list[float], expected: int, threads: str, others_nice: int = 0) -> list:
    """One size's row of the page's table: the pinned agent against itself unpinned and the bare round trip."""
    p50, p99, longest = percentiles(pinned)
    before = percentiles(unpinned) if unpinned else None
    return [size, others_nice, vessel, f"{p50:.2f}", f"{p99:.2f}", f"{longest:.2f}",
            "yes" if p50 <= 2.0 and p99 <= 5.0 else "no",
            f"{before[0]:.2f} / {before[1]:.2f}" if before else "-",
            f"{p50 / before[0]:.2f} / {p99 / before[1]:.2f}" if before else "-",
            f"{bare['round_trip_p50']:.3f} / {bare['round_trip_p99']:.3f}",
            f"{p50 / bare['round_trip_p50']:.1f}x / {p99 / bare['round_trip_p99']:.1f}x",
            f"{np.percentile(others, 50):.2f}" if others else "-", f"{len(pinned)}/{expected}", threads]


def where_row(size: int, pinned: list[float], bare: dict, summary: dict, waits: dict | None, load: float,
              others_nice: int = 0) -> list:
    """Where the pinned agent's median latency goes: its own reaction (its sensors' arrival to its command's
    put), of which CPU, and the rest (the bridge's puts of the vessel's sensors, the two hops, the bridge's
    receiving);
    what the scheduler says of the agent's CPU (`PinnedFleet.waits`)."""
    p50 = percentiles(pinned)[0]
    reaction, cpu = summary.get("reaction_ms") or {}, summary.get("reaction_cpu_ms") or {}

    def cell(record: dict, name: str) -> str:
        return f"{record[name]:.2f}" if record.get(name) is not None else "-"

    rest = p50 - reaction["p50"] if reaction.get("p50") is not None else float("nan")
    return [size, others_nice, f"{p50:.2f}", cell(reaction, "p50"), cell(reaction, "p99"), cell(cpu, "p50"),
            cell(cpu, "p99"),
            f"{rest:.2f}", f"{bare['round_trip_p50']:.3f}",
            *([f"{waits['run_ms']:.2f}", f"{waits['wait_ms']:.2f}", f"{100 * waits['others']:.0f}",
               f"{100 * waits['steal']:.1f}", f"{waits['bridge_run_ms']:.2f}", f"{waits['bridge_wait_ms']:.2f}"]
              if waits else ["-"] * 6), f"{load:.1f}"]


def section(rows: list[list], where: list[list], cpus: tuple[int, int] | None, skipped: str) -> list[str]:
    """The page's section on (g), as lines."""
    title = ["## One agent on a core of its own (real time, as on a boat's computer)", ""]
    if cpus is None:
        return [*title, f"Not measured: {skipped}.", ""]
    agent_cpu, rest_cpu = cpus
    return [
        *title,
        (f"The real-time fleet again, with the first vessel's agent pinned to CPU {agent_cpu} and the sim bridge, "
        f"the other agents and the launcher to CPU {rest_cpu} (`os.sched_setaffinity` on every thread; the "
        "launcher reads each thread's CPUs back 5 s into the run, last column). Its latency is the bridge's, "
        "as in the first table: from publishing the tick's sensors to receiving this agent's command. Beside it, "
        "from this run of the command: the same agent in the unpinned fleet above, and the bare Zenoh round "
        f"trip between an echo process on CPU {agent_cpu} and a ping process on CPU {rest_cpu}, measured just "
        "before the pinned fleet (the hop the pinned agent makes). The target of issue 32 is p50 <= 2 ms and "
        "p99 <= 5 ms. The CPUs are pinned for these processes only: whatever else the machine runs may still "
        f"run on CPU {agent_cpu}. Each size runs twice: with the other agents at the launcher's priority, and "
        "with them at niceness 19, which stands for vessels whose agents run on computers of their own (on a "
        "boat nothing else shares the bridge's and the drivers' CPU; here the other agents must, and they "
        "wake on the same tick as the bridge)."), "",
        markdown_table(["vessels", "other agents' niceness", "pinned agent", "p50 (ms)", "p99 (ms)", "max (ms)", "p50 <= 2 and p99 <= 5",
                        "same agent unpinned p50 / p99 (ms)", "pinned / unpinned p50 / p99",
                        "bare round trip across the CPUs p50 / p99 (ms)", "p50 / p99 over the bare round trip",
                        f"the other agents (CPU {rest_cpu}) p50 (ms)", "commands timed",
                        "threads on their CPU"], rows), "",
        ("Where the pinned agent's time goes: its own reaction (from the arrival of its sensors to its "
        "command's put, from its log's summary, read to 0.05 ms) and its tick thread's CPU over that stretch; the "
        "rest of the median latency is the bridge's side (putting the vessel's sensors, receiving the command, on "
        "the CPU it shares with the other agents), the two hops and the agent's callbacks of the first sensors. "
        "Then what the kernel's scheduler says between 5 s into the run and 2 s before its end "
        "(/proc/<pid>/task/*/schedstat, /proc/stat): per "
        f"tick, the time the pinned agent's threads ran and the time they waited, runnable, for CPU {agent_cpu}; "
        f"the share of CPU {agent_cpu}'s time that went to other processes of the machine and to the hypervisor "
        f"(steal); and the same two times of the bridge, on CPU {rest_cpu}. The load average is the machine's (every process of it) when the pinned run "
        "started."), "",
        markdown_table(["vessels", "other agents' niceness", "latency p50 (ms)", "own reaction p50 (ms)", "own reaction p99 (ms)",
                        "tick thread's CPU p50 (ms)", "tick thread's CPU p99 (ms)",
                        "latency p50 - own reaction p50 (ms)", "bare round trip p50 (ms)",
                        "agent ran per tick (ms)", "agent waited for its CPU per tick (ms)",
                        f"CPU {agent_cpu} to other processes (%)", f"CPU {agent_cpu} stolen (%)",
                        "bridge ran per tick (ms)", "bridge waited for its CPU per tick (ms)",
                        "load average (1 min)"], where), "",
    ]
