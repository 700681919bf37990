"""The agent's error policy: a failed tick commands STOP, is counted and told, and a run of them rebuilds the core.

- Any exception in a tick: counted (`TickFailures.total`), told on stderr and logged on `/<id>/errors` with the
  tick's inputs, the first of each kind (`error_kind`: type and place) and then at most one every
  `ERROR_REPEAT` s; the tick commands STOP. The core's state is kept (one bad tick usually leaves it usable);
  after `rebuild_after` failed ticks in a row `failed` says to rebuild it with no initial estimates (the
  deployment's are stale by then), as a vessel joining late starts.
- A command that is not finite or beyond the controller's limits (U_v, U_omega_c + |omega*|) fails the tick
  the same way (`check_command`): STOP goes out instead.
"""

from __future__ import annotations

import math
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

from agent.contract import seconds
from agent.core.params import ControlParams
from agent.core.records import Command

ERROR_REPEAT = 10.0    # s: a kind of tick error already told is told again at most this often
MAX_ERROR_KINDS = 64   # kinds of tick error remembered (each a place in the code; more is a storm)
LIMIT_SLACK = 1e-9     # relative: a command this far beyond a limit is rounding, not a fault


class CommandOutOfLimits(ValueError):
    """The core's command is not finite or beyond the controller's saturation limits."""


def command_limits(control: ControlParams) -> tuple[float, float]:
    """U_v and U_omega_c + |omega*| of the parameters ticking now (a mission `set` changes omega*)."""
    return control.max_speed, control.max_correction_yaw_rate + abs(control.yaw_rate)


def check_command(command: Command, control: ControlParams) -> None:
    """CommandOutOfLimits unless the command is finite and within `command_limits` (formation.py's
    `surge_and_yaw_rate` never gives more; this is the shell's own guard on what goes to the thrusters)."""
    max_surge, max_yaw_rate = command_limits(control)
    surge, yaw_rate = float(command.surge), float(command.yaw_rate)
    if not (math.isfinite(surge) and math.isfinite(yaw_rate)
            and abs(surge) <= max_surge * (1 + LIMIT_SLACK) and abs(yaw_rate) <= max_yaw_rate * (1 + LIMIT_SLACK)):
        raise CommandOutOfLimits(f"command ({surge!r} m/s, {yaw_rate!r} rad/s) beyond "
                                 f"({max_surge:g} m/s, {max_yaw_rate:g} rad/s)")


def error_kind(error: BaseException) -> str:
    """An exception's kind: its type and the place in our code it was raised from (the innermost frame under
    agent/, else the innermost), e.g. `ValueError@agent/core/estimators/base.py:115`."""
    frames = traceback.extract_tb(error.__traceback__)
    ours = [f for f in frames if "/agent/" in f.filename.replace("\\", "/")]
    frame = (ours or frames or [None])[-1]
    if frame is None:
        return type(error).__name__
    path = frame.filename.replace("\\", "/")
    where = path[path.rfind("/agent/") + 1:] if "/agent/" in path else Path(path).name
    return f"{type(error).__name__}@{where}:{frame.lineno}"


class TickFailures:
    """The failed ticks of one agent: how many, of which kinds, in a row, and the core rebuilds they caused."""

    def __init__(self, vessel: str, rebuild_after: int) -> None:
        self.vessel, self.rebuild_after = vessel, rebuild_after
        self.total = 0
        self.in_a_row = 0
        self.rebuilds = 0
        self.kinds: dict[str, list] = {}   # kind -> [count, monotonic time last told]

    def counts(self) -> dict[str, int]:
        return {"tick_errors": self.total, "core_rebuilds": self.rebuilds}

    def succeeded(self) -> None:
        self.in_a_row = 0

    def failed(self, error: Exception, stamp: int, log: Callable[[str, str, int], None]) -> bool:
        """Count a failed tick at `stamp` (ns); tell it (stderr, and `log(kind, text, count)`) the first time for
        its kind and then at most every ERROR_REPEAT s. True when the core is to be rebuilt (counted here)."""
        self.total += 1
        self.in_a_row += 1
        kind = error_kind(error)
        now = time.monotonic()
        entry = self.kinds.get(kind)
        if entry is None and len(self.kinds) < MAX_ERROR_KINDS:
            entry = self.kinds[kind] = [0, -math.inf]
        tell = entry is not None and now - entry[1] >= ERROR_REPEAT
        if entry is not None:
            entry[0] += 1
        if tell:
            entry[1] = now
            text = f"{type(error).__name__}: {error}"[:500]
            print(f"usv-agent {self.vessel}: tick at {seconds(stamp):.3f} s failed ({kind}, {entry[0]} so far): "
                  f"{text}; commanding STOP", file=sys.stderr)
            log(kind, text, entry[0])
        if self.in_a_row < self.rebuild_after:
            return False
        # The same failure tick after tick: the state is beyond use. Start again as a late joiner does.
        self.rebuilds += 1
        self.in_a_row = 0
        print(f"usv-agent {self.vessel}: {self.rebuild_after} failed ticks in a row: core rebuilt "
              f"({self.rebuilds} so far)", file=sys.stderr)
        return True
