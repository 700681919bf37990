"""What an agent writes to its MCAP log each tick; the agent process and `usv-log replay` both write it here.

Per tick, on topics under `/<id>/`:
- `inputs`: the tick's complete `TickInputs` (odometry, ranges, bearing, sonar points, the neighbours'
  shares), exactly, so that `usv-log replay` can feed them to the core again;
- `cmd` and `status`: what went out on the wire;
- `estimates`: every estimate with its covariance, each inter-vessel filter's updates of the tick
  (innovation, its predicted variance, the MCKF weight, accepted or not) and its pair's observability (the
  eigenvalues of its relative path's spread and the verdict), the PLKF's bearing update, the velocity terms
  of the controller and which limits saturated;
- `tf` (foxglove.FrameTransforms) and, once a second, `scene` (foxglove.SceneUpdate): see agent/runtime/foxglove.py;
- at the end, `summary`: the run as a whole (`TickLogger.summary`);
- `mission`, for every mission command judged: the command and the agent's answer (applied, or refused and
  why);
- `errors`, when a tick fails: the exception and the inputs that caused it (`TickLogger.error`; the first of
  each kind, then at most one every few seconds).

Each channel's JSON schema comes from a model of agent/runtime/log_schema.py; the messages themselves are plain
dicts (a pydantic object per tick would cost about as much as the tick).

JSON writes a float as the shortest text that reads back to the same float, so what is read back from a log
is bit for bit what the core saw.
"""

from __future__ import annotations

from collections.abc import Mapping

from pydantic import ConfigDict, Field

from agent.config import StrictModel
from agent.contract import Cmd, MissionAck, MissionCommand, Status, key
from agent.core.records import TickInputs, TickOutput, TickRecord, floats, inputs_to_json
from agent.runtime import foxglove
from agent.runtime.log_schema import AgentSummary, Estimates, Inputs


class TickError(StrictModel):
    """A tick that failed (agent/shell/failures.py), on `/<id>/errors`: the exception and the tick's inputs."""

    model_config = ConfigDict(title="usv.TickError")

    kind: str = Field(description="exception type and where it was raised (file:line)")
    message: str
    count: int = Field(ge=1, description="failures of this kind so far")
    inputs: Inputs | None = Field(description="the tick's inputs; None when reading them failed")


class MissionRecord(StrictModel):
    """A mission command the agent judged (agent/shell/mission.py), on `/<id>/mission`: the command as read
    (None if it could not be read) and the agent's answer."""

    model_config = ConfigDict(title="usv.MissionRecord")

    command: MissionCommand | None
    ack: MissionAck
    received_ns: int = Field(ge=0, description="when the command came, in the agent's clock (ns)")


def log_topic(vessel: str, name: str) -> str:
    """The topic of `name` in a vessel's log: the contract's key for what went on the wire (cmd, status),
    `/<id>/<name>` for the rest (inputs, estimates, tf, scene, summary)."""
    return key(vessel, name) if name in ("cmd", "status") else f"/{vessel}/{name}"


def estimates_to_json(record: TickRecord) -> dict:
    bearing = record.bearing_outcome
    return {
        "time": record.time, "phase": record.phase,
        "neighbours": {j: {
            "position": floats(n.position), "covariance": floats(n.covariance), "epoch": n.epoch,
            "iterations": n.iterations, "updates": n.updates, "rejected": n.rejected, "localised": n.localised,
            "excitation": [float(v) for v in n.excitation], "observability": n.observability,
            "outcomes": [{"stamp": stamp, "range": measured, "accepted": o.accepted, "reason": o.reason,
                          "iterations": o.iterations, "innovation": o.innovation,
                          "innovation_variance": o.innovation_variance, "weight": o.weight}
                         for stamp, measured, o in n.outcomes],
        } for j, n in record.neighbours.items()},
        "target_state": None if record.target_state is None else floats(record.target_state),
        "target_covariance": None if record.target_covariance is None else floats(record.target_covariance),
        "bearing": None if bearing is None else {
            "accepted": bearing.accepted, "reason": bearing.reason, "innovation": bearing.innovation,
            "innovation_variance": bearing.innovation_variance},
        "velocity": {"formation": floats(record.formation_velocity), "tracking": floats(record.tracking_velocity),
                     "avoidance": floats(record.avoidance_velocity),
                     "safety_correction": floats(record.safety_correction),
                     "command": floats(record.velocity_command)},
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
        self._scene: foxglove.StaticScene | None = None
        # Every tick's topics get their schemas and channels now, at start-up, not in the first tick.
        for name, model in (("inputs", Inputs), ("cmd", Cmd), ("status", Status), ("estimates", Estimates),
                            ("tf", foxglove.FrameTransforms), ("scene", foxglove.SceneUpdate)):
            log.prepare(log_topic(vessel, name), model)

    def tick(self, stamp: int, inputs: TickInputs, output: TickOutput, command, status=None,
             wire: dict[str, bytes] | None = None) -> None:
        """Log one tick at time `stamp` (ns): `command` and `status` are the contract's messages (already
        encoded in `wire` when they went out)."""
        wire = wire or {}
        self.log.log(log_topic(self.id, "inputs"), inputs_to_json(inputs), stamp, schema=Inputs)
        self.log.log(log_topic(self.id, "cmd"), command, stamp, data=wire.get("cmd"))
        if status is not None:
            self.log.log(log_topic(self.id, "status"), status, stamp, data=wire.get("status"))
        record = output.record
        if record is None:
            return
        self.log.log(log_topic(self.id, "estimates"), estimates_to_json(record), stamp, schema=Estimates)
        self._log_frames(stamp, inputs, record)

    def error(self, stamp: int, kind: str, message: str, count: int, inputs: TickInputs | None) -> None:
        """Log a failed tick at time `stamp` (ns): what was raised and the inputs that raised it."""
        self.log.log(log_topic(self.id, "errors"), {
            "kind": kind, "message": message, "count": count,
            "inputs": None if inputs is None else inputs_to_json(inputs)}, stamp, schema=TickError)

    def mission(self, stamp: int, command: MissionCommand | None, ack: MissionAck, received_ns: int) -> None:
        """Log one judged mission command at time `stamp` (ns); it came at `received_ns`."""
        self.log.log(log_topic(self.id, "mission"), {
            "command": None if command is None else command.model_dump(mode="json"),
            "ack": ack.model_dump(mode="json"), "received_ns": received_ns}, stamp, schema=MissionRecord)

    def summary(self, stamp: int, *, ticks: int, overruns: int, refused: Mapping[str, int], loop_seconds: float,
                cpu_seconds: float, core_cpu_seconds: float | None = None,
                reaction_ms: Mapping[str, float] | None = None,
                reaction_cpu_ms: Mapping[str, float] | None = None) -> None:
        """Log the run as a whole at time `stamp` (ns), once at the end: ticks run, wall-clock overruns, inputs
        refused by reason, the wall and CPU seconds from the first tick (the core's step's share apart), the
        reaction times and the tick thread's CPU to each command (ReactionTimes.summary). Built as the model
        (once a run), so a wrong value fails here rather than in a reader."""
        self.log.log(log_topic(self.id, "summary"), AgentSummary(
            ticks=ticks, overruns=overruns, refused=dict(refused), loop_seconds=loop_seconds,
            cpu_seconds=cpu_seconds, core_cpu_seconds=core_cpu_seconds, reaction_ms=reaction_ms,
            reaction_cpu_ms=reaction_cpu_ms), stamp)

    def _log_frames(self, stamp: int, inputs: TickInputs, record: TickRecord) -> None:
        target = record.target_state
        links = foxglove.estimate_links(
            self.id, inputs.odometry.heading, [(j, n.position[0], n.position[1]) for j, n in record.neighbours.items()],
            None if target is None else (float(target[0]), float(target[1])))
        self.log.log(log_topic(self.id, "tf"), foxglove.transforms(stamp, links), stamp,
                     schema=foxglove.FrameTransforms)
        if record.target_state is not None and stamp >= self._next_scene:
            self._next_scene = stamp + foxglove.SCENE_PERIOD_NS
            if self._scene is None:
                self._scene = foxglove.StaticScene(foxglove.target_entities(
                    0, foxglove.estimate_frame(self.id, "target"), self.radius, f"target as {self.id} sees it"))
            self.log.log(log_topic(self.id, "scene"), self._scene.at(stamp), stamp, schema=foxglove.SceneUpdate)
