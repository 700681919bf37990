"""GNSS adapter: a receiver's NMEA GGA sentences (read by pynmeagps) -> the contract's GnssFix, truth only.

The fixes go to `usv/<id>/truth/gnss` (agent.contract.gnss_truth_key), which no agent subscribes to: they
score a field trial (e_ij, e_io, e_c from GNSS positions, as a simulation is scored from its truth) and
never steer. GGA is NMEA 0183's "global positioning system fix data"
(https://gpsd.gitlab.io/gpsd/NMEA.html#_gga_global_positioning_system_fix_data):
`$--GGA,hhmmss.ss,ddmm.mm,N|S,dddmm.mm,E|W,<quality>,<satellites>,<hdop>,<altitude>,M,<geoid separation>,M,
<age of corrections>,<station>*hh`; any talker (GP, GN, GL, GA, ...).

`read_gga` gives (fix, "") or (None, why): `not_gga` (another sentence: a receiver sends several kinds,
which the driver passes over without counting them as refused), `no_fix` (quality 0, or no position),
`bad_number` (serial_port.read_sentence's rule), `bad_hemisphere` (N/S or E/W missing or another letter),
`out_of_range` (beyond 90 degrees of latitude or 180 of longitude).

More: docs/contract.md, "The driver bridge in detail", `driver_bridge/gnss.py`.
"""

from __future__ import annotations

from collections import Counter

from pydantic import Field

from agent.config import StrictModel
from agent.contract import GnssFix, Vec2
from driver_bridge.serial_port import read_sentence

GGA_FIELDS = 14


class ReceiverSettings(StrictModel):
    antenna: Vec2 = Field(
        (0.0, 0.0), description="antenna from the vessel's reference point: ahead, left (m)")


def read_gga(body: bytes) -> tuple[dict | None, str]:
    """The GnssFix fields (all but the header and the antenna) of a checked GGA body, or (None, why)."""
    message, why = read_sentence(body, "GGA", GGA_FIELDS)
    if message is None:
        return None, "not_gga" if why.startswith("not_") else why
    if message.quality in ("", 0) or message.lat == "" or message.lon == "":
        return None, "no_fix"
    if message.NS not in ("N", "S") or message.EW not in ("E", "W"):
        return None, "bad_hemisphere"
    # pynmeagps signs the degrees by the hemisphere letters
    if not (abs(message.lat) <= 90.0 and abs(message.lon) <= 180.0):
        return None, "out_of_range"
    utc = message.time
    return {"latitude": message.lat, "longitude": message.lon,
            "altitude": None if message.alt == "" else message.alt,
            "quality": message.quality, "satellites": None if message.numSV == "" else message.numSV,
            "hdop": None if message.HDOP == "" else message.HDOP,
            "utc_time": None if utc == "" else utc.hour * 3600 + utc.minute * 60 + utc.second
            + utc.microsecond * 1e-6}, ""


class GnssAdapter:
    """GGA bodies -> GnssFix messages; refusals by reason in `rejected`, other sentences counted in
    `passed_over` (not refusals: a receiver sends GSV, GSA, RMC, VTG and more every second)."""

    def __init__(self, settings: ReceiverSettings | None = None) -> None:
        self.settings = settings or ReceiverSettings()
        self.rejected: Counter[str] = Counter()
        self.passed_over = 0

    def fix(self, body: bytes, stamp_ns: int, seq: int, sender: str) -> GnssFix | None:
        fields, why = read_gga(body)
        if fields is None:
            if why == "not_gga":
                self.passed_over += 1
            else:
                self.rejected[why] += 1
            return None
        try:
            return GnssFix(stamp_ns=stamp_ns, seq=seq, sender=sender, antenna=self.settings.antenna, **fields)
        except ValueError:   # beyond the contract's bounds (an altitude of 1e30, a quality of 10, ...)
            self.rejected["out_of_range"] += 1
            return None
