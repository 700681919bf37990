"""`usv-lab runtime-bench`: what the Zenoh runtime costs on this machine. A benchmark, not a test.

(a) Bare Zenoh on loopback, the baseline: a ping process and an echo process with the agents' session
    settings; each ping carries its send time (CLOCK_MONOTONIC is shared by the processes of one machine),
    so one exchange gives the one-way publish-to-subscribe latency and the round trip.
(b) Sensor-to-command latency: the fleet in real-time mode (sim clock at 10 Hz of wall time), 4 and 12
    vessels; the sim bridge logs, per tick and vessel, the wall time from publishing the tick's sensors to
    receiving the agent's command (`/bridge/command_latency` in sim.mcap). This is a round trip through an
    agent, so it is set against the bare round trip measured just before it; and against each agent's own
    reaction time, clock to command, from its log's summary (agent/shell/reaction.py).
(c) The lockstep real-time factor of the Table II mission (MCKF, 4 vessels): simulated time over the wall
    time of the bridge's tick loop (`/bridge/summary`), and of the whole launch. Set against it, in the same
    run: the in-process runner on the same mission and seed (one process, no messaging: what the
    computation alone allows on one core), and the CPU each process spent per tick (every thread, Zenoh's
    included; from each process's own summary record), which is what the two cores have to share.
(d) The peak resident memory of every process of each run (/proc VmHWM).
(e) Where an agent's and the bridge's CPU per tick goes, against two floors measured in the same run: the
    shells in one process without Zenoh (lab/benchmarks/shell.py: decoding, gate, core, messages, logs, by
    section) and the transport floor (lab/benchmarks/transport_floor.py: the same lockstep message pattern between
    processes that do nothing else). What the fleet costs beyond the sum of the two is the price of six
    processes sharing two cores: thread hand-offs, cold caches, the scheduler.
(f) What one share costs its receiver to decode, by fleet size: a share carries the sender's n - 1 pair
    estimates, and every agent decodes n - 1 shares a tick. The receiver's decoding (`ReceivedShare`: its own
    estimate checked) against checking the whole message (`ShareMessage`), timed in this process.
(g) One agent on a CPU of its own, the rest on another, as on a boat: lab/benchmarks/pinned_agent.py.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh

from agent.contract import PairEstimate, ReceivedShare, ShareMessage, decode, encode
from agent.runtime.mcap_log import read_messages
from lab import arguments
from lab.benchmarks import pinned_agent
from lab.benchmarks.pinning import AffinityUnsupported, pin, pinned, usable_cpus
from lab.benchmarks.shell import AGENT_SECTIONS, SECTION_TEXT, run_shells
from lab.benchmarks.transport_floor import SIZES, loopback_config, transport_floor
from lab.experiments.scenarios import DEFAULT_DIR
from lab.harness.runner import run as run_in_process
from lab.report.markdown import invocation, markdown_table
from sim_bridge.fleet import Fleet, free_port
from sim_bridge.scenario import select_scenario, with_duration

PAYLOAD_BYTES = 300     # about one Odometry or Cmd message
WARM_UP_SECONDS = 30.0  # the most the echo process may take to import, listen and answer a first ping


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pings", type=arguments.positive_int, default=2000, help="bare Zenoh exchanges per baseline")
    parser.add_argument("--seconds", type=arguments.positive_float, default=30.0,
                        help="simulated (= wall) seconds of each real-time latency run")
    parser.add_argument("--sizes", type=arguments.positive_int, nargs="+", default=[4, 12],
                        help="fleet sizes of the latency runs (variants n<size>_r5 of table4_scale)")
    parser.add_argument("--pinned-sizes", type=arguments.positive_int, nargs="*", default=[4, 12],
                        help="fleet sizes of the runs with one agent pinned to a CPU of its own and the rest to "
                             "another (Linux, 2 CPUs or more); none: skip them")
    parser.add_argument("--others-nice", type=int, nargs="+", default=[0, 19], choices=range(20), metavar="N",
                        help="niceness of the other agents in the pinned runs, one run each (19: as if each ran on "
                             "a computer of its own)")
    parser.add_argument("--floor-ticks", type=arguments.positive_int, default=1000,
                        help="ticks of the transport floor (lab/benchmarks/transport_floor.py)")
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results"), help="where runtime_benchmark.md goes")
    parser.add_argument("--scenarios-dir", type=Path, default=DEFAULT_DIR, help="where the scenario files are")


def echo(port: int, seconds: float) -> None:
    """The echo side of (a): answer each ping at once, adding the one-way latency it measured."""
    with zenoh.open(loopback_config(listen=port)) as session:
        pong = session.declare_publisher("bench/pong")

        def on_ping(sample) -> None:
            arrived = time.monotonic_ns()
            sent = int(bytes(sample.payload.to_bytes()[:20]).decode())
            pong.put(f"{sent:020d}{arrived - sent:020d}".encode().ljust(PAYLOAD_BYTES, b" "))

        session.declare_subscriber("bench/ping", on_ping)
        time.sleep(seconds)


def bare_zenoh(pings: int, echo_cpus: set[int] | None = None) -> dict[str, float]:
    """One-way and round-trip latency percentiles (ms) of plain put/subscribe between two processes; the echo
    process pinned to `echo_cpus` if given (before it has imported Zenoh)."""
    port = free_port()
    seconds = WARM_UP_SECONDS + 5.0 + pings * 0.004
    child = subprocess.Popen([sys.executable, "-c",
                              f"from lab.benchmarks.runtime import echo; echo({port}, {seconds})"])
    if echo_cpus is not None:
        pin(child.pid, echo_cpus)
    one_way, round_trip = [], []
    counted_from = [time.monotonic_ns()]   # pongs of pings sent before this are the warm-up's, not counted
    try:
        with zenoh.open(loopback_config(connect=port)) as session:
            def on_pong(sample) -> None:
                now = time.monotonic_ns()
                text = bytes(sample.payload.to_bytes()[:40]).decode()
                sent, forward = int(text[:20]), int(text[20:40])
                if sent >= counted_from[0]:
                    one_way.append(forward * 1e-6)
                    round_trip.append((now - sent) * 1e-6)

            session.declare_subscriber("bench/pong", on_pong)
            ping = session.declare_publisher("bench/ping")

            def send() -> None:
                ping.put(f"{time.monotonic_ns():020d}".encode().ljust(PAYLOAD_BYTES, b" "))

            # Warm up until the echo answers (it has imported, listens, and the two sessions know of each
            # other's subscriber): then every ping that counts can come back.
            deadline = time.monotonic() + WARM_UP_SECONDS
            while not round_trip:
                if child.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"bare Zenoh baseline: the echo process did not answer within "
                                       f"{WARM_UP_SECONDS:.0f} s (exit code {child.poll()})")
                send()
                time.sleep(0.02)
            counted_from[0] = time.monotonic_ns()
            one_way.clear()
            round_trip.clear()
            for _ in range(pings):
                send()
                time.sleep(0.002)
            deadline = time.monotonic() + 2.0   # the last pongs are on their way
            while len(round_trip) < pings and time.monotonic() < deadline:
                time.sleep(0.01)
    finally:
        child.terminate()
        child.wait(timeout=10)
    if len(round_trip) < pings // 2:
        raise RuntimeError(f"bare Zenoh baseline: only {len(round_trip)} of {pings} pings came back")
    return {"one_way_p50": float(np.percentile(one_way, 50)), "one_way_p99": float(np.percentile(one_way, 99)),
            "round_trip_p50": float(np.percentile(round_trip, 50)),
            "round_trip_p99": float(np.percentile(round_trip, 99)), "samples": len(round_trip)}


def bridge_records(folder: Path) -> tuple[dict[str, list[float]], dict]:
    """Each vessel's sensor-to-command latencies (ms) and the bridge's summary, from its log."""
    latencies, summary = {}, {}
    for topic, _, message in read_messages(folder / "sim.mcap"):
        if topic == "/bridge/command_latency":
            for vessel, value in message["milliseconds"].items():
                latencies.setdefault(vessel, []).append(value)
        elif topic == "/bridge/summary":
            summary = message
    return latencies, summary


def pinning_cpus(sizes: list[int]) -> tuple[tuple[int, int] | None, str]:
    """The CPU for the pinned agent and the CPU for the rest, or None and why the pinned runs are skipped."""
    if not sizes:
        return None, "not asked for (`--pinned-sizes` with no size)"
    try:
        cpus = usable_cpus()
    except AffinityUnsupported as error:
        return None, f"skipped: {error}"
    if len(cpus) < 2:
        return None, f"skipped: this process may use {len(cpus)} CPU, and pinning an agent apart needs 2"
    return (cpus[0], cpus[1]), ""


def pinned_run(scale: Path, size: int, scratch: Path, pings: int, cpus: tuple[int, int], others_nice: int = 0):
    """(g): the bare round trip across the two CPUs, then the real-time fleet with its first vessel's agent on
    `cpus[0]` and the launcher, the bridge and the other agents (at `others_nice`) on `cpus[1]`. (baseline,
    fleet, its folder)."""
    agent_cpu, rest_cpu = cpus
    with pinned({rest_cpu}):   # this process and every child it starts, unless pinned apart
        baseline = bare_zenoh(pings, echo_cpus={agent_cpu})
        fleet = pinned_agent.PinnedFleet(scale, f"n{size}_r5", scratch / "runs", mode="realtime", cpus={agent_cpu},
                                         others_nice=others_nice)
        folder = fleet.run(on_time=fleet.look)
    return baseline, fleet, folder


def _log_summary(path: Path) -> dict:
    """The summary record a process logs at its end ({} without one)."""
    summary = {}
    for topic, _, message in read_messages(path):
        if topic.endswith("/summary"):
            summary = message
    return summary


def _reactions(folder: Path) -> tuple[list[dict], list[dict]]:
    """Each agent's reaction times (clock to command) and its tick thread's CPU to the command, from the summary
    at the end of its log (each log read once)."""
    wall, cpu = [], []
    for path in sorted(folder.glob("agent-*.mcap")):
        summary = _log_summary(path)
        wall += [summary["reaction_ms"]] if summary.get("reaction_ms") else []
        cpu += [summary["reaction_cpu_ms"]] if summary.get("reaction_cpu_ms") else []
    return wall, cpu


def _cpu_per_tick(folder: Path) -> dict[str, float]:
    """CPU milliseconds per tick of each process's loop, from the summary record each one logs at the end;
    `core-<id>` for the part of an agent's tick thread inside the core's step."""
    cpu = {}
    for path in sorted(folder.glob("*.mcap")):
        for topic, _, message in read_messages(path):
            if topic.endswith("/summary") and message.get("ticks"):
                name = "bridge" if topic == "/bridge/summary" else f"agent-{topic.split('/')[1]}"
                cpu[name] = 1e3 * message["cpu_seconds"] / message["ticks"]
                if message.get("core_cpu_seconds") is not None:
                    cpu[f"core-{topic.split('/')[1]}"] = 1e3 * message["core_cpu_seconds"] / message["ticks"]
    return cpu


def latency_row(size: int, latencies: dict[str, list[float]], summary: dict, baseline: dict, folder: Path) -> list:
    """(b)'s row: the fleet's sensor-to-command latency against the bare round trip and the agents' own."""
    every = [value for values in latencies.values() for value in values]
    expected = size * summary.get("ticks", 0)
    p50, p99 = np.percentile(every, 50), np.percentile(every, 99)
    own, cpu = _reactions(folder)
    return [size, f"{p50:.2f}", f"{p99:.2f}", f"{baseline['round_trip_p50']:.3f}",
            f"{baseline['round_trip_p99']:.3f}", f"{baseline['one_way_p50']:.3f}",
            f"{p50 / baseline['round_trip_p50']:.0f}x",
            f"{np.median([r['p50'] for r in own]):.2f}" if own else "-",
            f"{max(r['p99'] for r in own):.2f}" if own else "-",
            f"{np.median([r['p50'] for r in cpu]):.2f}" if cpu else "-",
            f"{len(every)}/{expected}"]


def in_process_baseline(path: Path, variant: str) -> tuple[float, float]:
    """The in-process runner on the same mission and seed: (real-time factor, mean core tick in ms)."""
    _, scenario = select_scenario(path, variant)
    started = time.perf_counter()
    trace = run_in_process(scenario)
    return scenario.duration / (time.perf_counter() - started), 1e3 * float(np.nanmean(trace.tick_seconds))


def _memory(folder: Path) -> dict[str, float]:
    return json.loads((folder / "memory.json").read_text())["peak_resident_mb"]


def run(args: argparse.Namespace) -> int:
    scale = args.scenarios_dir / "table4_scale.yaml"
    table2 = args.scenarios_dir / "table2_estimators.yaml"
    rows, memory_rows, pinned_rows, where_rows = [], [], [], []
    cpus, skipped = pinning_cpus(args.pinned_sizes)
    if cpus is None:
        print(f"runtime-bench: one agent on a core of its own: {skipped}", file=sys.stderr)
    unpinned: dict[int, dict[str, list[float]]] = {}   # size -> each vessel's latencies in (b)
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        timed = with_duration(scale, scratch, args.seconds)
        for size in sorted(set(args.sizes) | set(args.pinned_sizes if cpus else [])):
            if size in args.sizes:
                print(f"runtime-bench: bare Zenoh baseline, then {size} vessels in real time for "
                      f"{args.seconds:.0f} s", file=sys.stderr)
                baseline = bare_zenoh(args.pings)
                folder = Fleet(timed, f"n{size}_r5", scratch / "runs", mode="realtime").run()
                latencies, summary = bridge_records(folder)
                unpinned[size] = latencies
                rows.append(latency_row(size, latencies, summary, baseline, folder))
                memory_rows.append([f"real time, {size} vessels", *_memory_cells(_memory(folder))])
            for nice in (args.others_nice if size in args.pinned_sizes and cpus else []):
                print(f"runtime-bench: bare Zenoh across CPUs {cpus[0]} and {cpus[1]}, then {size} vessels in real "
                      f"time with one agent on CPU {cpus[0]} and the rest on CPU {cpus[1]} (the other agents at "
                      f"niceness {nice})", file=sys.stderr)
                load = os.getloadavg()[0]
                baseline, fleet, folder = pinned_run(timed, size, scratch, args.pings, cpus, nice)
                latencies, summary = bridge_records(folder)
                vessel = fleet.pinned_vessel
                others = [v for k, values in latencies.items() if k != vessel for v in values]
                threads = (f"agent {fleet.threads_on('agent', {cpus[0]})}, "
                           f"bridge {fleet.threads_on('bridge', {cpus[1]})}")
                pinned_rows.append(pinned_agent.row(
                    size, vessel, latencies.get(vessel, []), unpinned.get(size, {}).get(vessel), baseline, others,
                    summary.get("ticks", 0), threads, nice))
                where_rows.append(pinned_agent.where_row(size, latencies.get(vessel, []), baseline,
                                                         _log_summary(folder / f"agent-{vessel}.mcap"), fleet.waits(),
                                                         load, nice))
                memory_rows.append([f"real time, {size} vessels, one agent pinned, the others at niceness {nice}",
                                    *_memory_cells(_memory(folder))])
        print("runtime-bench: Table II (MCKF, 4 vessels, 60 s) in lockstep", file=sys.stderr)
        started = time.monotonic()
        fleet = Fleet(table2, "mckf", scratch / "runs")
        folder = fleet.run()
        launch_seconds = time.monotonic() - started
        _, summary = bridge_records(folder)
        cpu = _cpu_per_tick(folder)
        simulated = summary["ticks"] * fleet.scenario.world.dt
        memory_rows.append(["lockstep Table II, 4 vessels", *_memory_cells(_memory(folder))])
        print("runtime-bench: the same mission in process (the baseline)", file=sys.stderr)
        alone_factor, core_ms = in_process_baseline(table2, "mckf")
        print("runtime-bench: the same mission through the shells in one process, and the transport floor",
              file=sys.stderr)
        _, scenario = select_scenario(table2, "mckf")
        shells = run_shells(scenario, scratch / "shells")
        floor = transport_floor(len(scenario.world.vessels), args.floor_ticks)
    print("runtime-bench: a share's decoding by fleet size", file=sys.stderr)
    share_rows = share_decode_rows()
    factor = simulated / summary["loop_seconds"]
    lockstep = [[summary["ticks"], f"{simulated:.1f}", f"{summary['loop_seconds']:.2f}", f"{factor:.1f}x",
                 f"{launch_seconds:.1f}", f"{simulated / launch_seconds:.1f}x", summary["missed_commands"],
                 f"{alone_factor:.1f}x", f"{factor / alone_factor:.2f}", f"{100.0 / floor['loop_ms']:.0f}x"]]
    agents_cpu = float(np.mean([v for k, v in cpu.items() if k.startswith("agent-")]))
    fleet_core = float(np.mean([v for k, v in cpu.items() if k.startswith("core-")]))
    bridge_cpu = cpu.get("bridge", float("nan"))
    dt_ms = 1e3 * fleet.scenario.world.dt
    cores = os.cpu_count() or 1
    total_cpu = bridge_cpu + agents_cpu * len(fleet.scenario.world.vessels)
    shell_core = shells.per_tick_ms("core")
    cpu_rows = [[f"{bridge_cpu:.2f}", f"{agents_cpu:.2f}", f"{agents_cpu / core_ms:.1f}x", f"{core_ms:.2f}",
                 f"{total_cpu:.2f}", f"{cores * dt_ms / total_cpu:.1f}x", f"{cores * dt_ms / 50:.1f}"]]
    split_rows = [["the fleet over Zenoh (every thread)", f"{bridge_cpu:.3f}", f"{agents_cpu:.3f}"],
                  ["the shells in one process, no Zenoh", f"{shells.per_tick_ms('bridge'):.3f}",
                   f"{shells.agent_ms:.3f}"]]
    split_rows.insert(1, ["- of which the agent's core `step` (its tick thread)", "", f"{fleet_core:.3f}"])
    split_rows += [[f"- agent: {SECTION_TEXT[name]}", "", f"{shells.per_tick_ms(name):.3f}"] for name in AGENT_SECTIONS]
    split_rows += [["the transport floor: the same messages, no work", f"{floor['bridge_cpu_ms']:.3f}",
                    f"{floor['agent_cpu_ms']:.3f}"],
                   ["the rest: fleet - shells - floor", f"{bridge_cpu - shells.per_tick_ms('bridge') - floor['bridge_cpu_ms']:.3f}",
                    f"{agents_cpu - shells.agent_ms - floor['agent_cpu_ms']:.3f}"]]
    text = "\n".join([
        "# Runtime benchmark: the fleet over Zenoh on loopback", "",
        f"Command: `{invocation(args)}`", "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"{platform.system()} {platform.release()}. Every figure is from one run of the command above; the "
        "processes share the machine's cores, so the figures move with whatever else runs (from one run to the "
        "next by 15-30 % here). What each change to the runtime bought, measured by alternating runs before and "
        "after it: [runtime_changes.md](runtime_changes.md) (`usv-lab runtime-ab`).", "",
        "## Sensor-to-command latency (real-time mode)", "",
        "From the sim bridge publishing a vessel's sensors of the tick to it receiving that vessel's command (the "
        "bridge sends the clock first, then each vessel's sensors in a slot of its own over half of dt, `stagger`: "
        "a laptop's agents do not all wake at one instant): two Zenoh hops "
        "plus the agent's decoding, its tick and the command's encoding. The baseline is bare Zenoh between two "
        "processes (same session settings, 300-byte payloads), measured just before each fleet run; the ratio is "
        "the p50 latency over the baseline's p50 round trip. The agents' own reaction time is the wall time from "
        "the arrival of the last of its inputs (the clock, then its sensors) to its command's put (the median of "
        "the agents' medians, the largest "
        "of their 99th percentiles): its decoding and its tick, and, here, its waits for one of the cores the "
        "bridge and every agent share. The tick thread's CPU over the same stretch (median of the agents' "
        "medians) is that reaction without the waits, what a computer of the agent's own would take. The rest "
        "of the latency is the bridge's puts of the vessel's sensors, the two hops and the wait before each "
        "sensor's callback runs in the agent.", "",
        markdown_table(["vessels", "p50 (ms)", "p99 (ms)", "bare round trip p50 (ms)", "bare round trip p99 (ms)",
                        "bare one-way p50 (ms)", "p50 / bare round trip", "agents' own reaction p50 (ms)",
                        "agents' own reaction p99 (ms)", "tick thread's CPU to the command p50 (ms)",
                        "commands timed"], rows), "",
        *pinned_agent.section(pinned_rows, where_rows, cpus, skipped),
        "## Lockstep real-time factor (Table II, MCKF, 4 vessels)", "",
        "The bridge advances a tick when every agent has answered, and each agent waits for its neighbours' "
        "shares of the tick before (tests/test_lockstep.py checks the result equals the in-process runner). "
        "The last column is the factor of the transport floor's tick loop: the same messages between the same "
        "number of processes doing nothing else.", "",
        markdown_table(["ticks", "simulated (s)", "tick loop (s)", "real-time factor", "whole launch (s)",
                        "factor incl. start-up", "missed commands", "in process, same seed",
                        "over Zenoh / in process", "transport floor"], lockstep), "",
        "Where the time goes: CPU milliseconds per tick of each process (all its threads), against the core "
        "tick alone (the in-process run's mean core `step`). With every process busy all the time the "
        f"{cores} cores could give at best {cores} x {dt_ms:.0f} ms / (sum of CPU per tick) of real time; "
        f"{50}x real time needs the whole fleet's CPU per tick under {cores * dt_ms / 50:.1f} ms.", "",
        markdown_table(["sim bridge", "agent (mean)", "agent / core tick", "core tick (in process)",
                        "sum over processes", "factor if the cores were never idle", "CPU budget per tick for 50x"],
                       cpu_rows), "",
        "The same CPU against two floors measured in this run: the shells of the bridge and the agents in one "
        "process without Zenoh (lab/benchmarks/shell.py: the processes' own objects handing each other the wire "
        "bytes; an agent's tick by section), and the transport floor (lab/benchmarks/transport_floor.py: bridge and "
        f"{len(scenario.world.vessels)} agent processes exchanging the lockstep messages, payloads of "
        f"{', '.join(f'{k} {v} B' for k, v in SIZES.items())}, with no work on them; {floor['shares_per_tick']:.2f} "
        f"shares reached each agent per tick). In process the agent costs {shells.agent_ms / shell_core:.2f} "
        f"times its core. The same core `step` costs {fleet_core / shell_core:.2f} times as much CPU inside the "
        "fleet's agents as in the one process: what sharing two cores with five other processes does to the "
        "same Python code (cold caches, the scheduler), before any messaging.", "",
        markdown_table(["CPU per tick (ms)", "sim bridge", "agent (mean)"], split_rows), "",
        "## A share's decoding by fleet size", "",
        "A share carries the sender's estimate of each of its n - 1 pairs, and every agent receives n - 1 "
        "shares a tick. The receiver checks the share and its own estimate (`ReceivedShare`, "
        "agent/contract.py); checking every estimate (`ShareMessage`, what the sender builds) is the reference. "
        "Timed in this process, best of 5 batches; the last column is the receiver's decoding of a tick's "
        "shares.", "",
        markdown_table(["vessels", "share (bytes)", "receiver's decoding (us)", "every estimate checked (us)",
                        "ratio", "n - 1 shares per tick (ms)"], share_rows), "",
        "## Peak resident memory per process (MB)", "",
        markdown_table(["run", "sim bridge", "agents: min", "agents: max", "agents: mean"], memory_rows), "",
    ])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "runtime_benchmark.md").write_text(text)
    print(text)
    return 0


SHARE_SIZES = (4, 12, 50)


def share_payload(vessels: int) -> bytes:
    """A share of vessel "1" in a fleet of `vessels`: a target and a pair estimate for every other vessel."""
    return encode(ShareMessage(
        stamp_ns=12_300_000_000, seq=123, sender="1", position=(3.25, -1.5), heading=0.7, velocity=(1.2, 0.4),
        phase=2.1, target=(10.0, 5.0, 0.1, -0.2), target_covariance=tuple(np.diag([0.5, 0.5, 0.2, 0.2]).ravel()),
        neighbours={str(j): PairEstimate(position=(4.0 + j, -2.0), covariance=(0.05, 0.001, 0.04),
                                         stamp_ns=12_200_000_000) for j in range(2, vessels + 1)}))


def receive_share(payload: bytes, receiver: str):
    """What an agent's gate does with a share's bytes before it holds it (agent/shell/gate.py)."""
    message, _ = decode(ReceivedShare, payload)
    return message.estimate_for(receiver)[0]


def share_decode_rows(sizes=SHARE_SIZES, repeats: int = 2000) -> list[list]:
    """Per fleet size: payload bytes, microseconds for the receiver's decoding and for the whole message's
    check (the best of 5 batches of `repeats` each, the two alternating so that both see the same machine),
    their ratio, and the receiver's decoding of n - 1 shares."""
    def batch(call, payload) -> float:
        started = time.perf_counter()
        for _ in range(repeats):
            call(payload)
        return (time.perf_counter() - started) / repeats * 1e6

    def receiver(raw):
        return receive_share(raw, "2")

    def whole(raw):
        return decode(ShareMessage, raw)

    rows = []
    for n in sizes:
        payload = share_payload(n)
        times = [(batch(receiver, payload), batch(whole, payload)) for _ in range(5)]
        mine, every = min(t[0] for t in times), min(t[1] for t in times)
        rows.append([n, len(payload), f"{mine:.1f}", f"{every:.1f}", f"{mine / every:.2f}",
                     f"{(n - 1) * mine / 1e3:.3f}"])
    return rows


def _memory_cells(memory: dict[str, float]) -> list[str]:
    agents = [v for k, v in memory.items() if k.startswith("agent-")]
    return [f"{memory.get('bridge', float('nan')):.0f}", f"{min(agents):.0f}", f"{max(agents):.0f}",
            f"{np.mean(agents):.0f}"]
