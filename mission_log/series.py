"""A run's logs as arrays: each vessel's beliefs and the ground truth on their ticks, and the errors of the
one against the other. `usv-log metrics` and `usv-log plot` both read a run through these, so a figure shows
exactly what a metric averages. The readers are lenient: a missing or malformed field becomes NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mission_log.reader import Log, VesselLog


@dataclass
class Beliefs:
    """One vessel's estimates at its own ticks; NaN where it had none (target None, neighbour absent)."""
    t_ns: np.ndarray                    # (K,) log time
    target: np.ndarray                  # (K, 2) p^_io = estimated p_i - p_o
    neighbours: dict[str, np.ndarray]   # j -> (K, 2) p^_ij = estimated p_i - p_j


@dataclass
class TruthSeries:
    t_ns: np.ndarray                    # (T,) log time, sorted
    target: np.ndarray                  # (T, 2)
    vessels: dict[str, np.ndarray]      # id -> (T, 2), NaN while the vessel is not in the run

    def index(self, t_ns: np.ndarray) -> np.ndarray:
        """Index of the truth sample at each log time; -1 where none is within half a tick (in real runs
        the agents' ticks need not land exactly on the bridge's)."""
        t = np.asarray(t_ns, dtype=np.int64)
        n = len(self.t_ns)
        if n == 0:
            return np.full(t.shape, -1)
        tolerance = np.median(np.diff(self.t_ns)) / 2 if n > 1 else 1e6
        right = np.clip(np.searchsorted(self.t_ns, t), 0, n - 1)
        left = np.clip(right - 1, 0, n - 1)
        nearest = np.where(np.abs(self.t_ns[left] - t) <= np.abs(self.t_ns[right] - t), left, right)
        return np.where(np.abs(self.t_ns[nearest] - t) <= tolerance, nearest, -1)


def get(message, *keys):
    """message[k1][k2]..., or None where a level is missing or not a dict."""
    for key in keys:
        if not isinstance(message, dict):
            return None
        message = message.get(key)
    return message


def number(value) -> float | None:
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _xy(value) -> tuple[float, float]:
    """The first two numbers of a list as a point; NaN for None or anything malformed."""
    try:
        return float(value[0]), float(value[1])
    except (TypeError, IndexError, KeyError, ValueError):
        return math.nan, math.nan


def _points(values: list) -> np.ndarray:
    return np.array([_xy(v) for v in values], dtype=float).reshape(-1, 2)


def _id_key(vid: str) -> tuple:
    """Vessel ids in numeric order where they are numbers ('2' before '10')."""
    return (0, int(vid), "") if vid.isdigit() else (1, 0, vid)


def ordered(ids) -> list[str]:
    return sorted((str(i) for i in ids), key=_id_key)


def time_sorted(messages: list[tuple[int, dict]]) -> list[tuple[int, dict]]:
    return sorted(messages, key=lambda pair: pair[0])


def beliefs_of(vessel: VesselLog) -> Beliefs | None:
    messages = time_sorted(vessel.topic("estimates"))
    if not messages:
        return None
    ids = ordered({j for _, m in messages for j in (get(m, "neighbours") or {})})
    return Beliefs(
        t_ns=np.array([t for t, _ in messages], dtype=np.int64),
        target=_points([get(m, "target_state") for _, m in messages]),
        neighbours={j: _points([get(m, "neighbours", j, "position") for _, m in messages]) for j in ids},
    )


def truth_of(sim: Log) -> TruthSeries:
    messages = time_sorted(sim.messages("/truth"))
    ids = ordered({v for _, m in messages for v in (get(m, "vessels") or {})})
    return TruthSeries(
        t_ns=np.array([t for t, _ in messages], dtype=np.int64),
        target=_points([get(m, "target") for _, m in messages]),
        vessels={v: _points([get(m, "vessels", v, "position") for _, m in messages]) for v in ids},
    )


def islands_of(sim: Log | None) -> list[np.ndarray]:
    """Island outlines from the bridge's scene; the latest drawing of each id wins (they do not move)."""
    found: dict[str, np.ndarray] = {}
    for _, update in (sim.messages("/scene") if sim is not None else []):
        for entity in get(update, "entities") or []:
            if get(entity, "frame_id") != "world" or not str(get(entity, "id")).startswith("island/"):
                continue
            lines = get(entity, "lines") or [{}]
            points = get(lines[0], "points") or []
            outline = np.array([(p.get("x", math.nan), p.get("y", math.nan)) for p in points], dtype=float)
            if len(outline) >= 3:
                found[entity["id"]] = outline
    return list(found.values())


def take(rows: np.ndarray, index: np.ndarray) -> np.ndarray:
    """rows[index], with NaN where index is -1 (no sample)."""
    out = np.full((len(index), rows.shape[1]), np.nan)
    present = index >= 0
    out[present] = rows[index[present]]
    return out


def estimate_errors(vid: str, beliefs: Beliefs, truth: TruthSeries) -> tuple[np.ndarray, np.ndarray]:
    """e_ij (worst over i's neighbours) and e_io of vessel i, on the truth's ticks; NaN where unknown."""
    index = truth.index(beliefs.t_ns)
    p_i = take(truth.vessels[vid], index)
    e_io = np.linalg.norm(beliefs.target - (p_i - take(truth.target, index)), axis=1)
    worst = np.full(len(index), np.nan)
    for j, estimate in beliefs.neighbours.items():
        if j in truth.vessels:
            error = np.linalg.norm(estimate - (p_i - take(truth.vessels[j], index)), axis=1)
            worst = np.fmax(worst, error)    # fmax skips NaN: a neighbour absent at a tick does not count
    on_truth = np.full((2, len(truth.t_ns)), np.nan)
    present = index >= 0
    on_truth[:, index[present]] = worst[present], e_io[present]
    return on_truth[0], on_truth[1]


def centroid_error(truth: TruthSeries) -> np.ndarray:
    """e_c: distance from the mean position of the vessels present to the target."""
    if not truth.vessels:
        return np.full(len(truth.t_ns), np.nan)
    positions = np.stack(list(truth.vessels.values()))            # (N, T, 2)
    present = np.isfinite(positions).all(axis=2)
    total = np.where(present[..., None], positions, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):          # no vessel at a tick: NaN, as wanted
        mean = total / present.sum(axis=0)[:, None]
    return np.linalg.norm(mean - truth.target, axis=1)
