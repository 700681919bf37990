"""`usv-lab share-bench`: what the shares cost, broadcast (share format 1) against per pair (format 2).

For each fleet size n, the same lockstep mission runs through the agents' shells in one process
(lab/benchmarks/shell.py), once with each format, alternately, `--repeats` times each: every share is handed
to the receivers Zenoh's routing would hand it to (format 1: every agent but the sender; format 2: the one
receiver of its key). Measured per tick: the share payload bytes delivered (the fleet's and one agent's; Zenoh's
framing is not counted), the messages, and one agent's CPU in its callbacks on them (decoding, the gate), and
the rest of its tick besides the core (building and encoding its share among the rest). The fleets come from
`usv-lab fleet-bench`'s Table IV base (r* = 20 m; drawn start positions, seeded), and the commands of the two
formats are compared: only the transport differs, so they must be the same to the last bit.

Then, for the sizes in `--zenoh-sizes` (4 and 12; 50 processes do not fit 2 cores), the Table IV file's
`n<N>_r5` fleet runs as processes over Zenoh in lockstep (`usv-fleet`), once in each format: each agent's
status counts the shares its subscriptions were handed and their bytes (`shares_received`,
`share_bytes_received`), and its log's summary its process CPU per tick.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np
import yaml

from agent.runtime.mcap_log import read_messages
from lab import arguments
from lab.benchmarks.fleet import add_size_arguments, fleet_scenarios
from lab.benchmarks.shell import ShellRun, run_shells
from lab.experiments.scenarios import DEFAULT_DIR, load, resolve
from lab.report.markdown import invocation, machine, markdown_table
from sim_bridge.fleet import Fleet
from sim_bridge.scenario import with_duration

FORMATS = (1, 2)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_size_arguments(parser, 3.0)
    parser.add_argument("--repeats", type=arguments.positive_int, default=2,
                        help="runs of each format per size, taken alternately (the medians are shown)")
    parser.add_argument("--scale", default="table4_scale", metavar="NAME",
                        help="scenario file whose base the fleets start from")
    parser.add_argument("--scenarios-dir", type=Path, default=DEFAULT_DIR, help="where NAMEs are looked up")
    parser.add_argument("--zenoh-sizes", type=arguments.positive_int, nargs="*", default=[4, 12],
                        help="fleet sizes run as processes over Zenoh too (Table IV file's n<N>_r5 variants)")
    parser.add_argument("--zenoh-duration", type=arguments.positive_float, default=10.0,
                        help="simulated seconds of each run over Zenoh")
    parser.add_argument("--out", type=arguments.folder, default=Path("docs/results"),
                        help="where share_benchmark.md goes")


def measure(scenario, repeats: int) -> dict[int, list[ShellRun]]:
    """`repeats` runs of `scenario` in each share format, taken alternately (1, 2, 2, 1, ...)."""
    runs: dict[int, list[ShellRun]] = {f: [] for f in FORMATS}
    for r in range(repeats):
        for share_format in (FORMATS if r % 2 == 0 else FORMATS[::-1]):
            runs[share_format].append(run_shells(scenario, share_format=share_format))
    return runs


def figures(run: ShellRun) -> dict[str, float]:
    """Per tick: the fleet's share bytes, and one agent's share bytes, messages and CPU (ms)."""
    n, ticks = len(run.vessels), run.ticks
    return {"fleet_bytes": run.share_bytes / ticks, "agent_bytes": run.share_bytes / (ticks * n),
            "agent_messages": run.share_messages / (ticks * n),
            "decode_ms": 1e3 * run.share_seconds / (ticks * n), "publishing_ms": run.per_tick_ms("publishing")}


def median(runs: list[ShellRun], name: str) -> float:
    return statistics.median(figures(r)[name] for r in runs)


def rows_of(n: int, source: str, runs: dict[int, list[ShellRun]]) -> list[list[object]]:
    same = all(np.array_equal(a.commands, b.commands) for a in runs[1] + runs[2] for b in runs[2])
    before, after = runs[1], runs[2]
    ratio = median(after, "decode_ms") / median(before, "decode_ms")
    return [[n, source, f"{median(before, 'fleet_bytes'):,.0f}", f"{median(after, 'fleet_bytes'):,.0f}",
             f"{median(before, 'agent_bytes'):,.0f}", f"{median(after, 'agent_bytes'):,.0f}",
             f"{median(before, 'agent_messages'):.0f} / {median(after, 'agent_messages'):.0f}",
             f"{median(before, 'decode_ms'):.3f}", f"{median(after, 'decode_ms'):.3f}", f"{ratio:.2f}",
             f"{median(before, 'publishing_ms'):.3f}", f"{median(after, 'publishing_ms'):.3f}",
             "yes" if same else "NO"]]


def over_zenoh(size: int, duration: float, scenarios_dir: Path, scratch: Path) -> dict[int, dict[str, float]]:
    """The Table IV file's n<size>_r5 fleet over Zenoh in lockstep, once per format: per tick, one agent's
    shares received and their bytes (mean over the agents), and the agents' process CPU (ms, median)."""
    out = {}
    path = with_duration(scenarios_dir / "table4_scale.yaml", scratch, duration)
    for share_format in FORMATS:
        fleet = Fleet(path, f"n{size}_r5", scratch / "runs")
        for config in fleet.folder.glob("agent-*.yaml"):
            config.write_text(yaml.safe_dump(yaml.safe_load(config.read_text()) | {"share_format": share_format}))
        folder = fleet.run()
        received, cpu = [], []
        for log in sorted(folder.glob("agent-*.mcap")):
            last, summary = None, None
            for topic, _, message in read_messages(log):
                if topic.endswith("/status"):
                    last = message
                elif topic.endswith("/summary"):
                    summary = message
            ticks = summary["ticks"]
            received.append((last["health"]["shares_received"] / ticks,
                             last["health"]["share_bytes_received"] / ticks))
            cpu.append(1e3 * summary["cpu_seconds"] / ticks)
        out[share_format] = {"messages": float(np.mean([r[0] for r in received])),
                             "bytes": float(np.mean([r[1] for r in received])),
                             "cpu_ms": float(np.median(cpu))}
    return out


def zenoh_rows(size: int, figures: dict[int, dict[str, float]]) -> list[list[object]]:
    before, after = figures[1], figures[2]
    return [[size, f"{before['messages']:.1f} / {after['messages']:.1f}", f"{before['bytes']:,.0f}",
             f"{after['bytes']:,.0f}", f"{size * before['bytes']:,.0f}", f"{size * after['bytes']:,.0f}",
             f"{before['cpu_ms']:.2f}", f"{after['cpu_ms']:.2f}"]]


ZENOH_HEADER = ["n", "agent shares/tick, broadcast / per pair", "agent bytes/tick, broadcast", "per pair",
                "fleet bytes/tick, broadcast", "per pair", "agent process CPU ms/tick, broadcast", "per pair"]


def run(args: argparse.Namespace) -> int:
    (scale_path,) = resolve([args.scale], args.scenarios_dir)
    spec, variants = load(scale_path)
    rows, identical = [], True
    for n, scenario, source, _ in fleet_scenarios(spec.base, variants, args.sizes, args.duration, args.seed):
        runs = measure(scenario, args.repeats)
        rows += rows_of(n, source, runs)
        identical = identical and rows[-1][-1] == "yes"
        print(f"share-bench: n = {n}: " + ", ".join(f"{h} {v}" for h, v in zip(HEADER[1:], rows[-1][1:])), flush=True)
    zenoh = []
    with tempfile.TemporaryDirectory() as scratch:
        for n in args.zenoh_sizes:
            zenoh += zenoh_rows(n, over_zenoh(n, args.zenoh_duration, args.scenarios_dir, Path(scratch)))
            print(f"share-bench: n = {n} over Zenoh: " + ", ".join(
                f"{h} {v}" for h, v in zip(ZENOH_HEADER[1:], zenoh[-1][1:])), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "share_benchmark.md").write_text(render(rows, zenoh, args))
    print(f"share-bench: wrote {args.out / 'share_benchmark.md'}")
    if not identical:
        print("share-bench: the two formats' commands differ", flush=True)
    return 0 if identical else 1


HEADER = ["n", "start positions", "fleet bytes/tick, broadcast", "per pair", "agent bytes/tick, broadcast", "per pair",
          "agent messages/tick", "agent decode ms/tick, broadcast", "per pair", "decode per pair / broadcast",
          "agent rest of tick ms, broadcast", "per pair", "commands identical"]


def render(rows: list[list[object]], zenoh: list[list[object]], args: argparse.Namespace) -> str:
    return "\n".join([
        "# Shares: broadcast (format 1) against per pair (format 2)", "",
        f"Written by `{invocation(args)}`.", "",
        " ".join(__doc__.split("\n\n", 1)[1].split()), "",
        f"Each size: {args.duration:g} simulated s ({round(args.duration * 10) + 1} ticks), {args.repeats} runs "
        f"of each format, medians. CPU is thread time on a shared 2-core machine: compare the two formats of a "
        f"row, taken in the same run, not the rows of different pages.", "",
        markdown_table(HEADER, rows), "",
        "- bytes: the share payloads delivered to agents in a tick, all agents (fleet) and one (agent). Format 1 "
        "delivers each sender's one message, with its n - 1 pair estimates, to n - 1 agents; format 2 delivers "
        "to each agent one message per sender holding its own estimate only.",
        "- decode: one agent's callbacks on the shares of one tick (decoding and the input gate).",
        "- rest of tick: one agent's tick besides the core and its log: the shares delivered, the snapshot, the "
        "command, share and status built, checked and encoded (format 2 encodes the share's body once and "
        "joins each receiver's estimate to it).",
        "- commands identical: every command of every run of format 2 equals, bit for bit, those of every run "
        "of either format.", "",
        "## Over Zenoh", "",
        f"The fleets as processes in lockstep, {args.zenoh_duration:g} simulated s each, once per format. The "
        "bytes are the share payloads each agent's subscriptions were handed (its status's "
        "`share_bytes_received`), Zenoh's framing not counted; the fleet's is n times one agent's. The CPU is "
        "each agent process's, all its threads (Zenoh's too), per tick, the median agent.", "",
        markdown_table(ZENOH_HEADER, zenoh) if zenoh else "(not run: `--zenoh-sizes` empty)", "",
        "Machine:", "", *[f"- {line}" for line in machine()], ""])
