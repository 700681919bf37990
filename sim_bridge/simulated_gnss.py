"""Simulated GNSS receiver: a vessel's true position in the local frame -> its antenna's NMEA GGA sentence,
with noise drawn from the caller's seeded Generator.

`gga_sentence` writes one GGA (NMEA 0183 "global positioning system fix data", what driver_bridge/gnss.py
reads): `$GNGGA,hhmmss.ss,ddmm.mmmmmmm,N|S,dddmm.mmmmmmm,E|W,<quality>,<satellites>,<hdop>,<altitude>,M,
0.0,M,,*hh` and CR LF, with 7 decimals of an arc minute (0.2 mm), so that an RTK fix loses nothing to the
format. `simulated_gga` puts the antenna at p + R(psi) a (a: ahead, left of the reference point), adds
N(0, sigma^2) to east and to north independently at every fix (sigma per axis: 1.5 m for plain GNSS, 0.02 m
for RTK fixed), and writes the sentence of that point about the frame's origin (mission_log.local_frame).
A real receiver's error is correlated in time (multipath, the atmosphere: over minutes for plain GNSS);
this stand-in's is white.

More: docs/logs.md, "Scoring a field trial from GNSS".
"""

from __future__ import annotations

import math
from functools import reduce
from operator import xor
from typing import Literal

import numpy as np
from pydantic import Field, NonNegativeFloat

from agent.config import StrictModel
from agent.contract import Vec2
from mission_log.local_frame import LocalFrame

SATELLITES = 12
HDOP = 0.8


class SimulatedReceiver(StrictModel):
    origin: tuple[float, float] = Field(description="the local frame's origin: latitude, longitude (deg)")
    sigma: NonNegativeFloat = Field(1.5, description="noise east and north each (m): 1.5 GNSS, 0.02 RTK")
    quality: Literal[1, 2, 4, 5] = Field(1, description="GGA quality: 1 GNSS, 2 DGNSS, 4 RTK fixed, 5 float")
    antenna: Vec2 = Field((0.0, 0.0), description="antenna from the vessel's reference: ahead, left (m)")


def plain(origin: tuple[float, float], **more) -> SimulatedReceiver:
    return SimulatedReceiver(origin=origin, sigma=1.5, quality=1, **more)


def rtk(origin: tuple[float, float], **more) -> SimulatedReceiver:
    return SimulatedReceiver(origin=origin, sigma=0.02, quality=4, **more)


def checksum(body: str) -> str:
    """NMEA 0183: the XOR of the bytes between `$` and `*`, two hex digits. (The driver's checks it with
    pynmeagps, of the `driver` extra, which the simulator does without.)"""
    return f"{reduce(xor, body.encode('ascii'), 0):02X}"


def _angle(degrees: float, width: int) -> str:
    """|degrees| as d..dmm.mmmmmmm (`width` digits of degrees), the minutes rounded to 7 decimals."""
    units = round(abs(degrees) * 60 * 10**7)        # in 1e-7 arc minute: the rounding carries into degrees
    whole, minutes = divmod(units, 60 * 10**7)
    return f"{whole:0{width}d}{minutes // 10**7:02d}.{minutes % 10**7:07d}"


def _utc(seconds: float) -> str:
    centis = round(seconds * 100) % 8_640_000
    hours, rest = divmod(centis, 360_000)
    minutes, rest = divmod(rest, 6_000)
    return f"{hours:02d}{minutes:02d}{rest // 100:02d}.{rest % 100:02d}"


def gga_sentence(latitude: float, longitude: float, utc_seconds: float, quality: int = 1,
                 altitude: float = 0.0, satellites: int = SATELLITES, hdop: float = HDOP,
                 talker: str = "GN") -> bytes:
    """One GGA sentence, `$` to CR LF, of a fix at `latitude`, `longitude` (deg), `utc_seconds` of the day."""
    body = (f"{talker}GGA,{_utc(utc_seconds)},{_angle(latitude, 2)},{'N' if latitude >= 0 else 'S'},"
            f"{_angle(longitude, 3)},{'E' if longitude >= 0 else 'W'},{quality},{satellites:02d},{hdop:.1f},"
            f"{altitude:.1f},M,0.0,M,,")
    return f"${body}*{checksum(body)}\r\n".encode("ascii")


def antenna_position(position, heading: float, antenna) -> np.ndarray:
    """p + R(psi) a: the antenna in the local frame, `antenna` (ahead, left) turned by the heading psi."""
    c, s = math.cos(heading), math.sin(heading)
    ahead, left = antenna
    return np.asarray(position, dtype=float) + np.array([c * ahead - s * left, s * ahead + c * left])


def simulated_gga(position, heading: float, utc_seconds: float, receiver: SimulatedReceiver,
                  random: np.random.Generator) -> bytes:
    """The GGA of a vessel at local `position` (m: east, north) and `heading` (rad, counter-clockwise from
    east): its antenna's point plus N(0, sigma^2) east and north, draws taken from `random`."""
    noise = random.normal(0.0, receiver.sigma, 2)
    east, north = antenna_position(position, heading, receiver.antenna) + noise
    latitude, longitude = LocalFrame(*receiver.origin).to_geodetic(east, north)
    return gga_sentence(float(latitude), float(longitude), utc_seconds, receiver.quality)
