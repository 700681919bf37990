"""`usv-lab` is the lab's one front door: every subcommand's help works, `lab/cli.py` names every subcommand,
and every `usv-lab COMMAND` the README and docs/ tell a user to run is one of them."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import pytest

from lab import arguments, cli

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", sorted(cli.SUBCOMMANDS))
def test_every_subcommand_shows_its_help(name, capsys):
    with pytest.raises(SystemExit) as done:
        cli.main([name, "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: usv-lab {name}")
    assert cli.SUBCOMMANDS[name][1] in " ".join(out.split())   # the description is the one in SUBCOMMANDS


def test_the_help_and_the_docstring_name_every_subcommand(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    out = capsys.readouterr().out
    for name in cli.SUBCOMMANDS:
        assert re.search(rf"^\s+{re.escape(name)}\b", out, re.MULTILINE), name
        assert re.search(rf"\b{re.escape(name)}\b", cli.__doc__), name


def test_an_unknown_subcommand_is_refused_in_one_line(capsys):
    with pytest.raises(SystemExit) as done:
        cli.main(["no-such-command"])
    assert done.value.code == 2
    assert "invalid choice: 'no-such-command'" in capsys.readouterr().err


def _out_type(name: str):
    parser = argparse.ArgumentParser()
    cli.entry_points(cli.SUBCOMMANDS[name][0])[0](parser)
    return next((action.type for action in parser._actions if "--out" in action.option_strings), None)


# The subcommands whose --out is the folder their page goes into.
FOLDER_OUTS = sorted(name for name in cli.SUBCOMMANDS if _out_type(name) is arguments.folder)


def test_a_results_folder_that_is_a_file_is_refused_before_any_work(tmp_path, capsys):
    """`--out` of the commands that write a page into a folder: a file there is refused by argparse at once
    (`usv-lab fuzz --out docs/results/fuzz.md` used to fail with a traceback after five minutes of campaign)."""
    page = tmp_path / "fuzz.md"
    page.write_text("an earlier page\n")
    assert {"fuzz", "bench", "fleet-bench", "runtime-bench"} <= set(FOLDER_OUTS), FOLDER_OUTS
    for name in FOLDER_OUTS:
        with pytest.raises(SystemExit) as done:
            cli.main([name, "--out", str(page)])
        assert done.value.code == 2, name
        err = capsys.readouterr().err
        assert f"argument --out: {page} is a file, not a folder" in err, (name, err)
        assert err.strip().splitlines()[-1].startswith(f"usv-lab {name}: error:"), err
    assert page.read_text() == "an earlier page\n"


# The subcommands whose --out is the one file they write (a page, a config).
PAGE_OUTS = sorted(name for name in cli.SUBCOMMANDS if _out_type(name) is arguments.page)


def test_every_out_is_a_folder_or_a_page():
    """Each command's --out says which it is, so argparse refuses the other kind at once."""
    loose = [name for name in cli.SUBCOMMANDS if _out_type(name) not in (None, arguments.folder, arguments.page)]
    assert not loose, loose


def test_a_page_that_is_a_folder_is_refused_before_any_work(tmp_path, capsys):
    """`--out` of the commands that write one page: an existing folder there is refused by argparse at once
    (`usv-lab sea-states --out /tmp/x`, a folder, used to fail with a traceback after the whole campaign)."""
    assert {"sea-states", "sea-agent-ab", "sea-bench", "uwb-page", "fit-noise"} <= set(PAGE_OUTS), PAGE_OUTS
    for name in PAGE_OUTS:
        with pytest.raises(SystemExit) as done:
            cli.main([name, "--out", str(tmp_path)])
        assert done.value.code == 2, name
        err = capsys.readouterr().err
        assert f"argument --out: {tmp_path} is a folder, not a file" in err, (name, err)
        assert err.strip().splitlines()[-1].startswith(f"usv-lab {name}: error:"), err


def documented_commands() -> set[tuple[str, str]]:
    """(file, subcommand) of each `usv-lab WORD` in the README, docs/ and the configs' comments."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")),
             *sorted((ROOT / "configs").rglob("*.yaml"))]
    return {(str(path.relative_to(ROOT)), match) for path in files
            for match in re.findall(r"usv-lab ([a-z][a-z-]*)", path.read_text(encoding="utf-8"))}


def test_every_documented_usv_lab_command_exists():
    documented = documented_commands()
    assert len({name for _, name in documented}) >= 8       # the scan reads the docs
    unknown = sorted((path, name) for path, name in documented if name not in cli.SUBCOMMANDS)
    assert not unknown, f"documented but not a subcommand: {unknown}"


def test_no_document_runs_a_lab_module_directly():
    """`python -m lab.x` was the second front door; only `python -m lab` (= usv-lab) remains."""
    files = [ROOT / "README.md", ROOT / "Makefile", *sorted((ROOT / "docs").rglob("*.md")),
             *sorted((ROOT / "configs").rglob("*.yaml"))]
    found = [(str(path.relative_to(ROOT)), m) for path in files
             for m in re.findall(r"python -m lab\.[\w.]+", path.read_text(encoding="utf-8"))]
    assert not found


@pytest.mark.slow
def test_python_dash_m_lab_is_usv_lab():
    done = subprocess.run([sys.executable, "-m", "lab", "fit-noise", "--help"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "usage: usv-lab fit-noise" in done.stdout
