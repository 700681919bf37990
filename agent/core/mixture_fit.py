"""A Gaussian mixture fitted by EM to weighted samples: the raw-range estimator's noise density
(raw_range's `noise_components`) from samples of a noise model (agent/core/range_noise.py) or from
calibration ranges (lab/experiments/uwb_datasets.py)."""

from __future__ import annotations

import math

import numpy as np


def em_mixture(x: np.ndarray, weight: np.ndarray, shares: np.ndarray, means: np.ndarray, variances: np.ndarray,
               iterations: int, min_variance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`iterations` EM steps of a Gaussian mixture on samples x (N,) with weights `weight` (N,, summing to 1),
    from the start (shares, means, variances) (K,); variances floored at `min_variance`. Returns the three."""
    for _ in range(iterations):
        log_p = (np.log(shares)[:, None] - 0.5 * np.log(2 * math.pi * variances)[:, None]
                 - 0.5 * (x[None, :] - means[:, None]) ** 2 / variances[:, None])
        log_p -= log_p.max(axis=0)
        resp = np.exp(log_p)
        resp /= resp.sum(axis=0)
        resp *= weight[None, :]
        mass = resp.sum(axis=1)
        shares = mass / mass.sum()
        means = (resp @ x) / mass
        variances = np.maximum((resp * (x[None, :] - means[:, None]) ** 2).sum(axis=1) / mass, min_variance)
    return shares, means, variances
