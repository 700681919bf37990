"""A vessel's core state as plain JSON-ready data, and back: what lets replay start at any saved tick.

`state_to_json(state)` after tick k and `state_from_json(data, params)` give a state from which `step` on
the inputs of tick k+1 onward gives the same outputs, bit for bit, as the original run (floats go through
JSON as the shortest text that reads back to the same float). The agent logs a snapshot every
`snapshot_every` ticks on `/<id>/state`.

With other parameters than the recorded ones (replay with `--set`), each filter keeps its estimate and
covariance; a pair filter of another kind than the recorded one starts its own extra state (adaptive noise
scale and the like) afresh.
"""

from __future__ import annotations

import numpy as np

from agent.core.checks import checked_share
from agent.core.estimators import make_relative_estimator
from agent.core.estimators.plkf import PLKF
from agent.core.estimators.plkf_leeway import LeewayPLKF
from agent.core.neighbours import History, NeighbourPrior, NeighbourTrack, PairTiming
from agent.core.params import AgentParams
from agent.core.records import floats, share_from_json, share_to_json
from agent.core.state import Health, OwnMotion, VesselState

SNAPSHOT_VERSION = 3   # 2: pair filters keep both odometries at their epoch; 3: and their path spread
READS_SNAPSHOTS = (2, 3)   # a version-2 state starts each pair's path spread afresh (bookkeeping only)


def state_to_json(state: VesselState) -> dict:
    motion = state.motion
    return {
        "version": SNAPSHOT_VERSION,
        "vessel": state.vessel,
        "phase": state.phase,
        "own": _history_to_json(state.own),
        "own_arms": _history_to_json(state.own_arms),
        "motion": {"velocity": floats(motion.velocity), "stamp": motion.stamp,
                   "position": None if motion.position is None else floats(motion.position),
                   "yaw_rate": motion.yaw_rate, "leeway": floats(motion.leeway),
                   "set": floats(motion.set), "surge": motion.surge, "surge_command": motion.surge_command,
                   "drift": floats(motion.drift)},
        "tracks": {j: _track_to_json(track) for j, track in state.tracks.items()},
        "priors": {j: {"position": floats(p.position), "covariance": floats(p.covariance), "stamp": p.stamp}
                   for j, p in state.priors.items()},
        "tracker": None if state.tracker is None else state.tracker.export_state(),
        "health": state.health.as_dict(),
        "recent_ranges": {j: [list(pair) for pair in kept] for j, kept in state.recent_ranges.items()},
    }


def state_from_json(data: dict, params: AgentParams) -> VesselState:
    """The state `state_to_json` wrote, for a core running with `params`; ValueError if it is not one."""
    if data.get("version") not in READS_SNAPSHOTS:
        raise ValueError(f"state snapshot version {data.get('version')!r}; this build reads "
                         f"{', '.join(map(str, READS_SNAPSHOTS))}")
    motion = data["motion"]
    tracker = None
    if data["tracker"] is not None:
        # The leeway model's filter says its heading (plkf_leeway.py); the PLKF's does not.
        kind = LeewayPLKF if "heading" in data["tracker"] else PLKF
        tracker = kind(params.target, np.zeros(4), np.eye(4), dt=params.dt)
        tracker.restore_state(data["tracker"])
    return VesselState(
        vessel=data["vessel"],
        own=_history_from_json(data["own"], params.fleet.history_ticks, _point),
        motion=OwnMotion(velocity=np.array(motion["velocity"], dtype=float), stamp=motion["stamp"],
                         position=None if motion["position"] is None else np.array(motion["position"], dtype=float),
                         yaw_rate=float(motion.get("yaw_rate", 0.0)),
                         leeway=np.array(motion.get("leeway", (0.0, 0.0)), dtype=float),
                         set=np.array(motion.get("set", (0.0, 0.0)), dtype=float),
                         surge=float(motion.get("surge", 0.0)),
                         surge_command=float(motion.get("surge_command", 0.0)),
                         drift=np.array(motion.get("drift", (0.0, 0.0)), dtype=float)),
        tracks={j: _track_from_json(j, t, params, data["vessel"]) for j, t in data["tracks"].items()},
        priors={j: NeighbourPrior(np.array(p["position"], dtype=float),
                                  np.array(p["covariance"], dtype=float).reshape(2, 2), p["stamp"])
                for j, p in data["priors"].items()},
        tracker=tracker,
        phase=data["phase"],
        health=Health(**data["health"]),
        # A snapshot from before antennas has none: the antenna at the centre.
        own_arms=_history_from_json(data.get("own_arms", []), params.fleet.history_ticks, _point),
        recent_ranges={j: [(float(t), float(r)) for t, r in kept] for j, kept in data.get("recent_ranges", {}).items()},
    )


def _vector(value) -> np.ndarray:
    return np.array(value, dtype=float)


def _point(value) -> tuple[float, float]:
    """An (x, y) the track keeps as floats."""
    x, y = _vector(value).tolist()
    return x, y


def _history_to_json(history: History) -> list:
    return [[key, value if isinstance(value, float) else floats(value)] for key, value in history.items()]


def _history_from_json(pairs: list, size: int, convert) -> History:
    history = History(size)
    history.restore((int(key), convert(value)) for key, value in pairs)
    return history


def _track_to_json(track: NeighbourTrack) -> dict:
    return {
        "odometry": _history_to_json(track.odometry),
        "ranges": _history_to_json(track.ranges),
        "estimator": None if track.estimator is None else track.estimator.export_state(),
        "epoch": track.epoch,
        "epoch_own": None if track.epoch_own is None else floats(track.epoch_own),
        "epoch_other": None if track.epoch_other is None else floats(track.epoch_other),
        "last_range": track.last_range,
        "arms": _history_to_json(track.arms),
        "last_offset": floats(track.last_offset),
        "share": None if track.share is None else share_to_json(track.share),
        "last_heard": track.last_heard,
        "first_heard": track.first_heard,
        "updates": track.updates,
        "rejected": track.rejected,
        "last_iterations": track.last_iterations,
        "spread": track.spread.export_state(),
    }


def _track_from_json(neighbour: str, data: dict, params: AgentParams, vessel: str) -> NeighbourTrack:
    history = params.fleet.history_ticks
    track = NeighbourTrack(neighbour, params.relative, params.dt, history, PairTiming.of(params.fleet))
    track.odometry = _history_from_json(data["odometry"], history, _point)
    track.ranges = _history_from_json(data["ranges"], history, float)
    if data["estimator"] is not None:
        track.estimator = make_relative_estimator(params.relative, np.zeros(2), np.eye(2), dt=params.dt)
        track.estimator.restore_state(data["estimator"])
    track.epoch = data["epoch"]
    track.epoch_own = None if data["epoch_own"] is None else _point(data["epoch_own"])
    track.epoch_other = None if data["epoch_other"] is None else _point(data["epoch_other"])
    track.last_range = data["last_range"]
    track.arms = _history_from_json(data.get("arms", []), history, _point)
    track.last_offset = _point(data.get("last_offset", (0.0, 0.0)))
    if data["share"] is not None:
        # Checked as it was when it came in: the track keeps its estimate of our pair as checked floats.
        track.share = share_from_json(data["share"])
        checked = checked_share(track.share, vessel)
        if checked is None:
            raise ValueError(f"the share of neighbour {neighbour!r} is one the vessel would have refused")
        _, track.velocity, track.reciprocal = checked
    track.last_heard = data["last_heard"]
    track.first_heard = data["first_heard"]
    track.updates = data["updates"]
    track.rejected = data["rejected"]
    track.last_iterations = data["last_iterations"]
    if "spread" in data:
        track.spread.restore_state(data["spread"])
    return track
