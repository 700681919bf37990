"""Bearing adapter: pixel -> unit vector from the target to the vessel, checked against hand-worked cases."""

from __future__ import annotations

import math
import os

import pytest
from pydantic import ValidationError

from agent.contract import Bearing
from driver_bridge.bearing import BearingAdapter, CameraSettings, parse_detection
from driver_bridge.serial_port import LineReader, nmea_sentence, open_serial, pump

H = math.sqrt(0.5)


def adapter(**extra) -> BearingAdapter:
    return BearingAdapter(CameraSettings(**({"fx": 200.0, "cx": 320.0, "width": 640} | extra)))


def test_target_dead_ahead_of_a_vessel_heading_north():
    # Line of sight = heading = north (0, 1); the payload points back from the target: (0, -1).
    assert adapter().bearing(320.0, None, math.pi / 2) == pytest.approx((0.0, -1.0))


def test_target_right_of_centre_is_clockwise():
    # u = 520: xn = (520 - 320) / 200 = 1, so 45 deg to starboard. Heading east: line of sight south-east
    # (H, -H); from the target the vessel lies north-west: (-H, H).
    camera = adapter()
    assert camera.azimuth(520.0) == pytest.approx(-math.pi / 4)
    assert camera.bearing(520.0, None, 0.0) == pytest.approx((-H, H))


def test_mounting_yaw_is_added_counter_clockwise():
    # Camera on the port beam (pi/2) of a boat heading east sees north: payload (0, -1).
    assert adapter(mount_yaw=math.pi / 2).bearing(320.0, None, 0.0) == pytest.approx((0.0, -1.0))
    # Stern camera (pi) on a boat heading north-east (pi/4) sees south-west (5 pi/4): payload (H, H).
    assert adapter(mount_yaw=math.pi).bearing(320.0, None, math.pi / 4) == pytest.approx((H, H))


def test_pitched_camera_uses_the_row():
    # fx = fy = 400, principal point (320, 240), camera 0.3 rad down. u = 520 -> xn = 0.5.
    # A target on the horizon sits at yn = -tan(0.3) (row 240 - 400 tan 0.3 = 116.27), and then
    # alpha = -atan(0.5 cos 0.3) = -atan(0.477668) = -0.445623 rad, with or without the row.
    camera = adapter(fx=400.0, fy=400.0, cy=240.0, height=480, mount_pitch=0.3)
    horizon_row = 240.0 - 400.0 * math.tan(0.3)
    assert camera.azimuth(520.0, horizon_row) == pytest.approx(-0.445623, abs=1e-6)
    assert camera.azimuth(520.0) == pytest.approx(-0.445623, abs=1e-6)
    # On the image centre row the ray is 0.3 rad down: forward cos 0.3 = 0.955336, right 0.5,
    # alpha = -atan2(0.5, 0.955336) = -0.482173 rad.
    assert camera.azimuth(520.0, 240.0) == pytest.approx(-0.482173, abs=1e-6)
    # A level camera ignores the row.
    level = adapter(fy=200.0, cy=240.0)
    assert level.azimuth(520.0, 10.0) == pytest.approx(level.azimuth(520.0, 470.0))


def test_no_detection_and_bad_pixels_give_none_and_are_counted():
    camera = adapter(height=480)
    assert camera.bearing(None, None, 0.0) is None
    for column, row in [(-0.5, None), (640.0, None), (100.0, 480.0), (math.nan, None)]:
        assert camera.bearing(column, row, 0.0) is None
    assert camera.bearing(100.0, None, math.inf) is None
    assert camera.rejected == {"no_detection": 1, "outside_image": 3, "non_finite": 2}


def test_output_is_a_valid_contract_bearing():
    vector = adapter().bearing(433.0, None, 2.0)
    assert math.hypot(*vector) == pytest.approx(1.0)
    assert Bearing(stamp_ns=1, seq=0, sender="2", bearing=vector).bearing == vector


def test_settings_refuse_inconsistent_intrinsics():
    with pytest.raises(ValidationError, match="cx=700.0 is outside the image width"):
        CameraSettings(fx=200.0, cx=700.0, width=640)
    with pytest.raises(ValidationError, match="fy and cy together"):
        CameraSettings(fx=200.0, cx=320.0, width=640, fy=200.0)
    with pytest.raises(ValidationError, match="fx"):
        CameraSettings(fx=0.0, cx=320.0, width=640)


def test_detections_through_a_pty():
    master, slave = os.openpty()
    reader = open_serial(os.ttyname(slave), 115_200)
    try:
        os.write(master, b"$DET,520.0,*7C\r\n" + b"$DET,,*55\r\n" + b"$DET,9999,*00\r\n")
        lines = LineReader()
        bodies = pump(reader, lines.feed, timeout_s=2.0, want=2)
    finally:
        reader.close()   # a pyserial port
        for fd in (slave, master):
            os.close(fd)
    # Checksums by hand: XOR of "DET,520.0," = 0x7C and of "DET,," = 0x55; the third one is wrong.
    assert nmea_sentence("DET,520.0,") == b"$DET,520.0,*7C\r\n" and lines.rejected == {"bad_checksum": 1}
    camera = adapter()
    results = [camera.bearing(*parse_detection(body), 0.0) for body in bodies]
    assert results[0] == pytest.approx((-H, H)) and results[1] is None
    assert parse_detection(b"DET,abc,") is None and parse_detection(b"DET,,5") is None
