"""Thruster adapter: the differential mix by hand, yaw-first saturation, the watchdog, and the command line
written to a real pty."""

from __future__ import annotations

import math
import os
import re

import pytest
from pydantic import ValidationError

from driver_bridge.serial_port import open_serial, read_available, write_all
from driver_bridge.thrusters import ZERO_THRUST, Thrust, ThrusterAdapter, ThrusterSettings, command_line

# 50 N per thruster, thrusters 0.25 m off the centreline, d_u = 40 N/(m/s), d_r = 5 N m/(rad/s).
HULL = ThrusterSettings(max_thrust=50.0, half_beam=0.25, surge_drag=40.0, yaw_drag=5.0, timeout=0.5)


class thrust:  # lower case: reads as a value in the assertions
    """Equal to a Thrust whose (left, right) are approximately these."""

    def __init__(self, left: float, right: float):
        self.expected = (left, right)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Thrust) and (other.left, other.right) == pytest.approx(self.expected)

    def __repr__(self) -> str:
        return f"~Thrust{self.expected}"


def test_linear_mix_by_hand():
    # u = 1 m/s: T_l + T_r = 40 N. r = 0.5 rad/s: T_r - T_l = 5 * 0.5 / 0.25 = 10 N.
    # T_r = 25 N, T_l = 15 N -> 0.5 and 0.3 of 50 N.
    adapter = ThrusterAdapter(HULL)
    assert adapter.mix(1.0, 0.5) == thrust(0.3, 0.5)
    assert adapter.mix(1.0, -0.5) == thrust(0.5, 0.3)     # turning to starboard pushes harder on the left
    assert adapter.mix(-0.5, 0.0) == thrust(-0.2, -0.2)   # astern: 20 N in total, reversed
    assert adapter.events["saturated"] == 0


def test_saturation_keeps_the_turn_and_gives_up_speed():
    # u = 2.5, r = 0.5: T_l = 45 N, T_r = 55 N -> 0.9 / 1.1, over the limit. Mean 1.0, half-difference 0.1:
    # the mean is cut to 1 - 0.1 = 0.9, so (0.8, 1.0): the 0.2 difference (10 N, the turn) is kept.
    adapter = ThrusterAdapter(HULL)
    assert adapter.mix(2.5, 0.5) == thrust(0.8, 1.0)
    # r = 5 rad/s alone: T_r - T_l = 100 N -> half-difference 1.0: full differential (-1, 1) and no surge
    # left, whatever the surge asked for; r = 10 rad/s cannot do more than that.
    assert adapter.mix(1.0, 5.0) == thrust(-1.0, 1.0)
    assert adapter.mix(0.0, 10.0) == thrust(-1.0, 1.0)
    assert adapter.events["saturated"] == 3


def test_watchdog_stops_stale_commands_and_resumes():
    adapter = ThrusterAdapter(HULL)
    assert adapter.output(0.0) == ZERO_THRUST                    # nothing commanded yet
    adapter.command(1.0, 0.5, now=10.0)
    assert adapter.output(10.3) == thrust(0.3, 0.5)
    assert adapter.output(10.5) == thrust(0.3, 0.5)       # exactly at the timeout: still fresh
    assert adapter.output(10.51) == ZERO_THRUST and adapter.output(11.0) == ZERO_THRUST
    assert adapter.events["watchdog_stop"] == 1           # one stop event, not one per call
    adapter.command(1.0, 0.0, now=11.2)
    assert adapter.output(11.3) == thrust(0.4, 0.4)


def test_non_finite_and_out_of_order_commands():
    adapter = ThrusterAdapter(HULL)
    adapter.command(1.0, 0.0, now=5.0)
    assert adapter.command(math.nan, 0.0, now=5.1) == ZERO_THRUST and adapter.output(5.2) == ZERO_THRUST
    adapter.command(1.0, 0.0, now=5.3)
    assert adapter.command(1.0, math.inf, now=5.4) == ZERO_THRUST
    adapter.command(1.0, 0.0, now=5.5)
    assert adapter.command(1.0, 0.0, now=math.nan) == ZERO_THRUST and adapter.output(5.6) == ZERO_THRUST
    adapter.command(2.0, 0.0, now=5.7)
    assert adapter.command(0.5, 0.0, now=5.65) == thrust(0.8, 0.8)  # older than the last: ignored
    assert adapter.rejected == {"non_finite": 3, "out_of_order": 1}


def test_settings_refuse_non_positive_values():
    with pytest.raises(ValidationError, match="half_beam"):
        ThrusterSettings(max_thrust=50.0, half_beam=0.0, surge_drag=40.0, yaw_drag=5.0)
    with pytest.raises(ValidationError, match="timeout"):
        ThrusterSettings(max_thrust=50.0, half_beam=0.2, surge_drag=40.0, yaw_drag=5.0, timeout=-1.0)


LINE = re.compile(rb"^\$(THR,([+-]\d\.\d{3}),([+-]\d\.\d{3}))\*([0-9A-F]{2})\r\n$")


def test_command_lines_through_a_pty():
    master, slave = os.openpty()
    port = open_serial(os.ttyname(slave), 115_200)
    adapter = ThrusterAdapter(HULL)
    try:
        adapter.command(1.0, 0.5, now=0.0)
        for now in (0.1, 0.7):                            # fresh, then stale
            write_all(port, command_line(adapter.output(now)))
        received = b""
        while received.count(b"\n") < 2 and (chunk := read_available(master, 2.0)):
            received += chunk
    finally:
        port.close()   # a pyserial port
        for fd in (slave, master):
            os.close(fd)
    first, second = received.splitlines(keepends=True)
    match = LINE.match(first)
    checksum = 0
    for char in match.group(1):
        checksum ^= char
    assert int(match.group(4), 16) == checksum
    assert (float(match.group(2)), float(match.group(3))) == (0.3, 0.5)
    assert LINE.match(second).group(2, 3) == (b"+0.000", b"+0.000")  # the watchdog's stop
