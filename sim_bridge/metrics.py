"""The paper's metrics (Sec. VI), computed from a run's truth and the vessels' estimates.

- e_ij^p(k) = max_i max_j |p^_ij - p_ij|: worst inter-vessel estimate;
- e_io^p(k) = max_i |p^_io - p_io|, e_io^v(k) = max_i |v^_io - v_io|: worst target estimate;
- e_c(k) = |(1/n) sum_i p_i - p_o|: formation centre against the target;
- settling time: the first time from which every vessel's distance to the target stays within +-10 % of r*
  to the end of the run;
- the mean tick compute time.
"Mean" in the tables is the time average over the whole run, as in the paper's Tables II-IV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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


def settling_time(time: np.ndarray, radii: np.ndarray, radius: float, band: float = SETTLING_BAND
                  ) -> float | None:
    """First time from which all radii (k, n; NaN for absent vessels) stay within (1 +- band) r*."""
    inside = np.all(np.isnan(radii) | (np.abs(radii - radius) <= band * radius), axis=1)
    if not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    return float(time[0] if len(outside) == 0 else time[outside[-1] + 1])


def spacing_error(positions: np.ndarray, centre: np.ndarray) -> float:
    """Largest departure (rad) of the angular gaps between the vessels around `centre` from the uniform
    2 pi / n: zero when they are evenly spaced on the circle."""
    angles = np.sort(np.arctan2(*(np.asarray(positions) - centre).T[::-1]))
    gaps = np.diff(np.append(angles, angles[0] + 2 * math.pi))
    return float(np.max(np.abs(gaps - 2 * math.pi / len(angles))))


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
