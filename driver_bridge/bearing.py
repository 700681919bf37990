"""Bearing adapter: a detection's pixel -> the contract's unit vector FROM the target TO the vessel.

Conventions:
- Image: pixel column u grows to the right, row v grows downwards; (cx, cy) is the principal point and
  fx, fy the focal lengths in pixels of an undistorted pinhole camera (undistort the detection first).
- Hull: the camera looks along mount_yaw (rad) from the bow, counter-clockwise positive (pi/2 = to port),
  and is pitched down by mount_pitch (rad). Roll is not compensated.
- Common frame (docs/contract.md): heading is yaw in the fleet's common heading reference, counter-clockwise
  from the x axis; the Bearing payload is a unit vector in that same frame.

Azimuth of the line of sight relative to the camera axis, counter-clockwise positive (a target right of the
image centre gives a negative angle): with xn = (u - cx) / fx and yn = (v - cy) / fy, the ray in a level
camera frame is (forward, right) = (cos(pitch) - yn sin(pitch), xn), so alpha = -atan2(xn, cos(pitch) -
yn sin(pitch)). Without a row (or without fy, cy) the target is taken at the horizon (ray level), which
gives alpha = -atan2(xn cos(pitch), 1). Then beta = heading + mount_yaw + alpha is the direction from the
vessel to the target, and the payload is -(cos beta, sin beta).

`parse_detection` reads the detector's serial line (our format, NMEA framing, see serial_port):
`$DET,<u>,<v>*hh` with pixel coordinates as decimals (v may be empty), and `$DET,,*hh` for no detection.
"""

from __future__ import annotations

import math
from collections import Counter

from pydantic import Field, model_validator

from agent.config import PositiveFloat, StrictModel
from driver_bridge.serial_port import nmea_number


class CameraSettings(StrictModel):
    fx: PositiveFloat = Field(description="horizontal focal length (px)")
    cx: float = Field(allow_inf_nan=False, description="principal point column (px)")
    width: int = Field(gt=0, description="image width (px)")
    height: int | None = Field(None, gt=0, description="image height (px); rows are checked when given")
    fy: PositiveFloat | None = Field(None, description="vertical focal length (px), for the row")
    cy: float | None = Field(None, allow_inf_nan=False, description="principal point row (px)")
    mount_yaw: float = Field(0.0, allow_inf_nan=False, description="camera axis from the bow, CCW (rad)")
    mount_pitch: float = Field(0.0, gt=-math.pi / 2, lt=math.pi / 2,
                               description="camera axis below level (rad)")

    @model_validator(mode="after")
    def _principal_point_inside(self) -> CameraSettings:
        if not 0 <= self.cx <= self.width:
            raise ValueError(f"cx={self.cx} is outside the image width 0..{self.width}")
        if (self.fy is None) != (self.cy is None):
            raise ValueError("give fy and cy together (or neither)")
        return self


class BearingAdapter:
    """`bearing(column, row, heading)` -> (bx, by) unit vector from target to vessel, or None.

    Refusals are counted in `rejected`: `outside_image` (pixel not in [0, width) x [0, height)),
    `non_finite` (NaN or infinity in a pixel or the heading). `no_detection` counts frames without a target.
    """

    def __init__(self, settings: CameraSettings):
        self.settings = settings
        self.rejected: Counter[str] = Counter()

    def azimuth(self, column: float, row: float | None = None) -> float:
        """Angle (rad) of the line of sight from the camera axis, counter-clockwise positive."""
        s = self.settings
        xn = (column - s.cx) / s.fx
        cos_p, sin_p = math.cos(s.mount_pitch), math.sin(s.mount_pitch)
        if row is None or s.fy is None or s.cy is None:
            return -math.atan2(xn * cos_p, 1.0)  # target assumed on the horizon
        yn = (row - s.cy) / s.fy
        return -math.atan2(xn, cos_p - yn * sin_p)

    def bearing(self, column: float | None, row: float | None, heading: float) -> tuple[float, float] | None:
        if column is None:
            self.rejected["no_detection"] += 1
            return None
        if not all(math.isfinite(v) for v in (column, heading, 0.0 if row is None else row)):
            self.rejected["non_finite"] += 1
            return None
        s = self.settings
        row_outside = row is not None and s.height is not None and not 0 <= row < s.height
        if not 0 <= column < s.width or row_outside:
            self.rejected["outside_image"] += 1
            return None
        beta = heading + s.mount_yaw + self.azimuth(column, row)  # vessel -> target, common frame
        return (-math.cos(beta), -math.sin(beta))


def parse_detection(body: bytes) -> tuple[float | None, float | None] | None:
    """(column, row) from a checked `DET` body; (None, None) when nothing was detected; None if malformed."""
    return read_detection(body)[0]


def read_detection(body: bytes) -> tuple[tuple[float | None, float | None] | None, str]:
    """(detection, "") or (None, why): `not_det` (another sentence, or the wrong fields), `bad_number` (a
    field that is no finite decimal), `row_without_column`. Where the pixel lies is BearingAdapter's check."""
    fields = body.decode("ascii", "replace").split(",")
    if len(fields) != 3 or fields[0] != "DET":
        return None, "not_det"
    column = nmea_number(fields[1]) if fields[1] else None
    row = nmea_number(fields[2]) if fields[2] else None
    if (fields[1] and column is None) or (fields[2] and row is None):
        return None, "bad_number"
    if column is None and row is not None:
        return None, "row_without_column"
    return (column, row), ""
