"""The odometry noise of the pair filters (R_delta of (5)) from the sensors' specification.

Dead reckoning from a speed log and a compass moves s dt along the compass heading each period. A speed
error of standard deviation sigma_s spreads the displacement along the track by sigma_s dt, a heading error
sigma_psi (its bias included: a bias that differs between two vessels turns one's displacements against the
other's) across it by s dt sigma_psi (first order). The filters take R_delta as isotropic, per axis: the
larger of the two variances covers the displacement's error in every direction.
"""

from __future__ import annotations


def displacement_variance(speed_std: float, heading_std: float, speed: float, dt: float) -> float:
    """R_delta per axis per period (m^2): max((sigma_s dt)^2, (s dt sigma_psi)^2)."""
    return max((speed_std * dt) ** 2, (speed * dt * heading_std) ** 2)
