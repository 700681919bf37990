"""The wire contract between an agent and whatever stands in for the hardware (sim bridge or driver bridge).

Every message is a pydantic model encoded as JSON; every payload carries `stamp_ns` (its own time, in the
clock the fleet runs on), `seq` (per sender and key, increasing by one; informative: receivers judge freshness
by stamps) and `sender`. The same models give the wire format, the validation of bad input (types, and values
within the physical limits below: positions, speeds, angles, covariances that are symmetric positive
semi-definite, int64 stamps) and the JSON schema written into logs. Keys:

    usv/<id>/sensor/odom     Odometry      bridge -> agent   cumulative position and heading, own frame
    usv/<id>/sensor/uwb      Ranges        bridge -> agent   ranges to named peers (m)
    usv/<id>/sensor/bearing  Bearing       bridge -> agent   unit vector from the target to the vessel, or null
    usv/<id>/sensor/sonar    Sonar         bridge -> agent   obstacle points relative to the vessel (m)
    usv/<id>/sensor/vehicle  VehicleState  driver -> agent   an autopilot's mode and arming (optional; in the status)
    usv/<id>/cmd             Cmd           agent -> bridge   surge speed (m/s), yaw rate (rad/s)
    usv/<id>/share/<j>       ShareMessage  agent -> agent j  what neighbour j needs (share format 2)
    usv/<id>/share           ShareMessage  agent -> agents   the same for all, every pair estimate (format 1)
    usv/<id>/status          Status        agent -> anyone   estimates, covariances, health
    usv/<id>/alive           (liveliness token of the agent)
    sim/clock                Clock         sim bridge -> all sim time, one message per tick
    mission/all, mission/<id> MissionCommand operator -> agents   start, hold, resume, set (radius, yaw rate)
    usv/<id>/truth/gnss      GnssFix       driver -> scoring GNSS fixes of a field trial; no agent reads it

docs/contract.md is the page a driver-bridge author follows.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_serializer, model_validator

from agent.cholesky import cholesky_succeeds
from agent.config import StrictModel

FLEET_PREFIX = "usv"
CLOCK_KEY = "sim/clock"
# In real time on sim time the clock comes first and each vessel's sensors of the tick within this fraction of dt
# after it (the sim bridge's `stagger` is at most this); an agent waits for them a quarter of dt beyond it.
MAX_SENSOR_STAGGER = 0.5
TRUTH_KEY = "sim/truth"  # a simulation's ground truth each tick, in real time only: for viewers, no agent reads it
GNSS_TRUTH_TOPIC = "truth/gnss"  # usv/<id>/truth/gnss: GNSS fixes to score a field trial; no agent reads it
MISSION_PREFIX = "mission"
MISSION_ALL = "all"      # mission/all: every vessel; mission/<id>: one
MAX_RADIUS = 1e4         # m: the largest circle a mission command may ask for
MAX_YAW_RATE = math.pi   # rad/s: the fastest circling a mission command may ask for (a lap in 2 s)
LIVELINESS = "alive"
SHARE = "share"
# The share's format. 1: one message on usv/<id>/share to every agent, with all n - 1 pair estimates. 2: one
# message per receiver j on usv/<id>/share/<j>, with j's estimate only, so that Zenoh routes each to j alone.
SHARE_FORMAT = 2
# A pair's observability verdicts as the status states them; the core computes them (agent/core/observability.py,
# whose VERDICTS a test holds equal to these).
VERDICTS = ("observable", "mirror-ambiguous", "unobservable")

VESSEL_ID_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"
VesselId = Annotated[str, Field(pattern=VESSEL_ID_PATTERN)]
_VESSEL_ID = re.compile(VESSEL_ID_PATTERN.replace("$", r"\Z"))
MAX_SONAR_POINTS = 4096
MAX_PEERS = 256
# Physical limits of what a payload may say. Each is far beyond any mission and far inside what float arithmetic
# handles without overflow: a value beyond one is refused at the gate, so the core never sees it.
MAX_POSITION = 1e5        # m: positions, ranges, pair offsets and obstacle points (100 km)
MAX_SPEED = 1e3           # m/s: velocities in a share, the surge of a command
MAX_ANGLE = 1e6           # rad: headings, phases and yaw rates, wrapped or not (finite, and precise to 1e-10 rad)
MAX_LEVER_ARM = 20.0      # m: each component of an antenna's lever arm from its hull's centre
MAX_VARIANCE = MAX_POSITION**2   # m^2 (or (m/s)^2, rad^2): every entry of a covariance
MAX_STAMP_NS = 2**63 - 1  # stamps and sequence numbers are int64 on the wire
MAX_PAYLOAD_BYTES = 1 << 21   # 2 MiB: more than the largest valid message (a Clock's full `lost` list, ~1 MB)
COVARIANCE_TOLERANCE = 1e-9   # relative: asymmetry and negative eigenvalues allowed for rounding

Finite = Annotated[float, Field(allow_inf_nan=False)]
Coordinate = Annotated[float, Field(ge=-MAX_POSITION, le=MAX_POSITION, allow_inf_nan=False)]
Distance = Annotated[float, Field(ge=0, le=MAX_POSITION, allow_inf_nan=False)]
SpeedComponent = Annotated[float, Field(ge=-MAX_SPEED, le=MAX_SPEED, allow_inf_nan=False)]
Angle = Annotated[float, Field(ge=-MAX_ANGLE, le=MAX_ANGLE, allow_inf_nan=False)]
Variance = Annotated[float, Field(ge=-MAX_VARIANCE, le=MAX_VARIANCE, allow_inf_nan=False)]
StampNs = Annotated[int, Field(ge=0, le=MAX_STAMP_NS)]
Vec2 = tuple[Coordinate, Coordinate]
LeverArm = tuple[Annotated[float, Field(ge=-MAX_LEVER_ARM, le=MAX_LEVER_ARM, allow_inf_nan=False)], ...]
Velocity = tuple[SpeedComponent, SpeedComponent]


def _mirrored(size: int) -> tuple[tuple[int, int], ...]:
    """The row-major indices of each entry above the diagonal of a size x size matrix and of its mirror image."""
    return tuple((i * size + j, j * size + i) for i in range(size) for j in range(i + 1, size))


_MIRRORED = {size: _mirrored(size) for size in (2, 3, 4)}     # the sizes of the contract's covariances


def covariance_problem(values, size: int) -> str | None:
    """Why `values` (size x size, row-major) is not a covariance: not symmetric, or not positive semi-definite
    (both up to COVARIANCE_TOLERANCE of its largest entry); None if it is one. The entries are already finite
    and within +-MAX_VARIANCE.

    Every share, odometry and pair estimate is checked, several per tick: the usual case is decided in plain
    floats (a Cholesky factorisation of M + tolerance I that succeeds proves the smallest eigenvalue above
    -tolerance), and only a matrix it cannot clear goes to numpy's eigenvalues for the verdict."""
    if len(values) != size * size:
        return f"needs {size * size} numbers ({size}x{size}, row-major)"
    scale = max(map(abs, values))
    if scale == 0.0:
        return None
    tolerance = COVARIANCE_TOLERANCE * scale
    for upper, lower in _MIRRORED.get(size) or _mirrored(size):
        if abs(values[upper] - values[lower]) > tolerance:
            return "is not symmetric"
    if size == 2:
        return _semi_definite_2x2(values[0], 0.5 * (values[1] + values[2]), values[3], tolerance)
    if cholesky_succeeds(values, size, tolerance):
        return None
    matrix = np.array(values, dtype=float).reshape(size, size)
    if float(np.linalg.eigvalsh(0.5 * (matrix + matrix.T))[0]) < -tolerance:
        return "is not positive semi-definite"
    return None


def pair_covariance_problem(p11: float, p12: float, p22: float) -> str | None:
    """`covariance_problem` of the symmetric [[p11, p12], [p12, p22]] given by its three numbers (a share's pair
    estimate, n - 1 of them in every share): symmetric by construction, so only the eigenvalue is judged."""
    scale = max(abs(p11), abs(p12), abs(p22))
    if scale == 0.0:
        return None
    return _semi_definite_2x2(p11, p12, p22, COVARIANCE_TOLERANCE * scale)


def _semi_definite_2x2(a: float, b: float, c: float, tolerance: float) -> str | None:
    # Closed form: the smaller eigenvalue of [[a, b], [b, c]].
    smallest = 0.5 * (a + c) - math.hypot(0.5 * (a - c), b)
    return "is not positive semi-definite" if smallest < -tolerance else None


# ----- keys -----
def mission_key(vessel: str | None = None) -> str:
    """`mission/<vessel>`, or `mission/all` for the whole fleet (None)."""
    return f"{MISSION_PREFIX}/{MISSION_ALL if vessel is None else vessel}"


def key(vessel: str, topic: str) -> str:
    """`usv/<vessel>/<topic>`; topic is one of the names in TOPICS, or "alive" (the liveliness token)."""
    if topic not in TOPICS and topic != LIVELINESS:
        raise ValueError(f"unknown topic {topic!r}; known: {', '.join([*TOPICS, LIVELINESS])}")
    return f"{FLEET_PREFIX}/{vessel}/{topic}"


def gnss_truth_key(vessel: str) -> str:
    """`usv/<vessel>/truth/gnss`: the driver's GNSS fixes (GnssFix), outside every agent's subscriptions."""
    return f"{FLEET_PREFIX}/{vessel}/{GNSS_TRUTH_TOPIC}"


def share_key(sender: str, receiver: str | None = None) -> str:
    """`usv/<sender>/share/<receiver>` (format 2), or `usv/<sender>/share` for every agent (None: format 1)."""
    return key(sender, SHARE) if receiver is None else f"{key(sender, SHARE)}/{receiver}"


def shares_for(receiver: str) -> str:
    """Key expression of every sender's per-pair share to `receiver` (format 2)."""
    return share_key("*", receiver)


def share_receivers(key_expr: str) -> str | None:
    """Who receives a share published on `key_expr`: the receiver of a per-pair key, "*" for a broadcast
    key (every agent but the sender), None for a key that holds no share."""
    parts = str(key_expr).split("/")
    if len(parts) < 3 or parts[0] != FLEET_PREFIX or parts[2] != SHARE or len(parts) > 4:
        return None
    return parts[3] if len(parts) == 4 else "*"


def every(topic: str) -> str:
    """Key expression matching `topic` of every vessel (for subscribers)."""
    return key("*", topic)


def vessel_of(key_expr: str) -> str | None:
    """The vessel id in a `usv/<id>/...` key, or None."""
    parts = str(key_expr).split("/")
    return parts[1] if len(parts) >= 3 and parts[0] == FLEET_PREFIX else None


# ----- messages -----
class Header(StrictModel):
    stamp_ns: StampNs = Field(description="time of the content, ns, in the fleet's clock")
    seq: int = Field(ge=0, le=MAX_STAMP_NS, description="per sender and key, +1 per message (informative only)")
    sender: VesselId


class Odometry(Header):
    position: Vec2 = Field(description="cumulative dead-reckoned position in the vessel's own frame (m)")
    heading: Angle = Field(description="yaw in the common heading reference (rad)")
    covariance: tuple[Variance, ...] = Field(
        (0.0,) * 9, max_length=9, description="3x3 covariance of (x, y, yaw), row-major: symmetric, positive "
                                              "semi-definite")

    @field_validator("covariance")
    @classmethod
    def _three_by_three(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if len(value) == 9 and any(value[i] < 0 for i in (0, 4, 8)):
            raise ValueError("covariance has a negative variance")
        problem = covariance_problem(value, 3)
        if problem:
            raise ValueError(f"covariance {problem}")
        return value


class Ranges(Header):
    ranges: dict[VesselId, Distance] = Field(description="peer id -> measured range (m)")

    @field_validator("ranges")
    @classmethod
    def _not_too_many(cls, value: dict) -> dict:
        if len(value) > MAX_PEERS:
            raise ValueError(f"more than {MAX_PEERS} peers")
        return value


class Bearing(Header):
    bearing: Vec2 | None = Field(description="unit vector from the target to the vessel; null: no target")

    @field_validator("bearing")
    @classmethod
    def _unit(cls, value: tuple[float, float] | None) -> tuple[float, float] | None:
        if value is not None and abs(math.hypot(*value) - 1.0) > 0.5:
            raise ValueError("bearing must be a unit vector")
        return value


class Sonar(Header):
    points: list[Vec2] = Field(max_length=MAX_SONAR_POINTS,
                               description="obstacle points relative to the vessel (m)")


class Cmd(Header):
    surge: SpeedComponent = Field(description="surge speed (m/s)")
    yaw_rate: Angle = Field(description="yaw rate (rad/s)")


class PairEstimate(StrictModel):
    position: Vec2
    covariance: tuple[Variance, Variance, Variance] = Field(
        description="p11, p12, p22 of a symmetric positive semi-definite 2x2")
    stamp_ns: StampNs | None = Field(
        None, description="the time the estimate refers to, in the sender's clock, not after the share's stamp; "
                          "None: the share's stamp")

    @field_validator("covariance")
    @classmethod
    def _semi_definite(cls, value):
        problem = pair_covariance_problem(*value)
        if problem:
            raise ValueError(f"covariance {problem}")
        return value


class _ShareBody(Header):
    """What a share carries besides its pair estimates, and its checks."""

    position: Vec2
    heading: Angle
    velocity: Velocity
    phase: Angle
    target: tuple[Coordinate, Coordinate, SpeedComponent, SpeedComponent] | None = None
    target_covariance: tuple[Variance, ...] | None = Field(
        None, max_length=16, description="4x4, row-major: symmetric, positive semi-definite")
    antenna: LeverArm | None = Field(
        None, min_length=2, max_length=2,
        description="the sender's UWB antenna (forward, left) from its hull's centre (m); absent: at it")

    @field_validator("target_covariance")
    @classmethod
    def _four_by_four(cls, value):
        problem = None if value is None else covariance_problem(value, 4)
        if problem:
            raise ValueError(f"target_covariance {problem}")
        return value

    @model_serializer(mode="wrap")
    def _antenna_only_when_given(self, handler):
        # A share without an antenna is encoded as before the field existed, so that a receiver that predates
        # it (extra fields are refused) still takes the shares of a sender that has none.
        data = handler(self)
        if self.antenna is None:
            data.pop("antenna", None)
        return data

    @model_validator(mode="after")
    def _target_with_covariance(self):
        if (self.target is None) != (self.target_covariance is None):
            raise ValueError("target and target_covariance come together")
        return self

    def _not_later(self, estimates) -> list[str]:
        return [j for j, e in estimates if e.stamp_ns is not None and e.stamp_ns > self.stamp_ns]


class ShareMessage(_ShareBody):
    """Share of tick_io, on the wire: odometry at `stamp_ns`, commanded velocity, phase, estimates. What a
    sender builds, and the schema of the key; a receiver decodes it as `ReceivedShare`."""

    neighbours: dict[VesselId, PairEstimate] = Field(default_factory=dict, max_length=MAX_PEERS)

    @model_validator(mode="after")
    def _estimates_not_later(self):
        later = self._not_later(self.neighbours.items())
        if later:
            raise ValueError(f"estimates of {later[:3]} refer to a time after the share's stamp")
        return self


class ReceivedShare(_ShareBody):
    """A share as one receiver decodes it: everything checked as in `ShareMessage` except the pair estimates
    of other vessels, which only those vessels use (and check). A share carries n - 1 of them, and every
    vessel receives n - 1 shares a tick: checking them all would cost each vessel O(n^2) per tick.
    `estimate_for` checks the receiver's own."""

    neighbours: dict[VesselId, Any] = Field(default_factory=dict, max_length=MAX_PEERS)
    wire_name: ClassVar[str] = "ShareMessage"     # what a refusal's reason calls it

    def estimate_for(self, receiver: str) -> tuple[PairEstimate | None, str]:
        """(the sender's estimate of its pair with `receiver`, or None if it sent none; "") or (None, why it is
        not valid), as `ShareMessage` would have judged it."""
        if receiver not in self.neighbours:
            return None, ""
        try:
            estimate = PairEstimate.model_validate(self.neighbours[receiver])
        except ValidationError as error:
            return None, _invalid(self.wire_name, error, ("neighbours", receiver))
        if self._not_later([(receiver, estimate)]):
            return None, f"{self.wire_name}: estimates of {[receiver]} refer to a time after the share's stamp"
        return estimate, ""


class MissionCommand(Header):
    """What the operator tells the fleet (`mission/all`) or one vessel (`mission/<id>`). `sender` is the
    operator's id; (`sender`, `session`, `seq`) names one command: an agent refuses a second one of the same
    name while its stamp is within the input window (a replay), and a sender starting again takes a new
    session (usv-op: a random one per invocation), so that its seqs may start anywhere.
    `hold`: stop and keep station, as the watchdog does; `resume`, `start`: circle again; `set`: a new circle
    radius, yaw rate (its size) and/or direction, taken at the next tick."""

    command: Literal["start", "hold", "resume", "set"]
    session: str = Field("", max_length=32, pattern=r"^[A-Za-z0-9_-]*$",
                         description="the sender's session: a new one for each run of the sender")
    # strict: JSON true is not a radius of 1 m.
    radius: Annotated[float, Field(gt=0, le=MAX_RADIUS, allow_inf_nan=False, strict=True)] | None = Field(
        None, description="set: r*, the circle's radius (m)")
    yaw_rate: Annotated[float, Field(gt=0, le=MAX_YAW_RATE, allow_inf_nan=False, strict=True)] | None = Field(
        None, description="set: |omega*|, how fast to circle (rad/s); the direction stays unless given")
    direction: Literal["ccw", "cw"] | None = Field(
        None, description="set: circle counter-clockwise (ccw) or clockwise (cw), seen from above")

    @model_validator(mode="after")
    def _values_with_set(self):
        given = self.radius is not None or self.yaw_rate is not None or self.direction is not None
        if self.command == "set" and not given:
            raise ValueError("set needs radius, yaw_rate or direction")
        if self.command != "set" and given:
            raise ValueError(f"{self.command} takes no radius, yaw_rate or direction")
        return self


class MissionAck(StrictModel):
    """An agent's answer to the latest mission command it judged (in its status)."""

    sender: str = Field(max_length=64, description="the command's sender, as received")
    seq: int = Field(ge=0, le=MAX_STAMP_NS)
    command: str = Field(max_length=16)
    applied: bool = Field(description="false: refused, and `reason` says why")
    reason: str = Field("", max_length=300)
    stamp_ns: StampNs = Field(description="the tick at which it was applied or refused")


class WeakestPair(StrictModel):
    """The neighbour whose relative motion has told its pair filter least (agent/core/observability.py)."""

    neighbour: VesselId
    # Its square root is the path's width in its narrowest direction.
    excitation: Annotated[float, Field(ge=0, allow_inf_nan=False)] = Field(
        description="smallest eigenvalue of the relative path's spread over the observability window (m^2)")
    observability: Literal[VERDICTS]


CLOCK_SOURCE_SENSORS = "sensors"   # ClockOffset.source of this vessel's sensor stamps (its driver's clock)


class ClockOffset(StrictModel):
    """A clock that disagrees with the agent's: the stamps of one source (this vessel's sensors, or one
    neighbour's shares) run consistently further from the agent's clock than its input window allows."""

    source: Annotated[str, Field(pattern=VESSEL_ID_PATTERN)] = Field(
        description=f"'{CLOCK_SOURCE_SENSORS}' (this vessel's sensor stamps) or the id of the neighbour "
                    "whose shares are stamped so")
    # The median over the source's recent messages: > 0 ahead of the agent's clock, < 0 behind.
    offset: Annotated[float, Field(ge=-1e9, le=1e9, allow_inf_nan=False)] = Field(
        description="its stamps minus the agent's clock at their arrival (s), median of the recent ones")


VEHICLE_TOPIC = "sensor/vehicle"   # optional: only a driver with an autopilot publishes it; no tick reads it


class VehicleState(Header):
    """What an autopilot says of itself (a MAVLink HEARTBEAT), as its driver bridge reads it: the agent
    repeats the latest in its status for the operator and steers by nothing in it."""

    mode: str = Field(max_length=24, pattern=r"^[A-Za-z0-9_ ]*$",
                      description="the autopilot's mode (ArduPilot Rover: MANUAL, ACRO, HOLD, GUIDED, ...)")
    armed: bool = Field(description="the autopilot is armed: its motors follow commands")
    linked: bool = Field(description="its heartbeat came within the driver's link timeout")
    control: str = Field(max_length=16, pattern=r"^[a-z_]*$",
                         description="how the driver commands it: 'guided' set points or 'acro' sticks")
    refused: int = Field(0, ge=0, le=MAX_STAMP_NS, description="mode changes and arming the autopilot refused")


class Status(Header):
    phase: Finite
    command: tuple[Finite, Finite]
    shared: bool = Field(False, description="this tick published a share (the sim bridge's radio needs to know)")
    peers: list[VesselId] = Field(default_factory=list, max_length=MAX_PEERS,
                                  description="the agents this one sees alive (liveliness)")
    ticked: bool = Field(True, description="false for a heartbeat before the agent's first tick")
    target: tuple[Finite, Finite, Finite, Finite] | None = None
    health: dict[str, int] = Field(default_factory=dict)
    weakest_pair: WeakestPair | None = Field(None, description="None: no pair filter running this tick")
    held: bool = Field(False, description="a mission command `hold` is in force: commanding STOP")
    radius: Annotated[float, Field(gt=0, le=MAX_POSITION, allow_inf_nan=False)] | None = Field(
        None, description="r*: the radius of the circle this vessel steers to now (m)")
    mission: list[MissionAck] = Field(default_factory=list, max_length=8,
                                      description="the latest mission command judged from each sender")
    # Every source whose stamps run consistently outside the input window of the agent's clock.
    clocks: list[ClockOffset] = Field(
        default_factory=list, max_length=MAX_PEERS + 1,
        description="the alarm of clocks that disagree with the agent's (empty: none)")
    vehicle: VehicleState | None = Field(None, description="the autopilot's latest state; absent: no autopilot")

    @model_serializer(mode="wrap")
    def _vehicle_only_when_given(self, handler):
        # A vessel without an autopilot (every sim-bridge fleet) sends the bytes it sent before the field.
        data = handler(self)
        if self.vehicle is None:
            data.pop("vehicle", None)
        return data


class Clock(StrictModel):
    """One sim tick. It also carries the simulated radio's verdict on the shares of the tick before: which
    of them each agent gets now. That makes the fleet over Zenoh deliver exactly the shares the in-process
    runner delivers (packet loss included), whatever order the network brings them in."""

    stamp_ns: StampNs = Field(description="sim time of this tick")
    seq: int = Field(ge=0, le=MAX_STAMP_NS, description="tick number")
    sender: VesselId = "sim"
    previous_ns: StampNs | None = Field(None, description="the tick before, whose shares are delivered now")
    vessels: list[VesselId] | None = Field(None, max_length=MAX_PEERS,
                                           description="vessels in the world now (their sensors were published)")
    senders: list[VesselId] | None = Field(
        None, max_length=MAX_PEERS,
        description="vessels whose share of the previous tick is delivered now; null: every share that came")
    lost: list[tuple[VesselId, VesselId]] = Field(
        default_factory=list, max_length=MAX_PEERS * MAX_PEERS,
        description="[sender, receiver]: shares of the previous tick the simulated radio loses")
    lockstep: bool = Field(False, description="receivers wait (bounded) for the delivered shares before ticking")

    @model_validator(mode="after")
    def _previous_before(self):
        if self.previous_ns is not None and self.previous_ns >= self.stamp_ns:
            raise ValueError("previous_ns must be before stamp_ns")
        return self

    def delivered_to(self, receiver: str) -> set[str] | None:
        """Senders whose share of the previous tick `receiver` gets now; None: whatever has come."""
        if self.senders is None:
            return None
        lost = {sender for sender, to in self.lost if to == receiver}
        return {j for j in self.senders if j != receiver and j not in lost}


class GnssFix(Header):
    """A GNSS receiver's fix (NMEA GGA) of the vessel's antenna: truth for scoring a field trial, never an
    input of the agent (tests/test_architecture.py). stamp_ns: when the driver read it (the fleet's clock)."""
    latitude: float = Field(ge=-90, le=90, allow_inf_nan=False, description="WGS 84, north positive (deg)")
    longitude: float = Field(ge=-180, le=180, allow_inf_nan=False, description="WGS 84, east positive (deg)")
    altitude: Coordinate | None = Field(None, description="antenna above mean sea level (m); null: not given")
    quality: int = Field(ge=1, le=9, description="GGA fix quality: 1 GNSS, 2 DGNSS, 4 RTK fixed, 5 RTK float")
    satellites: int | None = Field(None, ge=0, le=999, description="satellites used; null: not given")
    hdop: float | None = Field(None, ge=0, le=100, allow_inf_nan=False, description="horizontal dilution")
    utc_time: float | None = Field(None, ge=0, lt=86401, allow_inf_nan=False,
                                   description="the receiver's UTC time of day of the fix (s); null: none")
    antenna: Vec2 = Field((0.0, 0.0), description="antenna from the vessel's reference: ahead, left (m)")


TOPICS: dict[str, type[StrictModel]] = {
    "sensor/odom": Odometry,
    "sensor/uwb": Ranges,
    "sensor/bearing": Bearing,
    "sensor/sonar": Sonar,
    VEHICLE_TOPIC: VehicleState,
    "cmd": Cmd,
    "share": ShareMessage,
    "status": Status,
}


# ----- decoding: bytes in, a message or a reason out, never an exception -----
def decode(model: type[StrictModel], payload: bytes | bytearray | memoryview) -> tuple[StrictModel | None, str]:
    """Parse and validate one payload. Returns (message, "") or (None, one-line reason)."""
    name = getattr(model, "wire_name", model.__name__)
    if len(payload) > MAX_PAYLOAD_BYTES:
        return None, f"{name}: payload of {len(payload)} bytes, more than {MAX_PAYLOAD_BYTES}"
    try:
        return model.model_validate_json(bytes(payload)), ""
    except ValidationError as error:
        return None, _invalid(name, error)
    except (ValueError, TypeError) as error:  # undecodable bytes
        return None, f"{name}: {error}"


def _invalid(name: str, error: ValidationError, within: tuple[str, ...] = ()) -> str:
    """A refusal's one-line reason: the message, where in it (`within` the path to the part validated) and
    the first problem found."""
    first = error.errors()[0]
    where = ".".join(str(p) for p in (*within, *first["loc"])) or "payload"
    return f"{name}: {where}: {first['msg']}"


def encode(message: StrictModel) -> bytes:
    return message.model_dump_json().encode("utf-8")


def encode_per_pair(message: ShareMessage, receivers) -> dict[str, bytes]:
    """Format 2: each of `receivers` -> the bytes `encode` gives of `message` with only that receiver's pair
    estimate (none if it has none). The body is encoded once and each estimate spliced in (`neighbours` is the
    last field), so a sender encodes n - 1 estimates a tick, as in format 1, and n - 1 short joins. A receiver
    that is no vessel id (a liveliness token's key may hold other characters) is left out."""
    body = message.model_copy(update={"neighbours": {}}).model_dump_json().encode("utf-8")
    if not body.endswith(b'"neighbours":{}}'):
        raise ValueError("a share's neighbours must be its last field")
    head = body[:-2]
    payloads = {}
    for receiver in receivers:
        if not _VESSEL_ID.match(receiver):
            continue
        estimate = message.neighbours.get(receiver)
        payloads[receiver] = body if estimate is None else b"".join(
            (head, b'"', receiver.encode("utf-8"), b'":', estimate.model_dump_json().encode("utf-8"), b"}}"))
    return payloads


# ----- time on the wire: whole nanoseconds -----
def seconds(stamp_ns: int) -> float:
    return stamp_ns * 1e-9


def nanoseconds(time_s: float) -> int:
    return round(time_s * 1e9)
