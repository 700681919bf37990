"""The simulator's GNSS receiver (sim_bridge/simulated_gnss.py) and the local frame
(mission_log/local_frame.py): GGA sentences and metres <-> degrees against values worked by hand, through the
driver's own GGA reader."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from driver_bridge.gnss import read_gga
from mission_log.local_frame import LocalFrame
from sim_bridge.simulated_gnss import SimulatedReceiver, checksum, gga_sentence, plain, rtk, simulated_gga

# WGS 84: a = 6378137 m, f = 1 / 298.257223563, e^2 = f (2 - f) = 0.00669437999014.
A, E2 = 6378137.0, (1 / 298.257223563) * (2 - 1 / 298.257223563)


def fix_of(sentence: bytes) -> dict:
    assert sentence.startswith(b"$") and sentence.endswith(b"\r\n")
    body, _, sent = sentence[1:-2].partition(b"*")
    assert sent.decode() == checksum(body.decode())
    fields, why = read_gga(body)
    assert why == "", why
    return fields


def test_the_checksum_of_the_textbook_gga():
    # NMEA 0183's textbook example (gpsd's "NMEA revealed"), checksum 47 as printed there.
    assert checksum("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") == "47"


def test_degrees_are_written_as_degrees_and_minutes_worked_by_hand():
    # 48.1173 deg = 48 deg + 0.1173 * 60 = 7.038 min; 11.516666... deg = 11 deg 31 min; south and west signed.
    sentence = gga_sentence(48.1173, 11 + 31 / 60, 12 * 3600 + 35 * 60 + 19, quality=4)
    assert sentence.startswith(b"$GNGGA,123519.00,4807.0380000,N,01131.0000000,E,4,12,0.8,0.0,M,0.0,M,,*")
    sentence = gga_sentence(-33.8688, -151.2106, 0.0)
    # 0.8688 * 60 = 52.128 min; 0.2106 * 60 = 12.636 min
    assert b",3352.1280000,S,15112.6360000,W," in sentence
    # 59.99999999999 min rounds to the next degree, not to "60.0000000" minutes
    assert b",4900.0000000,N," in gga_sentence(48 + 59.999999999999 / 60, 0.0, 0.0)
    fields = fix_of(sentence)
    assert (fields["latitude"], fields["longitude"]) == (pytest.approx(-33.8688, abs=1e-12),
                                                         pytest.approx(-151.2106, abs=1e-12))
    assert fields["utc_time"] == 0.0 and fields["quality"] == 1


def test_a_thousandth_of_a_degree_in_metres_worked_by_hand():
    # North at the equator: the meridian's radius M = a (1 - e^2) = 6335439.327 m, so 0.001 deg is
    # M * pi / 180 * 0.001 = 110.574 m. East at 60 N: N = a / sqrt(1 - e^2 sin^2 60) = 6394209.17 m on a
    # parallel of radius N cos 60, so 0.001 deg is N cos 60 sin(0.001 deg) = 55.800 m east, and the
    # parallel curves away from the tangent plane by N cos 60 (1 - cos 0.001 deg) sin 60 = 0.42 mm north.
    meridian = A * (1 - E2)
    assert LocalFrame(0.0, 0.0).to_local(0.001, 0.0) == pytest.approx([0.0, meridian * math.radians(0.001)],
                                                                      abs=1e-6)
    assert meridian * math.radians(0.001) == pytest.approx(110.574276, abs=1e-6)
    prime = A / math.sqrt(1 - E2 * 0.75)
    parallel = prime * 0.5
    east = parallel * math.sin(math.radians(0.001))
    north = parallel * (1 - math.cos(math.radians(0.001))) * math.sin(math.radians(60))
    assert LocalFrame(60.0, 10.0).to_local(60.0, 10.001) == pytest.approx([east, north], abs=1e-6)
    assert (east, north) == (pytest.approx(55.800002, abs=1e-6), pytest.approx(0.000422, abs=1e-6))
    # and back: the same metres give the same degrees
    lat, lon = LocalFrame(60.0, 10.0).to_geodetic(east, north)
    assert (float(lat), float(lon)) == (pytest.approx(60.0, abs=1e-12), pytest.approx(10.001, abs=1e-12))


def test_a_noiseless_fix_read_by_the_driver_comes_back_to_the_antenna_in_metres():
    # Heading north (pi / 2): the antenna 1 m ahead and 0.5 m left is 1 m north and 0.5 m west of the
    # reference point (-0.5, 1) m away.
    origin = (59.9, 10.7)
    receiver = SimulatedReceiver(origin=origin, sigma=0.0, quality=4, antenna=(1.0, 0.5))
    rng = np.random.default_rng(0)
    for position in ([0.0, 0.0], [12.5, -40.25], [-850.0, 1200.0]):
        fields = fix_of(simulated_gga(position, math.pi / 2, 45296.25, receiver, rng))
        local = LocalFrame(*origin).to_local(fields["latitude"], fields["longitude"])
        # 7 decimals of a minute: 1.85e-4 m of latitude, less of longitude
        assert local == pytest.approx(np.add(position, [-0.5, 1.0]), abs=2e-4)
        assert fields["quality"] == 4 and fields["utc_time"] == pytest.approx(45296.25)


@pytest.mark.parametrize("make, seed", [(plain, 11), (rtk, 12)])
def test_the_noise_has_the_stated_sigma_east_and_north_independently(make, seed):
    origin = (43.3, 5.4)
    receiver = make(origin)
    rng = np.random.default_rng(seed)
    count = 4000
    points = np.array([LocalFrame(*origin).to_local(**fix_fields(simulated_gga([3.0, -4.0], 0.3, k * 0.2,
                                                                                  receiver, rng)))
                       for k in range(count)]) - [3.0, -4.0]
    # Sample standard deviation of N draws: sigma within 4 sigma / sqrt(2 N) (its own spread), i.e. 4.5 %.
    assert points.std(axis=0) == pytest.approx([receiver.sigma] * 2, rel=4 / math.sqrt(2 * count))
    assert np.all(np.abs(points.mean(axis=0)) < 4 * receiver.sigma / math.sqrt(count))
    assert abs(np.corrcoef(points.T)[0, 1]) < 4 / math.sqrt(count)


def fix_fields(sentence: bytes) -> dict:
    fields = fix_of(sentence)
    return {"latitude": fields["latitude"], "longitude": fields["longitude"]}


def test_the_same_seed_gives_the_same_sentences_and_another_seed_others():
    receiver = plain((0.0, 0.0))
    first = [simulated_gga([1.0, 2.0], 0.0, k, receiver, np.random.default_rng(3)) for k in range(3)]
    again = [simulated_gga([1.0, 2.0], 0.0, k, receiver, np.random.default_rng(3)) for k in range(3)]
    other = [simulated_gga([1.0, 2.0], 0.0, k, receiver, np.random.default_rng(4)) for k in range(3)]
    assert first == again and first != other


# ----- the sim bridge's receivers for a live field trial: ptys a driver opens (sim_bridge/gnss_ptys.py) -----

ORIGIN = (59.9, 10.7)
TRUTH = {"vessels": {"1": {"position": [3.0, -4.0], "heading": math.pi / 2}}, "target": [1.0, 1.0]}


def read_sentences(link: str) -> list[bytes]:
    """What the pty behind `link` holds now, as the driver's serial port reads it, split in sentences."""
    import os

    fd = os.open(link, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    try:
        data = os.read(fd, 65536)
    except BlockingIOError:   # nothing written to it
        data = b""
    finally:
        os.close(fd)
    return [line + b"\n" for line in data.split(b"\n") if line]


def test_each_ids_gga_goes_into_its_own_pty_at_its_antenna_and_time(tmp_path):
    from sim_bridge.gnss_ptys import GnssPtys, SimulatedGnss

    links = {"1": str(tmp_path / "gnss-1.tty"), "2": str(tmp_path / "gnss-2.tty"), "target": str(tmp_path / "t.tty")}
    receiver = SimulatedReceiver(origin=ORIGIN, sigma=0.0, quality=4)
    ptys = GnssPtys(SimulatedGnss(receiver=receiver, links=links, antennas={"1": (0.6, -0.2)}), seed=1)
    try:
        wall_ns = 1_764_000_037_123_450_000   # a wall time (ns since 1970): its time of day is the GGA's UTC
        ptys.emit(TRUTH, wall_ns)
        (one,), (tag,) = read_sentences(links["1"]), read_sentences(links["target"])
        assert read_sentences(links["2"]) == []   # vessel 2 is not in the world: its receiver is silent
        assert ptys.written == {"1": 1, "target": 1} and not ptys.dropped
        frame = LocalFrame(*ORIGIN)
        fix = fix_of(one)
        # heading north: 0.6 m ahead is north, 0.2 m right is east
        assert np.array(frame.to_local(fix["latitude"], fix["longitude"])) == pytest.approx([3.2, -3.4], abs=1e-3)
        assert fix["quality"] == 4
        assert fix["utc_time"] == pytest.approx((wall_ns % 86_400_000_000_000) * 1e-9, abs=0.006)
        target = fix_of(tag)
        assert np.array(frame.to_local(target["latitude"], target["longitude"])) == pytest.approx([1.0, 1.0], abs=1e-3)
    finally:
        ptys.close()
    assert not any((tmp_path / name).exists() for name in ("gnss-1.tty", "gnss-2.tty", "t.tty"))


def test_a_pty_nobody_reads_drops_and_counts_its_sentences_and_the_world_goes_on(tmp_path):
    from sim_bridge.gnss_ptys import GnssPtys, SimulatedGnss

    ptys = GnssPtys(SimulatedGnss(receiver=rtk(ORIGIN), links={"1": str(tmp_path / "g.tty")}), seed=2)
    try:
        for k in range(5000):   # ~80 bytes each: far beyond a pty's buffer
            ptys.emit(TRUTH, k * 100_000_000)
        assert ptys.written["1"] + ptys.dropped["1"] == 5000
        assert ptys.dropped["1"] > 0 and ptys.written["1"] > 0
    finally:
        ptys.close()


def test_receivers_outside_the_sea_mode_are_refused_in_one_line(tmp_path, capsys):
    from agent.config import ConfigError
    from sim_bridge.bridge import BridgeSettings, SimBridge
    from sim_bridge.fleet import main as fleet
    from sim_bridge.gnss_ptys import SimulatedGnss
    from sim_bridge.scenario import select_scenario

    _, scenario = select_scenario("tests/data/short_scenario.yaml")
    settings = BridgeSettings(gnss=SimulatedGnss(receiver=plain(ORIGIN), links={"1": str(tmp_path / "g.tty")}))
    with pytest.raises(ConfigError, match="need the sea mode"):
        SimBridge(scenario, settings)
    assert not (tmp_path / "g.tty").exists()
    assert fleet(["run", "tests/data/short_scenario.yaml", "--gnss", "rtk", "--out", str(tmp_path / "runs")]) == 2
    assert "usv-fleet: --gnss: scenario 'short' is not in the sea mode" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()
