"""The serial side's fuzz campaign: bad lines and frames through the driver bridge's own handlers, in process.

`usv-lab fuzz` storms one agent over Zenoh (lab/benchmarks/fuzz.py); this is the same for `usv-driver`'s inputs.
Each parser gets its own `DriverBridge` (driver_bridge/node.py), fed through the very methods its select loop
calls, with a clock of the campaign's own (100 ms a line) so that a run repeats with its seed:

- `vhw`: the speed log's NMEA VHW sentences -> dead reckoning -> `usv/<id>/sensor/odom`;
- `nlink`: the UWB module's NLink Node_Frame2/Node_Frame3 binary frames -> `usv/<id>/sensor/uwb`;
- `det`: the detector's `$DET` sentences -> `usv/<id>/sensor/bearing` (one VHW sentence first: the heading);
- `cmd`: what the driver reads from Zenoh, `usv/<id>/cmd` payloads -> the command gate -> the `$THR` line
  written to the motor controller (the driver parses no `$THR`: it writes them);
- `gga`: a GNSS receiver's NMEA GGA sentences -> `usv/<id>/truth/gnss` (GnssFix, truth no agent reads).

Lines and frames come from one seeded numpy Generator, in the classes listed in docs/reliability.md §4
(`classes_for` says which apply).

Between bad lines come good ones (half as many). Checks: no exception escapes a handler; the last-resort
guard (`<port>_failed`) catches nothing either, so every refusal has its own reason; every message that
reaches the contract decodes and lies within it (positions and ranges within their bounds, a unit bearing,
known peers) and every `$THR` line carries a valid checksum and values within [-1, 1]; after the storm,
good lines are published again (odometry steering back inside the frame, after one sentence that turns
it: the walk may have left it at the edge, where outward steps are refused) and the thruster watchdog still
stops the thrusters.

More: docs/reliability.md §4, `lab/benchmarks/serial_fuzz.py`.
"""

from __future__ import annotations

import json
import math
import struct
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from agent.contract import MAX_POSITION, Bearing, GnssFix, Odometry, Ranges, decode
from driver_bridge.bearing import CameraSettings
from driver_bridge.node import (
    CameraPort,
    DriverBridge,
    DriverSettings,
    GnssPort,
    OdometryPort,
    ThrusterPort,
    UwbPort,
)
from driver_bridge.odometry import KNOT, OdometrySettings
from driver_bridge.serial_port import LineReader, nmea_checksum
from driver_bridge.thrusters import ThrusterSettings
from driver_bridge.uwb import LAYOUTS, UwbSettings
from lab import arguments
from lab.report.markdown import invocation, markdown_table

VESSEL = "1"
PARSERS = ("vhw", "nlink", "det", "cmd", "gga")   # gga last: the others' lines stay those of their seed
CLASSES = ("random_bytes", "extreme_numbers", "non_finite", "truncated", "wrong_fields", "overlong",
           "garbage_payload", "burst", "walk")
PEERS = {2: "2", 3: "3"}
STEP_NS = 100_000_000          # the campaign's wall clock advances 100 ms per line
START_NS = 1_700_000_000 * 10**9
AFTER_STORM = 200              # good lines after the storm, per parser
WALK_NS = 600 * 10**9          # the walk's sentences are ten minutes apart: 30 km a step
EXTREME_TEXT = ("1e30", "-1e30", "1e308", "-1e308", "1.7976931348623157e308", "-1.7976931348623157e308",
                "1" + "0" * 30 + ".0", "5e-324", "-0", "360.0001", "-5", "99999", "1e5", "4294967296",
                "1e-308", "100000.1")
NON_FINITE_TEXT = ("nan", "NaN", "-nan", "inf", "-inf", "Infinity", "-Infinity", "1e400", "-1e400", "INF")
JSON_EXTREMES = ("1e308", "-1e308", "1e400", "NaN", "Infinity", "-Infinity", "9223372036854775808",
                 "1" + "0" * 400, "-1", "1e3", "1000.0001", "1e6", "1000001", "5e-324")
JSON_NON_FINITE = ("NaN", "Infinity", "-Infinity", "1e400", "-1e400")
CAMERA = CameraSettings(fx=500.0, cx=320.0, width=640, height=480, fy=500.0, cy=240.0)
HULL = ThrusterSettings(max_thrust=100.0, half_beam=0.5, surge_drag=50.0, yaw_drag=20.0, timeout=0.5)


def classes_for(parser: str) -> tuple[str, ...]:
    return tuple(c for c in CLASSES if c != "walk" or parser == "vhw")


def sentence(body: str | bytes) -> bytes:
    """`$<body>*hh\\r\\n` with a valid checksum, whatever the body holds."""
    raw = body.encode("latin-1") if isinstance(body, str) else body
    return b"$" + raw + b"*" + f"{nmea_checksum(raw):02X}".encode() + b"\r\n"


def nlink_frame(mark: int, own_id: int, time_ms: int, nodes: list[tuple[int, int]],
                imu: tuple[float, ...] | None = None, count: int | None = None) -> bytes:
    """An NLink Node_Frame2 (mark 0x04) or Node_Frame3 (0x05) with `nodes` = [(node id, range in mm)], its
    length and checksum right; `imu` fills Frame2's gyro, acc and quaternion floats; `count` overrides the
    valid_node_count byte."""
    layout = LAYOUTS[mark]
    fixed = bytearray(layout.fixed)
    fixed[0:2] = bytes([0x55, mark])
    fixed[4:6] = bytes([2, own_id])
    fixed[layout.time_at: layout.time_at + 4] = struct.pack("<I", time_ms % 2**32)
    fixed[layout.count_at] = len(nodes) if count is None else count
    if imu is not None and mark == 0x04:
        values = (list(imu) * 10)[:10]
        fixed[40:64] = struct.pack("<6f", *values[:6])
        fixed[82:98] = struct.pack("<4f", *values[6:10])
    # a block: role, id, int24 range (mm), the two RSSI bytes, zeros to the block's size
    pad = layout.block - 7
    blocks = b"".join(bytes([1, node]) + struct.pack("<i", mm)[:3] + bytes([177, 159]) + bytes(pad)
                      for node, mm in nodes)
    frame = bytearray(fixed + blocks + b"\0")
    frame[2:4] = struct.pack("<H", len(frame) % 2**16)
    frame[-1] = sum(frame[:-1]) & 0xFF
    return bytes(frame)


class _Publisher:
    def __init__(self, topic: str, sink: list) -> None:
        self.topic, self.sink = topic, sink

    def put(self, payload: bytes) -> None:
        self.sink.append((self.topic, payload))


class _Sample:
    """What a Zenoh subscriber callback is given, as much of it as the driver reads."""

    class _Payload:
        def __init__(self, data: bytes) -> None:
            self.data = data

        def to_bytes(self) -> bytes:
            return self.data

    def __init__(self, data: bytes) -> None:
        self.payload = self._Payload(data)


@dataclass
class ParserResults:
    parser: str
    lines: Counter = field(default_factory=Counter)            # bad lines fed, by class
    good: int = 0                                             # good lines fed between them
    published: int = 0                                        # messages (or moving $THR lines) out
    refused: dict = field(default_factory=dict)               # the bridge's refusals(), by where and why
    escaped: Counter = field(default_factory=Counter)         # exceptions out of a handler, by type
    out_of_contract: list = field(default_factory=list)       # out beyond the contract: must stay empty
    after_storm: int = 0                                      # of the AFTER_STORM good lines, published
    watchdog_stopped: bool | None = None                      # cmd: thrusters stopped once commands ceased
    largest_position: float = 0.0                             # vhw: the largest |x|, |y| published (m)
    seconds: float = 0.0

    @property
    def total(self) -> int:
        return sum(self.lines.values())

    def reasons(self) -> Counter:
        """Every refusal by reason, wherever it was counted (line reader, parser, adapter, node)."""
        out: Counter = Counter()
        for where, counts in self.refused.items():
            for reason, n in counts.items():
                out[reason if where == "refused" else f"{where.replace('_refused', '')}:{reason}"] += n
        return out

    @property
    def failed(self) -> int:
        """Inputs the node's last-resort guard caught (`<port>_failed`): each means a check is missing."""
        return sum(n for reason, n in self.refused.get("refused", {}).items() if reason.endswith("_failed"))


class SerialLines:
    """Good and bad lines (or frames, or command payloads) for one parser, from `rng`; `now_ns` stamps the
    commands (the wall clock the driver judges them by)."""

    def __init__(self, parser: str, rng: np.random.Generator,
                 now_ns: Callable[[], int] = lambda: START_NS) -> None:
        self.parser, self.rng, self.now_ns = parser, rng, now_ns
        self.heading = float(rng.uniform(0, 360))   # compass degrees: where the good VHW sentences head

    # ----- good lines -----
    def good(self, heading: float | None = None) -> bytes:
        """A good line or frame (a VHW sentence on `heading`, compass degrees, if given)."""
        rng = self.rng
        if self.parser == "vhw":
            heading = (self.heading + float(rng.normal(0, 5))) % 360 if heading is None else heading
            return sentence(f"IIVHW,{heading:.1f},T,,M,{rng.uniform(0, 10):.2f},N,,K")
        if self.parser == "gga":
            return sentence(self._gga_body(quality=int(rng.choice([1, 2, 4, 5]))))
        if self.parser == "det":
            if rng.random() < 0.1:
                return sentence("DET,,")
            return sentence(f"DET,{rng.uniform(0, 640):.1f},{rng.uniform(0, 480):.1f}")
        if self.parser == "nlink":
            nodes = [(node, int(rng.integers(500, 50_000))) for node in PEERS]
            return nlink_frame(int(rng.choice([0x04, 0x05])), 1, int(rng.integers(2**32)), nodes)
        return json.dumps(self.command()).encode()

    def command(self) -> dict:
        rng = self.rng
        return {"stamp_ns": self.now_ns(), "seq": int(rng.integers(1000)), "sender": VESSEL,
                "surge": float(rng.uniform(-2, 2)), "yaw_rate": float(rng.uniform(-1, 1))}

    # ----- bad lines -----
    def _pick(self, values):
        return values[int(self.rng.integers(len(values)))]

    def bad(self, cls: str) -> bytes:
        """A bad line or frame of class `cls` (any but `burst`, which the campaign makes of the others)."""
        return getattr(self, f"_{self.parser}")(cls)

    def _random_bytes(self) -> bytes:
        rng = self.rng
        data = rng.bytes(int(rng.integers(1, 300)))
        if self.parser != "nlink" and rng.random() < 0.5:
            data = b"$" + data + (b"\r\n" if rng.random() < 0.7 else b"")
        return data

    def _text_lines(self, cls: str, good: str, numeric: list[int]) -> bytes:
        """The NMEA-framed classes for a sentence whose good body is `good`, numbers at fields `numeric`."""
        rng = self.rng
        fields = good.split(",")
        if cls == "random_bytes":
            return self._random_bytes()
        if cls in ("extreme_numbers", "non_finite"):
            pool = EXTREME_TEXT if cls == "extreme_numbers" else NON_FINITE_TEXT
            for i in rng.choice(numeric, int(rng.integers(1, len(numeric) + 1)), replace=False):
                fields[i] = self._pick(pool)
            return sentence(",".join(fields))
        if cls == "truncated":
            line = sentence(good)
            cut = line[: int(rng.integers(1, len(line) - 1))]
            return cut + (b"\r\n" if rng.random() < 0.5 else b"")
        if cls == "wrong_fields":
            choice = rng.random()
            if choice < 0.3:
                fields = fields[: int(rng.integers(1, len(fields)))]
            elif choice < 0.6:
                fields += [f"{rng.uniform(-1e3, 1e3):.1f}"] * int(rng.integers(1, 5))
            elif choice < 0.8:
                fields[0] = self._pick(("IIHDG", "GPRMC", "IIVBW", "DETX", "THR", "IIVHWX", ""))
            else:
                i = int(rng.integers(1, len(fields)))
                fields[i] = self._pick(("X", "T", "M", "N", "K", ",", "", "DET"))
            return sentence(",".join(fields))
        if cls == "overlong":
            if rng.random() < 0.5:
                fields[self._pick(numeric)] = "1" + "0" * int(rng.integers(250, 2000)) + ".0"   # 1e308 and on
                return sentence(",".join(fields))
            digits = rng.integers(48, 58, int(rng.integers(257, 5000)), dtype=np.uint8)
            return b"$" + bytes(digits)   # and no line end
        if cls == "garbage_payload":
            body = bytes(rng.integers(32, 127, int(rng.integers(0, 120)), dtype=np.uint8))
            body = body.replace(b"$", b"#").replace(b"*", b"+")
            if rng.random() < 0.5:
                body = fields[0].encode() + b"," + body
            return sentence(body)
        raise ValueError(f"no class {cls} here")

    def _vhw(self, cls: str) -> bytes:
        if cls == "walk":
            knots = 0.999 * OdometrySettings().max_speed / KNOT   # WALK_NS after the sentence before
            return sentence(f"IIVHW,{self.heading:.1f},T,,M,{knots:.3f},N,,K")
        good = f"IIVHW,{self.heading:.1f},T,{self.heading:.1f},M,5.0,N,9.3,K"
        return self._text_lines(cls, good, [1, 3, 5, 7])

    def _gga_body(self, quality: int = 1) -> str:
        """A GGA body anywhere on Earth, minutes below 60, as receivers write it."""
        rng = self.rng
        lat, lon = float(rng.uniform(0, 90)), float(rng.uniform(0, 180))
        minutes = [min((degrees % 1) * 60, 59.99999) for degrees in (lat, lon)]   # never 60.00000 rounded
        hhmmss = f"{int(rng.integers(24)):02d}{int(rng.integers(60)):02d}{float(rng.uniform(0, 59.99)):05.2f}"
        return (f"GPGGA,{hhmmss},{int(lat):02d}{minutes[0]:08.5f},{self._pick(('N', 'S'))},"
                f"{int(lon):03d}{minutes[1]:08.5f},{self._pick(('E', 'W'))},{quality},"
                f"{int(rng.integers(4, 30)):02d},{rng.uniform(0.5, 5):.2f},{rng.uniform(-100, 3000):.1f},M,"
                f"{rng.uniform(-100, 100):.1f},M,,")

    def _gga(self, cls: str) -> bytes:
        return self._text_lines(cls, self._gga_body(), [1, 2, 4, 6, 7, 8, 9, 11])

    def _det(self, cls: str) -> bytes:
        return self._text_lines(cls, "DET,320.0,240.0", [1, 2])

    def _nlink(self, cls: str) -> bytes:
        rng = self.rng
        mark = int(rng.choice([0x04, 0x05]))
        layout = LAYOUTS[mark]
        nodes = [(node, int(rng.integers(500, 50_000))) for node in PEERS]
        if cls == "random_bytes":
            return self._random_bytes()
        if cls == "extreme_numbers":
            extremes = [2**23 - 1, -(2**23), -1, 0, 1_000_001, 999_999, 8_000_000]
            many = [(int(rng.integers(256)), self._pick(extremes)) for _ in range(int(rng.integers(1, 65)))]
            return nlink_frame(mark, int(rng.integers(256)), 2**32 - 1, many)
        if cls == "non_finite":
            imu = tuple(float(self._pick((math.nan, math.inf, -math.inf, 3.4e38))) for _ in range(10))
            return nlink_frame(0x04, 1, int(rng.integers(2**32)), nodes, imu=imu)
        if cls == "truncated":
            frame = nlink_frame(mark, 1, 5, nodes)
            return frame[: int(rng.integers(1, len(frame)))]
        if cls == "wrong_fields":
            choice = rng.random()
            if choice < 0.4:   # the count disagrees with the length, the checksum right
                return nlink_frame(mark, 1, 5, nodes, count=int(rng.integers(256)))
            if choice < 0.7:   # a frame type this parser does not handle, framed like one
                frame = bytearray(nlink_frame(mark, 1, 5, nodes))
                frame[1] = self._pick((0x00, 0x01, 0x02, 0x03, 0x06, 0x55, 0xFF))
                frame[-1] = sum(frame[:-1]) & 0xFF
                return bytes(frame)
            frame = bytearray(nlink_frame(mark, 1, 5, nodes))   # a length field off by a little
            frame[2:4] = struct.pack("<H", len(frame) + int(self._pick((-2, -1, 1, 2, layout.block))))
            frame[-1] = sum(frame[:-1]) & 0xFF
            return bytes(frame)
        if cls == "overlong":
            length = self._pick((0xFFFF, layout.length(65), layout.length(255), 5000))
            return bytes([0x55, mark]) + struct.pack("<H", length) + rng.bytes(int(rng.integers(0, 600)))
        if cls == "garbage_payload":
            n = int(rng.integers(0, 8))
            frame = bytearray(layout.length(n))
            frame[:] = rng.bytes(len(frame))
            frame[0:2] = bytes([0x55, mark])
            frame[2:4] = struct.pack("<H", len(frame))
            frame[layout.count_at] = n
            frame[-1] = sum(frame[:-1]) & 0xFF
            return bytes(frame)
        raise ValueError(f"no class {cls} here")

    def _cmd(self, cls: str) -> bytes:
        rng = self.rng
        body = self.command()
        if cls == "random_bytes":
            return self._random_bytes() if rng.random() < 0.7 else b'{"stamp_ns": ' + rng.bytes(40)
        if cls in ("extreme_numbers", "non_finite"):
            pool = JSON_EXTREMES if cls == "extreme_numbers" else JSON_NON_FINITE
            text = json.dumps(body)
            names = rng.choice(["surge", "yaw_rate", "stamp_ns", "seq"], int(rng.integers(1, 3)),
                               replace=False)
            for name in names:
                text = text.replace(f'"{name}": {json.dumps(body[name])}', f'"{name}": {self._pick(pool)}')
            return text.encode()
        if cls == "truncated":
            text = json.dumps(body).encode()
            return text[: int(rng.integers(0, len(text)))]
        if cls == "wrong_fields":
            choice = rng.random()
            if choice < 0.3:
                del body[self._pick(list(body))]
            elif choice < 0.5:
                body["thrust"] = 1.0
            elif choice < 0.8:
                body["sender"] = self._pick(("2", "", "1 ", "x" * 40, 1, None))
            else:
                body[self._pick(list(body))] = self._pick(("1", None, [], {}, True, "NaN"))
            return json.dumps(body).encode()
        if cls == "overlong":
            return json.dumps(body | {"sender": "1" * int(rng.integers(1000, 100_000))}).encode()
        if cls == "garbage_payload":
            junk = {str(rng.integers(1000)): float(rng.normal()) for _ in range(int(rng.integers(0, 10)))}
            return json.dumps(junk if rng.random() < 0.5 else body | junk).encode()
        raise ValueError(f"no class {cls} here")


class _Campaign:
    """One parser's bridge, its clock, its generator of lines and its checks."""

    def __init__(self, parser: str, rng: np.random.Generator) -> None:
        self.parser, self.rng = parser, rng
        self.now_ns = START_NS
        self.monotonic = 1000.0
        self.out: list[tuple[str, bytes]] = []
        self.reported: list[str] = []
        settings = {
            "vhw": DriverSettings(odometry=OdometryPort(device="fuzz")),
            "det": DriverSettings(odometry=OdometryPort(device="fuzz"),
                                  camera=CameraPort(device="fuzz", camera=CAMERA)),
            "nlink": DriverSettings(uwb=UwbPort(device="fuzz", module=UwbSettings(peers=PEERS))),
            "cmd": DriverSettings(thrusters=ThrusterPort(device="fuzz", hull=HULL)),
            "gga": DriverSettings(gnss=GnssPort(device="fuzz")),
        }[parser]
        self.bridge = DriverBridge(VESSEL, settings, clock_ns=self.clock_ns, report=self.reported.append)
        self.publishers = {topic: _Publisher(topic, self.out)
                           for topic in ("sensor/odom", "sensor/uwb", "sensor/bearing", "truth/gnss")}
        self.results = ParserResults(parser)
        self.lines = SerialLines(parser, rng, now_ns=lambda: self.now_ns + STEP_NS)
        if parser == "det":   # the bearing needs a heading: one good VHW sentence first
            self.bridge._on_odometry(sentence("IIVHW,90.0,T,,M,1.0,N,,K"), self.publishers)
            self.out.clear()

    def clock_ns(self) -> int:
        """The campaign's wall clock: STEP_NS a line fed, and a microsecond each time it is read."""
        self.now_ns += 1000
        return self.now_ns

    # ----- feeding -----
    def feed(self, data: bytes, step: bool = True) -> None:
        """Hand `data` to the handler the driver's loop would call (after STEP_NS of the campaign's clocks,
        unless not `step`), then check what came out."""
        if step:
            self.now_ns += STEP_NS
            self.monotonic += STEP_NS * 1e-9
        bridge = self.bridge
        try:
            if self.parser == "vhw":
                bridge._on_odometry(data, self.publishers)
            elif self.parser == "det":
                bridge._on_camera(data, self.publishers)
            elif self.parser == "nlink":
                bridge._on_uwb(data, self.publishers)
            elif self.parser == "gga":
                bridge._on_gnss(data, self.publishers)
            else:
                bridge._on_command(_Sample(data))
                self._check_thrust(bridge.thrust_line(self.monotonic))
        except Exception as error:   # what the driver's loop would not survive: counted, must stay 0
            self.results.escaped[type(error).__name__] += 1
        self._check_out()

    def _check_out(self) -> None:
        for topic, payload in self.out:
            model = {"sensor/odom": Odometry, "sensor/uwb": Ranges, "sensor/bearing": Bearing,
                     "truth/gnss": GnssFix}[topic]
            message, reason = decode(model, payload)
            problem = reason or self._beyond(message)
            if problem:
                self.results.out_of_contract.append(f"{topic}: {problem}")
            elif topic == "sensor/odom":
                largest = max(map(abs, message.position))
                self.results.largest_position = max(self.results.largest_position, largest)
            self.results.published += 1
        self.out.clear()

    def _beyond(self, message) -> str:
        """What in a decoded message lies beyond what this campaign's bridge may say ("" if nothing)."""
        if isinstance(message, Odometry):
            inside = all(abs(c) <= MAX_POSITION for c in message.position)
            if not inside or not -math.pi <= message.heading <= math.pi:
                return f"odometry {message.position}, {message.heading}"
        elif isinstance(message, Ranges):
            limit = self.bridge.settings.uwb.module.max_range
            known = set(message.ranges) <= set(PEERS.values())
            if not known or not all(0 <= r <= limit for r in message.ranges.values()):
                return f"ranges {message.ranges}"
        elif isinstance(message, Bearing) and message.bearing is not None:
            if abs(math.hypot(*message.bearing) - 1.0) > 1e-9:
                return f"bearing {message.bearing}"
        return ""

    def _check_thrust(self, line: bytes) -> None:
        reader = LineReader()
        bodies = reader.feed(line)
        fields = bodies[0].decode().split(",") if len(bodies) == 1 else []
        try:
            left, right = float(fields[1]), float(fields[2])
            sound = len(fields) == 3 and fields[0] == "THR" and abs(left) <= 1.0 and abs(right) <= 1.0
        except (IndexError, ValueError):
            sound, left, right = False, math.nan, math.nan
        if not sound:
            self.results.out_of_contract.append(f"thrust line {line!r}")
        elif left or right:
            self.results.published += 1

    def heading_home(self) -> float:
        """The compass heading (deg) from the odometry's position towards its frame's origin."""
        state = self.bridge.dead_reckoning.state
        if state is None or math.hypot(state.x, state.y) < 1.0:
            return self.lines.heading
        east, north = -state.x, -state.y   # x east, y north (the VHW compass mapping)
        return math.degrees(math.atan2(east, north)) % 360

    # ----- the run -----
    def run(self, lines: int) -> ParserResults:
        rng, results = self.rng, self.results
        started = time.monotonic()
        classes = classes_for(self.parser)
        plan = [classes[i % len(classes)] for i in range(lines)]
        plan = [plan[i] for i in rng.permutation(len(plan))]
        gathered, size = 0, int(rng.integers(20, 201))
        for cls in plan:
            if cls == "burst":   # burst lines are gathered, then fed at once
                gathered += 1
                if gathered == size:
                    self._feed_burst(gathered)
                    gathered, size = 0, int(rng.integers(20, 201))
                continue
            if cls == "walk":
                self.now_ns += WALK_NS
            self.feed(self.lines.bad(cls))
            results.lines[cls] += 1
            if rng.random() < 0.5:
                self.feed(self.lines.good())
                results.good += 1
        if gathered:
            self._feed_burst(gathered)
        self.after_storm()
        results.refused = self.bridge.refusals()
        results.seconds = time.monotonic() - started
        return results

    def _feed_burst(self, count: int) -> None:
        """`count` bad lines of every other class, a good one after about every third (not counted), in a few
        large reads split at random; commands one after the other without time between."""
        rng = self.rng
        kinds = [c for c in classes_for(self.parser) if c not in ("burst", "walk")]
        pieces = []
        for _ in range(count):
            pieces.append(self.lines.bad(kinds[int(rng.integers(len(kinds)))]))
            if rng.random() < 0.3:
                pieces.append(self.lines.good())
        if self.parser == "cmd":   # a Zenoh payload comes whole
            for piece in pieces:
                self.feed(piece, step=False)
        else:
            data = (b"" if self.parser == "nlink" else b"\r\n").join(pieces)
            cuts = sorted(rng.integers(0, len(data), int(rng.integers(1, 5))).tolist())
            for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True):
                self.feed(data[a:b])
        self.results.lines["burst"] += count

    def after_storm(self) -> None:
        """Good lines alone: how many are published; for cmd, then silence: does the watchdog stop?"""
        results = self.results
        if self.parser in ("vhw", "det", "gga"):
            self.feed(b"\r\n")   # end whatever unfinished line the storm left
        if self.parser == "vhw":
            # Turn home first (not counted): at the edge the turn's arc may still bulge out, and be refused.
            self.feed(self.lines.good(self.heading_home()))
        before = results.published
        for _ in range(AFTER_STORM):
            self.feed(self.lines.good(self.heading_home()) if self.parser == "vhw" else self.lines.good())
        results.after_storm = results.published - before
        if self.parser == "cmd":
            self.monotonic += HULL.timeout + 0.2
            line = self.bridge.thrust_line(self.monotonic)
            results.watchdog_stopped = line.startswith(b"$THR,+0.000,+0.000*")


def run_serial_campaign(lines_per_parser: int = 20000, seed: int = 1,
                        progress: Callable[[str], None] | None = None) -> dict[str, ParserResults]:
    """At least `lines_per_parser` bad lines or frames through each parser, from one Generator seeded with
    `seed`; the results per parser (see ParserResults)."""
    rng = np.random.default_rng(seed)
    results = {}
    for parser in PARSERS:
        if progress is not None:
            progress(parser)
        results[parser] = _Campaign(parser, rng).run(lines_per_parser)
    return results


def sound(results: dict[str, ParserResults]) -> bool:
    """The campaign's verdict: nothing escaped, nothing beyond the contract, output again after the storm."""
    return all(not r.escaped and not r.out_of_contract and r.failed == 0 and r.after_storm > 0
               and r.watchdog_stopped is not False for r in results.values())


def render_serial_section(results: dict[str, ParserResults], command: str) -> str:
    """The markdown section of the serial campaign for the fuzz page."""
    rows = [[p, *[r.lines.get(c, "") if c in classes_for(p) else "-" for c in CLASSES], r.total, r.good]
            for p, r in results.items()]
    verdict = [[p, sum(r.escaped.values()), r.failed, len(r.out_of_contract), r.published,
                f"{r.after_storm} of {AFTER_STORM}",
                {True: "yes", False: "**no**", None: "-"}[r.watchdog_stopped],
                f"{r.seconds:.1f}"] for p, r in results.items()]
    lines = [
        "## Serial side: the driver bridge's parsers",
        "",
        "Generated by the command below (`usv-lab fuzz --serial-lines N --seed S`, or the serial side alone",
        "with `usv-lab serial-fuzz --lines N --seed S`: the same lines for the same N and S).",
        "`lab/benchmarks/serial_fuzz.py` describes the campaign and its classes; `tests/test_serial_fuzz.py` runs 2,000",
        "lines per parser in CI. Each parser is the driver's own handler (`usv-driver`'s `DriverBridge`), in",
        "process, on the campaign's clock.",
        "",
        "```",
        command,
        "```",
        "",
        markdown_table(["parser", "exceptions escaped", "caught by the last-resort guard",
                        "beyond the contract", "published", "good lines published after the storm",
                        "watchdog stops", "seconds"],
                       verdict),
        "",
        "`published`: messages out (odometry, ranges, bearings, GNSS fixes) or `$THR` lines that move the",
        "thrusters (cmd), good lines included. `beyond the contract`: a message that fails the contract or",
        "lies beyond this bridge's bounds (positions within 1e5 m, ranges within max_range to known peers,",
        "unit bearings), or a `$THR` line without a valid checksum or beyond [-1, 1].",
        "",
        "### Lines per parser and class",
        "",
        markdown_table(["parser", *CLASSES, "total", "good between"], rows),
        "",
        "### Refusals by reason",
        "",
        "A line is counted under the first check that refuses it (the line reader's `bad_checksum`,",
        "`malformed`, `too_long` before the sentence's own checks), not under its class; a burst mixes every",
        "class. `uwb:garbage` counts bytes skipped between frames, not frames; `camera:no_detection` counts",
        "`$DET,,` lines, published as a null bearing.",
        "",
    ]
    for parser, r in results.items():
        reasons = sorted(r.reasons().items(), key=lambda item: (-item[1], item[0]))
        lines += [f"**{parser}**" + (f" (largest |position| published: {r.largest_position:.0f} m)"
                                     if parser == "vhw" else ""), "",
                  markdown_table(["reason", "count"], reasons), ""]
    return "\n".join(lines)


def page_section(lines_per_parser: int, seed: int, command: str) -> tuple[str, bool]:
    """The campaign for `usv-lab fuzz` (progress on stdout): its page section, and whether it was sound."""
    print(f"serial side: {lines_per_parser} lines per parser, seed {seed} ...", flush=True)
    results = run_serial_campaign(lines_per_parser, seed,
                                  progress=lambda parser: print(f"  {parser}", flush=True))
    return render_serial_section(results, command), sound(results)


def add_arguments(parser) -> None:
    """`usv-lab serial-fuzz [--lines N] [--seed S]`: the serial campaign alone, its section on stdout (what
    `usv-lab fuzz --serial-lines N --seed S` puts on the page); exit 1 if it was not sound."""
    parser.add_argument("--lines", type=arguments.positive_int, default=20000, help="bad lines per parser")
    parser.add_argument("--seed", type=arguments.seed, default=1, help="seed of the lines' Generator")


def run(args) -> int:
    results = run_serial_campaign(args.lines, args.seed)
    print(render_serial_section(results, invocation(args)))
    return 0 if sound(results) else 1
