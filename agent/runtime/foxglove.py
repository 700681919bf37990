"""Foxglove messages in our MCAP logs, so that a log shows the mission in Foxglove's 3D panel.

Models of the parts of `foxglove.FrameTransforms`, `foxglove.SceneUpdate` and `foxglove.LocationFix` (the live
view's GNSS fixes) we write, field for field as Foxglove publishes them (tests/test_foxglove.py checks what we log against the published JSON schemas). A
channel whose schema is named `foxglove.<Name>` is drawn by Foxglove; its fields can be plotted like any other.

Frames (one tree across all of a run's files):

    world                          sim bridge only: the simulated world (ground truth)
    vessel/<id>                    the vessel, axes along the common heading reference (no rotation)
    vessel/<id>/hull               the vessel turned by its heading
    vessel/<id>/estimate/<j>       where vessel <id> believes neighbour j is
    vessel/<id>/estimate/target    where vessel <id> believes the target is
    target                         sim bridge only: the true target

An agent logs only the frames below its own `vessel/<id>` (it knows no world frame), so on a boat each
vessel's file is viewed from `vessel/<id>`; next to the sim bridge's file everything hangs off `world`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

from pydantic import BaseModel, ConfigDict, Field

SCENE_PERIOD_NS = 1_000_000_000   # the scene is redrawn once a second: enough for Foxglove to show it after a seek


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Time(_Message):
    sec: int = Field(ge=0)
    nsec: int = Field(ge=0, le=999_999_999)


class Duration(_Message):
    sec: int = 0
    nsec: int = Field(0, ge=0, le=999_999_999)


class Vector3(_Message):
    x: float
    y: float
    z: float = 0.0


class Quaternion(_Message):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


class Pose(_Message):
    position: Vector3 = Vector3(x=0.0, y=0.0)
    orientation: Quaternion = Quaternion()


class Color(_Message):
    r: float
    g: float
    b: float
    a: float = 1.0


class FrameTransform(_Message):
    timestamp: Time
    parent_frame_id: str
    child_frame_id: str
    translation: Vector3
    rotation: Quaternion


class FrameTransforms(_Message):
    model_config = ConfigDict(extra="forbid", title="foxglove.FrameTransforms")   # the schema name Foxglove knows

    transforms: list[FrameTransform]


class LocationFix(_Message):
    model_config = ConfigDict(extra="forbid", title="foxglove.LocationFix")   # drawn by Foxglove's Map panel

    timestamp: Time
    frame_id: str
    latitude: float
    longitude: float
    altitude: float
    position_covariance: list[float] = Field(min_length=9, max_length=9, description="ENU, row-major (m^2)")
    position_covariance_type: int = Field(ge=0, le=3, description="0 unknown, 1 approximated, 2 diagonal, 3 known")


class SpherePrimitive(_Message):
    pose: Pose
    size: Vector3
    color: Color


class LinePrimitive(_Message):
    type: int = Field(description="0 line strip, 1 line loop, 2 line list")
    pose: Pose
    thickness: float
    scale_invariant: bool
    points: list[Vector3]
    color: Color
    colors: list[Color] = Field(default_factory=list)
    indices: list[int] = Field(default_factory=list)


class TextPrimitive(_Message):
    pose: Pose
    billboard: bool
    font_size: float
    scale_invariant: bool
    color: Color
    text: str


class KeyValuePair(_Message):
    key: str
    value: str


class SceneEntity(_Message):
    timestamp: Time
    frame_id: str
    id: str
    lifetime: Duration = Duration()
    frame_locked: bool = True
    metadata: list[KeyValuePair] = Field(default_factory=list)
    arrows: list = Field(default_factory=list)
    cubes: list = Field(default_factory=list)
    spheres: list[SpherePrimitive] = Field(default_factory=list)
    cylinders: list = Field(default_factory=list)
    lines: list[LinePrimitive] = Field(default_factory=list)
    triangles: list = Field(default_factory=list)
    texts: list[TextPrimitive] = Field(default_factory=list)
    models: list = Field(default_factory=list)


class SceneUpdate(_Message):
    model_config = ConfigDict(extra="forbid", title="foxglove.SceneUpdate")

    deletions: list = Field(default_factory=list)
    entities: list[SceneEntity]


LINE_STRIP, LINE_LOOP = 0, 1
TARGET_COLOUR = Color(r=0.85, g=0.2, b=0.15)
CIRCLE_COLOUR = Color(r=0.5, g=0.5, b=0.5, a=0.8)
ISLAND_COLOUR = Color(r=0.35, g=0.55, b=0.25)


def vessel_frame(vessel: str) -> str:
    return f"vessel/{vessel}"


def estimate_frame(vessel: str, of: str) -> str:
    """Frame of vessel `vessel`'s estimate of `of` (a neighbour id, or "target")."""
    return f"vessel/{vessel}/estimate/{of}"


def time_of(stamp_ns: int) -> Time:
    return Time(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)


def yaw_rotation(yaw: float) -> Quaternion:
    return Quaternion(z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


def transforms(stamp_ns: int, links: Iterable[tuple[str, str, float, float, float]]) -> dict:
    """A FrameTransforms message, as the dict `FrameTransforms` would dump, from (parent, child, x, y, yaw)
    links all stamped `stamp_ns`. Built directly: it goes out every tick, and building the pydantic models
    cost more than the rest of the tick's log (tests/test_foxglove.py checks the two agree)."""
    when = {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}
    return {"transforms": [
        {"timestamp": when, "parent_frame_id": parent, "child_frame_id": child,
         "translation": {"x": float(x), "y": float(y), "z": 0.0},
         "rotation": {"x": 0.0, "y": 0.0, "z": math.sin(0.5 * yaw), "w": math.cos(0.5 * yaw)}}
        for parent, child, x, y, yaw in links]}


def estimate_links(vessel: str, heading: float, neighbours: Iterable[tuple[str, float, float]],
                   target: tuple[float, float] | None) -> list[tuple[str, str, float, float, float]]:
    """The frames of what vessel `vessel` believes, for `transforms`: its hull turned by `heading`, each
    neighbour j at -p^_ij and the target at -p^_io (p_ij = p_i - p_j), from (j, x, y) of p^_ij and (x, y) of
    p^_io. The agent's log and the operator's live view draw the same frames."""
    me = vessel_frame(vessel)
    links = [(me, f"{me}/hull", 0.0, 0.0, float(heading))]
    links += [(me, estimate_frame(vessel, j), -float(x), -float(y), 0.0) for j, x, y in sorted(neighbours)]
    if target is not None and all(math.isfinite(v) for v in target):
        links.append((me, estimate_frame(vessel, "target"), -float(target[0]), -float(target[1]), 0.0))
    return links


def world_links(positions: Mapping[str, Sequence[float]], headings: Mapping[str, float],
                target: Sequence[float]) -> list[tuple[str, str, float, float, float]]:
    """The ground truth's frames, for `transforms`: the target and each vessel in `world`, each hull turned by
    its heading (the sim bridge's log and the operator's live view)."""
    links = [("world", "target", float(target[0]), float(target[1]), 0.0)]
    for vessel, position in positions.items():
        frame = vessel_frame(vessel)
        links += [("world", frame, float(position[0]), float(position[1]), 0.0),
                  (frame, f"{frame}/hull", 0.0, 0.0, float(headings[vessel]))]
    return links


def circle(radius: float, points: int = 72) -> list[Vector3]:
    return [Vector3(x=radius * math.cos(2 * math.pi * k / points), y=radius * math.sin(2 * math.pi * k / points))
            for k in range(points)]


def target_entities(stamp_ns: int, frame: str, radius: float, label: str) -> list[SceneEntity]:
    """The target (a sphere) and the desired circle around it, drawn in `frame` (a target frame)."""
    when = time_of(stamp_ns)
    return [SceneEntity(
        timestamp=when, frame_id=frame, id=f"{frame}/marker",
        spheres=[SpherePrimitive(pose=Pose(), size=Vector3(x=0.6, y=0.6, z=0.6), color=TARGET_COLOUR)],
        lines=[LinePrimitive(type=LINE_LOOP, pose=Pose(), thickness=0.05, scale_invariant=False,
                             points=circle(radius), color=CIRCLE_COLOUR)],
        texts=[TextPrimitive(pose=Pose(position=Vector3(x=0.0, y=0.0, z=1.0)), billboard=True, font_size=12.0,
                             scale_invariant=True, color=TARGET_COLOUR, text=label)],
    )]


def island_entities(stamp_ns: int, frame: str, islands: Sequence[Sequence[Sequence[float]]]) -> list[SceneEntity]:
    """Each island's outline as a closed line in `frame`."""
    when = time_of(stamp_ns)
    return [SceneEntity(
        timestamp=when, frame_id=frame, id=f"island/{n}",
        lines=[LinePrimitive(type=LINE_LOOP, pose=Pose(), thickness=0.15, scale_invariant=False,
                             points=[Vector3(x=float(x), y=float(y)) for x, y in polygon], color=ISLAND_COLOUR)])
        for n, polygon in enumerate(islands)]


class StaticScene:
    """A SceneUpdate whose entities do not change but for their time stamps (the target marker and circle, the
    islands): built and checked as the models once, then only re-stamped each time it is logged."""

    def __init__(self, entities: list[SceneEntity]) -> None:
        self._message = SceneUpdate(entities=entities).model_dump(mode="json")

    def at(self, stamp_ns: int) -> dict:
        """The message stamped `stamp_ns`, as the dict `SceneUpdate` would dump (log it with that schema)."""
        when = {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}
        for entity in self._message["entities"]:
            entity["timestamp"] = when
        return self._message

