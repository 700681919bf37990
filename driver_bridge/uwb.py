"""UWB ranging adapter: Nooploop LinkTrack serial frames (NLink protocol) -> ranges in metres per peer vessel.

Source: Nooploop's NLink protocol V1.3 and its reference parsers (the sources are listed in the docs).

Every frame, little-endian throughout:
    byte 0      0x55 frame header
    byte 1      function mark: 0x04 NLink_LinkTrack_Node_Frame2, 0x05 NLink_LinkTrack_Node_Frame3
    bytes 2-3   uint16 frame length: the WHOLE frame, header and checksum included
    last byte   checksum: sum of every preceding byte, modulo 256
Node_Frame2 (position, IMU and ranges), 119-byte fixed part, then valid_node_count blocks of 13 bytes:
    4 role, 5 id, 6-9 uint32 system_time (ms), 10-12 eop xyz, 13-21 int24 pos xyz (mm), 22-30 int24 vel xyz
    (1e-4 m/s), 31-39 reserved, 40-51 float32 gyro, 52-63 float32 acc, 64-75 reserved, 76-81 int16 angles
    (0.01 deg), 82-97 float32 quaternion, 98-101 reserved, 102-105 uint32 local_time (ms), 106-115 reserved,
    116-117 uint16 voltage (mV), 118 uint8 valid_node_count;
    block: 0 role, 1 id, 2-4 int24 dis (mm), 5 fp_rssi, 6 rx_rssi (uint8, dB x -2), 7-10 system_time,
    11-12 reserved.
Node_Frame3 (ranges only), 21-byte fixed part, then blocks of 7 bytes:
    4 role, 5 id, 6-9 uint32 local_time, 10-13 uint32 system_time (ms), 14-17 reserved, 18-19 uint16 voltage
    (mV), 20 uint8 valid_node_count; block: 0 role, 1 id, 2-4 int24 dis (mm), 5 fp_rssi, 6 rx_rssi.

Only the ranges and the ranging-round time are used; the vessel positions stay the agent's business.

More: docs/contract.md, "The driver bridge in detail", `driver_bridge/uwb.py`.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Annotated

from pydantic import Field

from agent.config import PositiveFloat, StrictModel
from agent.contract import MAX_POSITION, VesselId

HEADER = 0x55
NodeNumber = Annotated[int, Field(ge=0, le=255)]


@dataclass(frozen=True)
class _Layout:
    name: str
    fixed: int          # bytes before the first node block
    block: int          # bytes per node block
    time_at: int        # offset of the uint32 system_time (ms)
    count_at: int       # offset of valid_node_count

    def length(self, nodes: int) -> int:
        return self.fixed + self.block * nodes + 1


LAYOUTS = {
    0x04: _Layout("node_frame2", fixed=119, block=13, time_at=6, count_at=118),
    0x05: _Layout("node_frame3", fixed=21, block=7, time_at=10, count_at=20),
}


class UwbSettings(StrictModel):
    """Which module node ids are which vessels, and the bounds of a believable frame."""

    peers: dict[NodeNumber, VesselId] = Field(description="LinkTrack node id (0-255) -> vessel id")
    # A longer length field is refused at once instead of waiting for bytes that will not come.
    max_nodes: int = Field(64, ge=1, le=255, description="most node blocks in one frame")
    max_range: PositiveFloat = Field(1000.0, le=MAX_POSITION, description="longest believable range (m); our "
                                     "choice, above LinkTrack's rated range (at most the contract's limit)")


@dataclass(frozen=True)
class RangeFrame:
    """One ranging round: ranges (m) and RSSI (first-path, received; dB) per known peer vessel."""

    frame: str                      # "node_frame2" or "node_frame3"
    node_id: int                    # this module's own node id
    system_time_ms: int             # the UWB network's synchronised clock at the round
    ranges: dict[str, float] = field(default_factory=dict)
    rssi: dict[str, tuple[float, float]] = field(default_factory=dict)


def _int24(raw: bytes, at: int) -> int:
    return int.from_bytes(raw[at: at + 3], "little", signed=True)


class NLinkParser:
    """Incremental parser: `feed(bytes)` returns the complete, checked frames found so far.

    Rejections are counted in `rejected` by reason: `garbage` (bytes skipped while looking for a header),
    `unknown_frame` (0x55 followed by a frame type not handled here), `bad_length` (impossible length field,
    or one disagreeing with valid_node_count), `bad_checksum`, and per range `unknown_node`,
    `negative_range`, `range_too_long`. After a bad frame only its first byte is dropped, so a real header
    hidden inside a false one is still found.
    """

    def __init__(self, settings: UwbSettings):
        self.settings = settings
        self.rejected: Counter[str] = Counter()
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[RangeFrame]:
        self._buffer += data
        frames: list[RangeFrame] = []
        while True:
            start = self._buffer.find(HEADER)
            skipped = len(self._buffer) if start < 0 else start
            if skipped:
                self.rejected["garbage"] += skipped
                del self._buffer[:skipped]
            if len(self._buffer) < 4:
                return frames
            layout = LAYOUTS.get(self._buffer[1])
            if layout is None:
                self._drop("unknown_frame")
                continue
            length = int.from_bytes(self._buffer[2:4], "little")
            if not self._plausible(layout, length):
                self._drop("bad_length")
                continue
            if len(self._buffer) < length:
                return frames  # wait for the rest
            raw = bytes(self._buffer[:length])
            if sum(raw[:-1]) & 0xFF != raw[-1]:
                self._drop("bad_checksum")
                continue
            if length != layout.length(raw[layout.count_at]):
                self._drop("bad_length")
                continue
            del self._buffer[:length]
            frames.append(self._decode(layout, raw))

    def _plausible(self, layout: _Layout, length: int) -> bool:
        blocks, rest = divmod(length - layout.fixed - 1, layout.block)
        return 0 <= blocks <= self.settings.max_nodes and rest == 0

    def _drop(self, reason: str) -> None:
        self.rejected[reason] += 1
        del self._buffer[:1]

    def _decode(self, layout: _Layout, raw: bytes) -> RangeFrame:
        ranges: dict[str, float] = {}
        rssi: dict[str, tuple[float, float]] = {}
        for k in range(raw[layout.count_at]):
            at = layout.fixed + k * layout.block
            vessel = self.settings.peers.get(raw[at + 1])
            distance = _int24(raw, at + 2) / 1000.0  # mm -> m
            if vessel is None:
                self.rejected["unknown_node"] += 1
            elif not math.isfinite(distance) or distance < 0:
                self.rejected["negative_range"] += 1
            elif distance > self.settings.max_range:
                self.rejected["range_too_long"] += 1
            else:
                ranges[vessel] = distance
                rssi[vessel] = (raw[at + 5] / -2.0, raw[at + 6] / -2.0)
        stamp = int.from_bytes(raw[layout.time_at: layout.time_at + 4], "little")
        return RangeFrame(layout.name, raw[5], stamp, ranges, rssi)
