"""A mission's logs, read into memory: one `VesselLog` per agent and, in simulation, the sim bridge's.

`load_run(paths)` takes a run folder (every `*.mcap` in it) or MCAP files. An agent's file is recognised by
its `vessel` metadata, the sim bridge's by its `/truth` topic, a GNSS log (the driver bridge's `gnss.log`:
one vessel's or the target's fixes) by its `usv/<id>/truth/gnss` topic. A file cut short (its process was killed) is
read up to its last complete chunk and marked `unfinished`; a file that is not an MCAP at all is an error
that names it, and so is a file whose log format version (its `usv-log-format` metadata) this reader does not
know. A file without that record was written before the version was recorded: it is read as version 1,
which has the same messages.

**Rotated logs.** A process whose log rotates (agent/runtime/mcap_log.py, `LogRotation`) writes a set of
parts, `agent-1.mcap`, `agent-1.part0001.mcap`, ..., each with a `usv-log-part` record naming its set and
its place. The parts of one set among the files given are joined, in part order, into one log of that
process. A part that is not there (deleted by the log's size bound, or not copied) is fine: the log says
which (`missing_parts`), and its messages are simply absent. `read_log_set(path)` reads a file together
with the other parts of its set in the same folder.

**Times.** Log times are the tick's time: sim time in simulation, Unix epoch on the wall clock. Reports give
times in seconds from the mission's start, `mission_start_ns(run)`.
"""

from __future__ import annotations

import json
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

import numpy as np

from agent.contract import FLEET_PREFIX, GNSS_TRUTH_TOPIC
from agent.runtime.mcap_log import FORMAT_RECORD, PART_RECORD, read_messages, read_metadata
from agent.shell.tick_log import log_topic

READS_FORMATS = ("1", "2", "3", "4", "5")  # the log format versions this reader knows (agent/runtime/mcap_log.py writes them)
UNRECORDED_FORMAT = "1"     # what a file from before the version was recorded holds


class LogError(ValueError):
    """A path that holds no readable log; the message says which and why."""


@dataclass
class Log:
    path: Path
    metadata: dict[str, str]
    topics: dict[str, list[tuple[int, dict]]]     # topic -> [(log time ns, message)] in file order
    unfinished: bool = False
    format_version: str = UNRECORDED_FORMAT
    parts: list[Path] = field(default_factory=list)       # the files read, in part order
    missing_parts: list[int] = field(default_factory=list)  # parts of the set before or between those read, absent
    set_id: str | None = None                             # the set of parts this log belongs to (None: unrecorded)
    part: int = 0                                         # the (first) part read

    def messages(self, topic: str) -> list[tuple[int, dict]]:
        return self.topics.get(topic, [])

    def last(self, topic: str) -> dict | None:
        found = self.topics.get(topic)
        return found[-1][1] if found else None


@dataclass
class VesselLog(Log):
    vessel: str = ""
    sessions: list[Path] = field(default_factory=list)   # the first file of each run of the agent, in time order

    @property
    def settings(self) -> dict | None:
        """The agent's node settings as it ran (None in a log written before they were recorded)."""
        text = self.metadata.get("settings")
        return None if text is None else json.loads(text)

    def topic(self, name: str) -> list[tuple[int, dict]]:
        """Messages of this vessel's topic `name` (inputs, estimates, summary, cmd, status, tf, scene)."""
        return self.messages(log_topic(self.vessel, name))


@dataclass
class RunLog:
    source: str
    vessels: dict[str, VesselLog] = field(default_factory=dict)
    sim: Log | None = None
    gnss: dict[str, Log] = field(default_factory=dict)   # vessel or target id -> its GNSS fixes (field trials)

    @property
    def has_truth(self) -> bool:
        return self.sim is not None and bool(self.sim.messages("/truth"))

    @property
    def logs(self) -> list[Log]:
        return [log for log in [*self.vessels.values(), self.sim, *self.gnss.values()] if log is not None]

    @property
    def unfinished(self) -> list[Path]:
        return [log.path for log in self.logs if log.unfinished]

    @property
    def missing_parts(self) -> dict[Path, list[int]]:
        """First file read -> the parts of its set that are not among the files (deleted by the size bound)."""
        return {log.path: log.missing_parts for log in self.logs if log.missing_parts}


def read_log(path: Path) -> Log:
    path = Path(path)
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    with path.open("rb") as handle:
        if handle.read(8) != b"\x89MCAP0\r\n":
            raise LogError(f"{path}: not an MCAP file")
    metadata = read_metadata(path)
    version = format_version(path, metadata)
    topics: dict[str, list[tuple[int, dict]]] = defaultdict(list)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for topic, stamp, message in read_messages(path):
            topics[topic].append((stamp, message))
    unfinished = any("unfinished MCAP" in str(w.message) for w in caught)
    run_metadata = metadata.get("run", {})
    part_record = metadata.get(PART_RECORD, {})
    try:
        part = int(part_record.get("part", 0))
    except ValueError:
        raise LogError(f"{path}: bad {PART_RECORD} record {part_record}") from None
    known = {"parts": [path], "set_id": part_record.get("set"), "part": part,
             "missing_parts": list(range(part))}   # read alone, the parts before this one are not here
    vessel = run_metadata.get("vessel")
    if vessel is not None:
        return VesselLog(path, run_metadata, dict(topics), unfinished, version, vessel=vessel, **known)
    return Log(path, run_metadata, dict(topics), unfinished, version, **known)


def join_parts(logs: list[Log]) -> Log:
    """The parts of one set (any order) as one log: messages in part order, unfinished if any part is, and
    the parts not among them (before the last one read) in `missing_parts`."""
    logs = sorted(logs, key=lambda log: log.part)
    first = logs[0]
    numbers = [log.part for log in logs]
    if len(set(numbers)) != len(numbers):
        twice = next(n for n in numbers if numbers.count(n) > 1)
        raise LogError(f"part {twice} of the log {first.path} given twice: "
                       f"{', '.join(str(log.path) for log in logs if log.part == twice)}")
    if len(logs) == 1:
        return first
    versions = {log.format_version for log in logs}
    if len(versions) > 1:
        raise LogError(f"{first.path}: its parts have different log format versions ({', '.join(sorted(versions))})")
    topics = _concatenated(logs)
    known = {"parts": [log.path for log in logs], "set_id": first.set_id, "part": first.part,
             "missing_parts": sorted(set(range(numbers[-1] + 1)) - set(numbers))}
    unfinished = any(log.unfinished for log in logs)
    if isinstance(first, VesselLog):
        return VesselLog(first.path, first.metadata, topics, unfinished, first.format_version,
                         vessel=first.vessel, **known)
    return Log(first.path, first.metadata, topics, unfinished, first.format_version, **known)


def _concatenated(logs: list[Log]) -> dict[str, list[tuple[int, dict]]]:
    """Each topic's messages of `logs`, one log after the other."""
    topics: dict[str, list[tuple[int, dict]]] = defaultdict(list)
    for log in logs:
        for topic, messages in log.topics.items():
            topics[topic].extend(messages)
    return dict(topics)


def _span(log: Log) -> tuple[int, int] | None:
    times = [t for messages in log.topics.values() for t, _ in messages]
    return (min(times), max(times)) if times else None


def gnss_owner(log: Log) -> str | None:
    """The id whose GNSS fixes `log` holds (its `usv/<id>/truth/gnss` topic), or None."""
    head, tail = f"{FLEET_PREFIX}/", f"/{GNSS_TRUTH_TOPIC}"
    owners = {t[len(head):-len(tail)] for t, found in log.topics.items()
              if found and t.startswith(head) and t.endswith(tail)}
    if len(owners) > 1:
        raise LogError(f"{log.path}: the GNSS fixes of several vessels in one log ({', '.join(sorted(owners))})")
    return owners.pop() if owners else None


def join_sessions(logs: list[VesselLog]) -> VesselLog:
    """The logs of one vessel's agent run after run (restarted by systemd or the launcher: each run writes
    its own log) as one log in time order, its files in `parts`. Logs that overlap in time are two agents
    with one vessel id at once, or one log given twice: an error that names both."""
    if len(logs) == 1:
        return logs[0]
    spans = {id(log): _span(log) for log in logs}
    logs = sorted(logs, key=lambda log: (spans[id(log)] or (0, 0))[0])
    for before, after in pairwise(logs):
        first, second = spans[id(before)], spans[id(after)]
        if first is not None and second is not None and second[0] <= first[1]:
            raise LogError(f"{after.path}: a second log of vessel {after.vessel} that overlaps in time with "
                           f"{before.path} (two agents with one id, or one log given twice)")
    versions = {log.format_version for log in logs}
    if len(versions) > 1:
        raise LogError(f"{logs[0].path}: the logs of vessel {logs[0].vessel} have different log format versions "
                       f"({', '.join(sorted(versions))})")
    first = logs[0]
    return VesselLog(first.path, first.metadata, _concatenated(logs), any(log.unfinished for log in logs),
                     first.format_version, parts=[path for log in logs for path in (log.parts or [log.path])],
                     missing_parts=first.missing_parts, set_id=first.set_id, part=first.part, vessel=first.vessel,
                     sessions=[log.path for log in logs])


def set_files(path: Path) -> list[Path]:
    """The files in `path`'s folder that may be parts of the same set: the set's first file and its
    `.partNNNN` files (by name; the `usv-log-part` records decide)."""
    path = Path(path)
    first = read_metadata(path).get(PART_RECORD, {}).get("first", path.name)
    stem, suffix = Path(first).stem, Path(first).suffix
    found = {path, *path.parent.glob(f"{glob_escape(stem)}.part[0-9]*{glob_escape(suffix)}")}
    if (path.parent / first).is_file():
        found.add(path.parent / first)
    return sorted(found)


def glob_escape(text: str) -> str:
    return "".join(f"[{c}]" if c in "*?[" else c for c in text)


def read_log_set(path: Path) -> Log:
    """`path` together with the other parts of its set in the same folder, as one log."""
    own = read_log(path)
    if own.set_id is None:
        return own
    logs = [own]
    for other in set_files(path):
        if other != Path(path):
            log = read_log(other)
            if log.set_id == own.set_id:
                logs.append(log)
    return join_parts(logs)


def format_version(path: Path, metadata: dict[str, dict[str, str]]) -> str:
    """The file's log format version, or LogError if this reader does not know it."""
    record = metadata.get(FORMAT_RECORD)
    version = UNRECORDED_FORMAT if record is None else record.get("version", "(none)")
    if version not in READS_FORMATS:
        raise LogError(f"{path}: log format version {version}, which this usv-log cannot read "
                       f"(it reads version {', '.join(READS_FORMATS)})")
    return version


def load_run(paths: list[Path] | Path) -> RunLog:
    """Read a run folder or a list of MCAP files; the parts of a rotated log are joined into one log."""
    paths = [Path(p) for p in (paths if isinstance(paths, list) else [paths])]
    files: list[Path] = []
    for path in paths:
        if path.is_dir():
            found = sorted(path.glob("*.mcap"))
            if not found:
                raise LogError(f"{path}: no .mcap files in this folder")
            files += found
        else:
            files.append(path)
    if not files:
        raise LogError("no log given")
    run = RunLog(source=", ".join(str(p) for p in paths))
    sets: dict[object, list[Log]] = {}
    for path in dict.fromkeys(files):   # a file named twice (a folder and a file in it) is read once
        log = read_log(path)
        sets.setdefault(log.set_id or path, []).append(log)
    sessions: dict[str, list[VesselLog]] = defaultdict(list)
    for parts in sets.values():
        log = join_parts(parts)
        if isinstance(log, VesselLog):
            sessions[log.vessel].append(log)
        elif log.messages("/truth"):
            run.sim = log
        elif (owner := gnss_owner(log)) is not None:
            earlier = run.gnss.get(owner)   # a restarted driver's logs: one track, sorted by time when read
            run.gnss[owner] = log if earlier is None else Log(earlier.path, earlier.metadata,
                                                               _concatenated([earlier, log]),
                                                               earlier.unfinished or log.unfinished,
                                                               earlier.format_version,
                                                               parts=[*earlier.parts, *log.parts])
    for vessel, logs in sessions.items():
        run.vessels[vessel] = join_sessions(logs)
    if not run.vessels and run.sim is None and not run.gnss:
        raise LogError(f"{run.source}: neither an agent's log, the sim bridge's nor a GNSS log")
    return run


def mission_start_ns(run: RunLog) -> int:
    """The mission's time zero (log time, ns). In the sim bridge's sea mode, its epoch (`/bridge/sea`);
    otherwise the first tick at which any agent had its odometry, or the sim bridge's first truth,
    whichever is earliest (an agent that ticks before its sensors come commands STOP: that wait is not the
    mission); failing those, the earliest message of any log. 0 in simulation; a Unix time on the wall clock."""
    if run.sim is not None and run.sim.messages("/bridge/sea"):
        return int(run.sim.messages("/bridge/sea")[0][1]["epoch_ns"])
    firsts = [min(t for t, data in log.topic("inputs") if data.get("odometry") is not None)
              for log in run.vessels.values()
              if any(data.get("odometry") is not None for _, data in log.topic("inputs"))]
    if run.sim is not None and run.sim.messages("/truth"):
        firsts.append(min(t for t, _ in run.sim.messages("/truth")))
    if not firsts:
        firsts = [t for log in run.logs for messages in log.topics.values() for t, _ in messages[:1]]
    return min(firsts, default=0)


@dataclass(frozen=True)
class RadiusSchedule:
    """r* of each vessel over time, as its agent steered to it (the `radius` of its status each tick: the
    configured circle, then what mission `set`s made of it). `None` for a vessel without statuses."""

    initial: float                                          # r* as the agents were set up
    vessels: dict[str, tuple[np.ndarray, np.ndarray]]       # vessel -> (log time ns, r* from that time on)

    def at(self, vessel: str, t_ns: np.ndarray) -> np.ndarray:
        """r* of `vessel` at log times `t_ns`: the value of its latest status at or before each time (the
        first one before its first status, the configured one without any)."""
        times = np.asarray(t_ns)
        if vessel not in self.vessels:
            return np.full(times.shape, self.initial)
        stamps, radii = self.vessels[vessel]
        return radii[np.clip(np.searchsorted(stamps, times, side="right") - 1, 0, len(radii) - 1)]

    def changes(self, start_ns: int = 0) -> list[tuple[float, str, float]]:
        """(seconds from `start_ns`, vessel, new r*) at every change of a vessel's r*, in time order; a run of
        ticks on the way to a new circle (the agent moves r* at a bounded rate) counts once, at its end."""
        found = []
        for vessel, (stamps, radii) in self.vessels.items():
            for k in np.flatnonzero(np.diff(radii) != 0) + 1:      # r* took a new value at status k
                if k + 1 == len(radii) or radii[k + 1] == radii[k]:   # and stays there: a jump, or a ramp's end
                    found.append(((int(stamps[k]) - start_ns) * 1e-9, vessel, float(radii[k])))
        return sorted(found)


def radius_schedule(run: RunLog, default: float = 5.0) -> RadiusSchedule:
    """Each vessel's r* over time from its statuses (RadiusSchedule)."""
    vessels = {}
    for vessel, log in run.vessels.items():
        pairs = [(t, float(m["radius"])) for t, m in log.topic("status") if m.get("radius") is not None]
        if pairs:
            stamps, radii = zip(*pairs)
            vessels[vessel] = (np.array(stamps, dtype=np.int64), np.array(radii))
    return RadiusSchedule(agent_radius(run, default), vessels)


def agent_radius(run: RunLog, default: float = 5.0) -> float:
    """r* as the agents were set up: from the first vessel whose log recorded its settings."""
    for vessel in sorted(run.vessels):
        try:
            return float(run.vessels[vessel].settings["agent"]["control"]["radius"])
        except (TypeError, KeyError, ValueError):
            continue    # a log without settings, or settings of another shape
    return default
