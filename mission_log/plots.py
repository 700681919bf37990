"""Figures of `usv-log plot RUN`: what a fleet did, and what each vessel believed, from a run's MCAP logs.

`trajectories.png` shows the true paths (with ground truth) beside each vessel's own picture of the
formation; `errors.png` compares the estimates with ground truth (only when the run has it);
`ranges.png` shows the range measurements and how the range filter weighed them. Without truth (a real boat)
every figure that does not need it is drawn from the agent logs alone. Matplotlib is imported inside
functions: the onboard agent must never load it, and only this ground-station tool does.
"""

from __future__ import annotations

import math
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mission_log.reader import RadiusSchedule, RunLog, VesselLog, radius_schedule
from mission_log.series import (
    Beliefs,
    TruthSeries,
    beliefs_of,
    centroid_error,
    estimate_errors,
    get,
    islands_of,
    number,
    ordered,
    take,
    time_sorted,
    truth_of,
)

DEFAULT_RADIUS = 5.0        # m, when no agent recorded its settings
BELIEF_WINDOW = 20.0        # s of trails in the "as vessel i sees it" panels; longer ones smear into blobs
OUTLIER_WEIGHT = 0.5        # an MCKF weight below this: the update was mostly ignored as an outlier
DPI = 115
ISLAND_FACE, ISLAND_EDGE = "#a3b296", "#5d6b52"    # grey-green
NEIGHBOUR_MARKERS = "os^DvP*X"
GAP_FACTOR = 1.5            # a step this many times the usual tick is a gap: the line is broken there


def plot_run(run: RunLog, out: Path, radius: float | None = None) -> list[Path]:
    """Write the PNG figures of a run to folder `out` (created if missing); returns their paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # r* as it was in force (mission `set`s included), unless the caller fixes one for the whole run
    schedule = radius_schedule(run, DEFAULT_RADIUS) if radius is None else RadiusSchedule(float(radius), {})
    radius = final_radius(schedule)
    truth = truth_of(run.sim) if run.has_truth else None
    beliefs = {vid: beliefs_of(run.vessels[vid]) for vid in ordered(run.vessels)}
    t0 = _start_ns(run, truth)
    colours = _palette(_all_ids(run, truth, beliefs))
    written = []
    if beliefs or truth is not None:
        path = out / "trajectories.png"
        written.append(_trajectories_figure(run, truth, beliefs, colours, radius, t0, path))
    if truth is not None:
        written.append(_errors_figure(truth, beliefs, colours, schedule, t0, out / "errors.png"))
    if beliefs:
        written.append(_ranges_figure(run, beliefs, colours, t0, out / "ranges.png"))
    return written


def _start_ns(run: RunLog, truth: TruthSeries | None) -> int:
    """The run's time zero: the earliest message any agent or the bridge logged."""
    firsts = [min(t for t, _ in v.topic(name)) for v in run.vessels.values()
              for name in ("inputs", "estimates") if v.topic(name)]
    if truth is not None and len(truth.t_ns):
        firsts.append(int(truth.t_ns[0]))
    return min(firsts, default=0)


def _seconds(t_ns, t0: int) -> np.ndarray:
    return (np.asarray(t_ns, dtype=np.int64) - t0) / 1e9   # subtract first: epoch ns do not fit a float


def _all_ids(run: RunLog, truth: TruthSeries | None, beliefs: dict[str, Beliefs | None]) -> list[str]:
    ids = set(run.vessels) | set(truth.vessels if truth else ())
    ids |= {j for b in beliefs.values() if b for j in b.neighbours}
    ids |= {str(j) for v in run.vessels.values() for _, m in v.topic("inputs")
            for j in get(m, "ranges") or {}}
    return ordered(ids)


def _palette(ids: list[str]) -> dict[str, tuple]:
    """One colour per vessel, the same in every figure."""
    import matplotlib  # deferred: see the module docstring

    cmap = matplotlib.colormaps["tab10" if len(ids) <= 10 else "tab20"]
    return {vid: cmap(n % cmap.N) for n, vid in enumerate(ids)}


def _with_gaps(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Insert a NaN where ticks are missing, so a line is not drawn across a vessel's absence."""
    t = np.asarray(t, dtype=float)
    values = np.asarray(values, dtype=float)
    if len(t) < 3:
        return t, values
    steps = np.diff(t)
    usual = np.median(steps)
    if not usual > 0:
        return t, values
    breaks = np.flatnonzero(steps > GAP_FACTOR * usual) + 1
    return np.insert(t, breaks, np.nan), np.insert(values, breaks, np.nan, axis=0)


def _last_finite(points: np.ndarray) -> np.ndarray | None:
    finite = np.flatnonzero(np.isfinite(points).all(axis=1))
    return points[finite[-1]] if len(finite) else None


# --- figures ------------------------------------------------------------------------------------------------


def _pyplot():
    """pyplot, drawing to files. Imported on the first figure, not with the module (see its docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@contextmanager
def _figure(path: Path, size: tuple[float, float]):
    """A figure saved to `path` at the end of the block, and closed even if drawing failed."""
    plt = _pyplot()
    fig = plt.figure(figsize=size, dpi=DPI, layout="constrained")
    try:
        yield fig
        fig.savefig(path)
    finally:
        plt.close(fig)


def _no_data(ax, text: str) -> None:
    ax.text(0.5, 0.6, text, transform=ax.transAxes, ha="center", va="center", color="0.4")


def _legend(ax, **options) -> None:
    """A legend, if anything in the panel has a label (matplotlib warns about an empty one)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**options)


def _circle(ax, centre, radius: float) -> None:
    from matplotlib.patches import Circle  # deferred: see the module docstring

    ax.add_patch(Circle(centre, radius, fill=False, ls=":", lw=1.1, color="0.35", zorder=2))


# trajectories.png


def _trajectories_figure(run, truth, beliefs, colours, radius, t0, path) -> Path:
    believers = list(beliefs)
    rows, columns = _belief_grid(len(believers), beside_map=truth is not None)
    with _figure(path, _trajectories_size(len(believers), truth is not None)) as fig:
        panels = fig
        if truth is not None:
            if believers:   # the map as tall as the block of belief panels beside it
                map_fig, panels = fig.subfigures(1, 2, width_ratios=[rows, columns])
            else:
                map_fig = fig
            _map_panel(map_fig.subplots(), truth, islands_of(run.sim), colours, radius)
        if believers:
            axes = panels.subplots(rows, columns, squeeze=False)
            for ax, vid in zip(axes.flat, believers, strict=False):
                _belief_panel(ax, vid, beliefs[vid], truth, colours, radius, t0)
            for ax in list(axes.flat)[len(believers):]:
                ax.set_visible(False)
        if truth is not None:
            fig.suptitle(f"Where the fleet went (ground truth) and where each vessel believed it was, "
                         f"r* = {radius:g} m")
        else:
            fig.suptitle(f"Where each vessel believed the fleet was (no ground truth), r* = {radius:g} m")
    return path


def _belief_grid(count: int, beside_map: bool) -> tuple[int, int]:
    """Rows and columns of the belief panels: a squarish block beside the map, otherwise a wide row."""
    if count == 0:
        return 0, 0
    if beside_map:
        rows = math.ceil(math.sqrt(count))
    else:
        rows = math.ceil(count / 3)
    return rows, math.ceil(count / rows)


def _trajectories_size(count: int, with_map: bool) -> tuple[float, float]:
    if count == 0:
        return 9.0, 8.0
    rows, columns = _belief_grid(count, with_map)
    if with_map:
        height = min(7.0, 14.0 * rows / (rows + columns))   # the map is as tall as the block of panels
        return height * (rows + columns) / rows, height + 0.5
    panel = min(6.0, 13.0 / columns)
    return panel * columns, panel * rows + 0.6


def _map_panel(ax, truth: TruthSeries, islands: list[np.ndarray], colours, radius: float) -> None:
    from matplotlib.patches import Polygon  # deferred: see the module docstring

    t = _seconds(truth.t_ns, int(truth.t_ns[0]) if len(truth.t_ns) else 0)
    for n, outline in enumerate(islands):
        ax.add_patch(Polygon(outline, closed=True, facecolor=ISLAND_FACE, edgecolor=ISLAND_EDGE, lw=0.8,
                             zorder=1, label="island" if n == 0 else None))
    for vid, positions in truth.vessels.items():
        _, path = _with_gaps(t, positions)
        ax.plot(path[:, 0], path[:, 1], color=colours[vid], lw=1.4, zorder=3, label=f"vessel {vid}")
        final = _last_finite(positions)
        if final is not None:
            ax.plot(*final, "o", color=colours[vid], mec="black", ms=7, zorder=4)
    _, target = _with_gaps(t, truth.target)
    ax.plot(target[:, 0], target[:, 1], "k--", lw=1.2, zorder=3, label="target")
    final_target = _last_finite(truth.target)
    if final_target is not None:
        ax.plot(*final_target, "*", color="black", ms=11, zorder=4)
        _circle(ax, final_target, radius)
        ax.plot([], [], ls=":", color="0.35", label=f"r* = {radius:g} m around the final target")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    ax.set_title("True paths (dots: final positions, star: final target)", fontsize=10)
    ax.legend(fontsize=8, loc="best", framealpha=0.8)


def _belief_panel(ax, vid: str, beliefs: Beliefs | None, truth: TruthSeries | None, colours, radius, t0) -> None:
    """Vessel i's formation in a frame centred on its estimated target: i at p^_io, j at p^_io - p^_ij."""
    _circle(ax, (0.0, 0.0), radius)
    ax.plot(0.0, 0.0, "+", color="black", ms=10, zorder=4)
    ax.set_title(f"As vessel {vid} sees it", fontsize=10)
    ax.set_xlabel("x from estimated target (m)")
    ax.set_ylabel("y from estimated target (m)")
    ax.grid(True, alpha=0.3)
    if beliefs is None or _last_finite(beliefs.target) is None:
        _no_data(ax, "no target estimate logged")
        return
    # the vessel's own last ticks, not the run's: one that left early still shows what it last believed
    window = beliefs.t_ns >= beliefs.t_ns[-1] - int(BELIEF_WINDOW * 1e9)
    t = _seconds(beliefs.t_ns[window], t0)
    own = beliefs.target[window]
    believed = {vid: own} | {j: own - estimate[window] for j, estimate in beliefs.neighbours.items()}
    index = truth.index(beliefs.t_ns[window]) if truth is not None else None
    for j, positions in believed.items():
        final = _last_finite(positions)
        if final is None:
            continue
        _, trail = _with_gaps(t, positions)
        itself = j == vid
        label = f"vessel {j}" + (" (itself)" if itself else "")
        ax.plot(trail[:, 0], trail[:, 1], color=colours[j], lw=1.6 if itself else 1.2, zorder=3, label=label)
        ax.plot(*final, "o", color=colours[j], mec="black", ms=8 if itself else 6, zorder=5)
        if index is not None and j in truth.vessels:
            _, actual = _with_gaps(t, take(truth.vessels[j], index) - take(truth.target, index))
            ax.plot(actual[:, 0], actual[:, 1], color=colours[j], ls="--", lw=0.7, zorder=2)
    if index is not None:
        ax.plot([], [], color="0.3", ls="--", lw=0.7, label="true, from true target")
    ax.set_title(f"As vessel {vid} sees it, {t[0]:.0f}-{t[-1]:.0f} s", fontsize=10)
    ax.set_aspect("equal", adjustable="datalim")
    _legend(ax, fontsize=7, loc="best", framealpha=0.8)


# errors.png


def final_radius(schedule: RadiusSchedule) -> float:
    """The r* the run ended with (the one most vessels had last), for the figures' circles."""
    finals = [float(radii[-1]) for _, radii in schedule.vessels.values()]
    return max(set(finals), key=finals.count) if finals else schedule.initial


def _errors_figure(truth: TruthSeries, beliefs, colours, schedule: RadiusSchedule, t0: int, path: Path) -> Path:
    t = _seconds(truth.t_ns, t0)
    with _figure(path, (11.0, 10.0)) as fig:
        axes = fig.subplots(4, 1, sharex=True)
        for vid, found in beliefs.items():
            if found is None or vid not in truth.vessels:
                continue
            e_ij, e_io = estimate_errors(vid, found, truth)
            _curve(axes[0], t, e_ij, colours[vid], f"vessel {vid}")
            _curve(axes[1], t, e_io, colours[vid], f"vessel {vid}")
        for vid, positions in truth.vessels.items():
            distance = np.linalg.norm(positions - truth.target, axis=1) - schedule.at(vid, truth.t_ns)
            _curve(axes[2], t, distance, colours[vid], f"vessel {vid}")
        _curve(axes[3], t, centroid_error(truth), "black", "fleet")
        changed = any(len(set(radii.tolist())) > 1 for _, radii in schedule.vessels.values())
        _label_errors(axes, "r* in force (set by the mission)" if changed else f"r* = {final_radius(schedule):g} m")
        fig.suptitle("Estimation and formation errors against ground truth")
    return path


def _curve(ax, t, values, colour, label) -> None:
    t, values = _with_gaps(t, values)
    ax.plot(t, values, color=colour, lw=1.1, label=label)


def _label_errors(axes, circle: str) -> None:
    panels = [
        (r"$e_{ij}$: each vessel's worst error in a neighbour's relative position $\hat p_{ij}$",
         r"$e_{ij}$ (m)"),
        (r"$e_{io}$: error in each vessel's position relative to the target, $\hat p_{io}$", r"$e_{io}$ (m)"),
        (f"True distance to the target minus {circle} (0: on the desired circle)",
         r"$|p_i - p_o| - r^*$ (m)"),
        (r"$e_c$: distance from the fleet's mean position to the target", r"$e_c$ (m)"),
    ]
    for ax, (title, unit) in zip(axes, panels, strict=True):
        ax.set_title(title, fontsize=10)
        ax.set_ylabel(unit)
        ax.grid(True, alpha=0.3)
        if ax.get_lines():
            ax.legend(fontsize=8, loc="upper right", ncol=4)
        else:
            _no_data(ax, "no agent estimates")
    axes[2].axhline(0.0, color="0.3", lw=0.8)
    axes[-1].set_xlabel("time (s)")


# ranges.png


@dataclass
class Update:
    """One inter-vessel range update of the filter, as the agent logged its outcome."""
    t: float            # s from the run's start
    neighbour: str
    z: float            # innovation / sqrt(innovation variance); NaN if the filter never computed one
    weight: float       # MCKF correntropy weight
    accepted: bool


def _ranges_figure(run: RunLog, beliefs, colours, t0: int, path: Path) -> Path:
    from matplotlib.cm import ScalarMappable  # deferred: see the module docstring
    from matplotlib.colors import Normalize

    ids = list(beliefs)
    # one shape per vessel in every row, so a single legend under the figure explains them all
    markers = {vid: NEIGHBOUR_MARKERS[n % len(NEIGHBOUR_MARKERS)] for n, vid in enumerate(colours)}
    scale = ScalarMappable(Normalize(0.0, 1.0), _pyplot().get_cmap("viridis").with_extremes(bad="0.6"))
    updates = {vid: _updates(run.vessels[vid], t0) for vid in ids}
    with _figure(path, (13.0, max(4.5, 1.2 + 2.9 * len(ids)))) as fig:
        axes = fig.subplots(len(ids), 2, sharex=True, squeeze=False)
        for (left, right), vid in zip(axes, ids, strict=True):
            _range_panel(left, vid, run.vessels[vid], beliefs[vid], colours, t0)
            _innovation_panel(right, vid, updates[vid], scale, markers)
        fig.colorbar(scale, ax=axes[:, 1], label="MCKF weight (near 0: outlier)")
        for ax in axes[-1]:
            ax.set_xlabel("time (s)")
        senders = ordered({u.neighbour for found in updates.values() for u in found})
        # at most 4 entries a row: a fleet's every neighbour in one row ran off both sides of the figure
        handles = _innovation_legend(senders, markers)
        fig.legend(handles=handles, loc="outside lower center", ncol=min(4, len(handles)), fontsize=8,
                   title="Right-hand panels", title_fontsize=8)
        fig.suptitle("Inter-vessel ranges: measurements, estimates and how the range filter weighed them")
    return path


def _measured_ranges(vessel: VesselLog, t0: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    found: dict[str, list[tuple[int, float]]] = defaultdict(list)
    for t, message in vessel.topic("inputs"):
        for j, value in (get(message, "ranges") or {}).items():
            if (metres := number(value)) is not None:
                found[str(j)].append((t, metres))
    return {j: (_seconds([t for t, _ in pairs], t0), np.array([r for _, r in pairs]))
            for j, pairs in found.items()}


def _range_panel(ax, vid: str, vessel: VesselLog, beliefs: Beliefs | None, colours, t0: int) -> None:
    """Measured ranges as dots, the range the estimate implies (|p^_ij|) as a line of the same colour."""
    measured = _measured_ranges(vessel, t0)
    estimated = beliefs.neighbours if beliefs is not None else {}
    for j in ordered(set(measured) | set(estimated)):
        if j in measured:
            ax.plot(*measured[j], ".", color=colours[j], ms=3, label=f"to vessel {j}")
        if j in estimated:
            t, implied = _with_gaps(_seconds(beliefs.t_ns, t0), np.linalg.norm(estimated[j], axis=1))
            ax.plot(t, implied, color=colours[j], lw=1.1, label=None if j in measured else f"to vessel {j}")
    ax.set_title(f"Vessel {vid}: measured ranges (dots) and " r"$|\hat p_{ij}|$ from its estimate (lines)",
                 fontsize=10)
    ax.set_ylabel("range (m)")
    ax.grid(True, alpha=0.3)
    if ax.get_lines():
        ax.legend(fontsize=7, loc="best", framealpha=0.8)
    else:
        _no_data(ax, "no ranges logged")


def _updates(vessel: VesselLog, t0: int) -> list[Update]:
    """The filter's range updates, once each, placed at their measurement stamp on the log's clock."""
    seen, found = set(), []
    for t_ns, message in time_sorted(vessel.topic("estimates")):
        tick = float(_seconds(t_ns, t0))
        agent_time = number(get(message, "time"))
        # stamps are on the agent's clock; the offset at this tick carries them onto the log's
        offset = tick - agent_time if agent_time is not None else None
        for j, estimate in (get(message, "neighbours") or {}).items():
            for outcome in get(estimate, "outcomes") or []:
                if not isinstance(outcome, dict):
                    continue
                key = (j, outcome.get("stamp"), outcome.get("range"), outcome.get("innovation"))
                if key in seen:      # a log that repeats recent outcomes must not double them
                    continue
                seen.add(key)
                stamp = number(outcome.get("stamp"))
                when = stamp + offset if stamp is not None and offset is not None else tick
                found.append(_update(str(j), when, outcome))
    return found


def _update(neighbour: str, when: float, outcome: dict) -> Update:
    innovation = number(outcome.get("innovation"))
    variance = number(outcome.get("innovation_variance"))
    z = innovation / math.sqrt(variance) if innovation is not None and variance and variance > 0 else math.nan
    weight = number(outcome.get("weight"))
    weight = math.nan if weight is None else weight
    return Update(when, neighbour, z, weight, bool(outcome.get("accepted", True)))


def _innovation_panel(ax, vid: str, updates: list[Update], scale, markers: dict[str, str]) -> None:
    """Normalised innovations coloured by MCKF weight, shaped by the neighbour ranged to."""
    ax.set_title(f"Vessel {vid}: normalised innovations of range updates", fontsize=10)
    ax.set_ylabel(r"$\nu / \sqrt{S}$ (standard deviations)")
    ax.grid(True, alpha=0.3)
    for level in (-3.0, 3.0):
        ax.axhline(level, color="0.5", ls=":", lw=0.8)
    if not updates:
        _no_data(ax, "no range updates logged")
        return
    for j in ordered({u.neighbour for u in updates}):
        used = [u for u in updates if u.neighbour == j and u.accepted]
        ax.scatter([u.t for u in used], [u.z for u in used], c=[u.weight for u in used], cmap=scale.cmap,
                   norm=scale.norm, marker=markers.get(j, "o"), s=16, lw=0, zorder=3)
    _outlier_marks(ax, updates)


def _outlier_marks(ax, updates: list[Update]) -> None:
    """Rings round the updates the MCKF down-weighted, red crosses on those the filter rejected outright."""
    from matplotlib.transforms import blended_transform_factory  # deferred: see the module docstring

    down = [u for u in updates if u.accepted and u.weight < OUTLIER_WEIGHT]
    ax.scatter([u.t for u in down], [u.z for u in down], s=70, facecolors="none", edgecolors="black", lw=0.8,
               zorder=4)
    rejected = [u for u in updates if not u.accepted]
    known = [u for u in rejected if math.isfinite(u.z)]
    ax.scatter([u.t for u in known], [u.z for u in known], marker="x", color="red", s=30, lw=1.2, zorder=5)
    # a rejection before any innovation was computed has no height: mark it along the top edge
    unknown = [u.t for u in rejected if not math.isfinite(u.z)]
    top = blended_transform_factory(ax.transData, ax.transAxes)
    ax.scatter(unknown, [0.97] * len(unknown), marker="x", color="red", s=30, lw=1.2, transform=top, zorder=5)


def _innovation_legend(senders: list[str], markers: dict[str, str]) -> list:
    from matplotlib.lines import Line2D  # deferred: see the module docstring

    return [
        *(Line2D([], [], color="0.45", marker=markers.get(j, "o"), ls="", label=f"range to vessel {j}")
          for j in senders),
        Line2D([], [], color="black", marker="o", mfc="none", ls="", ms=8,
               label=f"weight < {OUTLIER_WEIGHT:g}: outlier the MCKF down-weighted"),
        Line2D([], [], color="red", marker="x", ls="", label="rejected by the filter (not used)"),
        Line2D([], [], color="0.5", ls=":", label=r"$\pm 3$ standard deviations"),
    ]
