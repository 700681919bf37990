"""Every command the README shows and every example in the commands' `--help` texts, run as a user types them.

The README's commands are read from the README itself (its `sh` blocks and inline code that starts with a
command), so an example added there without being run here fails `test_every_readme_example_is_run`.
A line with placeholders (ID, FILE, N, `[...]`, `a|b`) is a synopsis: its command, subcommands and options
must exist. A concrete line is run: the fast ones here, the fleet walk-through (a real-time fleet, `usv-op`
against it, then `usv-log` on its run folder) in the slow test at the end, with PORT and $RUN filled in from
what `usv-fleet run` printed.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from importlib import import_module
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BIN = Path(sys.executable).parent

# Each console command and the function behind it, as pyproject.toml installs them.
SCRIPTS = dict(re.findall(r'^(usv-[a-z-]+) = "([\w.]+:\w+)"', (ROOT / "pyproject.toml").read_text(), re.M))
STARTS = ("python -m ", "make ", "source ", ".venv/bin/")

# What the walk-through fills in; anything else in capitals, brackets or alternatives is a placeholder.
FILLED = ("PORT", "$RUN")
PLACEHOLDER = re.compile(r"\b[A-Z][A-Z0-9_]*\b|[\[\]|…]|\.\.\.|\$\w+")


def readme_commands() -> list[str]:
    """Every command line of the README: the lines of its `sh` blocks (comments cut) and each inline code span
    that starts with a command, in order, without repeats."""
    text = README.read_text()
    found: list[str] = []
    blocks = re.findall(r"```sh\n(.*?)```", text, re.S)
    for block in blocks:
        found += [line.split("  #")[0].strip() for line in block.splitlines() if line.strip()]
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    found += [span.strip() for span in re.findall(r"`([^`\n]+)`", prose) 
              if span.split()[0] in SCRIPTS or span.startswith(STARTS)]
    return list(dict.fromkeys(found))


def is_synopsis(line: str, filled: tuple[str, ...] = ()) -> bool:
    """Has `line` a placeholder besides those `filled` (and the subcommands of `a|b|c`, each run when one is)?"""
    for name in filled:
        line = line.replace(name, "")
    if filled:
        line = re.sub(r"[a-z][\w-]*(\|[a-z][\w-]*)+", "x", line.replace("--set ...", ""))
    return bool(PLACEHOLDER.search(line))


def help_text(*words: str) -> str:
    """The `--help` of a command and subcommands (`usv-log`, `replay`), run in this process."""
    module, function = SCRIPTS[words[0]].split(":")
    rest = list(words[1:])
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exited:
        getattr(import_module(module), function)([*rest, "--help"])
    assert exited.value.code == 0, (words, out.getvalue())
    return out.getvalue()


def subcommands(text: str) -> list[str]:
    """The subcommands a help text lists (argparse's indented entries under its positional arguments)."""
    section = re.split(r"\n(?:options|optional arguments):", text.split("positional arguments:")[-1])[0]
    return re.findall(r"^    ([a-z][\w-]*)(?:\s|$)", section, re.M)


def all_help_texts() -> dict[tuple[str, ...], str]:
    texts = {}
    for command in SCRIPTS:
        words = (command,)
        texts[words] = top = help_text(*words)
        for sub in subcommands(top):
            texts[(*words, sub)] = help_text(*words, sub)
    return texts


def synopsis_parts(line: str) -> tuple[list[tuple[str, ...]], list[str]]:
    """The command paths a synopsis line names (`usv-log summary|metrics|plot RUN` names three) and its options."""
    words = shlex.split(line.replace("[", " ").replace("]", " ").replace("\\|", "|"))
    command = words[:1]
    rest = words[len(command):]
    paths = [tuple(command)]
    if rest and re.fullmatch(r"[a-z][\w-]*(\|[a-z][\w-]*)*", rest[0]):
        paths = [(*command, sub) for sub in rest[0].split("|")]
    options = [word.split("=")[0] for word in rest if word.startswith("--")]
    return paths, options


# ----- fast: every synopsis names what exists, and the short concrete lines run -----

def test_every_command_option_and_subcommand_the_readme_names_exists():
    texts = all_help_texts()
    checked = 0
    for line in readme_commands():
        if line.split()[0] not in SCRIPTS:
            continue
        paths, options = synopsis_parts(line)
        for path in paths:
            assert path in texts, f"README: `{line}`: {' '.join(path)} is not a command"
            for option in options:
                assert re.search(rf"(^|\s|\[){re.escape(option)}\b", texts[path]), \
                    f"README: `{line}`: {' '.join(path)} takes no {option}"
            checked += 1
    assert checked >= 25       # the README's tables of commands and subcommands, at least


@pytest.mark.slow
def test_the_make_targets_the_readme_names_exist():
    targets = [line.split()[1] for line in readme_commands() if line.startswith("make ")]
    assert {"demo", "test", "test-fast", "test-pythons", "compare", "scenarios"} <= set(targets)
    for target in targets:
        result = subprocess.run(["make", "-n", target], cwd=ROOT, capture_output=True, text=True, check=False)
        assert result.returncode == 0, (target, result.stderr)


@pytest.mark.slow
def test_the_agent_parameters_file_is_what_the_readme_says_generates_it():
    assert "python -m agent.core.params" in readme_commands()
    result = subprocess.run([sys.executable, "-m", "agent.core.params"], cwd=ROOT, capture_output=True, text=True,
                            check=False)
    assert result.returncode == 0, result.stderr
    assert result.stdout == (ROOT / "configs" / "agent.yaml").read_text()


@pytest.mark.slow
def test_every_python_m_the_readme_names_runs():
    """`python -m agent` and the others the README offers beside the commands start as their command does."""
    modules = [line.split()[2] for line in readme_commands()
               if line.startswith("python -m ") and line != "python -m agent.core.params"]
    assert {"agent", "sim_bridge", "mission_log", "lab"} <= set(modules)
    for module in dict.fromkeys(modules):
        result = subprocess.run([sys.executable, "-m", module, "--help"], cwd=ROOT, capture_output=True, text=True,
                                check=False)
        assert result.returncode == 0 and result.stdout.startswith("usage:"), (module, result.stderr)


@pytest.mark.slow
def test_the_activation_line_puts_the_commands_on_the_path():
    assert "source .venv/bin/activate" in readme_commands()
    result = subprocess.run(["bash", "-c", f"source {BIN / 'activate'} && command -v usv-log usv-op usv-fleet"],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == [str(BIN / name) for name in ("usv-log", "usv-op", "usv-fleet")]


@pytest.mark.slow
def test_the_examples_named_in_help_texts_exist(tmp_path):
    """Scenario names and the inventory offered as examples in `--help` (the set and replay examples run in the
    walk-through below)."""
    from sim_bridge.scenario import scenario_file

    texts = {path: " ".join(text.split()) for path, text in all_help_texts().items()}
    examples = {path: re.findall(r"e\.g\. ([^)]+?)(?:\)|$)", text) for path, text in texts.items()}
    names = examples[("usv-fleet", "run")][0].split(", ") + examples[("usv-lab", "scenario")][0].split(", ")
    assert names == ["table2_estimators", "cold_start", "table2_estimators"]
    for name in names:
        assert scenario_file(name).is_file()
    inventory = re.search(r"e\.g\. (\S+\.yaml)", texts[("usv-deploy", "render")]).group(1)
    rendered = subprocess.run([str(BIN / "usv-deploy"), "render", inventory, "--all", "--out", str(tmp_path)],
                              cwd=ROOT, capture_output=True, text=True, check=False)
    assert rendered.returncode == 0, rendered.stderr
    assert (tmp_path / "1" / "agent.yaml").is_file(), list(tmp_path.iterdir())


# ----- slow: the walk-through, against a real fleet -----

def _reader(stream, lines: list[str]) -> threading.Thread:
    thread = threading.Thread(target=lambda: lines.extend(iter(stream.readline, "")), daemon=True)
    thread.start()
    return thread


def _run(line: str, cwd: Path, timeout: float = 120.0) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    return subprocess.run(shlex.split(line), cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout,
                          check=False)


@pytest.mark.slow   # a fleet of processes for 30 s of real time, usv-op against it, usv-log after
def test_every_readme_example_is_run(tmp_path):
    readme = readme_commands()
    help_examples = " ".join(" ".join(text.split()) for text in all_help_texts().values())
    op_example = re.search(r"(set radius=\S+ yaw_rate=\S+ direction=\S+)", help_examples).group(1)
    replay_examples = re.search(r"e\.g\. (relative\.\S+) or '([^']+)'", help_examples).groups()
    ran: set[str] = set()
    scratch = tmp_path / "tmp"       # the fleet's temporary files, to see that it leaves none behind
    scratch.mkdir()
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "TMPDIR": str(scratch)}

    # The README's real-time fleet, run as written; it prints the usv-op line to watch it with.
    fleet_line = "usv-fleet run cold_start --duration 30 --mode realtime"
    assert fleet_line in readme
    fleet = subprocess.Popen(shlex.split(fleet_line), cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    said: list[str] = []
    readers = [_reader(fleet.stderr, said), _reader(fleet.stdout, said)]
    try:
        deadline = time.monotonic() + 60
        while not any("usv-op --connect" in line for line in said) and time.monotonic() < deadline:
            assert fleet.poll() is None, said
            time.sleep(0.2)
        printed = next(line for line in said if "usv-op --connect" in line)
        port = re.search(r"usv-op --connect tcp/127\.0\.0\.1:(\d+) status", printed).group(1)
        ran.add(fleet_line)
        time.sleep(4.0)     # the agents come up and start publishing

        status_line = "usv-op --connect tcp/127.0.0.1:PORT status"
        assert status_line in readme
        console = subprocess.Popen(shlex.split(status_line.replace("PORT", port)), env=env, stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True)
        shown: list[str] = []
        reader = _reader(console.stdout, shown)

        def every_vessel_shown() -> bool:
            return all(re.search(rf"^{vessel}\s+yes", "".join(shown), re.M) for vessel in "1234")

        deadline = time.monotonic() + 60      # a loaded machine takes its time to import and to hear them
        while not every_vessel_shown() and console.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        console.send_signal(signal.SIGINT)     # Ctrl-C, as the user ends it
        err = console.communicate(timeout=20)[1]
        reader.join(timeout=10)
        assert console.returncode == 0, err
        assert every_vessel_shown(), "".join(shown)
        ran.add(status_line)

        for line in ("usv-op --connect tcp/127.0.0.1:PORT hold", "usv-op --connect tcp/127.0.0.1:PORT set radius=8",
                     f"usv-op --connect tcp/127.0.0.1:PORT {op_example}",
                     "usv-op --connect tcp/127.0.0.1:PORT resume"):
            result = _run(line.replace("PORT", port), tmp_path, timeout=60)
            assert result.returncode == 0, (line, result.stdout, result.stderr)
            assert result.stdout.count("applied") == 4, (line, result.stdout)
            ran.add(line)
        assert fleet.wait(timeout=120) == 0, said
    finally:
        if fleet.poll() is None:
            fleet.kill()
            fleet.wait()
        for reader in readers:
            reader.join(timeout=10)
    assert not list(scratch.glob("usv-fleet-*")), "usv-fleet left its copy of the scenario behind"
    run = Path(re.search(r"run folder (\S+)", "".join(said)).group(1))
    run = run if run.is_absolute() else tmp_path / run
    assert (run / "sim.mcap").is_file()

    for sub in ("summary", "metrics", "plot"):
        result = _run(f"usv-log {sub} {run}", tmp_path)
        assert result.returncode == 0, (sub, result.stderr)
        assert result.stdout.strip(), sub
    ran.add("usv-log summary|metrics|plot $RUN")
    for change in replay_examples:
        result = _run(f"usv-log replay {run}/agent-1.mcap --set {shlex.quote(change)}", tmp_path)
        assert result.returncode == 0, (change, result.stderr)
        assert "ticks from the start" in result.stdout and '"estimator"' in result.stdout, result.stdout
    assert len(list((run / "replays").glob("agent-1*.mcap"))) == 2      # the second replay did not overwrite
    ran.add("usv-log replay $RUN/agent-1.mcap --set ...")
    # The run folder still reads as four vessels with the replays beside it.
    summary = _run(f"usv-log metrics {run}", tmp_path)
    assert summary.returncode == 0 and "replay" not in summary.stderr, summary.stderr

    # The router's example endpoint, as `usv-deploy router --help` gives it.
    listen = re.search(r"endpoints to listen on, e\.g\. (\S+)", help_examples).group(1)
    router = subprocess.Popen([str(BIN / "usv-deploy"), "router", "--listen", listen], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        import zenoh

        from agent.runtime.zenoh_session import ZenohSettings, zenoh_config

        time.sleep(2.0)
        assert router.poll() is None, router.communicate()
        port = listen.rsplit(":", 1)[1]
        with zenoh.open(zenoh_config(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))) as session:
            assert str(session.zid())
    finally:
        router.send_signal(signal.SIGINT)
        router.communicate(timeout=20)

    # Every README line with arguments, concrete or with only PORT or $RUN to fill, ran above or in the fast
    # tests (a bare command or subcommand, `usv-lab fuzz`, names one: the fast test checks that it exists).
    fast = {"python -m agent.core.params", "source .venv/bin/activate"}
    walk = [line for line in readme if not is_synopsis(line, FILLED) and not line.startswith(("make ", ".venv/bin/"))
            and line.split()[0] in SCRIPTS and len(line.split()) > len(synopsis_parts(line)[0][0])]
    missing = [line for line in walk if line not in ran | fast]
    assert not missing, f"README examples no test runs: {missing}"
