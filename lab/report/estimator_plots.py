"""Figures of the lab commands. Matplotlib is imported here only, never by the agent."""

from __future__ import annotations

from pathlib import Path

import numpy as np

COLOURS = {"rls": "#d62728", "huber_rls": "#ff7f0e", "kf": "#1f77b4", "akf": "#9467bd", "mckf": "#2ca02c"}
LABELS = {"rls": "RLS", "huber_rls": "Huber-RLS", "kf": "KF", "akf": "AKF", "mckf": "MCKF"}


def rmse_figure(time: np.ndarray, curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str,
                path: Path, bound: tuple[str, np.ndarray] | None = None) -> Path:
    """RMSE over time on a log axis, one line per estimator with a +-1 std band across runs.

    `curves` maps an estimator name to (rmse, std), each shaped like `time`. `bound`, if given, is a
    (label, values) floor drawn as a black dashed line (the Cramér–Rao bound of lab/experiments/bound.py).
    """
    # Matplotlib (the optional 'lab' extra, and slow to import) only when a figure is drawn: `usv-lab --help`
    # and every command module stay light.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=130)
    for name, (rmse, std) in curves.items():
        colour = COLOURS.get(name)
        ax.plot(time, rmse, color=colour, lw=1.4, label=LABELS.get(name, name))
        lower = np.maximum(rmse - std, rmse * 1e-2)  # a log axis cannot show <= 0
        ax.fill_between(time, lower, rmse + std, color=colour, alpha=0.15, lw=0)
    if bound is not None:
        ax.plot(time, bound[1], color="black", lw=1.2, ls="--", label=bound[0])
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("relative position RMSE (m)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(ncol=min(len(curves) + (bound is not None), 6), fontsize=8, loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
