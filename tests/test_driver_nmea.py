"""NMEA 0183 on pynmeagps at the driver's edge: what the library is given, and what it would do unguarded.

pynmeagps checks the checksums and names a standard sentence's fields; the framing (lines, their length,
noise before `$`) and the strict number rule stay the driver's. Each case is counted as the driver counted
it before the library, except where a test below says the rule changed, and why."""

from __future__ import annotations

import math

import pytest
from test_driver_odometry import xor_sentence

from driver_bridge.node import DriverBridge, DriverSettings, OdometryPort
from driver_bridge.odometry import KNOT, read_vhw
from driver_bridge.serial_port import LineReader, nmea_checksum, nmea_sentence, read_sentence


class Publisher:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.payloads.append(payload)


def bridge_fed(*lines: bytes) -> tuple[DriverBridge, Publisher]:
    bridge = DriverBridge("1", DriverSettings(odometry=OdometryPort(device="/dev/null")))
    odometry = Publisher()
    for line in lines:
        bridge._on_odometry(line, {"sensor/odom": odometry})
    return bridge, odometry


def test_checksums_are_the_xor_of_the_bytes_worked_by_hand():
    # "DET,," = 0x44 ^ 0x45 ^ 0x54 ^ 0x2C ^ 0x2C = 0x55 (the two commas cancel).
    assert nmea_checksum(b"DET,,") == 0x55 and nmea_sentence("DET,,") == b"$DET,,*55\r\n"
    # A byte above 0x7F counts as itself (one character a byte), not as its UTF-8 encoding.
    assert nmea_checksum(b"\xe9") == 0xE9 and nmea_checksum(b"A\xe9") == 0x41 ^ 0xE9


def test_the_framing_counts_each_bad_line_by_reason():
    good = xor_sentence("IIVHW,90.0,T,,M,2.0,N,,K")
    reader = LineReader(max_line=64)
    bodies = reader.feed(
        good.replace(good[-4:-2], good[-4:-2].lower())      # lower-case hex digits: still right
        + b"\x00\xff$" + good[1:]                          # noise before the `$`: skipped
        + good[:-5] + b"\r\n"                              # cut before its checksum
        + good[:-4] + b"00\r\n"                            # a wrong checksum
        + good[:-4] + b"Z1\r\n"                            # not hex
        + b"$" + b"9" * 70 + b"*00\r\n")                   # longer than max_line
    assert bodies == [b"IIVHW,90.0,T,,M,2.0,N,,K"] * 2
    assert reader.rejected == {"malformed": 1, "bad_checksum": 2, "too_long": 1}


def test_non_ascii_bytes_with_a_right_checksum_pass_the_framing_and_are_refused_by_the_sentence():
    # As before the library: the checksum is the bytes' XOR; the field is then no number.
    body = b"IIVHW,9\xe9,T,,M,2.0,N,,K"
    line = b"$" + body + b"*" + f"{nmea_checksum(body):02X}".encode() + b"\r\n"
    bridge, odometry = bridge_fed(line, b"$IIVHW\xff\xfe,1*00\r\n")
    assert bridge.refused == {"odometry_bad_number": 1}
    assert bridge.refusals()["odometry_lines_refused"] == {"bad_checksum": 1}
    assert odometry.payloads == []


def test_an_unknown_talker_is_read_as_before_and_a_sentence_pynmeagps_cannot_build_is_counted():
    # "ZZ" is no talker of NMEA 0183's list; the driver does not ask for one (validate=VALNONE).
    bridge, odometry = bridge_fed(xor_sentence("ZZVHW,90.0,T,,M,2.0,N,,K"))
    assert len(odometry.payloads) == 1 and not bridge.refusals()
    # pynmeagps 1.1.8 raises IndexError building a PASHR without fields; the driver never builds one it
    # did not ask for, so it is another sentence (not_vhw), not a failure of the last-resort guard.
    bridge, odometry = bridge_fed(xor_sentence("PASHR"), xor_sentence("GPGGA,1,2,3"),
                                  xor_sentence("IIHDT,90.0,T"))
    assert bridge.refused == {"odometry_not_vhw": 3} and odometry.payloads == []


def test_vhw_fields_come_by_name_from_pynmeagps():
    message, why = read_sentence(b"GPVHW,100.5,T,105.5,M,10.5,N,19.4,K", "VHW", 8)
    assert why == "" and message.talker == "GP" and message.msgID == "VHW"
    assert (message.hdgT, message.hdgM, message.spdN, message.spdK) == (100.5, 105.5, 10.5, 19.4)
    speed, heading = read_vhw(b"GPVHW,100.5,T,105.5,M,10.5,N,19.4,K")[0]
    assert speed == pytest.approx(10.5 * KNOT) and heading == pytest.approx(math.radians(100.5))
    # km/h when the knots are empty: 18 km/h = 5 m/s.
    assert read_vhw(b"VWVHW,,T,,M,,N,18.0,K") == (None, "bad_number")          # no heading
    assert read_vhw(b"VWVHW,0.0,T,,M,,N,18.0,K")[0] == pytest.approx((5.0, 0.0))


@pytest.mark.parametrize("body", ["IIVHW,90.0,T,nan,M,2.0,N,,K", "IIVHW,90.0,T,abc,M,2.0,N,,K",
                                  "IIVHW,90.0,T,,M,2.0,N,1_0,K"])
def test_a_garbled_number_in_a_field_the_odometry_does_not_use_now_refuses_the_sentence(body):
    """Changed with the library: pynmeagps types every field of the sentence, so a magnetic heading (or an
    unused km/h) that is no finite decimal refuses it as bad_number; before, only the fields used were
    read."""
    bridge, odometry = bridge_fed(xor_sentence(body))
    assert bridge.refused == {"odometry_bad_number": 1} and odometry.payloads == []


def test_a_vhw_without_a_talker_is_another_sentence():
    """Changed with the library: NMEA 0183's address is a two-letter talker and the sentence's id, so a bare
    `$VHW` is talker "VH", sentence "W" (pynmeagps's split); before, any address ending in VHW was read."""
    bridge, odometry = bridge_fed(xor_sentence("VHW,90.0,T,,M,2.0,N,,K"))
    assert bridge.refused == {"odometry_not_vhw": 1} and odometry.payloads == []
