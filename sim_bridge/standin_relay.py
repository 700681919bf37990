"""The Zenoh side of `usv-ardupilot-standin --sim ENDPOINT --vessel ID`: a stand-in whose hull is the sim's.

`SimRelay` takes the sim bridge's pose of the vessel each tick (`sim/autopilot/<id>/pose`, the odometry
reading the bridge would have given the agent), which the stand-in sends as ATTITUDE and LOCAL_POSITION_NED,
and publishes what the stand-in drives the hull at (`Drive` on `sim/autopilot/<id>/drive`) on each pose,
each set point taken and each change; the bridge steps its world on that (sim_bridge/autopilot_relay.py).

It also listens to the agent's own commands (`usv/<id>/cmd`), only to measure: the wall time from a command
reaching this process over Zenoh (as it reaches the sim bridge in a fleet without MAVLink) to the stand-in
taking it as a set point from the driver is its added latency, written with the set point in --record.
Callbacks only queue and wake the stand-in's loop (`wake_fd`), which does everything else.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque

import zenoh

from agent.angles import wrap_angle
from agent.contract import Cmd, Odometry, decode, encode, key
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from sim_bridge.autopilot_relay import Drive, as_sent, drive_key, pose_key

MAX_POSES = 64        # poses queued between two turns of the loop (the oldest dropped)
MAX_COMMANDS = 256    # agent commands (and set points ahead of theirs) remembered for the latency, by (u, r)
MATCH_NS = 1_000_000_000   # a command and a set point further apart than this are not each other's


class SimRelay:
    def __init__(self, endpoint: str, vessel: str, standin, modes: dict[int, str]) -> None:
        self.vessel, self.standin, self.modes = vessel, standin, modes
        self.session = zenoh.open(zenoh_config(ZenohSettings(connect=[endpoint])))
        self._lock = threading.Lock()
        self._poses: deque[Odometry] = deque(maxlen=MAX_POSES)
        self._commands: dict[tuple[float, float], int] = {}   # (u, r) as sent -> wall ns it reached us
        self._ahead: dict[tuple[float, float], int] = {}      # set points that came before their command: wall ns
        self.late: list[float] = []   # added latencies (ms, < 0) of set points that came before their command
        self._last_setpoint: tuple[float, float] | None = None
        self.refused = 0
        self.wake_fd, self._wake_write = os.pipe()
        for fd in (self.wake_fd, self._wake_write):
            os.set_blocking(fd, False)
        self._publisher = self.session.declare_publisher(drive_key(vessel))
        self._subscribers = [self.session.declare_subscriber(pose_key(vessel), self._on_pose),
                             self.session.declare_subscriber(key(vessel, "cmd"), self._on_command)]
        self._said: tuple | None = None
        self._heading: tuple[float, int] | None = None   # the last pose's heading (rad) and stamp (ns)

    def _on_pose(self, sample) -> None:
        message, _ = decode(Odometry, sample.payload.to_bytes())
        with self._lock:
            if message is None or message.sender != self.vessel:
                self.refused += 1
                return
            self._poses.append(message)
        try:
            os.write(self._wake_write, b"!")
        except OSError:   # the pipe is full: the loop is awake already
            pass

    def _on_command(self, sample) -> None:
        arrived = time.time_ns()
        message, _ = decode(Cmd, sample.payload.to_bytes())
        if message is None:
            return
        sent = as_sent(message)
        with self._lock:
            taken = self._ahead.pop(sent, None)
            if taken is not None and arrived - taken <= MATCH_NS:   # its set point beat it here
                self.late.append((taken - arrived) * 1e-6)
                return
            _remember(self._commands, sent, arrived)

    def arrival(self, u: float, r: float) -> int | None:
        """The wall ns the agent's command that this set point carries reached us (within MATCH_NS); None for a
        repeat of the last set point, or a set point ahead of its command (matched when that comes: `late`)."""
        now = time.time_ns()
        with self._lock:
            repeat, self._last_setpoint = self._last_setpoint == (u, r), (u, r)
            arrived = self._commands.pop((u, r), None)
            if arrived is not None and now - arrived <= MATCH_NS:
                return arrived
            if not repeat:
                _remember(self._ahead, (u, r), now)
            return None

    def late_matches(self) -> list[float]:
        """The added latencies (ms) of set points matched since the last call, that came before their command."""
        with self._lock:
            late, self.late = self.late, []
        return late

    def poses(self) -> list:
        """The messages for the driver from the poses that came since the last call."""
        try:
            os.read(self.wake_fd, 4096)
        except OSError:
            pass
        with self._lock:
            poses = list(self._poses)
            self._poses.clear()
        out = []
        for pose in poses:
            heading = pose.heading   # counter-clockwise from east; the stand-in's yaw is NED
            rate = 0.0
            if self._heading is not None and pose.stamp_ns > self._heading[1]:
                rate = wrap_angle(heading - self._heading[0]) / ((pose.stamp_ns - self._heading[1]) * 1e-9)
            self._heading = (heading, pose.stamp_ns)
            east, north = pose.position
            out += self.standin.pose(north, east, wrap_angle(math.pi / 2 - heading), rate, pose.stamp_ns)
        return out

    def publish(self, force: bool) -> None:
        """The stand-in's Drive, if `force` (a pose or a set point came) or it changed."""
        s = self.standin
        setpoint = None if s.setpoint is None else (float(s.setpoint[0]), float(s.setpoint[1]))
        said = (setpoint, s.u, s.r, s.mode, s.armed)
        if not force and said == self._said:
            return
        self._said = said
        if not all(math.isfinite(v) for v in (s.u, s.r)):
            return
        self._publisher.put(encode(Drive(stamp_ns=max(s.posed or 0, 0), sender=self.vessel, setpoint=setpoint,
                                         drive=(float(s.u), float(s.r)),
                                         mode=self.modes.get(s.mode, str(s.mode)), armed=s.armed)))

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._publisher.undeclare()
        self.session.close()
        for fd in (self.wake_fd, self._wake_write):
            os.close(fd)


def _remember(table: dict, sent: tuple[float, float], wall_ns: int) -> None:
    table.pop(sent, None)   # the newest last, so that the oldest goes first
    if len(table) >= MAX_COMMANDS:
        table.pop(next(iter(table)))
    table[sent] = wall_ns
