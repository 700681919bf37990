"""The MAVLink side of the fuzz campaign (lab/benchmarks/mavlink_fuzz.py): hostile datagrams over the loopback
into the driver's own autopilot link (pymavlink's parser) and MavlinkVehicle. What must hold: nothing raises,
each kind of bad input is refused under its own reason, odometry and set points stay within the contract,
and after the storm the good autopilot is heard and commanded again."""

from __future__ import annotations

import numpy as np
import pytest

from lab.benchmarks.mavlink_fuzz import (
    AFTER_STORM,
    CLASSES,
    GUIDED,
    HOLD,
    SETTLE_STEPS,
    _Campaign,
    run_mavlink_campaign,
    sound,
)

DATAGRAMS = 1500
SEED = 7


def test_a_mavlink_storm_raises_nothing_refuses_each_kind_by_reason_and_the_link_recovers():
    r = run_mavlink_campaign(DATAGRAMS, SEED)
    assert sum(r.datagrams.values()) >= DATAGRAMS and set(r.datagrams) == set(CLASSES), r.datagrams
    assert not r.escaped and r.failed == 0, (r.escaped, r.refused)
    assert r.out_of_contract == [], r.out_of_contract[:5]
    assert r.after_storm == AFTER_STORM and r.commanding
    assert sound(r)
    reasons = r.reasons()
    expected = ("bad_data", "wrong_system", "wrong_component", "heartbeat_flood", "mode_refused",
                "arm_refused", "stream_refused", "out_of_order", "stamp_ahead", "timesync_unmatched",
                "attitude_out_of_range", "command_out_of_range")
    assert all(reasons[reason] > 0 for reason in expected), reasons
    assert r.events["autopilot_rebooted"] > 0, r.events
    # Every frame the parser dropped reached the adapter as BAD_DATA and was counted there, once.
    assert reasons["bad_data"] == sum(r.parser_dropped.values()) == r.messages["BAD_DATA"]
    assert r.parser_dropped["bad_crc"] > 0 and r.parser_dropped["bad_prefix"] > 0, r.parser_dropped
    # The flood's heartbeats were parsed (not lost in the stream) and all but a few refused.
    assert reasons["heartbeat_flood"] >= r.frames["heartbeat_flood"] - r.datagrams["heartbeat_flood"]


def test_the_campaign_repeats_with_its_seed():
    def counts(seed: int) -> tuple:
        r = run_mavlink_campaign(300, seed)
        return r.reasons(), r.parser_dropped, r.datagrams, r.published, r.setpoints

    assert counts(3) == counts(3) != counts(4)


@pytest.fixture
def campaign():
    made = _Campaign(np.random.default_rng(1))
    yield made
    made.close()


def test_each_hostile_input_is_counted_once_under_its_reason_and_good_frames_go_on(campaign):
    """One input of each kind, by hand, after a second of good traffic (a heartbeat, a clock offset)."""
    c, ap, vehicle = campaign, campaign.autopilot, campaign.bridge.vehicle
    for _ in range(SETTLE_STEPS):
        c.step(good=True)
    assert vehicle.linked and (vehicle.mode, vehicle.armed) == (GUIDED, True) and c.results.published > 0

    def refused() -> dict:
        return dict(vehicle.rejected)

    def delta(before: dict) -> dict:
        return {k: v - before.get(k, 0) for k, v in vehicle.rejected.items() if v != before.get(k, 0)}

    before = refused()
    frame = bytearray(ap.pack(ap.state(c.boot_ms)[1:]))
    frame[-1] ^= 0x5A                                              # the CRC's high byte
    c.send(bytes(frame))
    assert delta(before) == {"bad_data": 1} and c.results.parser_dropped == {"bad_crc": 1}

    before = refused()
    stranger = c.mavlink.MAVLink(None, srcSystem=42, srcComponent=1)
    c.send(ap.pack([stranger.heartbeat_encode(11, 3, 1, HOLD, 4)], stranger))
    assert delta(before) == {"wrong_system": 1} and vehicle.mode == GUIDED

    before = refused()
    c.send(ap.pack([ap.heartbeat(HOLD, False) for _ in range(50)]))   # at the instant of the last one taken
    assert delta(before) == {"heartbeat_flood": 50} and (vehicle.mode, vehicle.armed) == (GUIDED, True)

    before = refused()
    c.send(ap.pack([ap.mav.command_ack_encode(176, 2)]))            # DO_SET_MODE: DENIED
    assert delta(before) == {"mode_refused": 1}
    assert sum("refused mode (command 176): DENIED" in line for line in c.reported) == 1

    before, published = refused(), c.results.published
    ap.state(c.boot_ms)
    c.send(ap.pack([ap.mav.local_position_ned_encode(c.boot_ms - 500, ap.north, ap.east, 0, 0, 0, 0)]))
    assert delta(before) == {"out_of_order": 1} and c.results.published == published

    c.step(good=False)                                             # a good position in MAVLink 1 framing
    before, published = refused(), c.results.published
    c.send(ap.pack(ap.state(c.boot_ms), v1=True))
    assert delta(before) == {} and c.results.published == published + 1

    published = c.results.published
    for _ in range(20):
        c.step(good=True)
    assert c.results.published == published + 20 and not c.results.escaped and not c.results.out_of_contract
