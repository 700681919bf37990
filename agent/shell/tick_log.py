"""What an agent writes to its MCAP log each tick; the agent process and `usv-log replay` both write it here.

Per tick, on topics under `/<id>/`:
- `inputs`: the tick's complete `TickInputs` (odometry, ranges, bearing, sonar points, the neighbours'
  shares), exactly, so that `usv-log replay` can feed them to the core again;
- `cmd` and `status`: what went out on the wire;
- `estimates`: every estimate with its covariance, each inter-vessel filter's updates of the tick
  (innovation, its predicted variance, the MCKF weight, accepted or not), the PLKF's bearing update, the
  velocity terms of the controller and which limits saturated;
- `tf` (foxglove.FrameTransforms) and, once a second, `scene` (foxglove.SceneUpdate): see agent/foxglove.py.

JSON writes a float as the shortest text that reads back to the same float, so what is read back from a log
is bit for bit what the core saw.
"""

from __future__ import annotations

import math

import numpy as np

from agent.contract import key
from agent.core.records import Odometry, Share, TickInputs
from agent.core.vessel import TickOutput, TickRecord
from agent.runtime import foxglove



def log_topic(vessel: str, name: str) -> str:
    """The topic of `name` in a vessel's log: the contract's key for what went on the wire (cmd, status),
    `/<id>/<name>` for the rest (inputs, estimates, tf, scene, summary)."""
    return key(vessel, name) if name in ("cmd", "status") else f"/{vessel}/{name}"


def _floats(values) -> list[float]:
    return np.asarray(values, dtype=float).ravel().tolist()


def _odometry_to_json(odometry: Odometry) -> dict:
    return {"stamp": float(odometry.stamp), "position": _floats(odometry.position),
            "heading": float(odometry.heading)}


def _odometry_from_json(data: dict) -> Odometry:
    return Odometry(data["stamp"], np.array(data["position"], dtype=float), data["heading"])


def share_to_json(share: Share) -> dict:
    return {
        "sender": share.sender, "odometry": _odometry_to_json(share.odometry), "velocity": _floats(share.velocity),
        "phase": float(share.phase),
        "target": None if share.target is None else _floats(share.target),
        "target_covariance": None if share.target_covariance is None else _floats(share.target_covariance),
        "neighbours": {j: {"position": _floats(p), "covariance": _floats(c)} for j, (p, c) in share.neighbours.items()},
    }


def share_from_json(data: dict) -> Share:
    return Share(
        sender=data["sender"], odometry=_odometry_from_json(data["odometry"]),
        velocity=np.array(data["velocity"], dtype=float), phase=data["phase"],
        target=None if data["target"] is None else np.array(data["target"], dtype=float),
        target_covariance=None if data["target_covariance"] is None
        else np.array(data["target_covariance"], dtype=float).reshape(4, 4),
        neighbours={j: (np.array(e["position"], dtype=float), np.array(e["covariance"], dtype=float).reshape(2, 2))
                    for j, e in data["neighbours"].items()},
    )


def inputs_to_json(inputs: TickInputs) -> dict:
    return {
        "time": float(inputs.time),
        "odometry": None if inputs.odometry is None else _odometry_to_json(inputs.odometry),
        "ranges": {j: float(r) for j, r in inputs.ranges.items()},
        "bearing": None if inputs.bearing is None else _floats(inputs.bearing),
        "obstacle_points": None if inputs.obstacle_points is None
        else np.asarray(inputs.obstacle_points, dtype=float).reshape(-1, 2).tolist(),
        "shares": {j: share_to_json(share) for j, share in inputs.shares.items()},
    }


def inputs_from_json(data: dict) -> TickInputs:
    points = data["obstacle_points"]
    return TickInputs(
        time=data["time"],
        odometry=None if data["odometry"] is None else _odometry_from_json(data["odometry"]),
        ranges=dict(data["ranges"]),
        shares={j: share_from_json(s) for j, s in data["shares"].items()},
        bearing=None if data["bearing"] is None else np.array(data["bearing"], dtype=float),
        obstacle_points=None if points is None else np.array(points, dtype=float).reshape(-1, 2),
    )


def estimates_to_json(record: TickRecord) -> dict:
    bearing = record.bearing_outcome
    return {
        "time": record.time, "phase": record.phase,
        "neighbours": {j: {
            "position": _floats(n.position), "covariance": _floats(n.covariance), "epoch": n.epoch,
            "iterations": n.iterations, "updates": n.updates, "rejected": n.rejected,
            "outcomes": [{"stamp": stamp, "range": measured, "accepted": o.accepted, "reason": o.reason,
                          "iterations": o.iterations, "innovation": o.innovation,
                          "innovation_variance": o.innovation_variance, "weight": o.weight}
                         for stamp, measured, o in n.outcomes],
        } for j, n in record.neighbours.items()},
        "target_state": None if record.target_state is None else _floats(record.target_state),
        "target_covariance": None if record.target_covariance is None else _floats(record.target_covariance),
        "bearing": None if bearing is None else {
            "accepted": bearing.accepted, "reason": bearing.reason, "innovation": bearing.innovation,
            "innovation_variance": bearing.innovation_variance},
        "velocity": {"formation": _floats(record.formation_velocity), "tracking": _floats(record.tracking_velocity),
                     "avoidance": _floats(record.avoidance_velocity),
                     "safety_correction": _floats(record.safety_correction),
                     "command": _floats(record.velocity_command)},
        "saturated": {name: bool(flag) for name, flag in record.saturated.items()},
        "health": dict(record.health),
    }


class TickLogger:
    """Writes one vessel's ticks to an `McapLog`."""

    def __init__(self, log, vessel: str, radius: float) -> None:
        self.log = log
        self.id = vessel
        self.radius = radius
        self._next_scene = 0

    def tick(self, stamp: int, inputs: TickInputs, output: TickOutput, command, status=None,
             wire: dict[str, bytes] | None = None) -> None:
        """Log one tick at time `stamp` (ns): `command` and `status` are the contract's messages (already
        encoded in `wire` when they went out)."""
        wire = wire or {}
        self.log.log(log_topic(self.id, "inputs"), inputs_to_json(inputs), stamp)
        self.log.log(log_topic(self.id, "cmd"), command, stamp, data=wire.get("cmd"))
        if status is not None:
            self.log.log(log_topic(self.id, "status"), status, stamp, data=wire.get("status"))
        record = output.record
        if record is None:
            return
        self.log.log(log_topic(self.id, "estimates"), estimates_to_json(record), stamp)
        self._log_frames(stamp, inputs, record)

    def _log_frames(self, stamp: int, inputs: TickInputs, record: TickRecord) -> None:
        me = foxglove.vessel_frame(self.id)
        links = [(me, f"{me}/hull", 0.0, 0.0, float(inputs.odometry.heading))]
        # p_ij = p_i - p_j: neighbour j sits at -p^_ij from vessel i, the target at -p^_io.
        links += [(me, foxglove.estimate_frame(self.id, j), -float(n.position[0]), -float(n.position[1]), 0.0)
                  for j, n in sorted(record.neighbours.items())]
        if record.target_state is not None and all(math.isfinite(v) for v in record.target_state[:2]):
            links.append((me, foxglove.estimate_frame(self.id, "target"), -float(record.target_state[0]),
                          -float(record.target_state[1]), 0.0))
        self.log.log(log_topic(self.id, "tf"), foxglove.transforms(stamp, links), stamp,
                     schema=foxglove.FrameTransforms)
        if record.target_state is not None and stamp >= self._next_scene:
            self._next_scene = stamp + foxglove.SCENE_PERIOD_NS
            frame = foxglove.estimate_frame(self.id, "target")
            self.log.log(log_topic(self.id, "scene"), foxglove.SceneUpdate(entities=foxglove.target_entities(
                stamp, frame, self.radius, f"target as {self.id} sees it")), stamp)
