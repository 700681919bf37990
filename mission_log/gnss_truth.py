"""Ground truth from GNSS: a field trial's fixes (the driver bridges' GNSS logs) as a TruthSeries, so that
`usv-log metrics` scores a field trial with the functions that score a simulation.

- The local frame (x east, y north; mission_log.local_frame) is about the target: its surveyed position
  (`surveyed`: latitude, longitude), or the first fix of its GNSS tag (the GNSS log of id `target_id`).
- A fix is of the antenna, q; the vessel's reference point is p = q - R(psi) a, a being the fix's antenna
  (ahead, left: the driver's gnss.receiver.antenna) and psi the vessel's heading at the fix's time, from its
  agent's log (its odometry's, in the common reference; interpolated). An antenna off the reference point
  with no heading to turn it by is an error, and so is a target tag off its reference point (a target's
  heading is unknown).
- One time line for all: from the first fix to the last, at the median interval between fixes; each track
  is interpolated onto it (TruthSeries.at), NaN outside its own span and across a gap of more than
  MAX_GAP_S without a fix.
- Times: the driver stamps a fix on its boat's clock, the agent its estimates on the same boat's clock; the
  boats' clocks must agree with each other (docs/boats.md, the field-trial checklist).

More: docs/logs.md, "Scoring a field trial from GNSS".
"""

from __future__ import annotations

import math

import numpy as np

from agent.contract import gnss_truth_key
from mission_log.local_frame import LocalFrame
from mission_log.reader import LogError, RunLog
from mission_log.series import TruthSeries, get, number, ordered, time_sorted

MAX_GAP_S = 2.0
TARGET = "target"


def fixes_of(run: RunLog, owner: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps ns, latitude and longitude (F, 2) deg, antennas (F, 2) m) of `owner`'s GNSS log, in time order;
    malformed fixes left out."""
    rows = []
    for t, fix in time_sorted(run.gnss[owner].messages(gnss_truth_key(owner))):
        lat, lon = number(get(fix, "latitude")), number(get(fix, "longitude"))
        antenna = get(fix, "antenna") or [0.0, 0.0]
        try:
            ahead, left = float(antenna[0]), float(antenna[1])
        except (TypeError, IndexError, KeyError, ValueError):
            continue
        if lat is not None and lon is not None and math.isfinite(ahead) and math.isfinite(left):
            rows.append((t, lat, lon, ahead, left))
    if not rows:
        raise LogError(f"{run.gnss[owner].path}: no readable GNSS fix of {owner}")
    table = np.array([r[1:] for r in rows], dtype=float)
    return np.array([r[0] for r in rows], dtype=np.int64), table[:, :2], table[:, 2:]


def headings(run: RunLog, vessel: str, t_ns: np.ndarray) -> np.ndarray | None:
    """The vessel's heading (rad) at `t_ns` from its agent's odometry (log time), interpolated on the
    unwrapped angle and held beyond its ends; None without an agent's log with odometry."""
    log = run.vessels.get(vessel)
    inputs = [] if log is None else log.topic("inputs")
    pairs = [(t, number(get(m, "odometry", "heading"))) for t, m in inputs]
    pairs = [(t, h) for t, h in time_sorted(pairs) if h is not None]
    if not pairs:
        return None
    stamps = np.array([t for t, _ in pairs], dtype=np.int64)
    unwrapped = np.unwrap([h for _, h in pairs])
    return np.interp((t_ns - stamps[0]).astype(float), (stamps - stamps[0]).astype(float), unwrapped)


def reference_points(run: RunLog, owner: str, frame: LocalFrame, t_ns, latlon, antennas,
                     target: bool = False) -> np.ndarray:
    """p = q - R(psi) a of each fix of `owner` (the target's tag if `target`; module docstring)."""
    points = frame.to_local(latlon[:, 0], latlon[:, 1])
    if not np.any(antennas):
        return points
    psi = None if target else headings(run, owner, t_ns)
    if psi is None:
        what = "the target's tag" if target else f"vessel {owner}'s antenna"
        raise LogError(f"{what} is off its reference point by {antennas[0].tolist()} m, but the run has no "
                       "heading to turn that by (an agent's log with odometry)")
    c, s = np.cos(psi), np.sin(psi)
    ahead, left = antennas[:, 0], antennas[:, 1]
    return points - np.stack([c * ahead - s * left, s * ahead + c * left], axis=1)


def on_time_line(t_ns: np.ndarray, points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """`points` at times `t_ns` interpolated onto `line` (TruthSeries.at), NaN across gaps over MAX_GAP_S."""
    track = TruthSeries(t_ns, points, {})
    out = track.at(points, line)
    after = np.clip(np.searchsorted(t_ns, line), 1, max(len(t_ns) - 1, 1))
    gap = (t_ns[after] - t_ns[after - 1]) * 1e-9 > MAX_GAP_S if len(t_ns) > 1 else np.zeros(len(line), bool)
    out[gap & ~np.isin(line, t_ns)] = np.nan
    return out


def gnss_truth(run: RunLog, target_id: str = TARGET,
               surveyed: tuple[float, float] | None = None) -> TruthSeries:
    """The run's truth from its GNSS logs (module docstring): every id but `target_id` a vessel; the target
    at `surveyed` (latitude, longitude) or, without it, where its GNSS log puts it."""
    vessels = ordered(set(run.gnss) - {target_id})
    if not vessels:
        raise LogError(f"{run.source}: no vessel's GNSS log (the driver bridge's gnss.log)")
    if surveyed is None and target_id not in run.gnss:
        raise LogError(f"{run.source}: no target position: give its surveyed latitude and longitude "
                       f"(--target-at LAT,LON) or the GNSS log of its tag (id {target_id})")
    tracks = {owner: fixes_of(run, owner) for owner in [*vessels, *([target_id] if surveyed is None else [])]}
    frame = LocalFrame(*(surveyed if surveyed is not None else tracks[target_id][1][0]))
    steps = [np.diff(t) for t, _, _ in tracks.values() if len(t) > 1]
    step = int(np.median(np.concatenate(steps))) if steps else 1
    start = min(int(t[0]) for t, _, _ in tracks.values())
    end = max(int(t[-1]) for t, _, _ in tracks.values())
    line = np.arange(start, end + 1, max(step, 1), dtype=np.int64)
    points = {owner: on_time_line(t, reference_points(run, owner, frame, t, latlon, antennas,
                                                      surveyed is None and owner == target_id), line)
              for owner, (t, latlon, antennas) in tracks.items()}
    target = np.zeros((len(line), 2)) if surveyed is not None else points.pop(target_id)
    return TruthSeries(line, target, points)
