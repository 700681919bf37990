"""GNSS truth from the driver: NMEA GGA (by pynmeagps) -> GnssFix on `usv/<id>/truth/gnss`, values worked by
hand, bad sentences refused by reason; the process end to end over a pseudo-terminal and Zenoh."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
import yaml
import zenoh
from conftest import wait_until
from test_driver_odometry import xor_sentence

from agent.contract import GnssFix, decode
from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from driver_bridge.gnss import read_gga
from driver_bridge.node import DriverBridge, DriverSettings, GnssPort
from sim_bridge.fleet import free_port

# u-blox's example GGA (NMEA 0183 as its receivers write it): 47 deg 17.11399' N, 8 deg 33.91590' E.
GGA = "GPGGA,092725.00,4717.11399,N,00833.91590,E,1,08,1.01,499.6,M,48.0,M,,"
NOW_NS = 1_700_000_000 * 10**9


class Publisher:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.payloads.append(payload)


def fed(*bodies: str, antenna=(0.0, 0.0)) -> tuple[DriverBridge, list[GnssFix]]:
    settings = DriverSettings(gnss=GnssPort(device="/dev/null", receiver={"antenna": antenna}))
    bridge = DriverBridge("1", settings, clock_ns=lambda: NOW_NS)
    truth = Publisher()
    for body in bodies:
        bridge._on_gnss(xor_sentence(body), {"truth/gnss": truth})
    fixes = [decode(GnssFix, payload) for payload in truth.payloads]
    assert all(reason == "" for _, reason in fixes), fixes
    return bridge, [fix for fix, _ in fixes]


def test_a_gga_fix_in_degrees_worked_by_hand():
    (fix,) = fed(GGA, antenna=(0.4, -0.1))[1]
    # ddmm.mmmmm: 47 + 17.11399 / 60 = 47.285233167 deg; 8 + 33.91590 / 60 = 8.565265 deg.
    assert fix.latitude == pytest.approx(47.285233167, abs=1e-9)
    assert fix.longitude == pytest.approx(8.565265, abs=1e-9)
    # 09:27:25 UTC = 9 * 3600 + 27 * 60 + 25 = 34045 s of the day; stamped when the driver read it.
    assert (fix.utc_time, fix.stamp_ns, fix.seq, fix.sender) == (34045.0, NOW_NS, 0, "1")
    assert (fix.quality, fix.satellites, fix.hdop, fix.altitude) == (1, 8, 1.01, 499.6)
    assert fix.antenna == (0.4, -0.1)


def test_southern_and_western_fixes_are_negative_and_rtk_is_told_by_its_quality():
    body = "GNGGA,235959.5,3352.1280,S,15112.6380,W,4,14,0.6,12.0,M,22.1,M,1.0,0001"
    (fix,) = fed(body)[1]
    # 33 + 52.128 / 60 = 33.8688; 151 + 12.638 / 60 = 151.210633...
    assert fix.latitude == pytest.approx(-33.8688, abs=1e-9)
    assert fix.longitude == pytest.approx(-(151 + 12.638 / 60), abs=1e-9)
    assert fix.quality == 4 and fix.utc_time == pytest.approx(86399.5)


def test_bad_fixes_are_refused_by_reason_and_other_sentences_passed_over():
    bad = {
        "GPGGA,092725.00,,,,,0,00,99.99,,,,,,": "no_fix",                                      # no fix yet
        "GPGGA,092725.00,4717.11399,N,00833.91590,E,0,08,1.01,499.6,M,48.0,M,,": "no_fix",     # quality 0
        "GPGGA,092725.00,4717.11399,X,00833.91590,E,1,08,1.01,499.6,M,48.0,M,,": "bad_hemisphere",
        "GPGGA,092725.00,4767.11399,N,00833.91590,E,1,08,1.01,499.6,M,48.0,M,,": "bad_number",  # 67 minutes
        "GPGGA,252725.00,4717.11399,N,00833.91590,E,1,08,1.01,499.6,M,48.0,M,,": "bad_number",  # hour 25
        "GPGGA,092725.00,4717.11399,N,00833.91590,E,1,1_0,1.01,499.6,M,48.0,M,,": "bad_number",
        "GPGGA,092725.00,4717.11399,N,00833.91590,E,1,08,nan,499.6,M,48.0,M,,": "bad_number",
        "GPGGA,092725.00,9100.00000,N,00833.91590,E,1,08,1.01,499.6,M,48.0,M,,": "out_of_range",  # 91 deg
        "GPGGA,092725.00,4717.11399,N,00833.91590,E,1,08,1.01,1e30,M,48.0,M,,": "out_of_range",   # altitude
        "GPGGA,092725.00,4717.11399,N,00833.91590,E,12,08,1.01,499.6,M,48.0,M,,": "out_of_range",  # quality
    }
    for body, reason in bad.items():
        alone, fixes = fed(body)
        assert alone.refusals() == {"gnss_refused": {reason: 1}} and fixes == [], body
    assert read_gga(GGA.encode())[1] == "" and read_gga(b"GPGSV,1,1,01,01,40,083,46") == (None, "not_gga")
    others = ["GPGSV,1,1,01,01,40,083,46",
              "GPRMC,092725.00,A,4717.11399,N,00833.91590,E,0.004,77.52,091202,,,A",
              "GPGGA,092725.00,4717.11399,N,00833.91590,E,1,08,1.01,499.6,M,48.0,M,"]   # a field short
    bridge, fixes = fed(*bad, *others, GGA)
    assert len(fixes) == 1 and fixes[0].seq == 0      # the good one, first of its key's sequence
    assert bridge.refusals() == {"gnss_refused": {"no_fix": 2, "bad_hemisphere": 1, "bad_number": 4,
                                                  "out_of_range": 3}}
    assert bridge.gnss.passed_over == 3


def test_the_fixes_published_are_written_to_the_gnss_log_that_usv_log_reads(tmp_path):
    """gnss.log: every fix published goes to the driver's own MCAP log on the truth key, with its antenna;
    refused sentences do not; usv-log reads the file as vessel 1's GNSS track."""
    from mission_log.reader import load_run

    path = tmp_path / "gnss-1.mcap"
    settings = DriverSettings(gnss=GnssPort(device="/dev/null", receiver={"antenna": [0.4, -0.1]},
                                            log=str(path)))
    clock = iter(range(NOW_NS, NOW_NS + 10**10, 200_000_000))
    bridge = DriverBridge("1", settings, clock_ns=lambda: next(clock))
    bridge.open_gnss_log()
    truth = Publisher()
    for body in (GGA, "GPGGA,092725.00,,,,,0,00,99.99,,,,,,", GGA.replace("092725.00", "092725.20")):
        bridge._on_gnss(xor_sentence(body), {"truth/gnss": truth})
    bridge.gnss_log.close()
    run = load_run(tmp_path)
    assert list(run.gnss) == ["1"] and not run.vessels and run.sim is None
    logged = run.gnss["1"].messages("usv/1/truth/gnss")
    published = [decode(GnssFix, payload)[0] for payload in truth.payloads]
    assert [(t, GnssFix.model_validate(m)) for t, m in logged] == [(f.stamp_ns, f) for f in published]
    assert [m["utc_time"] for _, m in logged] == [34045.0, pytest.approx(34045.2)]
    assert logged[0][1]["antenna"] == [0.4, -0.1] and run.gnss["1"].metadata == {"gnss_of": "1"}


def test_a_gnss_log_that_cannot_be_written_is_one_line_naming_it(tmp_path):
    (tmp_path / "file").write_text("")
    settings = DriverSettings(gnss=GnssPort(device="/dev/null", log=str(tmp_path / "file" / "gnss.mcap")))
    with pytest.raises(OSError, match=r"cannot write the GNSS log \(gnss.log .*file/gnss.mcap\): "):
        DriverBridge("1", settings).open_gnss_log()


@pytest.mark.slow
def test_the_driver_publishes_gnss_fixes_as_truth_over_zenoh_and_no_sensor_key_carries_them(tmp_path):
    master, slave = os.openpty()
    port = free_port()
    config = tmp_path / "driver.yaml"
    config.write_text(yaml.safe_dump({"zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
                                      "gnss": {"device": os.ttyname(slave), "baud": 38400,
                                               "receiver": {"antenna": [0.5, 0.0]},
                                               "log": str(tmp_path / "gnss-1.mcap")}}))
    command = [sys.executable, "-m", "driver_bridge", "--vessel", "1", "--config", str(config)]
    driver = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    truth, sensors = [], []
    try:
        with zenoh.open(zenoh_config(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))) as session:
            session.declare_subscriber("usv/1/truth/gnss", lambda s: truth.append(s.payload.to_bytes()))
            session.declare_subscriber("usv/1/sensor/**", lambda s: sensors.append(s.payload.to_bytes()))
            assert wait_until(lambda: list(session.info.peers_zid()), 15), "the driver bridge's session"

            def sent() -> bool:
                os.write(master, xor_sentence("GPGSV,1,1,01,01,40,083,46") + xor_sentence(GGA))
                return wait_until(lambda: truth, 0.3)

            assert wait_until(sent, 15), "no GnssFix on usv/1/truth/gnss"
            time.sleep(0.3)
        driver.send_signal(signal.SIGTERM)
        output, _ = driver.communicate(timeout=15)
    finally:
        if driver.poll() is None:
            driver.kill()
        os.close(master)
        os.close(slave)
    assert driver.returncode == 0, output
    fix, reason = decode(GnssFix, truth[0])
    assert reason == "" and fix.sender == "1" and fix.antenna == (0.5, 0.0)
    assert fix.latitude == pytest.approx(47.285233167, abs=1e-9) and abs(fix.stamp_ns - time.time_ns()) < 60e9
    assert sensors == []
    from mission_log.reader import load_run
    run = load_run(tmp_path / "gnss-1.mcap")
    assert not run.unfinished                                       # closed on SIGTERM
    logged = run.gnss["1"].messages("usv/1/truth/gnss")
    assert [GnssFix.model_validate(m) for _, m in logged] == [decode(GnssFix, p)[0] for p in truth]
    assert "'truth/gnss':" in output and "'gnss_other_sentences':" in output, output
