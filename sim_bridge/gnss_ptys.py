"""The sim bridge's GNSS receivers for a live simulated field trial: each vessel's and the target tag's GGA,
written into a pseudo-terminal that a real `usv-driver` opens as its GNSS serial device.

For each id in `links` the bridge opens a pty (os.openpty, raw: no echo, no line editing), and makes the
link path a symbolic link to its device (e.g. /dev/pts/7), so the driver's config can name it before the
bridge runs. Every tick of the sea mode it writes one GGA per id (sim_bridge/simulated_gnss.py: seeded
white noise, `receiver`'s sigma and quality, each id's antenna turned by its heading; the target has no
heading and carries its tag at its reference point), stamped with the tick's true UTC time of day. The
driver stamps each sentence as it reads it, on its vessel's clock, as aboard (driver_bridge/node.py).

Only the sea mode (wall-clock agents) can use it: the driver stamps on the wall clock, so the agents'
estimates and the fixes share a clock only there. A sentence the pty cannot take (no driver reads it and
its buffer is full) is dropped and counted in `dropped`, never waited for: the world does not stop for a
receiver. `close` removes the links.

More: docs/logs.md, "Scoring a field trial from GNSS"; docs/fleet.md (`usv-fleet run --gnss`).
"""

from __future__ import annotations

import os
import tty
from collections import Counter
from pathlib import Path

import numpy as np
from pydantic import Field

from agent.config import StrictModel
from agent.contract import Vec2
from sim_bridge.simulated_gnss import SimulatedReceiver, simulated_gga

ORIGIN = (59.9, 10.7)      # the local frame's origin (deg): any will do; a fjord's
TARGET = "target"          # the target tag's id, as mission_log.gnss_truth reads it
GNSS_STREAM = 31           # the noise's own stream of the run's seed (issue 31)
DAY_S = 86_400


class SimulatedGnss(StrictModel):
    receiver: SimulatedReceiver = Field(description="origin, noise and fix quality of every receiver")
    links: dict[str, str] = Field(description="vessel id (or 'target') -> the path of its pty's link")
    antennas: dict[str, Vec2] = Field({}, description="vessel id -> its antenna: ahead, left (m); default 0, 0")


class GnssPtys:
    def __init__(self, settings: SimulatedGnss, seed: int) -> None:
        self.settings = settings
        self.random = np.random.default_rng([seed, GNSS_STREAM])
        self.written: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self.masters: dict[str, int] = {}
        self._slaves: list[int] = []   # held open: a pty whose slave side was never opened hangs up
        try:
            for owner, link in settings.links.items():
                master, slave = os.openpty()
                self.masters[owner] = master
                self._slaves.append(slave)
                tty.setraw(slave)
                os.set_blocking(master, False)
                path = Path(link)
                path.unlink(missing_ok=True)
                path.symlink_to(os.ttyname(slave))
        except OSError:
            self.close()
            raise

    def emit(self, truth: dict, wall_ns: int) -> None:
        """One GGA per id from a tick's truth record (bridge.truth_record) at the true wall time `wall_ns`."""
        utc = (wall_ns % (DAY_S * 10**9)) * 1e-9
        for owner, master in self.masters.items():
            if owner == TARGET:
                position, heading = truth["target"], 0.0
            elif owner in truth["vessels"]:
                state = truth["vessels"][owner]
                position, heading = state["position"], state["heading"]
            else:
                continue   # not in the world (yet, or any more): its receiver is silent
            receiver = self.settings.receiver.model_copy(
                update={"antenna": (0.0, 0.0) if owner == TARGET else self.settings.antennas.get(owner, (0.0, 0.0))})
            sentence = simulated_gga(position, heading, utc, receiver, self.random)
            try:
                if os.write(master, sentence) == len(sentence):
                    self.written[owner] += 1
                    continue
            except OSError:   # BlockingIOError: the pty's buffer is full (its driver reads nothing)
                pass
            self.dropped[owner] += 1

    def close(self) -> None:
        for fd in [*self.masters.values(), *self._slaves]:
            try:
                os.close(fd)
            except OSError:
                pass
        self.masters, self._slaves = {}, []
        for link in self.settings.links.values():
            path = Path(link)
            if path.is_symlink():
                path.unlink(missing_ok=True)
