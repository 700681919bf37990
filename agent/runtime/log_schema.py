"""The JSON schemas of the log channels `usv-log` reads back: models of exactly what the writers write.

- `Inputs` and `Estimates`: what `tick_log.inputs_to_json` and `tick_log.estimates_to_json` write each tick
  on `/<id>/inputs` and `/<id>/estimates`;
- `CoreState`: the core's state after a tick, every `snapshot_every` ticks on `/<id>/state`;
- `AgentSummary`: the agent's record of the whole run on `/<id>/summary` (`TickLogger.summary`);
- `BridgeSummary`, `LoggedTruth` and `CommandLatency`: the sim bridge's `/bridge/summary`, `/truth` and
  `/bridge/command_latency`.

The per-tick messages stay plain dicts encoded by orjson: building these models every tick would cost about
as much as the tick. A model is used once per channel, for the JSON schema written into the MCAP file (the
summaries, written once, are built as models and so validated too). tests/test_log_format.py validates real
logged messages against the schemas in the file, so a writer that drifts from its model fails there.

Numbers are JSON numbers: the core never produces a non-finite value (orjson would write it as null, which
these schemas refuse). Matrices are flattened row by row. A change that an older reader would misread needs
a new `FORMAT_VERSION` (agent/runtime/mcap_log.py) and the readers taught to read it (mission_log/reader.py).
"""

from __future__ import annotations

from dataclasses import fields
from typing import Annotated, Literal

from pydantic import ConfigDict, Field, create_model

from agent.config import StrictModel
from agent.core.observability import VERDICTS
from agent.core.state import Health


def _floats(n: int, what: str):
    return Annotated[list[float], Field(min_length=n, max_length=n, description=what)]


Vector2 = _floats(2, "x, y (m or m/s)")
Matrix2 = _floats(4, "2x2 covariance, row by row")
Vector4 = _floats(4, "[p_x, p_y, v_x, v_y]")
Matrix4 = _floats(16, "4x4 covariance, row by row")
Count = Annotated[int, Field(ge=0)]


# ----- /<id>/inputs: the tick's complete TickInputs -----


class LoggedOdometry(StrictModel):
    stamp: float = Field(description="s")
    position: Vector2 = Field(description="cumulative dead-reckoned position in the vessel's odometry frame (m)")
    heading: float = Field(description="rad")


class SharedEstimate(StrictModel):
    position: Vector2 = Field(description="p_jk, the sender's estimate of neighbour k (m)")
    covariance: Matrix2
    stamp: float = Field(description="the time the estimate refers to, the sender's clock (s)")


class LoggedShare(StrictModel):
    sender: str
    odometry: LoggedOdometry
    velocity: Vector2 = Field(description="the velocity the sender commanded from its odometry stamp (m/s)")
    phase: float = Field(description="oscillator phase (rad)")
    target: Vector4 | None = Field(description="[p_jo; v_o], None before the sender has a target estimate")
    target_covariance: Matrix4 | None
    neighbours: dict[str, SharedEstimate]
    antenna: Vector2 | None = Field(None, description="the sender's UWB antenna (forward, left) (m)")


class Inputs(StrictModel):
    model_config = ConfigDict(title="usv.Inputs")

    time: float = Field(description="the tick's time (s)")
    odometry: LoggedOdometry | None = Field(description="None: no fresh odometry")
    ranges: dict[str, float] = Field(description="neighbour id -> range (m)")
    bearing: Vector2 | None = Field(description="unit vector from the target to the vessel; None: no bearing")
    obstacle_points: list[Vector2] | None = Field(description="sonar points relative to the vessel (m)")
    shares: dict[str, LoggedShare] = Field(description="neighbour id -> its latest share")
    range_stamp: float | None = Field(description="when the ranges were measured (s); None: at `time`")
    # Measured before `range_stamp` since the last tick, oldest first.
    earlier_ranges: list[tuple[float, dict[str, float]]] = Field(
        default_factory=list, description="earlier range sets: [stamp (s), neighbour id -> range (m)]")


# ----- /<id>/estimates: the tick's TickRecord -----


class RangeUpdate(StrictModel):
    stamp: float = Field(description="s")
    range: float = Field(description="m")
    accepted: bool
    reason: str
    iterations: Count
    innovation: float
    innovation_variance: float
    weight: float = Field(description="MCKF correntropy weight")


class NeighbourEstimate(StrictModel):
    position: Vector2 = Field(description="p^_ij at the tick's time (m)")
    covariance: Matrix2
    epoch: float = Field(description="time the filter state refers to (s)")
    iterations: Count
    updates: Count
    rejected: Count
    outcomes: list[RangeUpdate] = Field(description="each range update this tick ran")
    # Its covariance small enough and its estimate agreeing with the ranges.
    localised: bool = Field(False, description="steered the formation this tick")
    # The spread of the relative path at the range epochs over the observability window
    # (agent/core/observability.py).
    excitation: Annotated[list[float], Field(
        min_length=2, max_length=2, description="smallest and largest eigenvalue of the relative path's "
                                                "spread, (41) (m^2)")]
    # mirror-ambiguous: a straight line; unobservable: no relative motion.
    observability: Literal[VERDICTS] = Field(
        description="what the relative path lets the ranges tell: observable, mirror-ambiguous or unobservable")


class BearingUpdate(StrictModel):
    accepted: bool
    reason: str
    innovation: float = Field(description="cross-bearing component (m)")
    innovation_variance: float


class VelocityTerms(StrictModel):
    formation: Vector2
    tracking: Vector2
    avoidance: Vector2
    safety_correction: Vector2
    command: Vector2


class Saturation(StrictModel):
    formation: bool
    avoidance: bool
    yaw_rate: bool
    speed: bool
    safety_filter: bool


# The core's health counters, field for field (a new counter appears here without an edit).
HealthCounters = create_model("HealthCounters", __base__=StrictModel,
                              **{f.name: (Count, ...) for f in fields(Health)})


class Estimates(StrictModel):
    model_config = ConfigDict(title="usv.Estimates")

    time: float = Field(description="s")
    phase: float = Field(description="rad")
    neighbours: dict[str, NeighbourEstimate]
    target_state: Vector4 | None = Field(description="x^_io = [p_io; v_io]; None before a target estimate")
    target_covariance: Matrix4 | None
    bearing: BearingUpdate | None = Field(description="the PLKF's update; None before it has a target")
    velocity: VelocityTerms
    saturated: Saturation
    health: HealthCounters


# ----- /<id>/state: the core's state after a tick (agent/core/snapshot.py) -----


class UpdateRecord(StrictModel):
    accepted: bool
    reason: str
    iterations: Count
    innovation: float
    innovation_variance: float
    weight: float
    noise_scale: float


class FilterDiagnostics(StrictModel):
    predictions: Count
    updates: Count
    rejected: Count
    last: UpdateRecord


class PairFilterState(StrictModel):
    name: str = Field(description="the estimator (mckf, kf, akf, rls, huber_rls)")
    position: Vector2 = Field(description="p^_ij at the filter's epoch (m)")
    covariance: Annotated[list[float], Field(min_length=3, max_length=3, description="P_11, P_12, P_22")]
    pair: Annotated[list[float], Field(min_length=3, max_length=3,
                                       description="displacement x, y (m) and intervals since the last range epoch")]
    diagnostics: FilterDiagnostics
    extra: dict[str, float | int | list[float]] = Field(description="the estimator's own state (AKF scale, ...)")


class TargetFilterState(StrictModel):
    state: Vector4 = Field(description="x^_io")
    covariance: Matrix4
    predictions: Count
    updates: Count
    skipped: Count
    rejected: Count


StampedVector = Annotated[list[int | list[float]], Field(min_length=2, max_length=2,
                                                         description="[stamp in microseconds, [x, y]]")]
StampedRange = Annotated[list[int | float], Field(min_length=2, max_length=2,
                                                  description="[stamp in microseconds, range (m)]")]


class TrackState(StrictModel):
    odometry: list[StampedVector] = Field(description="the neighbour's cumulative odometry by stamp")
    ranges: list[StampedRange] = Field(description="ranges to the neighbour by stamp")
    estimator: PairFilterState | None = Field(description="None until the pair filter has started")
    epoch: int | None = Field(description="stamp (microseconds) the filter state refers to")
    epoch_own: Vector2 | None = Field(description="this vessel's odometry at the epoch (m)")
    epoch_other: Vector2 | None = Field(description="the neighbour's odometry at the epoch (m)")
    last_range: float | None
    arms: list[StampedVector] = Field([], description="the neighbour's antenna arm R(psi) a by stamp (m)")
    last_offset: Vector2 = Field((0.0, 0.0), description="the antennas' offset delta_ij at last_range (m)")
    share: LoggedShare | None
    last_heard: float = Field(description="s")
    first_heard: float = Field(description="s")
    updates: Count
    rejected: Count
    last_iterations: Count
    spread: Annotated[list[float], Field(
        min_length=8, max_length=8, description="the relative path's spread (agent/core/observability.py): "
                                                "path x, y, weight, mean x, y, scatter 11, 12, 22")]


class PendingPrior(StrictModel):
    position: Vector2
    covariance: Matrix2
    stamp: float | None = Field(description="s; None: at the vessel's first tick")


class OwnMotionState(StrictModel):
    velocity: Vector2
    stamp: float | None
    position: Vector2 | None


class CoreState(StrictModel):
    model_config = ConfigDict(title="usv.CoreState")

    version: int = Field(description="the snapshot's own version (agent/core/snapshot.py)")
    vessel: str
    phase: float | None
    own: list[StampedVector] = Field(description="own cumulative odometry by stamp")
    own_arms: list[StampedVector] = Field([], description="own antenna arm vector R(psi) a by stamp (m)")
    motion: OwnMotionState
    tracks: dict[str, TrackState]
    priors: dict[str, PendingPrior] = Field(description="initial estimates of neighbours not yet started")
    tracker: TargetFilterState | None
    health: HealthCounters


# ----- the end of a run -----


class ReactionSummary(StrictModel):
    """The agent's reaction times over a run (agent/shell/reaction.py), read to 0.05 ms."""

    model_config = ConfigDict(title="usv.ReactionSummary")

    p50: float = Field(ge=0, description="median (ms)")
    p99: float = Field(ge=0, description="99th percentile (ms)")
    max: float = Field(ge=0, description="longest (ms)")
    ticks: Count = Field(description="ticks timed")


class AgentSummary(StrictModel):
    model_config = ConfigDict(title="usv.AgentSummary")

    ticks: Count
    overruns: Count = Field(description="wall-clock ticks that started late")
    refused: dict[str, Count] = Field(description="inputs the gate refused, by reason")
    loop_seconds: float = Field(description="wall time from the first tick to the end (s)")
    cpu_seconds: float = Field(description="CPU time of the process, all threads, over the same span (s)")
    # Against the same step timed alone: what sharing the machine costs it.
    core_cpu_seconds: float | None = Field(
        None, description="CPU time of the tick thread inside the core's step over the same span (s)")
    # The trigger is the sim clock's arrival (in real time its own sensors', when they come after it) or the
    # timer; on lockstep sim time this includes the wait for the neighbours' shares.
    reaction_ms: ReactionSummary | None = Field(
        None, description="from each tick's trigger to its command's put (ms)")
    # The reaction without the waits for a core: what a computer of the agent's own would take.
    reaction_cpu_ms: ReactionSummary | None = Field(
        None, description="the tick thread's CPU from the start of each tick to its command's put (ms)")


class BridgeSummary(StrictModel):
    model_config = ConfigDict(title="usv.BridgeSummary")

    ticks: Count
    loop_seconds: float = Field(description="wall time from tick 0 to the end (s)")
    cpu_seconds: float = Field(description="s")
    missed_commands: Count
    startup_missing: list[str] = Field(description="vessels whose agent was not ready in time")
    watchdog_stops: Count
    refused: Count = Field(description="commands and statuses refused as malformed or misattributed")


# ----- the sim bridge's ground truth -----


class TrueVessel(StrictModel):
    position: Vector2 = Field(description="world frame (m)")
    heading: float = Field(description="rad")


class LoggedTruth(StrictModel):
    model_config = ConfigDict(title="usv.Truth")

    time: float = Field(description="s")
    vessels: dict[str, TrueVessel]
    target: Vector2
    target_velocity: Vector2


class CommandLatency(StrictModel):
    model_config = ConfigDict(title="usv.CommandLatency")

    milliseconds: dict[str, float] = Field(description="vessel id -> sensors published to its command received")
