"""`usv-log summary`: what a mission's logs hold and how the processes fared.

Per vessel: the span of its log, message counts, rates and gaps per topic, what its input gate refused, tick
overruns, the time its commands spent at each limit, its estimators' health in windows of time, and each pair's
observability (the share of ticks it was observable, when it first was, the spans it was not, and the last
eigenvalues of its relative path's spread; agent/core/observability.py). For the
sim bridge: ticks, missed commands, watchdog stops, command latency. Times are seconds from the mission's
start (mission_log.reader.mission_start_ns), on either clock; the start itself is given once, as a UTC time
on the wall clock. A log rotated into parts says how many were read and which are missing.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from agent.shell.tick_log import log_topic
from mission_log.reader import Log, RunLog, mission_start_ns

WALL_CLOCK_NS = 10**17   # log times past this (1973) are Unix times: the wall clock, not sim time

GAP_FACTOR = 2.5   # an interval this many times the topic's median interval is a gap


def topic_statistics(messages: list[tuple[int, dict]]) -> dict:
    """Count, mean rate, and gaps (intervals over GAP_FACTOR x the median) of one topic's log times."""
    stamps = np.array([t for t, _ in messages], dtype=np.int64)
    result = {"messages": int(stamps.size), "rate_hz": None, "gaps": 0, "largest_gap_s": None}
    if stamps.size >= 2:
        intervals = np.diff(np.sort(stamps)) * 1e-9
        span = (stamps.max() - stamps.min()) * 1e-9
        result["rate_hz"] = float((stamps.size - 1) / span) if span > 0 else None
        median = float(np.median(intervals))
        result["largest_gap_s"] = float(intervals.max())
        result["gaps"] = int(np.sum(intervals > GAP_FACTOR * median)) if median > 0 else 0
    return result


def _span(log: Log, origin_ns: int = 0) -> tuple[float, float] | None:
    """First and last log time of `log`, in seconds from `origin_ns`."""
    stamps = [t for messages in log.topics.values() for t, _ in messages]
    return ((min(stamps) - origin_ns) * 1e-9, (max(stamps) - origin_ns) * 1e-9) if stamps else None


def health_windows(estimates: list[tuple[int, dict]], window: float, origin_ns: int = 0) -> list[dict]:
    """The inter-vessel filters' and the target filter's work in consecutive windows of `window` seconds,
    from the first estimate on; the windows' times are seconds from `origin_ns`."""
    if not estimates:
        return []
    # Integers first: an epoch time in ns does not fit a float's 53 bits.
    start, end = (estimates[0][0] - origin_ns) * 1e-9, (estimates[-1][0] - origin_ns) * 1e-9
    last = max(1, math.ceil((end - start) / window - 1e-9)) - 1   # a tick on the last boundary closes the last window
    rows: dict[int, dict] = {}
    for t, m in estimates:
        k = min(int(((t - origin_ns) * 1e-9 - start) // window), last)
        row = rows.setdefault(k, {"from_s": start + k * window, "to_s": start + (k + 1) * window, "ticks": 0,
                                  "relative_updates": 0, "relative_refused": 0, "iterations": [], "weights": [],
                                  "nis": [], "bearing_updates": 0, "bearing_refused": 0, "neighbours": 0})
        row["ticks"] += 1
        row["neighbours"] = max(row["neighbours"], len(m["neighbours"]))
        for neighbour in m["neighbours"].values():
            for o in neighbour.get("outcomes", []):
                if not o["accepted"]:
                    row["relative_refused"] += 1
                    continue
                row["relative_updates"] += 1
                row["iterations"].append(o["iterations"])
                row["weights"].append(o["weight"])
                if o["innovation_variance"] > 0:
                    row["nis"].append(o["innovation"] ** 2 / o["innovation_variance"])
        bearing = m.get("bearing")
        if bearing is not None:
            row["bearing_updates" if bearing["accepted"] else "bearing_refused"] += 1
    result = []
    for k in sorted(rows):
        row = rows[k]
        for name, values in (("mean_iterations", row.pop("iterations")), ("mean_weight", row.pop("weights")),
                             ("mean_nis", row.pop("nis"))):
            row[name] = float(np.mean(values)) if values else None
        result.append(row)
    return result


def pair_observability(estimates: list[tuple[int, dict]], origin_ns: int = 0) -> dict[str, dict]:
    """Per neighbour: its pair's observability over the log (format 5 on; a neighbour whose estimates do not
    say is left out). `not_observable` lists the stretches it was not, [from s, to s, verdict], each to the
    next tick with another verdict (or to its last tick)."""
    pairs: dict[str, dict] = {}
    for t, m in estimates:
        time = (t - origin_ns) * 1e-9
        for j, n in m["neighbours"].items():
            verdict = n.get("observability")
            if verdict is None:
                continue
            pair = pairs.setdefault(j, {"ticks": 0, "observable_ticks": 0, "first_observable_s": None,
                                        "spans": [], "last": None, "last_s": None})
            pair["ticks"] += 1
            open_span = pair["spans"][-1] if pair["spans"] and pair["spans"][-1][1] is None else None
            if open_span is not None and verdict != open_span[2]:
                open_span[1] = time
            if verdict == "observable":
                pair["observable_ticks"] += 1
                if pair["first_observable_s"] is None:
                    pair["first_observable_s"] = time
            elif open_span is None or verdict != open_span[2]:
                pair["spans"].append([time, None, verdict])
            pair["last"], pair["last_s"] = n, time
    result = {}
    for j, pair in sorted(pairs.items()):
        last = pair["last"]
        spans = [[start, pair["last_s"] if end is None else end, verdict] for start, end, verdict in pair["spans"]]
        result[j] = {"ticks": pair["ticks"], "observable_fraction": pair["observable_ticks"] / pair["ticks"],
                     "first_observable_s": pair["first_observable_s"], "not_observable": spans,
                     "final": last["observability"], "final_excitation": list(last["excitation"])}
    return result


def _parts(log: Log) -> dict:
    return {"parts": [str(path) for path in log.parts], "missing_parts": list(log.missing_parts),
            "sessions": [str(path) for path in getattr(log, "sessions", [])]}


def vessel_summary(log, window: float, origin_ns: int = 0) -> dict:
    span = _span(log, origin_ns)
    status = log.last(log_topic(log.vessel, "status")) or {}
    final = log.last(log_topic(log.vessel, "summary")) or {}
    estimates = log.topic("estimates")
    health = status.get("health", {})
    refused = final.get("refused") or {k[len("rejected_"):]: v for k, v in health.items() if k.startswith("rejected_")}
    ticks = len(log.topic("inputs"))
    dt = float(np.median(np.diff([t for t, _ in log.topic("inputs")]))) * 1e-9 if ticks > 1 else 0.0
    saturation: dict[str, float] = {}
    for _, m in estimates:
        for name, flag in m.get("saturated", {}).items():
            saturation[name] = saturation.get(name, 0.0) + (dt if flag else 0.0)
    return {
        "file": str(log.path), "unfinished": log.unfinished, **_parts(log),
        "from_s": None if span is None else span[0], "to_s": None if span is None else span[1],
        "duration_s": None if span is None else span[1] - span[0],
        "ticks": ticks, "ticks_with_estimates": len(estimates),
        "topics": {topic: topic_statistics(messages) for topic, messages in sorted(log.topics.items())},
        "refused": dict(sorted(refused.items())),
        "overruns": final.get("overruns", health.get("overruns", 0)),
        "log_errors": health.get("log_errors", 0),
        "core_health": {k: v for k, v in health.items() if not k.startswith("rejected_")
                        and k not in ("overruns", "log_errors")},
        "saturation_s": saturation,
        "cpu_ms_per_tick": 1e3 * final["cpu_seconds"] / final["ticks"] if final.get("ticks") else None,
        "reaction_ms": final.get("reaction_ms"),
        "health_over_time": health_windows(estimates, window, origin_ns),
        "observability": pair_observability(estimates, origin_ns),
        "mission": mission_commands(log.topic("mission"), origin_ns),
    }


def mission_commands(records: list[tuple[int, dict]], origin_ns: int = 0) -> list[dict]:
    """Every mission command the vessel judged (its `mission` topic), in log order: when (s from the
    origin), who sent it, what it said, and whether it was applied or why not."""
    found = []
    for stamp, record in records:
        ack, command = record["ack"], record.get("command") or {}
        values = {k: command[k] for k in ("radius", "yaw_rate", "direction") if command.get(k) is not None}
        found.append({"time_s": (stamp - origin_ns) * 1e-9, "sender": ack["sender"], "seq": ack["seq"],
                      "command": ack["command"], "values": values, "applied": ack["applied"],
                      "reason": ack["reason"]})
    return found


def sim_summary(log: Log) -> dict:
    span = _span(log)
    final = log.last("/bridge/summary") or {}
    latencies = [v for _, m in log.messages("/bridge/command_latency") for v in m["milliseconds"].values()]
    return {
        "file": str(log.path), "unfinished": log.unfinished, **_parts(log),
        "duration_s": None if span is None else span[1] - span[0],
        "ticks": final.get("ticks", len(log.messages("/truth"))),
        "missed_commands": final.get("missed_commands"), "watchdog_stops": final.get("watchdog_stops"),
        "startup_missing": final.get("startup_missing", []),
        "refused": final.get("refused"),
        "command_latency_ms": None if not latencies else {
            "p50": float(np.percentile(latencies, 50)), "p99": float(np.percentile(latencies, 99))},
        "topics": {topic: topic_statistics(messages) for topic, messages in sorted(log.topics.items())},
    }


def run_summary(run: RunLog, window: float = 10.0) -> dict:
    origin = mission_start_ns(run)
    return {"source": run.source, "start_ns": origin, "clock": "wall" if origin >= WALL_CLOCK_NS else "sim",
            "vessels": {v: vessel_summary(log, window, origin) for v, log in sorted(run.vessels.items())},
            "sim": None if run.sim is None else sim_summary(run.sim)}


def _start_line(summary: dict) -> str:
    if summary.get("clock") == "wall":
        when = datetime.fromtimestamp(summary["start_ns"] // 10**9, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
        return f"Times are seconds from the mission's start, {when} (wall clock)."
    return f"Times are seconds of sim time from the mission's start ({summary.get('start_ns', 0) * 1e-9:.1f} s)."


def _missing(parts: list[int]) -> str:
    """[0, 1, 2, 5] -> '0-2, 5'."""
    runs: list[list[int]] = []
    for n in parts:
        if runs and n == runs[-1][-1] + 1:
            runs[-1].append(n)
        else:
            runs.append([n])
    return ", ".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in runs)


def _fmt(value, digits: int = 2) -> str:
    if value is None:
        return "–"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _topic_table(topics: dict) -> list[str]:
    lines = ["| topic | messages | rate (Hz) | gaps | largest gap (s) |", "|---|---|---|---|---|"]
    for topic, s in topics.items():
        lines.append(f"| `{topic}` | {s['messages']} | {_fmt(s['rate_hz'], 1)} | {s['gaps']} | "
                     f"{_fmt(s['largest_gap_s'], 2)} |")
    return lines


SPANS_SHOWN = 4   # not-observable spans listed per pair; the rest are counted


def _observability_table(pairs: dict[str, dict]) -> list[str]:
    lines = ["Pair observability (the relative path's spread over the window, docs/estimation.md):", "",
             ("| neighbour | observable (% of ticks) | first observable (s) | last verdict | last λ_min, λ_max (m²) | "
              "not observable (s) |"), "|---|---|---|---|---|---|"]
    for j, p in pairs.items():
        spans = [f"{start:.1f}–{end:.1f} {verdict}" for start, end, verdict in p["not_observable"][:SPANS_SHOWN]]
        more = len(p["not_observable"]) - SPANS_SHOWN
        if more > 0:
            spans.append(f"and {more} more")
        low, high = p["final_excitation"]
        lines.append(f"| {j} | {100 * p['observable_fraction']:.0f} | {_fmt(p['first_observable_s'], 1)} | "
                     f"{p['final']} | {low:.2f}, {high:.2f} | {', '.join(spans) or 'none'} |")
    return lines + [""]


def _mission_table(vessels: dict) -> list[str]:
    """Every mission command the fleet received, once per command: who applied it and who refused it, why."""
    commands: dict[tuple, dict] = {}
    for vessel, s in vessels.items():
        for c in s.get("mission", []):
            entry = commands.setdefault((c["sender"], c["seq"], c["command"]), {**c, "applied_by": [], "refused": {}})
            entry["time_s"] = min(entry["time_s"], c["time_s"])
            if c["applied"]:
                entry["applied_by"].append(vessel)
            else:
                entry["refused"].setdefault(c["reason"], []).append(vessel)
    if not commands:
        return []
    lines = ["## Mission commands", "", "| time (s) | sender | seq | command | applied by | refused by |",
             "|---|---|---|---|---|---|"]
    for c in sorted(commands.values(), key=lambda c: c["time_s"]):
        what = c["command"] + "".join(f" {k}={v:g}" if isinstance(v, float) else f" {k}={v}"
                                      for k, v in c["values"].items())
        lines.append(f"| {c['time_s']:.1f} | {c['sender']} | {c['seq']} | {what} | "
                     f"{', '.join(c['applied_by']) or 'none'} | "
                     + ("; ".join(f"{', '.join(who)} ({why})" for why, who in c["refused"].items()) or "none") + " |")
    return [*lines, ""]


def summary_markdown(summary: dict) -> str:
    lines = [f"# Summary of {summary['source']}", "", _start_line(summary), ""]
    vessels = summary["vessels"]
    if vessels:
        lines += [("| vessel | from (s) | to (s) | ticks | with estimates | refused inputs | overruns | "
                  "CPU per tick (ms) | reaction p50 / p99 (ms) | log |"), "|---|---|---|---|---|---|---|---|---|---|"]
        for v, s in vessels.items():
            refused = ", ".join(f"{k} {n}" for k, n in s["refused"].items()) or "none"
            reaction = s.get("reaction_ms")   # logs before the agent timed its reactions have none
            reacted = "-" if not reaction else f"{_fmt(reaction['p50'])} / {_fmt(reaction['p99'])}"
            lines.append(f"| {v} | {_fmt(s['from_s'], 1)} | {_fmt(s['to_s'], 1)} | {s['ticks']} | "
                         f"{s['ticks_with_estimates']} | {refused} | {s['overruns']} | {_fmt(s['cpu_ms_per_tick'])} | "
                         f"{reacted} | {'**unfinished**' if s['unfinished'] else 'complete'} |")
        lines.append("")
    sim = summary["sim"]
    if sim is not None:
        latency = sim["command_latency_ms"]
        lines += ["## Sim bridge", "",
                  f"{sim['ticks']} ticks, {_fmt(sim['missed_commands'])} missed commands, "
                  f"{_fmt(sim['watchdog_stops'])} watchdog stops, {_fmt(sim['refused'])} refused messages"
                  + ("" if latency is None else
                     f"; sensor-to-command latency p50 {latency['p50']:.2f} ms, p99 {latency['p99']:.2f} ms")
                  + ("" if not sim["startup_missing"] else
                     f". **No agent came for vessel(s) {', '.join(sim['startup_missing'])}**"), ""]
    lines += _mission_table(vessels)
    for v, s in vessels.items():
        lines += [f"## Vessel {v}", ""]
        if s["unfinished"]:
            lines += [("The log is unfinished (the process was killed, or a write failed): read up to its last "
                      "complete chunk."), ""]
        if len(s.get("sessions", [])) > 1:
            lines += [f"The agent ran {len(s['sessions'])} times (restarted), one log each, read in time order: "
                      + ", ".join(f"`{Path(path).name}`" for path in s["sessions"]) + ".", ""]
        # Each run's log is a file of its own: more files than runs means a log was rotated.
        if len(s.get("parts", [])) > max(1, len(s.get("sessions", []))) or s.get("missing_parts"):
            lines += [f"The log was rotated: {len(s['parts'])} part(s) read"
                      + (f"; part(s) {_missing(s['missing_parts'])} missing (deleted by the log's size bound, or "
                         "not copied): their messages are not in these figures" if s["missing_parts"] else "")
                      + ".", ""]
        lines += _topic_table(s["topics"]) + [""]
        if s["saturation_s"]:
            lines += ["Time at a limit: " + ", ".join(f"{k} {t:.1f} s" for k, t in s["saturation_s"].items()), ""]
        counters = {k: n for k, n in s["core_health"].items() if n}
        lines += ["Core health counters: " + (", ".join(f"{k} {n}" for k, n in counters.items()) or "all zero"), ""]
        if s["health_over_time"]:
            lines += [("| from (s) | to (s) | neighbours | range updates | refused | mean MCKF iterations | "
                      "mean weight | mean NIS | bearing updates | bearings refused |"),
                      "|---|---|---|---|---|---|---|---|---|---|"]
            for row in s["health_over_time"]:
                lines.append(f"| {row['from_s']:.0f} | {row['to_s']:.0f} | {row['neighbours']} | "
                             f"{row['relative_updates']} | {row['relative_refused']} | {_fmt(row['mean_iterations'])} | "
                             f"{_fmt(row['mean_weight'])} | {_fmt(row['mean_nis'])} | {row['bearing_updates']} | "
                             f"{row['bearing_refused']} |")
            lines.append("")
        if s.get("observability"):
            lines += _observability_table(s["observability"])
    return "\n".join(lines) + "\n"
