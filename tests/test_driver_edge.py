"""The driver bridge's inputs bounded at the edge, in process: a sentence with a valid checksum that decodes
to values beyond the contract (a speed log saying 1e30 knots) is refused and counted, never raised, and no
sequence of valid-but-large samples walks the dead-reckoned position out of the contract's bounds."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from pydantic import ValidationError
from test_driver_odometry import xor_sentence

from agent.contract import MAX_POSITION, Odometry, decode
from driver_bridge.node import DriverBridge, DriverSettings, OdometryPort
from driver_bridge.odometry import DeadReckoning, OdometrySettings
from driver_bridge.thrusters import ThrusterAdapter, ThrusterSettings


class Publisher:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.payloads.append(payload)


HUGE = ["1e30", "-1e30", "1e308", "-1e308", "1.7976931348623157e308", "1" + "0" * 30 + ".0"]


def test_a_vhw_sentence_of_1e30_knots_with_a_valid_checksum_is_refused_and_counted_not_raised():
    bridge = DriverBridge("1", DriverSettings(odometry=OdometryPort(device="/dev/null")))
    odometry = Publisher()
    publishers = {"sensor/odom": odometry}
    started = time.time()
    bridge._on_odometry(xor_sentence("IIVHW,90.0,T,,M,2.0,N,,K"), publishers)
    for speed in HUGE:
        time.sleep(0.01)   # wall time goes on between sentences, as on a boat: the speed is integrated
        bridge._on_odometry(xor_sentence(f"IIVHW,90.0,T,,M,{speed},N,,K"), publishers)   # raised before
        bridge._on_odometry(xor_sentence(f"IIVHW,90.0,T,,M,,N,{speed},K"), publishers)   # km/h alike
    time.sleep(0.01)
    bridge._on_odometry(xor_sentence("IIVHW,90.0,T,,M,2.0,N,,K"), publishers)
    elapsed = time.time() - started
    messages = [decode(Odometry, payload)[0] for payload in odometry.payloads]
    assert len(messages) == 2 and None not in messages          # the two good ones, nothing else
    assert all(abs(c) <= MAX_POSITION for m in messages for c in m.position)
    assert 0 < messages[1].position[0] <= 2 * 1852 / 3600 * elapsed   # 2 kn all the way, not 1e30
    assert bridge.dead_reckoning.rejected == {"speed_out_of_range": 2 * len(HUGE)}
    assert bridge.refusals()["dead_reckoning_refused"] == {"speed_out_of_range": 2 * len(HUGE)}


def test_absurd_headings_and_numbers_in_a_valid_sentence_are_refused_by_reason():
    bridge = DriverBridge("1", DriverSettings(odometry=OdometryPort(device="/dev/null")))
    publishers = {"sensor/odom": Publisher()}
    for body in ("IIVHW,1e30,T,,M,2.0,N,,K", "IIVHW,-5,T,,M,2.0,N,,K", "IIVHW,nan,T,,M,2.0,N,,K",
                 "IIVHW,90,T,,M,inf,N,,K", "IIVHW,90,T,,M,1e400,N,,K", "IIVHW,90,T,,M,1_0,N,,K",
                 "IIVHW,90,T,,M,,N,,K", "IIHDG,90,T,,M,2.0,N,,K", "IIVHW,90,T,,M,2.0,N,,K,extra"):
        bridge._on_odometry(xor_sentence(body), publishers)
    assert bridge.refused == {"odometry_heading_out_of_range": 2, "odometry_bad_number": 4,
                              "odometry_no_speed": 1, "odometry_not_vhw": 2}
    assert publishers["sensor/odom"].payloads == []


def test_no_run_of_valid_but_large_samples_walks_the_position_out_of_the_contract():
    """Seeded random walks at 1 to 1e3 m/s (the contract's largest speed; beyond the speed bound too), with
    gaps of up to a day between samples: every state is a valid contract message, and the steps that
    would leave the contract's square are refused and counted (the walk does reach its edge)."""
    rng = np.random.default_rng(5)
    edge_reached = 0
    for walk in range(24):
        odometry = DeadReckoning(OdometrySettings(yaw_input=("yaw", "yaw_rate")[walk % 2]))
        stamp, heading = 1.7e9, float(rng.uniform(-math.pi, math.pi))
        for _ in range(200):
            stamp += float(10 ** rng.uniform(-3, 5))
            speed = float(rng.choice([-1, 1]) * 10 ** rng.uniform(0, 3))      # 1 to 1000 m/s either way
            yaw = heading + float(rng.normal(0, 0.01)) if walk % 2 == 0 else float(rng.normal(0, 0.001))
            state = odometry.update(stamp, speed, yaw)
            if state is not None:
                message = state.message(seq=0, sender="1")    # raised for a position beyond 1e5 m before
                assert decode(Odometry, message.model_dump_json().encode())[0] is not None
                assert abs(state.x) <= MAX_POSITION and abs(state.y) <= MAX_POSITION
        assert odometry.rejected["speed_out_of_range"] > 0
        edge_reached += odometry.rejected["position_out_of_bounds"] > 0
    print(f"{edge_reached} of 24 walks reached the edge")
    assert edge_reached >= 12, edge_reached


def test_at_the_frames_edge_steps_out_are_refused_and_the_odometry_resumes_when_the_vessel_heads_back():
    odometry = DeadReckoning(OdometrySettings())        # yaw: heading counter-clockwise from x
    stamp, states = 0.0, []
    for _ in range(40):                                 # 40 m/s east, 100 s apart: 4 km a step, 160 km in all
        states.append(odometry.update(stamp, 40.0, 0.0))
        stamp += 100.0
    edge = odometry.state
    assert MAX_POSITION - 4000 < edge.x <= MAX_POSITION and states[-1] is edge
    assert odometry.rejected == {"position_out_of_bounds": 40 - 26}   # 25 steps of 4 km fit within 1e5 m
    stamp -= 100.0                                      # the last sample's
    back = [odometry.update(stamp + k, 40.0, math.pi) for k in range(1, 11)]   # turned round: heading west
    assert all(state is not edge for state in back)     # each one published again
    # 1 s from the last (refused) sample, not from the last published one: a turn of 40 m, then 9 s westwards
    assert edge.x - 400 < back[-1].x < edge.x - 300 and abs(back[-1].y) < 30


def test_the_thrust_mix_is_within_full_thrust_and_turns_the_way_asked_for_any_hull_and_command():
    """Seeded hulls across the whole range the settings allow (1e-300 to 1e6) and commands from 0 to 1e308
    either way: the output is a number within [-1, 1] and turns the way the yaw rate asks. A hull beyond the
    settings' bounds, whose mix overflowed to NaN (a starboard turn came out as full to port), is refused."""
    with pytest.raises(ValidationError, match="max_thrust"):
        ThrusterSettings(max_thrust=1e308, half_beam=1e-300, surge_drag=1e308, yaw_drag=1e308)
    rng = np.random.default_rng(9)
    for _ in range(3000):
        hull = ThrusterSettings(**{name: float(10 ** rng.uniform(-300, 6))
                                   for name in ("max_thrust", "half_beam", "surge_drag", "yaw_drag")})
        surge, yaw_rate = (float(rng.choice([-1, 1]) * 10 ** rng.uniform(-5, 308)) for _ in range(2))
        mixed = ThrusterAdapter(hull).mix(surge, yaw_rate)
        assert abs(mixed.left) <= 1.0 and abs(mixed.right) <= 1.0, (hull, surge, yaw_rate, mixed)
        assert (mixed.right - mixed.left) * yaw_rate >= 0, (hull, surge, yaw_rate, mixed)
