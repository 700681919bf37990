"""Error histories over Monte Carlo runs, and the summaries every lab result reports."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class ErrorHistory:
    """Position error norms of each estimator at each epoch of each run."""

    time: np.ndarray                  # (N,) seconds since the first epoch
    errors: dict[str, np.ndarray]     # estimator -> (runs, N) error norms |p^ - p| (m); [:, 0] is the start

    @property
    def runs(self) -> int:
        return next(iter(self.errors.values())).shape[0]

    def rmse(self, name: str) -> np.ndarray:
        """RMSE over runs at each epoch, (N,)."""
        return np.sqrt(np.mean(self.errors[name] ** 2, axis=0))

    def spread(self, name: str) -> np.ndarray:
        """Standard deviation over runs of the error norm at each epoch, (N,)."""
        return np.std(self.errors[name], axis=0)

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
