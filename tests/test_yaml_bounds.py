"""YAML files cost bounded memory: an alias bomb and a file beyond the size limit are refused in one line that
names the file, before they cost more than a few megabytes (agent/config.py `read_yaml`)."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from agent.config import MAX_YAML_BYTES, ConfigError, load_yaml, read_yaml
from agent.core.params import AgentParams
from agent.shell.settings import NodeSettings
from mission_log.replay import parse_assignments
from sim_bridge.scenario import load_scenarios
from usv_deploy.inventory import load_inventory

ADDRESS_SPACE = 2 << 30   # the child's address space: a bomb that goes off fails in seconds, not the machine


def alias_bomb(levels: int = 9) -> str:
    """An agent process's settings file (NodeSettings) whose `agent.control.radius` is a list of lists of
    aliases: 9**levels strings once expanded, in a few hundred bytes."""
    strings = ",".join(['"lol"'] * 9)
    lines = ["agent:", "  control:", f"    radius: [&a [{strings}],"]
    previous = "a"
    for name in "bcdefghijk"[:levels - 2]:
        lines.append(f"      &{name} [" + ",".join(["*" + previous] * 9) + "],")
        previous = name
    lines.append("      [" + ",".join(["*" + previous] * 9) + "]]")
    return "\n".join(lines) + "\n"


# Runs the command given after it, then prints its exit code and its peak resident memory (kB).
MEASURED = ("import resource, subprocess, sys; code = subprocess.call(sys.argv[1:]); "
            "print(code, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


@pytest.mark.slow
def test_alias_bomb_refused_by_the_agent_in_a_few_megabytes(tmp_path: Path) -> None:
    """`usv-agent --config bomb.yaml`: exit 2, one line naming the file, and a peak resident memory of a
    started Python process (the bomb expands to 387 million strings: gigabytes before the loader's bound)."""
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(alias_bomb())
    assert len(bomb.read_bytes()) <= 400
    # The agent runs under a small Python that measures it alone: a child forked straight from this test
    # process (hundreds of MB late in the suite) counts the forked image in its ru_maxrss before it execs.
    process = subprocess.run([sys.executable, "-c", MEASURED, sys.executable, "-m", "agent", "--vessel", "1",
                              "--config", str(bomb)], capture_output=True, text=True, timeout=180, check=False,
                             preexec_fn=_limit_memory)
    returncode, peak_kb = (int(word) for word in process.stdout.split())
    err = process.stderr
    peak_mb = peak_kb / 1024
    lines = err.strip().splitlines()
    print(f"alias bomb ({len(bomb.read_bytes())} bytes): exit {returncode}, the agent's peak RSS {peak_mb:.0f} MB: "
          f"{err.strip()}")
    assert returncode == 2, err[-2000:]
    assert len(lines) == 1 and str(bomb) in lines[0] and "alias" in lines[0], err[-2000:]
    assert "Traceback" not in err
    assert peak_mb < 300, f"{peak_mb:.0f} MB"


@pytest.mark.parametrize("levels", [5, 9])
def test_alias_bomb_refused_before_validation(tmp_path: Path, levels: int) -> None:
    """Every loader refuses an alias expansion beyond the bound; a small bomb (9**5 = 59,049 strings: under
    the bound) is an ordinary bad value, told as one."""
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(alias_bomb(levels))
    with pytest.raises(ConfigError) as raised:
        load_yaml(NodeSettings, bomb)
    message = str(raised.value)
    assert message.startswith(str(bomb))
    if levels == 9:
        assert "alias" in message and len(message) < 200
    else:
        assert "agent.control.radius" in message


def test_recursive_alias_refused(tmp_path: Path) -> None:
    path = tmp_path / "loop.yaml"
    path.write_text("a: &a [1, *a]\n")
    with pytest.raises(ConfigError, match="recursive alias") as raised:
        read_yaml(path)
    assert str(path) in str(raised.value)


def _big(path: Path, head: str) -> Path:
    """A valid YAML file of a few MB: `head` then comment lines."""
    filler = "# " + "x" * 70 + "\n"
    path.write_text(head + filler * (3 * MAX_YAML_BYTES // len(filler)))
    return path


@pytest.mark.slow
def test_file_over_the_limit_refused_before_it_is_read(tmp_path: Path) -> None:
    """A 3 MB settings file, scenario or inventory (valid YAML) is refused naming the file and the limit,
    whichever loader reads it; one just within the limit loads."""
    settings = _big(tmp_path / "agent.yaml", "control: {radius: 6.0}\n")
    scenario = _big(tmp_path / "scenario.yaml", "name: big\nbase: {}\n")
    inventory = _big(tmp_path / "fleet.yaml", "vessels: {}\n")
    for load, path in ((lambda p: load_yaml(AgentParams, p), settings), (load_scenarios, scenario),
                       (load_inventory, inventory)):
        with pytest.raises(ConfigError, match="larger than 1,000,000 bytes") as raised:
            load(path)
        assert str(raised.value).startswith(str(path))
    within = tmp_path / "within.yaml"
    filler = "# " + "x" * 70 + "\n"
    within.write_text("control: {radius: 6.0}\n" + filler * ((MAX_YAML_BYTES - 100) // len(filler)))
    assert os.path.getsize(within) <= MAX_YAML_BYTES
    assert load_yaml(AgentParams, within).control.radius == 6.0


def test_replay_set_value_bounded() -> None:
    """`usv-log replay --set key=<YAML>`: the value goes through the same bounded loader."""
    bomb = alias_bomb().split("radius: ", 1)[1].replace("\n", " ")
    with pytest.raises(ConfigError, match="alias"):
        parse_assignments([f"control.radius={bomb}"])
    assert parse_assignments(["control.radius=6.5"]) == {"control": {"radius": 6.5}}
