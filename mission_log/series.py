"""A run's logs as arrays: each vessel's beliefs and the ground truth on their ticks, and the errors of the
one against the other. `usv-log metrics` and `usv-log plot` both read a run through these, so a figure shows
exactly what a metric averages. The readers are lenient: a missing or malformed field becomes NaN.

**Times.** An estimate is compared with the truth at the true time it refers to. A vessel's estimates refer
to its tick's time, which is its odometry's stamp in its own clock. In the sim bridge's sea mode each vessel's
clock is off by its own offset and drift (`/bridge/sea`, `ClockModel`); `true_time_ns` undoes that, and the
truth is interpolated to the result (`TruthSeries.at`). Comparing with the nearest truth tick instead would
compare positions up to a tick apart (100 ms, a few cm at 0.5 m/s): an error of the metric, not of the
estimator. In lockstep the clocks are the sim's, every estimate falls on a truth tick, and nothing is
interpolated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mission_log.reader import Log, VesselLog


@dataclass
class Beliefs:
    """One vessel's estimates at its own ticks; NaN where it had none (target None, neighbour absent)."""
    t_ns: np.ndarray                    # (K,) log time
    target: np.ndarray                  # (K, 2) p^_io = estimated p_i - p_o
    neighbours: dict[str, np.ndarray]   # j -> (K, 2) p^_ij = estimated p_i - p_j
    # (K,) the time the estimates refer to, in the vessel's own clock (ns): the tick's time, which is its
    # odometry's stamp. None: the log times (on a wall clock the log time is when the tick ran, not this).
    stamp_ns: np.ndarray | None = None

    @property
    def stamps(self) -> np.ndarray:
        return self.t_ns if self.stamp_ns is None else self.stamp_ns


@dataclass(frozen=True)
class ClockModel:
    """One vessel's clock as the sim bridge's sea mode ran it (`/bridge/sea`; sim_bridge/world.py,
    `VesselClock`): at true time t (s from the run's epoch) it reads c(t) = t + offset + drift * t, and a stamp
    is epoch_ns + c(t) in ns. The bridge logs the truth at epoch_ns + t, so undoing c puts a vessel's stamp on
    the truth's time line."""
    epoch_ns: int
    offset_s: float
    drift: float        # s per s (1 ppm = 1e-6)


def true_time_ns(stamp_ns, clock: ClockModel | None) -> np.ndarray:
    """The true time (ns, on the truth's time line: epoch_ns + t) of stamps taken on a vessel's clock, by
    inverting c: t = (x - offset) / (1 + drift), with x = stamp - epoch. Without a clock model (lockstep and
    ideal runs, where every process stamps with the sim's time) the stamps are the true times, unchanged.

    The epoch is subtracted in integers first: an epoch time in ns (~1.8e18) does not fit a float's 53 bits,
    but a mission's span does (to well under a ns). The result is rounded to whole ns, as a stamp is."""
    stamps = np.asarray(stamp_ns, dtype=np.int64)
    if clock is None:
        return stamps.copy()
    since = (stamps - np.int64(clock.epoch_ns)).astype(float)
    true = (since - clock.offset_s * 1e9) / (1.0 + clock.drift)
    return np.int64(clock.epoch_ns) + np.rint(true).astype(np.int64)


def clocks_of(sim: Log | None) -> dict[str, ClockModel]:
    """Each vessel's clock from the sim bridge's `/bridge/sea` record; empty without one (no sea mode). A
    vessel whose entry is malformed is left out, so its stamps are taken as true times."""
    found = sim.messages("/bridge/sea") if sim is not None else []
    if not found:
        return {}
    record = found[0][1]
    try:
        epoch_ns = int(get(record, "epoch_ns"))
    except (TypeError, ValueError):
        return {}
    clocks = {}
    for vessel, clock in (get(record, "clocks") or {}).items():
        offset, drift_ppm = number(get(clock, "offset_s")), number(get(clock, "drift_ppm"))
        if offset is not None and drift_ppm is not None:
            clocks[str(vessel)] = ClockModel(epoch_ns, offset, drift_ppm * 1e-6)
    return clocks


@dataclass
class TruthSeries:
    t_ns: np.ndarray                    # (T,) log time, sorted
    target: np.ndarray                  # (T, 2)
    vessels: dict[str, np.ndarray]      # id -> (T, 2), NaN while the vessel is not in the run
    clocks: dict[str, ClockModel] = field(default_factory=dict)   # sea mode: each vessel's clock (else empty)

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

    def at(self, rows: np.ndarray, t_ns) -> np.ndarray:
        """`rows` (T, 2; the target or a vessel) at each time, interpolated on a straight line between the two
        samples around it: the bridge logs the truth once a tick, but an estimate may refer to any time in
        between. A time that is a sample's takes that sample as it is (lockstep: bit for bit the tick's).
        NaN outside the truth's span, and where the row is NaN (vessel absent) at either sample around."""
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        out = np.full((len(t), rows.shape[1]), np.nan)
        n = len(self.t_ns)
        if n == 0:
            return out
        right = np.searchsorted(self.t_ns, t)                   # the first sample at or after t
        exact = (right < n) & (self.t_ns[np.minimum(right, n - 1)] == t)
        out[exact] = rows[right[exact]]
        between = ~exact & (right > 0) & (right < n)
        after = right[between]
        before = after - 1
        # Integers first: on the wall clock the times are Unix times in ns, too large for a float.
        weight = ((t[between] - self.t_ns[before]) / (self.t_ns[after] - self.t_ns[before]))[:, None]
        out[between] = rows[before] + weight * (rows[after] - rows[before])
        return out


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
        stamp_ns=np.array([_stamp_ns(get(m, "time"), t) for t, m in messages], dtype=np.int64),
    )


def _stamp_ns(seconds, log_ns: int) -> int:
    """A record's `time` (s, the vessel's clock) in ns; the log time where it has none. The whole seconds
    are taken apart from the fraction: a Unix time times 1e9 in one float would be off by up to 128 ns."""
    seconds = number(seconds)
    if seconds is None or abs(seconds) >= 9e9:     # none, or beyond int64 ns (about 292 years)
        return int(log_ns)
    whole = math.floor(seconds)
    return whole * 1_000_000_000 + round((seconds - whole) * 1e9)


def truth_of(sim: Log) -> TruthSeries:
    messages = time_sorted(sim.messages("/truth"))
    ids = ordered({v for _, m in messages for v in (get(m, "vessels") or {})})
    return TruthSeries(
        t_ns=np.array([t for t, _ in messages], dtype=np.int64),
        target=_points([get(m, "target") for _, m in messages]),
        vessels={v: _points([get(m, "vessels", v, "position") for _, m in messages]) for v in ids},
        clocks=clocks_of(sim),
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
    """e_ij (worst over i's neighbours) and e_io of vessel i, on the truth's ticks; NaN where unknown.

    Each estimate is compared with the truth at the true time it refers to (its stamp through the vessel's
    clock model, then the truth interpolated there), so that a clock offset or a tick that does not fall on
    the bridge's does not count as an estimation error. It is then placed on the truth tick nearest that time
    (none beyond half a tick), so that the vessels' errors line up tick by tick for the worst over vessels;
    of two estimates placed on one tick the later counts."""
    when = true_time_ns(beliefs.stamps, truth.clocks.get(vid))
    index = truth.index(when)
    p_i = truth.at(truth.vessels[vid], when)
    e_io = np.linalg.norm(beliefs.target - (p_i - truth.at(truth.target, when)), axis=1)
    worst = np.full(len(index), np.nan)
    for j, estimate in beliefs.neighbours.items():
        if j in truth.vessels:
            error = np.linalg.norm(estimate - (p_i - truth.at(truth.vessels[j], when)), axis=1)
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
