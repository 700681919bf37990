"""A mission's logs, read into memory: one `VesselLog` per agent file and, in simulation, the sim bridge's.

`load_run(paths)` takes a run folder (every `*.mcap` in it) or MCAP files. An agent's file is recognised by
its `vessel` metadata, the sim bridge's by its `/truth` topic. A file cut short (its process was killed) is
read up to its last complete chunk and marked `unfinished`; a file that is not an MCAP at all is an error
that names it, and so is a file whose log format version (its `usv-log-format` metadata) this reader does not
know. A file without that record was written before the version was recorded: it is read as version 1,
which has the same messages.
"""

from __future__ import annotations

import json
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from agent.runtime.mcap_log import FORMAT_RECORD, read_messages, read_metadata
from agent.shell.tick_log import log_topic

READS_FORMATS = ("1", "2")  # the log format versions this reader knows (agent/runtime/mcap_log.py writes them)
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

    def messages(self, topic: str) -> list[tuple[int, dict]]:
        return self.topics.get(topic, [])

    def last(self, topic: str) -> dict | None:
        found = self.topics.get(topic)
        return found[-1][1] if found else None


@dataclass
class VesselLog(Log):
    vessel: str = ""

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

    @property
    def has_truth(self) -> bool:
        return self.sim is not None and bool(self.sim.messages("/truth"))

    @property
    def unfinished(self) -> list[Path]:
        return [log.path for log in [*self.vessels.values(), self.sim] if log is not None and log.unfinished]


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
    vessel = run_metadata.get("vessel")
    if vessel is not None:
        return VesselLog(path, run_metadata, dict(topics), unfinished, version, vessel=vessel)
    return Log(path, run_metadata, dict(topics), unfinished, version)


def format_version(path: Path, metadata: dict[str, dict[str, str]]) -> str:
    """The file's log format version, or LogError if this reader does not know it."""
    record = metadata.get(FORMAT_RECORD)
    version = UNRECORDED_FORMAT if record is None else record.get("version", "(none)")
    if version not in READS_FORMATS:
        raise LogError(f"{path}: log format version {version}, which this usv-log cannot read "
                       f"(it reads version {', '.join(READS_FORMATS)})")
    return version


def load_run(paths: list[Path] | Path) -> RunLog:
    """Read a run folder or a list of MCAP files."""
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
    for path in files:
        log = read_log(path)
        if isinstance(log, VesselLog):
            if log.vessel in run.vessels:
                raise LogError(f"{path}: a second log of vessel {log.vessel} (the first is {run.vessels[log.vessel].path})")
            run.vessels[log.vessel] = log
        elif log.messages("/truth"):
            run.sim = log
    if not run.vessels and run.sim is None:
        raise LogError(f"{run.source}: neither an agent's log nor the sim bridge's")
    return run


def agent_radius(run: RunLog, default: float = 5.0) -> float:
    """r* as the agents were set up: from the first vessel whose log recorded its settings."""
    for vessel in sorted(run.vessels):
        try:
            return float(run.vessels[vessel].settings["agent"]["control"]["radius"])
        except (TypeError, KeyError, ValueError):
            continue    # a log without settings, or settings of another shape
    return default
