"""The agent's MCAP log over its run: one file per mission, each tick written, a failure to write counted.

The settings go in the file's metadata whole (with the logged inputs they are all `usv-log replay` needs).
After a sim restart the ticks go to a new file, `<name>-mission<n>.mcap` (at most MAX_MISSION_LOGS, so a
forged clock cannot fill the disk), so that each file replays on its own. What goes in per tick is
agent/shell/tick_log.py's; a value that cannot be written is counted (`errors`), never raised into the tick.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from agent.core.snapshot import state_to_json
from agent.core.state import VesselState
from agent.runtime.log_schema import CoreState
from agent.runtime.mcap_log import McapLog
from agent.shell.settings import NodeSettings
from agent.shell.startup import StartupError
from agent.shell.tick_log import TickLogger, log_topic

MAX_MISSION_LOGS = 20  # log files of one run at most (one per sim restart)


class Recorder:
    def __init__(self, vessel: str, settings: NodeSettings) -> None:
        self.vessel, self.settings = vessel, settings
        self.log: McapLog | None = None   # opened once the vessel id is known to be free (`open`)
        self.tick_log: TickLogger | None = None
        self.errors = 0
        self.mission = 1

    def _say(self, line: str) -> None:
        print(f"usv-agent {self.vessel}: {line}", file=sys.stderr)

    def open(self) -> None:
        """The MCAP log of this mission, if the settings name one; StartupError (one line) if it cannot be
        written. Opened only after the id check, so that an agent refused for a taken id never truncates the
        log of the agent that has it."""
        if not self.settings.log:
            if self.mission == 1:
                self._say("no MCAP log: the settings name none (log: FILE, e.g. agent-{vessel}-{start}.mcap, "
                          "records the mission for usv-log)")
            return
        start = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        path = Path(self.settings.log.replace("{vessel}", self.vessel).replace("{start}", start))
        metadata = {"vessel": self.vessel, "clock": self.settings.clock, "settings": self.settings.model_dump_json()}
        if self.mission > 1:
            path = path.with_name(f"{path.stem}-mission{self.mission}{path.suffix}")
            metadata["mission"] = str(self.mission)
        try:
            self.log = McapLog(path, metadata=metadata, rotation=self.settings.log_rotation, announce=self._say)
        except OSError as error:
            raise StartupError(f"cannot write its log {path}: {error.strerror or error}") from None
        self.tick_log = TickLogger(self.log, self.vessel, self.settings.agent.control.radius)
        if self.settings.snapshot_every:
            self.log.prepare(log_topic(self.vessel, "state"), CoreState)

    def next_mission(self, summary) -> None:
        """The simulation restarted: the log of the mission so far is finished (`summary()` written last) and
        the next one starts a new file, up to MAX_MISSION_LOGS; beyond, the missions go on in the last file."""
        self.mission += 1
        if self.log is not None and self.mission <= MAX_MISSION_LOGS:
            summary()
            self.close()
            self.log = None
            try:
                self.open()
            except StartupError as error:
                self.errors += 1
                self._say(f"no log for the new mission: {error}")
        elif self.log is not None and self.mission == MAX_MISSION_LOGS + 1:
            self._say(f"{MAX_MISSION_LOGS} restarts of the simulation: the next missions go on in {self.log.path.name}")

    def tick(self, stamp: int, inputs, output, command, status, wire, judged, state: VesselState,
             ticks: int) -> None:
        """One tick at `stamp` (ns), the mission commands `judged` in it, and every `snapshot_every` ticks the
        core's state after it (replay can start at the next one, agent/core/snapshot.py)."""
        if self.log is None:
            return
        try:
            self.tick_log.tick(stamp, inputs, output, command, status, wire)
            for order, ack, received in judged:
                self.tick_log.mission(stamp, order, ack, received)
            every = self.settings.snapshot_every
            if every and ticks % every == 0:
                self.log.log(log_topic(self.vessel, "state"), state_to_json(state), stamp, schema=CoreState)
        except Exception as error:  # noqa: BLE001  (a bad value must not stop the vessel's control)
            # A write error (a full disk) is not raised: the log counts it, says so and resumes by itself.
            self.errors += 1
            if self.errors == 1:
                self._say(f"logging failed: {type(error).__name__}: {error}")

    def error(self, stamp: int, kind: str, text: str, count: int, inputs) -> None:
        """A failed tick, with its inputs (TickLogger.error)."""
        if self.log is None:
            return
        try:
            self.tick_log.error(stamp, kind, text, count, inputs)
        except Exception:  # noqa: BLE001
            self.errors += 1

    def summary(self, stamp: int, **figures) -> None:
        """The run as a whole (TickLogger.summary); it must not stop a clean shutdown."""
        if self.log is None:
            return
        try:
            self.tick_log.summary(stamp, **figures)
        except Exception:  # noqa: BLE001
            self.errors += 1

    def counts(self) -> dict[str, int]:
        """For the status: the writes that failed, here and in the file (`McapLog.errors`); 1 while the log is
        suspended (its disk full), and the messages it dropped meanwhile."""
        log = self.log
        return {"log_errors": self.errors + (log.errors if log is not None else 0),
                "log_suspended": int(log is not None and log.suspended),
                "log_dropped": log.dropped if log is not None else 0}

    def close(self) -> None:
        """Finish the file (again: a no-op)."""
        if self.log is not None:
            self.log.close()
