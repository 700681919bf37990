"""The MAVLink side of the fuzz campaign: hostile byte streams at the driver's autopilot link, in process.

`usv-driver` with a `mavlink:` section opens its link (driver_bridge/mavlink_link.py, pymavlink's mavutil) as
`udpin` on the loopback; the campaign is the other end, a UDP socket that plays the autopilot (system 1,
component 1: heartbeats in GUIDED and armed, ATTITUDE and LOCAL_POSITION_NED, answers to TIMESYNC) and sends
the agent's commands through the driver's own command handler. Every datagram goes through the driver's own
path (`DriverBridge._on_mavlink`: the link's parser, then MavlinkVehicle), on a clock of the campaign's own
(20 ms a datagram) so that a run repeats with its seed. Classes (one seeded numpy Generator):
random_bytes; truncated and bad_crc (a good frame cut, or one byte of it changed); wrong_system and
wrong_component (valid frames); any_fields (valid frames, any values: NaN, infinities, 3.4e38, integer
extremes); heartbeat_flood (20-200 heartbeats at once); refusal (COMMAND_ACK refusing the mode, arming or
stream rates); clock (positions whose time_boot_ms is out of order, far ahead, or a reboot's); mavlink1
(the good frames in MAVLink 1 framing: taken); burst (the others in one stream, cut at random).

Checks: no exception escapes and the driver's last-resort guard (`mavlink_failed`) catches nothing; every
odometry published decodes by the contract and lies within it; every set point on the wire is finite, within
the contract's speed bound, in the documented frame and type mask, to the autopilot's ids; after the storm
(one second to settle: a heartbeat and a TIMESYNC), every good position is published again and the set
points carry the agent's command. The parser's drops are counted by pymavlink's reason.
"""

from __future__ import annotations

import json
import math
import re
import select
import socket
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from agent.contract import MAX_POSITION, MAX_SPEED, Odometry, decode
from driver_bridge.mavlink_link import mavlink_module, open_link
from driver_bridge.mavlink_vehicle import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_FRAME_BODY_NED,
    ROVER_MODES,
    VELOCITY_YAW_RATE,
    MavlinkSettings,
    MavlinkVehicle,
)
from driver_bridge.node import DriverBridge, DriverSettings
from lab import arguments
from lab.benchmarks.serial_fuzz import _Publisher, _Sample
from lab.report.markdown import invocation, markdown_table

VESSEL = "1"
CLASSES = ("random_bytes", "truncated", "bad_crc", "wrong_system", "wrong_component", "any_fields",
           "heartbeat_flood", "refusal", "clock", "mavlink1", "burst")
STEP_NS = 20_000_000            # the campaign's clocks advance 20 ms per datagram
START_NS = 1_700_000_000 * 10**9
BOOT_NS = START_NS - 600 * 10**9   # the autopilot booted ten minutes before the campaign
SETTLE_STEPS = 50               # one second of good traffic after the storm before counting
AFTER_STORM = 200               # good positions after the storm
GUIDED, HOLD = ROVER_MODES["GUIDED"], ROVER_MODES["HOLD"]
FLOATS = (math.nan, -math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e30, -0.0, 1e-45, 7.0, 1e5, -1e5)
AGENT = (0.8, 0.1)              # the agent's command after the storm (surge m/s, yaw rate rad/s)


def _reason(text: str) -> str:
    """pymavlink's BAD_DATA reason without its numbers."""
    for key, name in (("prefix", "bad_prefix"), ("CRC", "bad_crc"), ("incompat", "bad_incompat_flags"),
                      ("length", "bad_length"), ("signature", "bad_signature"), ("header", "bad_header")):
        if key in text:
            return name
    return re.sub(r"[^a-z]+", "_", text.lower()).strip("_")[:40] or "other"


@dataclass
class MavlinkResults:
    datagrams: Counter = field(default_factory=Counter)      # bad datagrams (bursts: pieces) fed, by class
    frames: Counter = field(default_factory=Counter)         # hostile frames among them, by class
    good: int = 0                                            # good datagrams between them
    parser_dropped: Counter = field(default_factory=Counter)  # BAD_DATA out of pymavlink's parser, by reason
    messages: Counter = field(default_factory=Counter)       # parsed messages handed to the vehicle, by type
    refused: dict = field(default_factory=dict)              # the bridge's refusals(), by where and why
    events: Counter = field(default_factory=Counter)         # the vehicle's events (reboots, link lost, ...)
    escaped: Counter = field(default_factory=Counter)        # exceptions out of the driver: must stay 0
    out_of_contract: list = field(default_factory=list)      # beyond the contract: must stay empty
    published: int = 0                                       # odometry messages out
    setpoints: int = 0                                       # set points on the wire
    after_storm: int = 0                                     # of the AFTER_STORM good positions, published
    commanding: bool = False                                 # the last set point carries the agent's command
    seconds: float = 0.0

    @property
    def failed(self) -> int:
        return self.refused.get("refused", {}).get("mavlink_failed", 0)

    def reasons(self) -> Counter:
        return Counter(self.refused.get("vehicle_refused", {}))


class Autopilot:
    """The frames of the autopilot (good and hostile), from `rng`; `boot_ms` its clock."""

    def __init__(self, rng: np.random.Generator, mavlink) -> None:
        self.rng, self.mavlink = rng, mavlink
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.north = self.east = 0.0
        self.yaw = float(rng.uniform(-math.pi, math.pi))

    def _sender(self, system: int, component: int):
        return self.mavlink.MAVLink(None, srcSystem=system, srcComponent=component)

    def _pick(self, values):
        return values[int(self.rng.integers(len(values)))]

    def _f(self) -> float:
        rng = self.rng
        if rng.random() < 0.6:
            return float(self._pick(FLOATS))
        return float(rng.normal(0, 10.0 ** rng.integers(0, 8)))

    # ----- good frames -----
    def heartbeat(self, mode: int = GUIDED, armed: bool = True):
        return self.mav.heartbeat_encode(11, 3, 1 | (128 if armed else 0), mode, 4)

    def state(self, boot_ms: int) -> list:
        """ATTITUDE and LOCAL_POSITION_NED now, the boat 0.02 m further along its heading."""
        self.yaw = (self.yaw + 0.002 + math.pi) % (2 * math.pi) - math.pi
        self.north += 0.02 * math.cos(self.yaw)
        self.east += 0.02 * math.sin(self.yaw)
        return [self.mav.attitude_encode(boot_ms, 0.0, 0.0, self.yaw, 0.0, 0.0, 0.1),
                self.mav.local_position_ned_encode(boot_ms, self.north, self.east, 0.0, 1.0, 0.0, 0.0)]

    def pack(self, messages, mav=None, v1: bool = False) -> bytes:
        return b"".join(m.pack(mav or self.mav, force_mavlink1=v1) for m in messages)

    # ----- hostile frames -----
    def any_message(self, mav, boot_ms: int):
        """A message the adapter reads, with any field values."""
        rng, f = self.rng, self._f
        kind = int(rng.integers(6))
        if kind == 0:
            byte = lambda: int(rng.integers(256))  # noqa: E731
            return mav.heartbeat_encode(byte(), byte(), byte(),
                                        int(self._pick((0, 4, 15, 2**32 - 1, int(rng.integers(2**32))))),
                                        int(rng.integers(256)))
        if kind == 1:
            return mav.attitude_encode(int(rng.integers(2**32)), f(), f(), f(), f(), f(), f())
        if kind == 2:
            ms = int(self._pick((boot_ms, 0, 2**32 - 1, int(rng.integers(2**32)))))
            return mav.local_position_ned_encode(ms, f(), f(), f(), f(), f(), f())
        if kind == 3:
            ends = (0, 1, -1, 2**63 - 1, -(2**63), int(rng.integers(-(2**62), 2**62)))
            return mav.timesync_encode(int(self._pick(ends)), int(self._pick(ends)))
        if kind == 4:
            return mav.command_ack_encode(int(rng.integers(2**16)), int(rng.integers(256)))
        return mav.set_position_target_local_ned_encode(int(rng.integers(2**32)), 1, 191,
                                                        int(rng.integers(256)), int(rng.integers(2**16)),
                                                        *(f() for _ in range(11)))

    def bad(self, cls: str, boot_ms: int) -> tuple[bytes, int]:
        """The bytes of one hostile datagram of class `cls`, and how many frames it holds."""
        rng = self.rng
        if cls == "random_bytes":
            data = rng.bytes(int(rng.integers(1, 300)))
            if rng.random() < 0.5:   # start like a frame: the parser reads a header and waits for the rest
                data = bytes([self._pick((0xFD, 0xFE))]) + data
            return data, 1
        if cls in ("truncated", "bad_crc"):
            frame = bytearray(self.pack([self.any_message(self.mav, boot_ms) if rng.random() < 0.5
                                         else self.state(boot_ms)[1]], v1=rng.random() < 0.3))
            if cls == "truncated":
                return bytes(frame[: int(rng.integers(1, len(frame)))]), 1
            at = int(rng.integers(1, len(frame)))   # the magic kept: a frame, checked and refused
            frame[at] ^= int(rng.integers(1, 256))
            return bytes(frame), 1
        if cls in ("wrong_system", "wrong_component"):
            system = int(rng.integers(2, 256)) if cls == "wrong_system" else 1
            others = (0, 191, 190, int(rng.integers(2, 256)))
            component = 1 if cls == "wrong_system" else int(self._pick(others))
            sender = self._sender(system, component)
            good = [self.heartbeat(int(rng.integers(20)), bool(rng.random() < 0.5)), *self.state(boot_ms)]
            message = self._pick(good) if rng.random() < 0.5 else self.any_message(sender, boot_ms)
            return self.pack([message], sender), 1
        if cls == "any_fields":
            return self.pack([self.any_message(self.mav, boot_ms)], v1=rng.random() < 0.3), 1
        if cls == "heartbeat_flood":
            n = int(rng.integers(20, 201))
            beats = [self.heartbeat(int(self._pick((GUIDED, HOLD, 0, 99))), bool(rng.random() < 0.5))
                     for _ in range(n)]
            return self.pack(beats), n
        if cls == "refusal":
            command = int(self._pick((MAV_CMD_DO_SET_MODE, MAV_CMD_COMPONENT_ARM_DISARM,
                                      MAV_CMD_SET_MESSAGE_INTERVAL)))
            return self.pack([self.mav.command_ack_encode(command, int(rng.integers(1, 7)))]), 1
        if cls == "clock":
            choice = rng.random()
            if choice < 0.4:     # out of order: a little behind the last
                ms = boot_ms - int(rng.integers(20, 900))
            elif choice < 0.7:   # a reboot's clock
                ms = int(rng.integers(0, 5000))
            else:                # ahead of what is possible
                ms = boot_ms + int(rng.integers(300, 10**7))
            position = self.mav.local_position_ned_encode(ms % 2**32, self.north, self.east, 0, 0, 0, 0)
            return self.pack([position]), 1
        if cls == "mavlink1":
            return self.pack([self.heartbeat(), *self.state(boot_ms)], v1=True), 3
        raise ValueError(f"no class {cls} here")


class _Campaign:
    """The driver's bridge and its link on the loopback, the autopilot's socket, the clocks and the checks."""

    def __init__(self, rng: np.random.Generator) -> None:
        _, self.mavlink = mavlink_module()
        self.rng = rng
        self.now_ns, self.mono = START_NS, 1000.0
        self.results = MavlinkResults()
        self.out: list[tuple[str, bytes]] = []
        self.reported: list[str] = []
        self.link = open_link("udpin:127.0.0.1:0", 115_200, 1, 191)
        settings = DriverSettings(mavlink=MavlinkSettings(url="udpin:127.0.0.1:0", arm=True))
        self.bridge = DriverBridge(VESSEL, settings, clock_ns=self.clock_ns, report=self.reported.append)
        self.bridge.vehicle = MavlinkVehicle(settings.mavlink, self.link.mav, VESSEL, self.reported.append)
        self.publishers = {"sensor/odom": _Publisher("sensor/odom", self.out)}
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.socket.bind(("127.0.0.1", 0))
        self.socket.setblocking(False)
        self.address = self.link.connection.port.getsockname()
        self.autopilot = Autopilot(rng, self.mavlink)
        self.reader = self.mavlink.MAVLink(None)   # what the driver sends, read back off the wire
        self.reader.robust_parsing = True
        self.last_setpoint = None
        self._tap()

    def _tap(self) -> None:
        """Count what the link's parser hands the vehicle (BAD_DATA by reason) on its way there."""
        messages, results = self.link.messages, self.results

        def tapped() -> list:
            out = messages()
            for msg in out:
                kind = msg.get_type()
                results.messages[kind] += 1
                if kind == "BAD_DATA":
                    results.parser_dropped[_reason(str(msg.reason))] += 1
            return out

        self.link.messages = tapped

    def clock_ns(self) -> int:
        return self.now_ns

    @property
    def boot_ms(self) -> int:
        return (self.now_ns - BOOT_NS) // 1_000_000 - 1   # made a millisecond before it comes

    def close(self) -> None:
        self.socket.close()
        self.link.close()

    # ----- the wire -----
    def send(self, data: bytes) -> None:
        """One datagram to the driver, which reads it (and whatever follows) as its loop would."""
        self.socket.sendto(data, self.address)
        self._call(self.bridge._on_mavlink, self.link, self.publishers, self.mono)
        while select.select([self.link.fd], [], [], 0)[0]:
            self._call(self.bridge._on_mavlink, self.link, self.publishers, self.mono)
        self._check_odometry()

    def step(self, good: bool) -> None:
        """STEP_NS on; the autopilot's state (a heartbeat each second) if `good`; what the driver sends."""
        self.now_ns += STEP_NS
        self.mono += STEP_NS * 1e-9
        if good:
            beat = [self.autopilot.heartbeat()] if (self.now_ns - START_NS) % 10**9 == 0 else []
            self.send(self.autopilot.pack([*beat, *self.autopilot.state(self.boot_ms)]))
            self.results.good += 1
        self._call(self.bridge._drive_vehicle, self.link, self.mono)
        self._read_wire()

    def command(self, surge: float, yaw_rate: float) -> None:
        body = {"stamp_ns": self.now_ns, "seq": 0, "sender": VESSEL, "surge": surge, "yaw_rate": yaw_rate}
        self._call(self.bridge._on_command, _Sample(json.dumps(body).encode()))

    def _call(self, handler, *args) -> None:
        try:
            handler(*args)
        except Exception as error:   # what the driver's loop would not survive: counted, must stay 0
            self.results.escaped[type(error).__name__] += 1

    def _read_wire(self) -> None:
        """The driver's datagrams: set points checked, TIMESYNC requests answered as the autopilot would."""
        while True:
            try:
                data = self.socket.recv(65536)
            except BlockingIOError:
                return
            for msg in self.reader.parse_buffer(data) or []:
                kind = msg.get_type()
                if kind == "SET_POSITION_TARGET_LOCAL_NED":
                    self._check_setpoint(msg)
                elif kind == "TIMESYNC" and msg.tc1 == 0:
                    reply = self.autopilot.mav.timesync_encode((self.now_ns - BOOT_NS), msg.ts1)
                    self.send(self.autopilot.pack([reply]))

    def _check_setpoint(self, msg) -> None:
        self.results.setpoints += 1
        self.last_setpoint = (msg.vx, msg.yaw_rate)
        sound = (math.isfinite(msg.vx) and math.isfinite(msg.yaw_rate) and abs(msg.vx) <= MAX_SPEED
                 and abs(msg.yaw_rate) <= MAX_SPEED and msg.vy == 0.0 and msg.vz == 0.0
                 and msg.type_mask == VELOCITY_YAW_RATE and msg.coordinate_frame == MAV_FRAME_BODY_NED
                 and (msg.target_system, msg.target_component) == (1, 1))
        if not sound:
            self.results.out_of_contract.append(f"set point {msg}")

    def _check_odometry(self) -> None:
        for _, payload in self.out:
            message, reason = decode(Odometry, payload)
            if reason:
                self.results.out_of_contract.append(f"odometry: {reason}")
            elif not (all(abs(c) <= MAX_POSITION for c in message.position)
                      and -math.pi <= message.heading <= math.pi):
                self.results.out_of_contract.append(f"odometry {message.position}, {message.heading}")
            self.results.published += 1
        self.out.clear()

    # ----- the run -----
    def run(self, datagrams: int) -> MavlinkResults:
        rng, results = self.rng, self.results
        started = time.monotonic()
        for _ in range(SETTLE_STEPS):   # the link comes up: heartbeats, a clock offset, odometry
            self.step(good=True)
        plan = [CLASSES[i % len(CLASSES)] for i in range(datagrams)]
        plan = [plan[i] for i in rng.permutation(len(plan))]
        for cls in plan:
            if rng.random() < 0.1:   # the agent's command, now and then beyond any bound
                self.command(*(self.autopilot._f() if rng.random() < 0.3 else float(rng.uniform(-2, 2))
                               for _ in range(2)))
            if cls == "burst":
                self._burst()
            else:
                data, frames = self.autopilot.bad(cls, self.boot_ms)
                self.send(data)
                results.datagrams[cls] += 1
                results.frames[cls] += frames
            self.step(good=rng.random() < 0.5)
        self.after_storm()
        results.refused = self.bridge.refusals()
        results.events = Counter(self.bridge.vehicle.events)
        results.seconds = time.monotonic() - started
        return results

    def _burst(self) -> None:
        """A few hostile datagrams of the other classes and good state in one stream, cut at random."""
        rng, kinds = self.rng, CLASSES[:-1]
        pieces = []
        for _ in range(int(rng.integers(2, 8))):
            cls = kinds[int(rng.integers(len(kinds)))]
            data, frames = self.autopilot.bad(cls, self.boot_ms)
            pieces.append(data)
            self.results.frames["burst"] += frames
            if rng.random() < 0.3:
                pieces.append(self.autopilot.pack(self.autopilot.state(self.boot_ms)))
        data = b"".join(pieces)
        cuts = sorted(rng.integers(0, len(data), int(rng.integers(1, 4))).tolist())
        for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True):
            if b > a:
                self.send(data[a:b])
                self.results.datagrams["burst"] += 1

    def after_storm(self) -> None:
        """Good traffic alone, the agent commanding: a second to settle, then AFTER_STORM positions."""
        for k in range(SETTLE_STEPS + AFTER_STORM):
            if k % 5 == 0:
                self.command(*AGENT)
            if k == SETTLE_STEPS:
                before = self.results.published
            self.step(good=True)
        self.results.after_storm = self.results.published - before
        expected = self.autopilot.mav.set_position_target_local_ned_encode(
            0, 1, 1, 0, 0, 0, 0, 0, AGENT[0], 0, 0, 0, 0, 0, 0, -AGENT[1])
        wire = self.reader.parse_buffer(expected.pack(self.autopilot.mav))[0]   # the float32 values
        self.results.commanding = self.last_setpoint == (wire.vx, wire.yaw_rate)


def run_mavlink_campaign(datagrams: int = 20000, seed: int = 1) -> MavlinkResults:
    """At least `datagrams` hostile datagrams at the driver's link, from a Generator seeded with `seed`."""
    campaign = _Campaign(np.random.default_rng(seed))
    try:
        return campaign.run(datagrams)
    finally:
        campaign.close()


def sound(r: MavlinkResults) -> bool:
    """Nothing escaped or caught by the guard, nothing beyond the contract, odometry and commands again."""
    return (not r.escaped and r.failed == 0 and not r.out_of_contract and r.after_storm == AFTER_STORM
            and r.commanding)


def render_mavlink_section(r: MavlinkResults, command: str) -> str:
    """The markdown section of the MAVLink campaign for the fuzz page."""
    table = lambda counts: markdown_table(  # noqa: E731
        ["reason", "count"], sorted(counts.items(), key=lambda item: (-item[1], item[0])))
    return "\n".join([
        "## MAVLink side: the driver's autopilot link",
        "",
        "Generated by the command below (`usv-lab fuzz --mavlink-datagrams N --seed S`, or the MAVLink side",
        "alone with `usv-lab mavlink-fuzz --datagrams N --seed S`: the same datagrams for the same N and S).",
        "`lab/benchmarks/mavlink_fuzz.py` describes the campaign and its classes;",
        "`tests/test_mavlink_fuzz.py` runs 1,500 datagrams in CI. Each datagram goes over the loopback into",
        "the driver's own link (pymavlink's parser) and its `MavlinkVehicle`, in process, on the campaign's",
        "clock.",
        "",
        "```",
        command,
        "```",
        "",
        markdown_table(["exceptions escaped", "caught by the last-resort guard", "beyond the contract",
                        "odometry published", "set points sent", "good positions published after the storm",
                        "commanding after the storm", "seconds"],
                       [[sum(r.escaped.values()), r.failed, len(r.out_of_contract), r.published, r.setpoints,
                         f"{r.after_storm} of {AFTER_STORM}", "yes" if r.commanding else "**no**",
                         f"{r.seconds:.1f}"]]),
        "",
        "### Datagrams and frames per class",
        "",
        markdown_table(["class", "datagrams", "frames"],
                       [[c, r.datagrams[c], r.frames[c]] for c in CLASSES] + [["good between", r.good, ""]]),
        "",
        "### Dropped by the parser (BAD_DATA, by pymavlink's reason)",
        "",
        table(r.parser_dropped),
        "",
        "### Refused by the vehicle adapter, by reason",
        "",
        "`bad_data` counts the parser's drops above again; a refused mode, arming or stream rate is a",
        "COMMAND_ACK refusing it, said once on stderr.",
        "",
        table(r.reasons()),
        "",
        "Events: " + (", ".join(f"{k} {v}" for k, v in sorted(r.events.items())) or "none") + ".",
        "",
    ])


def page_section(datagrams: int, seed: int, command: str) -> tuple[str, bool]:
    """The campaign for `usv-lab fuzz` (progress on stdout): its page section, and whether it was sound."""
    print(f"MAVLink side: {datagrams} datagrams, seed {seed} ...", flush=True)
    results = run_mavlink_campaign(datagrams, seed)
    return render_mavlink_section(results, command), sound(results)


def add_arguments(parser) -> None:
    """`usv-lab mavlink-fuzz [--datagrams N] [--seed S]`: the MAVLink campaign alone, its section on stdout;
    exit 1 if it was not sound."""
    parser.add_argument("--datagrams", type=arguments.positive_int, default=20000, help="hostile datagrams")
    parser.add_argument("--seed", type=arguments.seed, default=1, help="seed of the datagrams' Generator")


def run(args) -> int:
    results = run_mavlink_campaign(args.datagrams, args.seed)
    print(render_mavlink_section(results, invocation(args)))
    return 0 if sound(results) else 1

