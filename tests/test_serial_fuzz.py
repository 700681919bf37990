"""The serial side's fuzz campaign in CI: 2,000 bad lines or frames through each of the driver bridge's
parsers (lab/benchmarks/serial_fuzz.py describes the classes). What must hold: no exception escapes a handler, the
last-resort guard catches nothing (every refusal has its own reason), nothing that reaches the contract lies
beyond it, good lines are published again after the storm and the thruster watchdog still stops the
thrusters."""

from __future__ import annotations

import numpy as np
import pytest

from agent.contract import MAX_POSITION
from driver_bridge.serial_port import LineReader
from lab.benchmarks.serial_fuzz import (
    AFTER_STORM,
    PARSERS,
    SerialLines,
    classes_for,
    run_serial_campaign,
    sound,
)

PER_PARSER = 2000
SEED = 11


@pytest.mark.slow
def test_a_serial_fuzz_storm_raises_nothing_and_nothing_beyond_the_contract_gets_out():
    results = run_serial_campaign(PER_PARSER, SEED)
    assert set(results) == set(PARSERS)
    for parser, r in results.items():
        assert r.total >= PER_PARSER and set(r.lines) == set(classes_for(parser)), (parser, r.lines)
        assert not r.escaped, (parser, r.escaped)                    # the 1e30 VHW line raised here before
        assert r.failed == 0, (parser, r.refused)
        assert r.out_of_contract == [], (parser, r.out_of_contract[:5])
        assert r.after_storm == AFTER_STORM, (parser, r.after_storm)
    assert results["cmd"].watchdog_stopped is True
    assert sound(results)
    # The storm met the bounds, not only the framing: speeds and headings beyond them, the walk to the edge.
    vhw = results["vhw"].reasons()
    assert vhw["dead_reckoning:speed_out_of_range"] > 0 and vhw["odometry_heading_out_of_range"] > 0, vhw
    assert vhw["dead_reckoning:position_out_of_bounds"] > 0, vhw
    assert 0.5 * MAX_POSITION < results["vhw"].largest_position <= MAX_POSITION
    nlink = results["nlink"].reasons()
    reasons = ("range_too_long", "negative_range", "bad_checksum", "bad_length", "unknown_frame",
               "unknown_node")
    assert all(nlink[f"uwb:{reason}"] > 0 for reason in reasons), nlink
    det = results["det"].reasons()
    assert det["camera:outside_image"] > 0 and det["camera_bad_number"] > 0, det
    cmd = results["cmd"].reasons()
    assert cmd["command_malformed"] > 0 and cmd["command_other_vessel"] > 0, cmd
    gga = results["gga"].reasons()   # the GNSS truth: numbers, hemispheres and the contract's bounds met
    assert gga["gnss:bad_number"] > 0 and gga["gnss:out_of_range"] > 0 and gga["gnss:bad_hemisphere"] > 0, gga


@pytest.mark.slow
def test_the_campaign_repeats_with_its_seed():
    def counts(seed: int) -> dict:
        return {p: (r.reasons(), r.lines, r.published) for p, r in run_serial_campaign(300, seed).items()}

    assert counts(3) == counts(3) and counts(3) != counts(4)


def test_the_extreme_lines_are_well_framed_and_carry_the_issues_numbers():
    maker = SerialLines("vhw", np.random.default_rng(1))
    lines = b"".join(maker.bad("extreme_numbers") for _ in range(400))
    reader = LineReader()
    assert len(reader.feed(lines)) == 400 and not reader.rejected        # every checksum valid
    assert all(f",{text},".encode() in lines for text in ("1e30", "-1e308", "1e308"))
