"""Error histories over Monte Carlo runs, reduced as the runs arrive, and the summaries every lab result
reports.

A campaign of thousands of runs must not hold every run's curve on the client (issue #16): each run is
folded into running moments per epoch as it comes, in run order, so the figures are the same bit for bit
whoever ran the runs and in whatever order they finished.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


class RunningMoments:
    """Per-element statistics of arrays of one shape that arrive one run at a time: count, mean and
    population standard deviation (Welford's update), root mean square and maximum. A NaN element of a run
    is left out of that element's statistics; an element no run had reads NaN. Memory does not grow with
    the number of runs."""

    def __init__(self, shape: int | tuple[int, ...]) -> None:
        self.count = np.zeros(shape)
        self._mean = np.zeros(shape)
        self._m2 = np.zeros(shape)
        self._squares = np.zeros(shape)
        self._maximum = np.full(shape, -math.inf)

    def add(self, values) -> None:
        values = np.asarray(values, dtype=float)
        present = ~np.isnan(values)
        kept = np.where(present, values, 0.0)
        self.count += present
        delta = np.where(present, kept - self._mean, 0.0)
        self._mean += np.where(present, delta / np.maximum(self.count, 1.0), 0.0)
        self._m2 += np.where(present, delta * (kept - self._mean), 0.0)
        self._squares += kept * kept
        self._maximum = np.where(present, np.maximum(self._maximum, kept), self._maximum)

    def _seen(self, value: np.ndarray) -> np.ndarray:
        return np.where(self.count > 0, value, np.nan)

    @property
    def mean(self) -> np.ndarray:
        return self._seen(self._mean)

    @property
    def std(self) -> np.ndarray:
        return self._seen(np.sqrt(self._m2 / np.maximum(self.count, 1.0)))

    @property
    def rms(self) -> np.ndarray:
        return self._seen(np.sqrt(self._squares / np.maximum(self.count, 1.0)))

    @property
    def maximum(self) -> np.ndarray:
        return self._seen(self._maximum)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.count, self._mean, self._m2, self._squares, self._maximum))


def moments_by_name(names: Iterable[str], shape: int | tuple[int, ...]) -> dict[str, RunningMoments]:
    return {name: RunningMoments(shape) for name in names}


@dataclass
class ErrorHistory:
    """Position error norms |p^ - p| of each estimator at each epoch, over the runs added so far."""

    time: np.ndarray                          # (N,) seconds since the first epoch
    moments: dict[str, RunningMoments]        # estimator -> its error norms' moments at each epoch (N,)

    @property
    def runs(self) -> int:
        return int(next(iter(self.moments.values())).count.max(initial=0))

    def add_errors(self, errors: np.ndarray) -> None:
        """One run's errors, (estimators, N) in the order of `moments`."""
        for moments, curve in zip(self.moments.values(), errors, strict=True):
            moments.add(curve)

    def rmse(self, name: str) -> np.ndarray:
        """RMSE over runs at each epoch, (N,)."""
        return self.moments[name].rms

    def spread(self, name: str) -> np.ndarray:
        """Standard deviation over runs of the error norm at each epoch, (N,)."""
        return self.moments[name].std

    def largest_error(self, name: str) -> float:
        """The largest error norm of any run at any epoch."""
        return float(np.nanmax(self.moments[name].maximum))

    def time_averaged_rmse(self, name: str, start: float = 0.0) -> float:
        """Time average of the RMSE curve over [start, end], weighting epochs by time (trapezoid rule), so
        that irregular sampling does not bias it. A single epoch in the window is its own average."""
        keep = self.time >= start - 1e-9
        time, rmse = self.time[keep], self.rmse(name)[keep]
        if len(time) == 0:
            return math.nan
        if len(time) == 1:
            return float(rmse[0])
        return float(np.trapezoid(rmse, time) / (time[-1] - time[0]))

    def final_rmse(self, name: str) -> float:
        return float(self.rmse(name)[-1])
