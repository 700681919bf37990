"""A real autopilot's telemetry through the MAVLink adapter: tests/data/ardusub/excerpt.tlog, 30 s of a tlog
a ground station recorded from an ROV running ArduSub 4.1.1 (EKF3) on 2023-05-04, taken from
clydemcqueen/ardusub_log_tools, testing/small.tlog at commit 2b7c8b137e265b2fc3d75659390628ede9b5b6aa, MIT
licence (tests/data/ardusub/README.md, LICENSE). No public ArduPilot Rover or boat log was found
(docs/boats.md, "A real log through the adapter"); ArduSub sends the same messages from the same AHRS and
EKF3.

The adapter opens the file with its own link (pymavlink reads a tlog by its path) and takes every message, as
the driver does, the replay's clock being the tlog's receive stamps. Its odometry is checked against the EKF's
other outputs in the same log, within the accuracy the log itself states."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from driver_bridge.mavlink_link import open_link
from driver_bridge.mavlink_vehicle import MavlinkSettings, MavlinkVehicle

LOG = Path(__file__).parent / "data" / "ardusub" / "excerpt.tlog"
LICENCE = "MIT"
RECORDS = 904                      # the excerpt's tlog records (make_excerpt.py)
# WGS-84 equatorial radius: one 1e-7 degree step of latitude, in metres (MAVLink's GLOBAL_POSITION_INT unit).
LAT_STEP = 6_378_137.0 * math.radians(1e-7)


def replay() -> dict:
    """Every message of the excerpt through the adapter's link into MavlinkVehicle, in order, at its stamp."""
    link = open_link(str(LOG), 115_200, 1, 1)
    vehicle = MavlinkVehicle(MavlinkSettings(url=str(LOG)), link.mav, "rov")
    # The log's autopilot asks the ground station for the time (TIMESYNC tc1 = 0, ts1 = its boot clock in ns
    # as it sent); the answers are not in it. Each ask is handed to the adapter as the answer to a request of
    # ours made as it came (round trip 0): the offset is then the receive stamp minus the autopilot's clock.
    answer = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = mavlink2.MAVLink(None)
    out = {"messages": 0, "positions": 0, "odometry": [], "attitude": {}, "used_attitude": [], "global": {},
           "yaw_rate": [], "gyro_noise": None, "vehicle": vehicle}
    last_attitude = None
    while batch := link.messages():
        for msg in batch:
            out["messages"] += 1
            now_ns, mono = round(msg._timestamp * 1e9), msg._timestamp
            kind = msg.get_type()
            if kind == "PARAM_VALUE" and msg.param_id == "EK3_GYRO_P_NSE":
                out["gyro_noise"] = msg.param_value
            odometry = vehicle.receive(msg, now_ns, mono)
            if kind == "ATTITUDE":
                last_attitude = msg.time_boot_ms
                out["attitude"][msg.time_boot_ms] = msg
                out["yaw_rate"].append((msg.time_boot_ms, vehicle.yaw_rate()))
            elif kind == "LOCAL_POSITION_NED":
                out["positions"] += 1
            elif kind == "GLOBAL_POSITION_INT":
                out["global"][msg.time_boot_ms] = msg
            elif kind == "TIMESYNC" and msg.tc1 == 0:
                (reply,) = parser.parse_buffer(answer.timesync_encode(msg.ts1, now_ns).pack(answer))
                vehicle.receive(reply, now_ns, mono)
            if odometry is not None:
                out["odometry"].append((odometry, msg.time_boot_ms))
                out["used_attitude"].append(last_attitude)
            vehicle.tick(now_ns, mono)
    link.close()
    return out


@pytest.fixture(scope="module")
def run() -> dict:
    return replay()


def test_the_real_log_decodes_and_every_position_becomes_odometry(run):
    """All 904 records parse (no BAD_DATA); each LOCAL_POSITION_NED becomes odometry once the adapter has the
    autopilot's heartbeat and a clock offset, stamped at its time_boot_ms plus that offset."""
    vehicle, odometry = run["vehicle"], run["odometry"]
    assert run["messages"] == RECORDS
    assert run["gyro_noise"] is not None
    # Refused only before the first heartbeat and the first TIMESYNC (at 0.9 s in the excerpt): 3 positions.
    assert set(vehicle.rejected) <= {"odometry_without_link", "odometry_without_clock"}
    assert sum(vehicle.rejected.values()) <= 3
    assert len(odometry) == run["positions"] - sum(vehicle.rejected.values()) >= 80
    assert vehicle.offset_ns is not None
    for (a, boot_a), (b, boot_b) in zip(odometry, odometry[1:]):
        assert b.stamp_ns - a.stamp_ns == (boot_b - boot_a) * 1_000_000   # the autopilot's clock, to the ns
        assert b.seq == a.seq + 1


def test_position_increments_match_the_ekfs_global_position_within_its_resolution(run):
    """Odometry (east, north) from the first position against GLOBAL_POSITION_INT of the same time_boot_ms,
    made local (WGS-84, flat over these decimetres). GLOBAL_POSITION_INT holds latitude and longitude in
    integer 1e-7 degrees: each value is within one step of the EKF's (truncated or rounded), an increment
    within two: 2.2 cm north, 1.5 cm east here. A swapped axis or sign is off by the motion (decimetres)."""
    odometry, fixes = run["odometry"], run["global"]
    first = fixes[odometry[0][1]]
    east_step = LAT_STEP * math.cos(math.radians(first.lat * 1e-7))
    errors, spans = [], []
    for odo, boot in odometry:
        fix = fixes[boot]
        north, east = (fix.lat - first.lat) * LAT_STEP, (fix.lon - first.lon) * east_step
        errors.append((odo.position[0] - east, odo.position[1] - north))
        spans.append((east, north))
    errors, spans = np.abs(errors), np.asarray(spans)
    assert np.ptp(spans[:, 0]) > 0.2 and np.ptp(spans[:, 1]) > 0.2      # the EKF's position moved, both axes
    assert errors[:, 0].max() <= 2 * east_step
    assert errors[:, 1].max() <= 2 * LAT_STEP


def test_heading_matches_the_ekfs_heading_within_its_resolution_and_the_turn_since_attitude(run):
    """Odometry heading (counter-clockwise from east) against GLOBAL_POSITION_INT.hdg of the same time_boot_ms
    (centidegrees clockwise from north). The adapter takes the yaw of the last ATTITUDE, `lag` ms before the
    position: the bound is one centidegree plus the turn in `lag` at the larger rate of the two ATTITUDEs
    around it, and the EKF's stated gyro noise (EK3_GYRO_P_NSE, rad/s, in the log) for a change in between."""
    noise, attitudes = run["gyro_noise"], run["attitude"]
    times = sorted(attitudes)
    for (odo, boot), used in zip(run["odometry"], run["used_attitude"]):
        after = next((t for t in times if t > used), used)
        rate = max(abs(attitudes[used].yawspeed), abs(attitudes[after].yawspeed))
        bound = math.radians(0.01) + (boot - used) / 1e3 * (rate + noise)
        error = abs(math.remainder(odo.heading - (math.pi / 2 - math.radians(run["global"][boot].hdg / 100)),
                                   2 * math.pi))
        assert error <= bound, (boot, math.degrees(error), math.degrees(bound))


def test_yaw_rate_matches_the_heading_differentiated_within_the_ekfs_gyro_noise(run):
    """The adapter's yaw rate (the IMU's, counter-clockwise) integrated over each interval between two
    odometries (trapezoids over the ATTITUDEs, 50 ms apart) against the heading change: the mean rates agree
    within the gyro noise the EKF states (EK3_GYRO_P_NSE = 0.015 rad/s, 1 sigma, from the log). The sign of
    the rate or of the heading reversed is off by twice the rate (up to 0.04 rad/s here)."""
    rates = dict(run["yaw_rate"])
    times = sorted(rates)
    odometry, used = run["odometry"], run["used_attitude"]
    residuals, turns = [], []
    for (a, _), (b, _), start, end in zip(odometry, odometry[1:], used, used[1:]):
        span = [t for t in times if start <= t <= end]
        turned = np.trapezoid([rates[t] for t in span], [t / 1e3 for t in span])
        change = math.remainder(b.heading - a.heading, 2 * math.pi)
        residuals.append((change - turned) / ((end - start) / 1e3))
        turns.append(change / ((end - start) / 1e3))
    assert len(residuals) >= 80
    assert max(np.abs(turns)) > run["gyro_noise"] / 2    # fast enough somewhere for a reversed sign to show
    assert max(np.abs(residuals)) <= run["gyro_noise"]
