"""`usv-log`: post-mission analysis of MCAP logs (also `python -m mission_log`).

    usv-log summary RUN...            what the logs hold: counts, rates, gaps, refusals, overruns, health
    usv-log metrics RUN... [--truth sim|gnss] [--target-at LAT,LON] [--target-gnss ID]
                                      the paper's metrics with ground truth (the sim's, or a field trial's
                                      GNSS fixes), self-consistency without
    usv-log plot RUN... [--out DIR]   trajectories, errors, ranges and residuals as PNG files
    usv-log replay LOG --out FILE [--set key=value ...] [--params FILE] [--start SECONDS]
                                      a vessel's recorded inputs through the core again
    usv-log export --ros2 RUN... [--out DIR]
                                      the logs as a rosbag2 (MCAP) that `ros2 bag play` plays

RUN is a run folder (every *.mcap in it) or MCAP files; the parts of a rotated log (agent-1.mcap,
agent-1.part0001.mcap, ...) read as one log. Reports are Markdown on standard output, with times in seconds
from the mission's start; --json writes the figures as JSON too.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from agent.config import ConfigError, deep_merge, load_yaml
from agent.core.params import AgentParams
from mission_log.local_frame import MissingField
from mission_log.metrics import metrics_markdown, run_metrics
from mission_log.plots import plot_run
from mission_log.reader import LogError, load_run
from mission_log.replay import parse_assignments, replay
from mission_log.ros2_export import MissingExtra, default_out, export_ros2
from mission_log.summary import run_summary, summary_markdown


def _run_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", nargs="+", type=Path, help="a run folder, or MCAP files")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")


def _load(paths: list[Path]):
    run = load_run(paths if len(paths) > 1 else paths[0])
    for path in run.unfinished:
        print(f"usv-log: warning: {path} is unfinished (its process was killed, or a write failed?); read up to "
              "its last complete chunk", file=sys.stderr)
    for path, missing in run.missing_parts.items():
        print(f"usv-log: note: {path}: part(s) {', '.join(map(str, missing))} of this log are not among the files "
              "(deleted by its size bound, or not copied); read without them", file=sys.stderr)
    return run


def _write_json(path: Path | None, data: dict) -> None:
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data, indent=2))


def summary_command(args) -> int:
    result = run_summary(_load(args.run), args.window)
    print(summary_markdown(result), end="")
    _write_json(args.json, result)
    return 0


def metrics_command(args) -> int:
    run = _load(args.run)
    result = run_metrics(run, args.radius, args.truth, args.target_gnss, args.target_at)
    print(metrics_markdown(result, run.source), end="")
    _write_json(args.json, result)
    return 0


def latitude_longitude(text: str) -> tuple[float, float]:
    """`LAT,LON` in degrees (WGS 84), or an argparse error that says what is wrong."""
    try:
        lat, lon = (float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: want LAT,LON in degrees, e.g. 59.91,10.75") from None
    if not (abs(lat) <= 90 and abs(lon) <= 180):
        raise argparse.ArgumentTypeError(f"{text!r}: latitude within 90 and longitude within 180 degrees")
    return lat, lon


def plot_command(args) -> int:
    run = _load(args.run)
    out = args.out or (args.run[0] if args.run[0].is_dir() else args.run[0].parent) / "plots"
    for path in plot_run(run, out, args.radius):
        print(path)
    return 0


def default_replay_path(log: Path) -> Path:
    """`replays/<stem>.mcap` beside the log: a subfolder, so that the run folder's analysis does not read the
    replay as another vessel; numbered rather than overwriting an earlier replay."""
    folder = log.parent / "replays"
    candidate, n = folder / log.name, 1
    while candidate.exists():
        n += 1
        candidate = folder / f"{log.stem}-{n}{log.suffix}"
    return candidate


def replay_command(args) -> int:
    changes = {}
    if args.params is not None:
        # An AgentParams file, checked as one: only the keys it names change the recorded settings.
        changes = load_yaml(AgentParams, args.params).model_dump(mode="json", exclude_unset=True)
    changes = deep_merge(changes, parse_assignments(args.set))
    if args.start is not None and args.start < 0:
        raise ConfigError(f"--start {args.start}: must be zero or more seconds")
    result = replay(args.log, args.out or default_replay_path(args.log), changes, args.start)
    same = result.commands_identical == result.commands_compared and result.estimates_identical == result.ticks
    began = "the start" if result.resumed_at is None else f"the state saved at {result.resumed_at:.1f} s"
    print(f"usv-log replay: vessel {result.vessel}, {result.ticks} ticks from {began} -> {result.out}")
    print(f"  changes: {json.dumps(changes) if changes else 'none'}")
    print(f"  commands identical to the recorded ones: {result.commands_identical}/{result.commands_compared} "
          f"(largest difference: surge {result.max_surge_difference:.3g} m/s, yaw rate "
          f"{result.max_yaw_rate_difference:.3g} rad/s); estimates identical: {result.estimates_identical}/"
          f"{result.ticks}")
    if not changes and not same:
        print("  the replay with unchanged settings differs from the recording: report this", file=sys.stderr)
        return 1
    return 0


def export_command(args) -> int:
    run = _load(args.run)
    out = args.out or default_out(args.run[0])
    result = export_ros2(run, out)
    print(f"usv-log export: {sum(result.counts.values())} messages on {len(result.counts)} topics -> {result.out}")
    for topic in sorted(result.counts):
        print(f"  {topic}  {result.types[topic]}  {result.counts[topic]}")
    if result.partial is not None:
        print(f"usv-log export: partial: {result.partial} (written in the bag's custom_data, usv_partial)",
              file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="usv-log", description="Post-mission analysis of the fleet's MCAP logs.")
    commands = parser.add_subparsers(dest="command", required=True)
    summary = commands.add_parser("summary", help="counts, rates, gaps, refusals, overruns, estimator health")
    _run_arguments(summary)
    summary.add_argument("--window", type=float, default=10.0, help="seconds per row of the health table")
    summary.set_defaults(handler=summary_command)
    metrics = commands.add_parser("metrics", help="the paper's metrics (with truth) and self-consistency figures")
    _run_arguments(metrics)
    metrics.add_argument("--radius", type=float, default=None, help="r* (default: from the agents' settings)")
    metrics.add_argument("--truth", choices=("sim", "gnss"), default=None,
                         help="the ground truth: the sim bridge's, or the GNSS logs' (default: the sim's "
                              "when its log is there, else the GNSS logs')")
    metrics.add_argument("--target-at", type=latitude_longitude, default=None, metavar="LAT,LON",
                         help="with GNSS: the target's surveyed position (default: its tag's GNSS log)")
    metrics.add_argument("--target-gnss", default="target", metavar="ID",
                         help="with GNSS: the id of the target tag's GNSS log; every other is a vessel's")
    metrics.set_defaults(handler=metrics_command)
    plot = commands.add_parser("plot", help="PNG figures: trajectories, errors, ranges and residuals")
    plot.add_argument("run", nargs="+", type=Path, help="a run folder, or MCAP files")
    plot.add_argument("--out", type=Path, default=None, help="folder for the PNGs (default: RUN/plots)")
    plot.add_argument("--radius", type=float, default=None, help="r* (default: from the agents' settings)")
    plot.set_defaults(handler=plot_command)
    again = commands.add_parser("replay", help="a vessel's recorded inputs through the core, same or new settings")
    again.add_argument("log", type=Path, help="an agent's MCAP log")
    again.add_argument("--out", type=Path, default=None,
                       help="the new MCAP file (default: replays/<log's name> beside the log, never overwritten)")
    again.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="change one agent parameter, e.g. relative.estimator=mckf or "
                            "'relative.estimator={name: mckf, bandwidths: [9999,9999,1.5]}' (repeatable)")
    again.add_argument("--params", type=Path, default=None,
                       help="an AgentParams file (as configs/agent.yaml): the parameters it names change")
    again.add_argument("--start", type=float, default=None, metavar="SECONDS",
                       help="start from the last state the agent saved before this time (s after its first "
                            "tick) instead of the beginning")
    again.set_defaults(handler=replay_command)
    export = commands.add_parser("export", help="the logs in another format: --ros2, a rosbag2 for ROS 2's tools")
    export.add_argument("run", nargs="+", type=Path, help="a run folder, or MCAP files")
    form = export.add_mutually_exclusive_group(required=True)
    form.add_argument("--ros2", action="store_true",
                      help="a rosbag2 folder (MCAP storage, CDR): odometry, commands, estimates, TF and the truth "
                           "(needs the ros2 extra: pip install 'usv-circumnav[ros2]')")
    export.add_argument("--out", type=Path, default=None,
                        help="the bag's folder, which must not exist (default: ros2/ in the run folder, numbered "
                             "rather than overwriting)")
    export.set_defaults(handler=export_command)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.handler(args)
    except (LogError, ConfigError, MissingExtra, MissingField) as error:
        print(f"usv-log: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
