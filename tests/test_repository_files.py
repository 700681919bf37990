"""The repository as a fresh clone has it: no tracked file is one that .gitignore says to ignore (configs/agent.yaml
was both: a user's edit to it showed in `git status`, while the file claimed to be ignored)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(not (ROOT / ".git").exists() or shutil.which("git") is None,
                    reason="needs the git checkout (CI runs on a clone)")
def test_no_tracked_file_is_ignored():
    result = subprocess.run(["git", "ls-files", "--cached", "--ignored", "--exclude-standard"], cwd=ROOT,
                            capture_output=True, text=True, check=True)
    assert result.stdout.split() == []
