"""Metrics of a mission: the paper's, from truth and estimates, and self-consistency ones from the logs alone.

The paper's metrics (Sec. VI), from a run's truth (the sim's, or a field trial's GNSS: mission_log.gnss_truth)
and the vessels' estimates (the in-process runner's trace, or the logs):
- e_ij^p(k) = max_i max_j |p^_ij - p_ij|: worst inter-vessel estimate;
- e_io^p(k) = max_i |p^_io - p_io|, e_io^v(k) = max_i |v^_io - v_io|: worst target estimate.
  From the logs, at the true time each estimate refers to (mission_log.series.estimate_errors);
- e_c(k) = |(1/n) sum_i p_i - p_o|: formation centre against the target;
- settling time: the first time from which every vessel's distance to the target stays within +-10 % of r*
  to the end of the run, r* being the circle in force for that vessel at each moment (its statuses say which:
  the configured one, then what the operator's `set`s made of it; mission_log.reader.RadiusSchedule), in
  seconds from the mission's start (mission_log.reader.mission_start_ns);
- the mean tick compute time.
"Mean" in the tables is the time average over the whole run, as in the paper's Tables II-IV.

Without ground truth (a real boat without GNSS logs) nothing can be compared with the truth, so the figures
are self-consistency ones that need only the agents' logs:
- normalised innovation squared (NIS) of each filter's updates: innovation^2 / predicted variance. A
  consistent filter averages 1, and 95 % of its updates fall under the chi-square(1) 95 % point (3.84).
  The MCKF's mean weight says how much it discounted (1: not at all);
- pair agreement: vessel i's p^_ij against vessel j's p^_ji, which should be its exact opposite;
- target agreement: i's and j's target estimates against i's estimate of where j is,
  (p^_io - p^_jo) - p^_ij, which is zero when all three agree.

More: docs/logs.md, "The modules in detail", `mission_log/metrics.py`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy.stats import chi2

from mission_log.gnss_truth import TARGET, gnss_truth
from mission_log.reader import LogError, RunLog, mission_start_ns, radius_schedule
from mission_log.series import TruthSeries, beliefs_of, centroid_error, estimate_errors, truth_of

NIS_BOUND_95 = float(chi2.ppf(0.95, 1))
SETTLING_BAND = 0.10


@dataclass(frozen=True)
class RunMetrics:
    mean_e_ij: float
    mean_e_io: float
    mean_e_io_velocity: float
    mean_e_c: float
    settling_time: float | None     # None: never settled
    mean_tick_ms: float
    p99_tick_ms: float


def settling_time(time: np.ndarray, radii: np.ndarray, radius, band: float = SETTLING_BAND) -> float | None:
    """First time from which all radii (k, n; NaN for absent vessels) stay within (1 +- band) r*; `radius` is
    r*, one value or one per tick and vessel (k, n)."""
    inside = np.all(np.isnan(radii) | (np.abs(radii - radius) <= band * radius), axis=1)
    if not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    return float(time[0] if len(outside) == 0 else time[outside[-1] + 1])


def gap_departures(positions: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The angular gaps (rad) between neighbouring vessels around `centre`, in the order of their angles, less
    the uniform 2 pi / n: all zero when they are evenly spaced on the circle."""
    angles = np.sort(np.arctan2(*(np.asarray(positions) - centre).T[::-1]))
    gaps = np.diff(np.append(angles, angles[0] + 2 * math.pi))
    return gaps - 2 * math.pi / len(angles)


def spacing_error(positions: np.ndarray, centre: np.ndarray) -> float:
    """Largest departure (rad) of the angular gaps between the vessels around `centre` from the uniform
    2 pi / n: zero when they are evenly spaced on the circle."""
    return float(np.max(np.abs(gap_departures(positions, centre))))


def nan_mean(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if len(finite) else math.nan


def summarise(time, e_ij, e_io, e_io_velocity, e_c, radii, radius, tick_seconds) -> RunMetrics:
    ticks = np.asarray(tick_seconds, dtype=float)
    ticks = ticks[np.isfinite(ticks)]
    return RunMetrics(
        mean_e_ij=nan_mean(np.asarray(e_ij)),
        mean_e_io=nan_mean(np.asarray(e_io)),
        mean_e_io_velocity=nan_mean(np.asarray(e_io_velocity)),
        mean_e_c=nan_mean(np.asarray(e_c)),
        settling_time=settling_time(np.asarray(time), np.asarray(radii), radius),
        mean_tick_ms=float(ticks.mean() * 1e3) if len(ticks) else math.nan,
        p99_tick_ms=float(np.percentile(ticks, 99) * 1e3) if len(ticks) else math.nan,
    )



def truth_metrics(run: RunLog, radius: float | None = None, truth: TruthSeries | None = None) -> dict:
    """The paper's metrics from the logs: worst e_ij and e_io over the vessels at each tick (each estimate
    against the truth at its true time, see the module's docstring), e_c, settling time (s from the
    mission's start), and their means. `truth`: the run's ground truth (None: the sim bridge's). `radius`:
    judge settling against this r* throughout; None: against each vessel's r* in force at each tick, from
    its statuses."""
    truth = truth_of(run.sim) if truth is None else truth
    start_ns = mission_start_ns(run)
    vessels = list(truth.vessels)
    n = len(truth.t_ns)
    e_ij, e_io = np.full(n, np.nan), np.full(n, np.nan)
    for vessel, log in run.vessels.items():
        beliefs = beliefs_of(log)
        if beliefs is None or vessel not in truth.vessels:
            continue
        worst_ij, error_io = estimate_errors(vessel, beliefs, truth)
        e_ij, e_io = np.fmax(e_ij, worst_ij), np.fmax(e_io, error_io)   # fmax: a vessel absent at a tick does not count
    positions = np.stack([truth.vessels[v] for v in vessels], axis=1)   # (T, n, 2)
    radii = np.linalg.norm(positions - truth.target[:, None, :], axis=-1)
    schedule = radius_schedule(run)
    if radius is None:
        wanted = np.stack([schedule.at(v, truth.t_ns) for v in vessels], axis=1)
        initial, changes = schedule.initial, schedule.changes(start_ns)
    else:
        wanted, initial, changes = radius, radius, []
    # Subtract in integers first: an epoch time in ns does not fit a float's 53 bits.
    time = (truth.t_ns - start_ns) * 1e-9
    metrics = summarise(time, e_ij, e_io, np.full(n, np.nan), centroid_error(truth), radii, wanted, [])
    return {"vessels": vessels, "ticks": n, "radius": initial, "radius_changes": changes,
            "mean_e_ij": metrics.mean_e_ij, "mean_e_io": metrics.mean_e_io, "mean_e_c": metrics.mean_e_c,
            "settling_time": metrics.settling_time, "start_ns": start_ns}


def circle_words(result: dict) -> str:
    """r* of a run in words: the configured circle and every change a `set` made, e.g. "r* = 5.0 m, 8.0 m
    from 21.3 s (vessels 1, 2, 3, 4)"."""
    words = f"r* = {result['radius']:g} m"
    grouped: dict[tuple[float, float], list[str]] = {}
    for seconds, vessel, radius in result.get("radius_changes", []):
        grouped.setdefault((round(seconds, 1), radius), []).append(vessel)
    for (seconds, radius), who in sorted(grouped.items()):
        words += f", {radius:g} m from {seconds:.1f} s ({'vessel' if len(who) == 1 else 'vessels'} {', '.join(who)})"
    return words


def _nis(pairs: list[tuple[float, float]]) -> dict:
    values = np.array([innovation**2 / variance for innovation, variance in pairs if variance > 0])
    if values.size == 0:
        return {"updates": 0, "mean_nis": None, "within_95": None}
    return {"updates": int(values.size), "mean_nis": float(values.mean()),
            "within_95": float(np.mean(values <= NIS_BOUND_95))}


def innovation_statistics(run: RunLog) -> dict:
    """NIS per filter over its accepted updates: each inter-vessel filter of each vessel (with its mean
    MCKF weight) and each vessel's target filter (bearing updates)."""
    result = {}
    for vessel, log in sorted(run.vessels.items()):
        relative: dict[str, list] = {}
        weights: dict[str, list] = {}
        bearings = []
        for _, m in log.topic("estimates"):
            for j, neighbour in m["neighbours"].items():
                for o in neighbour.get("outcomes", []):
                    if o["accepted"]:
                        relative.setdefault(j, []).append((o["innovation"], o["innovation_variance"]))
                        weights.setdefault(j, []).append(o["weight"])
            bearing = m.get("bearing")
            if bearing is not None and bearing["accepted"]:
                bearings.append((bearing["innovation"], bearing["innovation_variance"]))
        result[vessel] = {
            "relative": {j: {**_nis(v), "mean_weight": float(np.mean(weights[j]))} for j, v in sorted(relative.items())},
            "target": _nis(bearings),
        }
    return result


def _spread(errors: list[float]) -> dict:
    if not errors:
        return {"ticks": 0, "mean_m": None, "p95_m": None, "max_m": None}
    values = np.array(errors)
    return {"ticks": int(values.size), "mean_m": float(values.mean()), "p95_m": float(np.percentile(values, 95)),
            "max_m": float(values.max())}


def agreement(run: RunLog) -> dict:
    """Pair agreement |p^_ij + p^_ji| and target agreement |(p^_io - p^_jo) - p^_ij| over the ticks both
    vessels logged."""
    estimates = {v: dict(log.topic("estimates")) for v, log in run.vessels.items()}
    pairs, targets = {}, {}
    for i, j in combinations(sorted(estimates), 2):
        pair_errors, target_errors = [], []
        for t in sorted(estimates[i].keys() & estimates[j].keys()):
            mine, theirs = estimates[i][t], estimates[j][t]
            p_ij = mine["neighbours"].get(j, {}).get("position")
            p_ji = theirs["neighbours"].get(i, {}).get("position")
            if p_ij is not None and p_ji is not None:
                pair_errors.append(math.hypot(p_ij[0] + p_ji[0], p_ij[1] + p_ji[1]))
            if p_ij is not None and mine["target_state"] is not None and theirs["target_state"] is not None:
                gap = np.array(mine["target_state"][:2]) - np.array(theirs["target_state"][:2]) - np.array(p_ij)
                target_errors.append(float(np.hypot(*gap)))
        pairs[f"{i}-{j}"] = _spread(pair_errors)
        targets[f"{i}-{j}"] = _spread(target_errors)
    return {"pairs": pairs, "targets": targets}


def truth_source(run: RunLog, wanted: str | None = None) -> str | None:
    """Which truth scores the run: `wanted` ("sim" or "gnss"), or by default the sim bridge's when its log is
    there, else the GNSS logs' when there are any; None without either."""
    if wanted == "sim" and not run.has_truth:
        raise LogError(f"{run.source}: --truth sim, but no sim bridge log with /truth among the files")
    if wanted == "gnss" and not run.gnss:
        raise LogError(f"{run.source}: --truth gnss, but no GNSS log (the driver bridge's gnss.log) among "
                       "the files")
    return wanted or ("sim" if run.has_truth else "gnss" if run.gnss else None)


def run_metrics(run: RunLog, radius: float | None = None, truth: str | None = None, target_id: str = TARGET,
                target_at: tuple[float, float] | None = None) -> dict:
    """Everything `usv-log metrics` reports: truth metrics when the run has a truth (`truth`: "sim", "gnss" or
    None for truth_source's choice; with GNSS the target is `target_id`'s log or surveyed at `target_at`;
    settling against `radius`, or the r* in force at each moment if None), and the self-consistency figures
    always."""
    source = truth_source(run, truth)
    scored = None
    if source is not None:
        series = gnss_truth(run, target_id, target_at) if source == "gnss" else None
        scored = truth_metrics(run, radius, series) | {"source": source}
        if source == "gnss":
            scored["target"] = "surveyed" if target_at is not None else f"tagged ({target_id})"
    return {
        "truth": scored,
        "innovations": innovation_statistics(run),
        "agreement": agreement(run),
    }


def _cell(value, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def metrics_markdown(result: dict, source: str) -> str:
    lines = [f"# Metrics of {source}", ""]
    truth = result["truth"]
    if truth is None:
        lines += [("**No ground truth** (no sim bridge log with `/truth` and no GNSS log among the files): "
                   "the paper's metrics need it. "
                   "What follows checks the estimates against each other instead."), ""]
    else:
        settling = "never" if truth["settling_time"] is None else f"{truth['settling_time']:.1f} s after the start"
        origin = ("the sim bridge's" if truth.get("source", "sim") == "sim" else
                  f"the GNSS fixes (the target {truth.get('target')}; the fixes' own noise is in these "
                  "figures)")
        lines += ["## Against the ground truth (the paper's metrics)", "", f"Truth: {origin}.", "",
                  f"{len(truth['vessels'])} vessels, {truth['ticks']} ticks, {circle_words(truth)}", "",
                  "| mean e_ij (m) | mean e_io (m) | mean e_c (m) | settling time |", "|---|---|---|---|",
                  (f"| {_cell(truth['mean_e_ij'])} | {_cell(truth['mean_e_io'])} | {_cell(truth['mean_e_c'])} | "
                  f"{settling} |"), ""]
    lines += ["## Normalised innovations (NIS)", "",
              (f"A consistent filter averages 1 with 95 % of updates under {NIS_BOUND_95:.2f}. The mean weight is "
              "how much the MCKF trusted its range updates (1: fully; outliers get less)."), "",
              "| vessel | filter | updates | mean NIS | within 95 % | mean weight |",
              "|---|---|---|---|---|---|"]
    for vessel, filters in result["innovations"].items():
        for j, s in filters["relative"].items():
            lines.append(f"| {vessel} | p_{vessel}{j} (ranges) | {s['updates']} | {_cell(s['mean_nis'], 2)} | "
                         f"{_cell(s['within_95'], 2)} | {_cell(s['mean_weight'], 2)} |")
        s = filters["target"]
        lines.append(f"| {vessel} | target (bearings) | {s['updates']} | {_cell(s['mean_nis'], 2)} | "
                     f"{_cell(s['within_95'], 2)} | |")
    lines += ["", "## Agreement between vessels", "",
              ("Pair: |p^_ij + p^_ji| (each vessel's estimate of the other should be the exact opposite). Target: "
              "|(p^_io - p^_jo) - p^_ij| (two target estimates and one inter-vessel estimate closing the triangle)."),
              "", "| pair | ticks | pair mean (m) | pair p95 (m) | pair max (m) | target mean (m) | target p95 (m) |",
              "|---|---|---|---|---|---|---|"]
    for name, p in result["agreement"]["pairs"].items():
        q = result["agreement"]["targets"][name]
        lines.append(f"| {name} | {p['ticks']} | {_cell(p['mean_m'])} | {_cell(p['p95_m'])} | {_cell(p['max_m'])} | "
                     f"{_cell(q['mean_m'])} | {_cell(q['p95_m'])} |")
    return "\n".join(lines) + "\n"
