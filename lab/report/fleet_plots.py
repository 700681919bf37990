"""Figures of `usv-lab scenario`: fleet trajectories (the paper's Figs. 7, 9, 11, 12, 14) and errors over time
(Figs. 8, 10, 13, 15). Matplotlib is imported inside the functions, so only the lab ever loads it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lab.harness.runner import RunTrace
from lab.report.estimator_plots import COLOURS, LABELS
from sim_bridge.scenario import Scenario

OCCLUSION_STRIDE = 10        # draw every 10th blocked line of sight; all of them would hide the paths
ERROR_LABELS = (r"$e_{ij}^p$ (m)", r"$e_{io}^p$ (m)", r"$e_c$ (m)")
LOG_SPAN = 100.0             # a panel gets a log axis when its curves span more than two decades


def _pyplot():
    # Matplotlib only when a figure is drawn (the module docstring says why), here and below.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def variant_style(name: str, index: int) -> tuple[str, str]:
    """(colour, line style) of a variant's curve. A variant named after an estimator ('mckf') gets that
    estimator's colour of the other lab figures; one that ends in it ('paper_mckf') gets the same colour
    dashed, so the two versions of an estimator read as a pair. Anything else takes the default cycle."""
    if name in COLOURS:
        return COLOURS[name], "-"
    endings = [e for e in COLOURS if name.endswith(f"_{e}")]
    if endings:
        return COLOURS[max(endings, key=len)], "--"   # 'paper_huber_rls' is Huber-RLS, not RLS
    return f"C{index % 10}", "-"


def _grid(count: int) -> tuple[int, int]:
    columns = min(count, 3 if count > 4 else 2) if count > 1 else 1
    return math.ceil(count / columns), columns


def trajectory_figure(panels: dict[str, tuple[RunTrace, Scenario]], title: str, path: Path) -> Path:
    """One panel per variant: vessel paths, target path, desired circle, islands and blocked sight lines."""
    plt = _pyplot()
    rows, columns = _grid(len(panels))
    fig, axes = plt.subplots(rows, columns, figsize=(4.6 * columns, 4.4 * rows), dpi=110, squeeze=False,
                             layout="constrained")   # constrained: keeps panel titles clear of the title
    for ax, (name, (trace, scenario)) in zip(axes.flat, panels.items()):
        _trajectory_panel(ax, trace, scenario)
        ax.set_title(LABELS.get(name, name), fontsize=10)
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    fig.suptitle(title)
    return _save(plt, fig, path)


def _trajectory_panel(ax, trace: RunTrace, scenario: Scenario) -> None:
    # Deferred like _pyplot's matplotlib, which has loaded these by now.
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Polygon

    for island in scenario.world.islands:
        ax.add_patch(Polygon(island, closed=True, facecolor="0.6", edgecolor="0.35", lw=0.8, zorder=1))
    palette = "tab10" if len(trace.vessels) <= 10 else "tab20"
    colours = _colours(palette, len(trace.vessels))
    blocked = []
    for n, vessel in enumerate(trace.vessels):
        path = trace.positions[:, n]
        present = np.flatnonzero(np.all(np.isfinite(path), axis=1))
        if len(present) == 0:
            continue
        # NaN rows (the vessel is absent) break the line, so a vessel that leaves is not drawn after it left.
        ax.plot(path[:, 0], path[:, 1], color=colours[n], lw=1.1, zorder=3)
        start, end = path[present[0]], path[present[-1]]
        ax.plot(*start, "o", color=colours[n], ms=5, mfc="none", zorder=4)
        ax.plot(*end, "^", color=colours[n], ms=6, zorder=4)
        ax.annotate(vessel, start, textcoords="offset points", xytext=(4, 4), fontsize=7, color=colours[n])
        ticks = np.flatnonzero(trace.occluded[:, n] & np.all(np.isfinite(path), axis=1))[::OCCLUSION_STRIDE]
        blocked += [(path[k], trace.target[k]) for k in ticks]
    if blocked:
        ax.add_collection(LineCollection(blocked, colors="red", linestyles=":", linewidths=0.6, zorder=2))
    ax.plot(trace.target[:, 0], trace.target[:, 1], "k--", lw=1.2, zorder=3)
    final = trace.target[-1]
    radius = scenario.agent.control.radius
    angle = np.linspace(0.0, 2 * math.pi, 200)
    ax.plot(final[0] + radius * np.cos(angle), final[1] + radius * np.sin(angle), color="0.5", ls=":", lw=1.0,
            zorder=2)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    handles = [
        Line2D([], [], color="0.3", marker="o", mfc="none", ls="", label="start"),
        Line2D([], [], color="0.3", marker="^", ls="", label="end"),
        Line2D([], [], color="k", ls="--", label="target"),
        Line2D([], [], color="0.5", ls=":", label=f"r* = {radius:g} m around the final target"),
    ]
    if scenario.world.islands:
        handles.append(Patch(facecolor="0.6", edgecolor="0.35", label="island"))
    if blocked:
        handles.append(Line2D([], [], color="red", ls=":", lw=0.8, label="sight line blocked"))
    ax.legend(handles=handles, fontsize=6, loc="best", framealpha=0.8)


def _colours(palette: str, count: int) -> list:
    import matplotlib  # deferred like _pyplot's

    cmap = matplotlib.colormaps[palette]
    return [cmap(i % cmap.N) for i in range(count)]


def error_figure(curves: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], events: list[tuple[float, str]],
                 title: str, path: Path) -> Path:
    """Three stacked panels e_ij, e_io, e_c over time; `curves` maps a variant to (time (K,), the mean over
    runs (3, K), their std (3, K)); `events` are (time, text) of vessels joining or leaving, drawn as dashed
    lines."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(8.0, 8.5), dpi=120, sharex=True, layout="constrained")
    for panel, ax in enumerate(axes):
        stats = {name: (time, mean[panel], std[panel]) for name, (time, mean, std) in curves.items()}
        log = _spans_decades([mean for _, mean, _ in stats.values()])
        for index, (name, (time, mean, std)) in enumerate(stats.items()):
            colour, style = variant_style(name, index)
            ax.plot(time, mean, color=colour, ls=style, lw=1.2, label=LABELS.get(name, name))
            lower = np.maximum(mean - std, mean * 1e-2) if log else mean - std   # log cannot show <= 0
            ax.fill_between(time, lower, mean + std, color=colour, alpha=0.15, lw=0)
        if log:
            ax.set_yscale("log")
        else:
            ax.set_ylim(bottom=0.0)
        ax.set_ylabel(ERROR_LABELS[panel])
        ax.grid(True, which="both", alpha=0.3)
        for when, _ in events:
            ax.axvline(when, color="0.3", ls="--", lw=0.9)
    for when, text in _merged(events):
        axes[0].annotate(text, (when, 1.0), xycoords=("data", "axes fraction"), xytext=(3, -10),
                         textcoords="offset points", fontsize=7, va="top")
    axes[-1].set_xlabel("time (s)")
    axes[0].legend(ncol=min(len(curves), 5), fontsize=8, loc="upper right")
    fig.suptitle(title)
    return _save(plt, fig, path)


def _spans_decades(curves: list[np.ndarray]) -> bool:
    values = np.concatenate([c[np.isfinite(c) & (c > 0)] for c in curves]) if curves else np.array([])
    return len(values) > 0 and values.max() / values.min() > LOG_SPAN


def _merged(events: list[tuple[float, str]]) -> list[tuple[float, str]]:
    """One label per time: '5 joins (join), 4 leaves (dropout)'."""
    texts: dict[float, list[str]] = {}
    for when, text in events:
        texts.setdefault(when, []).append(text)
    return [(when, ", ".join(parts)) for when, parts in texts.items()]


def radius_spacing_figure(panels: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, float]], title: str,
                          path: Path) -> Path:
    """One panel per variant: each vessel's distance to the target over time (radii (K, n)) with the band
    r* ± 10 %, and on a second axis the spacing error (K,) in degrees; `panels` maps a variant to (time,
    radii, spacing error (rad), r*)."""
    plt = _pyplot()
    rows, columns = _grid(len(panels))
    fig, axes = plt.subplots(rows, columns, figsize=(4.8 * columns, 3.4 * rows), dpi=110, squeeze=False,
                             layout="constrained")
    for ax, (name, (time, radii, spacing, radius)) in zip(axes.flat, panels.items()):
        colours = _colours("tab10", radii.shape[1])
        ax.axhspan(0.9 * radius, 1.1 * radius, color="0.85", lw=0)
        for n in range(radii.shape[1]):
            ax.plot(time, radii[:, n], color=colours[n], lw=1.0)
        ax.set_ylim(0.0, max(2.0 * radius, float(np.nanmax(np.minimum(radii, 4.0 * radius)))))
        ax.set_xlabel("time (s)")
        ax.set_ylabel("distance to the target (m)")
        ax.grid(True, alpha=0.3)
        twin = ax.twinx()
        twin.plot(time, np.degrees(spacing), color="k", ls=":", lw=1.0)
        twin.set_ylabel("spacing error (deg, dotted)")
        twin.set_ylim(bottom=0.0)
        ax.set_title(LABELS.get(name, name), fontsize=10)
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    fig.suptitle(title)
    return _save(plt, fig, path)
