"""Odometry adapter: dead reckoning checked against hand-worked paths, and NMEA VHW samples through a pty."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from pydantic import ValidationError

from agent.contract import Odometry, decode, encode
from boat.presets import PRESETS
from driver_bridge.odometry import DeadReckoning, OdometrySettings, parse_vhw
from driver_bridge.serial_port import LineReader, open_serial, pump
from sim_bridge.hull import HullFleet

COMPASS = {"yaw_sign": -1, "yaw_offset": math.pi / 2}  # clockwise from north -> CCW from east


def run(samples, **settings):
    odometry = DeadReckoning(OdometrySettings(**settings))
    state = None
    for sample in samples:
        state = odometry.update(*sample)
    return odometry, state


def test_straight_run_north_and_covariance_growing_with_distance():
    # heading pi/2 (north), 2 m/s for 10 s: (0, 20), 20 m travelled; var = 1e-3 m^2/m * 20 m = 0.02 m^2.
    samples = [(0.5 * k, 2.0, math.pi / 2) for k in range(21)]
    _, state = run(samples, position_variance_per_m=1e-3, heading_variance=4e-4)
    assert (state.x, state.y) == pytest.approx((0.0, 20.0), abs=1e-12)
    assert state.distance == pytest.approx(20.0) and state.heading == pytest.approx(math.pi / 2)
    assert state.covariance == pytest.approx((0.02, 0, 0, 0, 0.02, 0, 0, 0, 4e-4))


def test_speed_is_integrated_with_the_trapezoid():
    # 0 m/s at t=0, 2 m/s at t=1: a steady acceleration covers (0 + 2) / 2 * 1 = 1 m.
    _, state = run([(0.0, 0.0, 0.0), (1.0, 2.0, 0.0)])
    assert (state.x, state.y) == pytest.approx((1.0, 0.0))


def test_quarter_circle_from_yaw_readings_is_exact():
    # 1 m/s turning at 0.1 rad/s: radius 10 m. Starting east at the origin, the centre is (0, 10), so a
    # quarter turn (t = (pi/2) / 0.1 = 5 pi s) ends at (10, 10) heading north, after 10 * pi/2 = 15.708 m.
    times = np.linspace(0.0, 5 * math.pi, 158)
    _, state = run([(t, 1.0, 0.1 * t) for t in times])
    assert (state.x, state.y) == pytest.approx((10.0, 10.0), abs=1e-9)
    assert state.heading == pytest.approx(math.pi / 2) and state.distance == pytest.approx(5 * math.pi)


def test_full_circle_from_an_integrated_yaw_rate_closes():
    # 2 pi / 60 rad/s for 60 s at 1 m/s: one full turn of 60 m path, back at the origin.
    # Heading variance: 1e-4 (initial) + 1e-6 rad^2/s * 60 s = 1.6e-4.
    rate = 2 * math.pi / 60
    _, state = run([(0.1 * k, 1.0, rate) for k in range(601)], yaw_input="yaw_rate", initial_heading=0.3)
    assert (state.x, state.y) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert state.heading == pytest.approx(0.3) and state.distance == pytest.approx(60.0)
    assert state.covariance[8] == pytest.approx(1.6e-4)


def test_yaw_rate_is_integrated_with_the_trapezoid():
    # rate 0 at t=0 and 0.2 rad/s at t=1: turn (0 + 0.2) / 2 * 1 = 0.1 rad.
    _, state = run([(0.0, 0.0, 0.0), (1.0, 0.0, 0.2)], yaw_input="yaw_rate")
    assert state.heading == pytest.approx(0.1)


def test_compass_heading_maps_to_the_common_reference():
    # Compass 90 deg (east) -> heading 0: 1 m/s for 10 s ends at (10, 0). Compass 0 (north) -> pi/2.
    _, state = run([(0.0, 1.0, math.pi / 2), (10.0, 1.0, math.pi / 2)], **COMPASS)
    assert (state.x, state.y) == pytest.approx((10.0, 0.0), abs=1e-12) and state.heading == pytest.approx(0.0)
    _, state = run([(0.0, 0.0, 0.0)], **COMPASS)
    assert state.heading == pytest.approx(math.pi / 2)


def test_turn_across_the_seam_takes_the_short_way():
    # 179 deg -> -179 deg is a 2 deg turn to port, not 358 deg to starboard. Chord of a 1 m arc turning
    # 2 deg: sin(1 deg) / (1 deg in rad) = 1 - 0.0174533^2 / 6 = 0.99994923 m, along 180 deg.
    a, b = math.radians(179), math.radians(-179)
    _, state = run([(0.0, 1.0, a), (1.0, 1.0, b)])
    assert state.x == pytest.approx(-0.99994923, abs=1e-8) and state.y == pytest.approx(0.0, abs=1e-12)
    assert state.heading == pytest.approx(b)


def test_bad_samples_are_refused_counted_and_change_nothing():
    odometry, state = run([(0.0, 1.0, 0.0), (1.0, 1.0, 0.0)])
    for sample in [(math.nan, 1.0, 0.0), (2.0, math.inf, 0.0), (2.0, 1.0, math.nan), (1.0, 1.0, 0.0),
                   (0.5, 1.0, 0.0)]:
        assert odometry.update(*sample) is state
    assert odometry.rejected == {"non_finite": 3, "out_of_order": 2}
    assert DeadReckoning().update(math.nan, 0.0, 0.0) is None  # nothing accepted yet


def test_state_is_a_valid_contract_message():
    _, state = run([(100.0, 1.0, 0.0), (100.1, 1.0, 0.0)])
    message = state.message(seq=4, sender="3")
    decoded, reason = decode(Odometry, encode(message))
    assert reason == "" and decoded.stamp_ns == 100_100_000_000
    assert decoded.position == pytest.approx((0.1, 0.0))


def test_settings_refuse_bad_values_with_the_field_name():
    with pytest.raises(ValidationError, match="position_variance_per_m"):
        OdometrySettings(position_variance_per_m=-1.0)
    with pytest.raises(ValidationError, match="yaw_sign"):
        OdometrySettings(yaw_sign=2)


def test_vhw_known_sentence():
    # The example of the nmea crate's docs: $GPVHW,100.5,T,105.5,M,10.5,N,19.4,K*4F.
    (body,) = LineReader().feed(b"$GPVHW,100.5,T,105.5,M,10.5,N,19.4,K*4F\r\n")
    speed, heading = parse_vhw(body)
    assert speed == pytest.approx(10.5 * 1852 / 3600) and heading == pytest.approx(math.radians(100.5))
    assert parse_vhw(b"GPVHW,100.5,T,105.5,M,,N,,K") is None and parse_vhw(b"GPHDT,1.0,T") is None


def xor_sentence(body: str) -> bytes:
    checksum = 0
    for char in body.encode():
        checksum ^= char
    return f"${body}*{checksum:02X}\r\n".encode()


def test_vhw_samples_through_a_pty():
    master, slave = os.openpty()
    reader = open_serial(os.ttyname(slave), 4800)  # NMEA 0183's standard rate
    try:
        lines = LineReader()
        os.write(master, xor_sentence("IIVHW,90.0,T,,M,10.0,N,,K") + b"$IIVHW,90.0,T,,M,99.0,N,,K*00\r\n"
                 + xor_sentence("IIVHW,90.0,T,,M,10.0,N,,K") + xor_sentence("IIVHW,90.0,T,,M,,N,18.0,K"))
        bodies = pump(reader, lines.feed, timeout_s=2.0, want=3)
    finally:
        reader.close()   # a pyserial port
        for fd in (slave, master):
            os.close(fd)
    assert lines.rejected == {"bad_checksum": 1}
    odometry = DeadReckoning(OdometrySettings(**COMPASS))
    for stamp, body in enumerate(bodies):
        state = odometry.update(float(stamp), *parse_vhw(body))
    # 10 kn = 10 * 1852 / 3600 = 5.144444 m/s; 18 km/h = 5 m/s. Heading 90 deg true = east = 0 rad.
    # x = 5.144444 * 1 + (5.144444 + 5) / 2 * 1 = 10.216667 m.
    assert (state.x, state.y) == pytest.approx((10.216667, 0.0), abs=1e-6)
    assert state.heading == pytest.approx(0.0)


# --- the hull's sideslip (sway_preset) ---------------------------------------------------------------------

@pytest.mark.parametrize("preset, radius", [(None, 0.52 / 0.105),
                                            ("otter", math.hypot(0.52, 0.1524) / 0.105)])
def test_a_steady_turn_is_dead_reckoned_on_the_circle_the_sideslip_makes(preset, radius):
    # Log 0.52 m/s, heading turning at 0.105 rad/s: without the sway the track is a circle of u / r = 4.952 m;
    # the Otter skids at v = -0.1524 m/s there (tests/test_sway.py), so it runs on sqrt(u^2 + v^2) / r
    # = 5.161 m.
    odometry = DeadReckoning(OdometrySettings(sway_preset=preset))
    points = []
    for k in range(3001):
        state = odometry.update(0.1 * k, 0.52, math.remainder(0.105 * 0.1 * k, 2 * math.pi))
        if k > 3000 - 598:                      # the last 59.8 s: one turn (2 pi / 0.105 = 59.84 s)
            points.append((state.x, state.y))
    points = np.array(points)
    distances = np.hypot(*(points - points.mean(axis=0)).T)
    assert distances == pytest.approx(np.full(len(points), radius), abs=0.01)


def hull_circle_errors(preset):
    """The dead-reckoning error against the Otter hull's own track (calm water), over its second circle."""
    hulls = HullFleet(PRESETS["otter"], 1, 0.02, 1)
    odometry = DeadReckoning(OdometrySettings(sway_preset=preset))
    odometry.update(0.0, 0.0, 0.0)
    errors, t = [], 0.0
    for k in range(1200):
        hulls.advance(t, 0.1, np.array([0.52]), np.array([0.105]), t)
        t += 0.1
        state = odometry.update(t, float(hulls.state[3][0]), float(hulls.state[2][0]))
        if k >= 600:
            errors.append(math.hypot(state.x - hulls.state[0][0], state.y - hulls.state[1][0]))
    return np.array(errors)


def test_the_otters_sway_model_cuts_the_error_against_the_hulls_track_by_three_orders():
    # Fed the hull's own surge through the water and heading at 10 Hz: without the sway the track misses by
    # up to sin(b) 2 rho = 2.90 m (tests/test_sway.py); measured 2.83 m, and 5.4e-4 m with the Otter's model.
    plain, corrected = hull_circle_errors(None), hull_circle_errors("otter")
    assert 0.9 * 2.90 <= plain.max() <= 1.01 * 2.90
    assert corrected.max() <= 1e-3
    assert plain.max() / corrected.max() >= 1000


def test_with_the_sway_model_bad_samples_are_still_refused_and_change_nothing():
    good = [(0.1 * k, 0.52, 0.0105 * k) for k in range(50)]
    bad = [(math.nan, 0.5, 0.0), (9.0, math.nan, 0.0), (9.0, 0.5, math.inf), (9.0, 60.0, 0.0),
           (9.0, 0.5, 2e6), (0.05, 0.5, 0.0)]
    _, state = run(good, sway_preset="otter")
    odometry = DeadReckoning(OdometrySettings(sway_preset="otter"))
    for n, sample in enumerate(good):
        after = odometry.update(*sample)
        if n == 20:
            for refused in bad:
                assert odometry.update(*refused) is after
    assert odometry.state == state                                           # the same floats, every one
    assert odometry.rejected == {"non_finite": 3, "speed_out_of_range": 1, "yaw_out_of_range": 1,
                                 "out_of_order": 1}
    plain = run(good)[1]
    assert (state.x, state.y) != (plain.x, plain.y)                          # the sway did act


def test_an_unknown_sway_preset_is_refused_with_the_field_name():
    with pytest.raises(ValidationError, match="sway_preset"):
        OdometrySettings(sway_preset="titanic")
