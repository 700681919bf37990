"""A local tangent frame about a stated geodetic origin: WGS 84 latitude and longitude to and from metres.

x east, y north (m), as the fleet's world frame (docs/contract.md), on the plane tangent to the WGS 84
ellipsoid at `origin` (latitude, longitude in degrees; height in metres); pymap3d's geodetic2enu and
enu2geodetic (the `field` extra) do the work. Heights are left out: a point is taken at the origin's
height, so a fix's altitude does not move it (the fleet is on the sea). A point on the plane taken back to
latitude and longitude and into the plane again moves by d^3 / (2 R^2): 0.01 mm at d = 1 km from the origin.

More: docs/logs.md, "Scoring a field trial from GNSS".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FIELD_EXTRA = "install the field extra: pip install 'usv-circumnav[field]'"


class MissingField(ImportError):
    """pymap3d (the `field` extra) is not installed; the message says how to install it."""


def _pymap3d():
    try:
        import pymap3d
    except ImportError:
        raise MissingField(f"latitude and longitude to metres need pymap3d: {FIELD_EXTRA}") from None
    return pymap3d


@dataclass(frozen=True)
class LocalFrame:
    latitude: float         # deg, WGS 84
    longitude: float        # deg
    height: float = 0.0     # m above the ellipsoid

    def to_local(self, latitude, longitude) -> np.ndarray:
        """(..., 2) east, north (m) of WGS 84 points (deg), at the origin's height."""
        lat, lon = np.asarray(latitude, dtype=float), np.asarray(longitude, dtype=float)
        east, north, _ = _pymap3d().geodetic2enu(lat, lon, np.full(lat.shape, self.height),
                                                 self.latitude, self.longitude, self.height)
        return np.stack([np.asarray(east, dtype=float), np.asarray(north, dtype=float)], axis=-1)

    def to_geodetic(self, east, north) -> tuple[np.ndarray, np.ndarray]:
        """Latitude, longitude (deg) of local points (m) on the tangent plane."""
        e, n = np.asarray(east, dtype=float), np.asarray(north, dtype=float)
        lat, lon, _ = _pymap3d().enu2geodetic(e, n, np.zeros(e.shape),
                                              self.latitude, self.longitude, self.height)
        return np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
