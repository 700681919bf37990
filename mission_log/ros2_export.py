"""`usv-log export --ros2`: a run's logs as a rosbag2 for ROS 2 users, written with `rosbags` (the `ros2` extra).

`export_ros2(run, out)` writes the folder `out`: `metadata.yaml` (rosbag2 metadata version 8) and one MCAP file
in rosbag2's profile (`ros2`, schemas `ros2msg`, messages `cdr`), for `ros2 bag play out`. Per vessel,
under its namespace `usv_<id>`: `odom` (nav_msgs/Odometry), `cmd_vel` (geometry_msgs/Twist), `estimate/<j>`
and `estimate/target` (geometry_msgs/PoseWithCovarianceStamped); the frames of all of them on `/tf`
(tf2_msgs/TFMessage); with the sim bridge's log, the truth on `/truth/usv_<id>` and `/truth/target`
(nav_msgs/Odometry in `world`). docs/logs.md ("ROS 2") gives the frames, the axes (REP-103), the stamps and the
covariance layout.

Bag time is each source message's log time; header stamps are the time the data refers to (the odometry's
stamp, the estimate's tick, the truth's tick). Messages go out in log-time order, one stream at a time merged,
so the export holds one message of each stream in memory, not the bag. A log cut short or missing parts is
exported as far as it goes, and the bag's `custom_data` says so (`usv_partial`).
"""

from __future__ import annotations

import heapq
import math
import re
import shutil
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agent.shell.tick_log import log_topic
from mission_log.reader import Log, LogError, RunLog, VesselLog

ROS2_EXTRA = "pip install 'usv-circumnav[ros2]'"
METADATA_VERSION = 8        # rosbag2's metadata of Jazzy: QoS profiles as a string, custom_data, ros_distro
WORLD = "world"
ODOMETRY, TWIST, TF = "nav_msgs/msg/Odometry", "geometry_msgs/msg/Twist", "tf2_msgs/msg/TFMessage"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
NAME_TOKEN = re.compile(r"[A-Za-z][A-Za-z0-9_]*")     # a ROS 2 name token: no leading digit, no '-'

# (log time ns, topic, message type, message)
Item = tuple[int, str, str, object]


class MissingExtra(ImportError):
    """The `ros2` extra is not installed; the message says how to install it."""


def load_rosbags():
    """The rosbags modules the export needs, or MissingExtra."""
    try:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise MissingExtra(f"usv-log export --ros2 needs rosbags: {ROS2_EXTRA}") from None

    def writer(out: Path):
        """A rosbag2 writer of MCAP storage whose chunks are zstd-compressed (as our logs are)."""
        bag = Writer(out, version=METADATA_VERSION, storage_plugin=StoragePlugin.MCAP)
        bag.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        return bag
    return writer, get_typestore(Stores.ROS2_JAZZY)


def namespace(vessel: str) -> str:
    """The ROS name of vessel `vessel`: `usv_<id>`, its '-' as '_' (a ROS 2 name token has no '-' and does not
    start with a digit, and vessel ids are often numbers)."""
    name = "usv_" + vessel.replace("-", "_")
    if not NAME_TOKEN.fullmatch(name) or "__" in name:
        raise LogError(f"vessel {vessel!r}: no ROS 2 name can be made of this id ({name} is not one)")
    return name


def ros_ns(seconds: float) -> int:
    """A time in seconds (a record's float) as integer nanoseconds for a ROS stamp."""
    if not math.isfinite(seconds) or seconds < 0:
        raise LogError(f"time {seconds!r} s cannot be a ROS 2 stamp (it needs a finite time from 0 on)")
    return round(seconds * 1e9)


@dataclass
class Messages:
    """Builds the ROS 2 messages of rosbags' typestore from our records."""

    typestore: object
    types: dict = field(init=False)
    _ids: dict[str, str] = field(default_factory=dict)    # ROS name -> the vessel id that made it

    def __post_init__(self) -> None:
        self.types = self.typestore.types

    def name(self, vessel: str) -> str:
        """`namespace(vessel)`, refusing two ids that make the same name in one bag (`a-b` and `a_b`)."""
        name = namespace(vessel)
        other = self._ids.setdefault(name, vessel)
        if other != vessel:
            raise LogError(f"vessels {other} and {vessel} make the same ROS 2 name {name}")
        return name

    def _t(self, name: str, **fields):
        return self.types[name](**fields)

    def header(self, stamp_ns: int, frame: str):
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        stamp = self._t("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)
        return self._t("std_msgs/msg/Header", stamp=stamp, frame_id=frame)

    def vector(self, x: float = 0.0, y: float = 0.0, z: float = 0.0):
        return self._t("geometry_msgs/msg/Vector3", x=float(x), y=float(y), z=float(z))

    def yaw(self, yaw: float):
        """The rotation by `yaw` (rad, counter-clockwise) about z."""
        return self._t("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))

    def pose(self, x: float, y: float, yaw: float, covariance: np.ndarray | None = None):
        position = self._t("geometry_msgs/msg/Point", x=float(x), y=float(y), z=0.0)
        pose = self._t("geometry_msgs/msg/Pose", position=position, orientation=self.yaw(yaw))
        return self._t("geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=planar(covariance))

    def twist(self, x: float, y: float, yaw_rate: float):
        return self._t(TWIST, linear=self.vector(x, y), angular=self.vector(z=yaw_rate))

    def odometry(self, stamp_ns: int, frame: str, child: str, x: float, y: float, yaw: float,
                 velocity: tuple[float, float] = (0.0, 0.0)):
        twist = self._t("geometry_msgs/msg/TwistWithCovariance", twist=self.twist(*velocity, 0.0),
                        covariance=planar(None))
        return self._t(ODOMETRY, header=self.header(stamp_ns, frame), child_frame_id=child,
                       pose=self.pose(x, y, yaw), twist=twist)

    def estimate(self, stamp_ns: int, frame: str, x: float, y: float, covariance: np.ndarray):
        return self._t(POSE, header=self.header(stamp_ns, frame), pose=self.pose(x, y, 0.0, covariance))

    def transforms(self, links: list[tuple[int, str, str, float, float, float]]):
        """A TFMessage of (stamp ns, parent, child, x, y, yaw) links."""
        return self._t(TF, transforms=[self._t(
            "geometry_msgs/msg/TransformStamped", header=self.header(stamp, parent), child_frame_id=child,
            transform=self._t("geometry_msgs/msg/Transform", translation=self.vector(x, y),
                              rotation=self.yaw(yaw)))
            for stamp, parent, child, x, y, yaw in links])


def planar(block: np.ndarray | None) -> np.ndarray:
    """A 6x6 covariance of (x, y, z, rot x, rot y, rot z), row-major, with the 2x2 `block` of (x, y) in its top
    left corner and zeros elsewhere (zeros throughout without a block)."""
    covariance = np.zeros((6, 6))
    if block is not None:
        covariance[:2, :2] = block
    return covariance.reshape(36)


def vessel_streams(log: VesselLog, make: Messages) -> list[Iterator[Item]]:
    """The ROS 2 messages of one agent's log, one stream per source topic, each in log-time order."""
    ns = make.name(log.vessel)
    odom, aligned, hull = f"{ns}/odom", f"{ns}/odom_aligned", f"{ns}/base_link"

    def odometry() -> Iterator[Item]:
        last = None
        for t, inputs in log.topic("inputs"):
            reading = inputs.get("odometry")
            if reading is None or reading["stamp"] == last:   # no fresh odometry, or the same sample again
                continue
            last = reading["stamp"]
            stamp = ros_ns(reading["stamp"])
            (x, y), heading = reading["position"], reading["heading"]
            yield t, f"/{ns}/odom", ODOMETRY, make.odometry(stamp, odom, hull, x, y, heading)
            yield t, "/tf", TF, make.transforms([(stamp, odom, aligned, x, y, 0.0),
                                                 (stamp, aligned, hull, 0.0, 0.0, heading)])

    def commands() -> Iterator[Item]:
        for t, command in log.topic("cmd"):
            yield t, f"/{ns}/cmd_vel", TWIST, make.twist(command["surge"], 0.0, command["yaw_rate"])

    def estimates() -> Iterator[Item]:
        last = None
        for t, record in log.topic("estimates"):
            stamp = ros_ns(record["time"])
            found = [(f"estimate/{make.name(j)}", n["position"], np.reshape(n["covariance"], (2, 2)))
                     for j, n in sorted(record["neighbours"].items())]
            if record.get("target_state") is not None:
                found.append(("estimate/target", record["target_state"][:2],
                              np.reshape(record["target_covariance"], (4, 4))[:2, :2]))
            for name, (px, py), covariance in found:
                # p^_ij = p_i - p_j: the neighbour (or the target) is at -p^ from the vessel.
                yield t, f"/{ns}/{name}", POSE, make.estimate(stamp, aligned, -px, -py, covariance)
            if found and stamp != last:   # a tick at the time of the last: tf2 keeps one per frame and stamp
                last = stamp
                yield t, "/tf", TF, make.transforms([(stamp, aligned, f"{ns}/{name}", -px, -py, 0.0)
                                                     for name, (px, py), _ in found])

    return [guarded(odometry(), log, log_topic(log.vessel, "inputs")),
            guarded(commands(), log, log_topic(log.vessel, "cmd")),
            guarded(estimates(), log, log_topic(log.vessel, "estimates"))]


def guarded(stream: Iterator[Item], log: Log, topic: str) -> Iterator[Item]:
    """`stream`, with a message it cannot convert (a log edited or damaged by hand) turned into one LogError
    that names the file and the topic."""
    try:
        yield from stream
    except LogError as error:
        raise LogError(f"{log.path}: {topic}: {error}") from None
    except (KeyError, TypeError, ValueError, IndexError) as error:
        raise LogError(f"{log.path}: {topic}: a message of a shape the export cannot read "
                       f"({type(error).__name__}: {error})") from None


def truth_stream(log, make: Messages) -> Iterator[Item]:
    """The sim bridge's `/truth`: each vessel and the target in `world`, stamped with the truth's log time."""
    for t, truth in log.messages("/truth"):
        links = []
        for vessel, state in sorted(truth["vessels"].items()):
            child = f"truth/{make.name(vessel)}"
            (x, y), heading = state["position"], state["heading"]
            yield t, f"/{child}", ODOMETRY, make.odometry(t, WORLD, child, x, y, heading)
            links.append((t, WORLD, child, x, y, heading))
        (x, y), velocity = truth["target"], truth["target_velocity"]
        yield t, "/truth/target", ODOMETRY, make.odometry(t, WORLD, "truth/target", x, y, 0.0, tuple(velocity))
        links.append((t, WORLD, "truth/target", x, y, 0.0))
        yield t, "/tf", TF, make.transforms(links)


def partial_note(run: RunLog) -> str | None:
    """What the logs lack (files cut short, parts not among them), in one line; None when they are whole."""
    notes = [f"{path.name} cut short" for path in run.unfinished]
    notes += [f"{path.name}: part(s) {', '.join(map(str, parts))} missing"
              for path, parts in run.missing_parts.items()]
    return "; ".join(notes) or None


@dataclass
class Exported:
    out: Path
    counts: dict[str, int]              # topic -> messages
    types: dict[str, str]               # topic -> message type
    partial: str | None                 # what the logs lacked (None: whole)


def export_ros2(run: RunLog, out: Path) -> Exported:
    """Write `run` as the rosbag2 folder `out` (which must not exist). On an error nothing is left behind."""
    new_writer, typestore = load_rosbags()
    out = Path(out)
    if out.exists():
        raise LogError(f"{out}: already exists; not overwriting (give another --out)")
    make = Messages(typestore)
    streams = [s for log in run.vessels.values() for s in vessel_streams(log, make)]
    if run.sim is not None:
        streams.append(guarded(truth_stream(run.sim, make), run.sim, "/truth"))
    partial = partial_note(run)
    counts: Counter[str] = Counter()
    types: dict[str, str] = {}
    writer = new_writer(out)
    connections = {}
    try:
        writer.open()
        writer.set_custom_data("usv_source", run.source)
        if partial is not None:
            writer.set_custom_data("usv_partial", partial)
        for t, topic, kind, message in heapq.merge(*streams, key=lambda item: item[0]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, kind, typestore=typestore)
                types[topic] = kind
            writer.write(connections[topic], t, typestore.serialize_cdr(message, kind))
            counts[topic] += 1
        if not counts:
            raise LogError(f"{run.source}: no odometry, command, estimate or truth to export")
        writer.close()
    except BaseException:
        writer.abort()
        shutil.rmtree(out, ignore_errors=True)
        raise
    return Exported(out, dict(counts), types, partial)


def default_out(run_path: Path) -> Path:
    """`ros2` in the run folder (beside the files given), numbered rather than overwriting an earlier export."""
    folder = run_path if run_path.is_dir() else run_path.parent
    candidate, n = folder / "ros2", 1
    while candidate.exists():
        n += 1
        candidate = folder / f"ros2-{n}"
    return candidate
