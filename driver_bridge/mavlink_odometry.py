"""MAVLink ODOMETRY (#331) as the vessel's pose: its frames turned into north, east and a NED yaw. Pure.

`odometry_pose(frame_id, child_frame_id, x, y, q, yawspeed)` -> (north, east, yaw, yaw_rate) or the reason
it is refused (counted by the caller). yaw is clockwise from north (ATTITUDE's convention), yaw_rate
counter-clockwise (rad/s, the agent's). Frames (mavlink.io, common.xml, MAV_FRAME):
- pose `frame_id`: MAV_FRAME_LOCAL_NED (1): x north, y east, the quaternion's yaw clockwise from north;
  MAV_FRAME_LOCAL_ENU (4): x east, y north, its yaw counter-clockwise from east: NED yaw = pi/2 - yaw.
  Local frames aligned with the vehicle (LOCAL_FRD 20, LOCAL_FLU 21) have no common heading: refused.
- `q` is (w, x, y, z) of the body in that frame; yaw = atan2(2(wz + xy), 1 - 2(y^2 + z^2)). A quaternion
  further than 10 % from unit length is refused.
- the turn rate about the vertical has the sign of the child frame's z axis: z down (BODY_NED 8, BODY_FRD
  12, LOCAL_NED 1, LOCAL_FRD 20): a positive yawspeed turns clockwise, r = -yawspeed; z up (LOCAL_ENU 4,
  LOCAL_FLU 21): r = yawspeed. Other child frames are refused.
"""

from __future__ import annotations

import math

MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_ENU = 1, 4
Z_DOWN = (1, 8, 12, 20)   # LOCAL_NED, BODY_NED, BODY_FRD, LOCAL_FRD
Z_UP = (4, 21)            # LOCAL_ENU, LOCAL_FLU
UNIT_TOLERANCE = 0.1


def quaternion_yaw(w: float, x: float, y: float, z: float) -> float:
    """The rotation about the frame's third axis of the body (w, x, y, z), in (-pi, pi]."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def odometry_pose(frame_id: int, child_frame_id: int, x: float, y: float, q, yawspeed: float
                  ) -> tuple[float, float, float, float] | str:
    """(north, east, NED yaw, counter-clockwise yaw rate), or why not: odometry_frame, non_finite,
    odometry_quaternion."""
    if frame_id not in (MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_ENU) or child_frame_id not in Z_DOWN + Z_UP:
        return "odometry_frame"
    values = (x, y, yawspeed, *q)
    if len(q) != 4 or not all(math.isfinite(v) for v in values):
        return "non_finite"
    if abs(math.sqrt(sum(c * c for c in q)) - 1.0) > UNIT_TOLERANCE:
        return "odometry_quaternion"
    yaw = quaternion_yaw(*q)
    rate = -yawspeed if child_frame_id in Z_DOWN else yawspeed
    if frame_id == MAV_FRAME_LOCAL_NED:
        return x, y, yaw, rate
    return y, x, math.remainder(math.pi / 2 - yaw, 2 * math.pi), rate
