"""Small helpers to write result tables and the command that produced them."""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
from collections.abc import Sequence

import numpy as np


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    def cell(value: object) -> str:
        return f"{value:.3f}" if isinstance(value, float) else str(value)

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def invocation(args: argparse.Namespace) -> str:
    """The command line that produced `args`, as a user would type it again.

    `cli.main` stores the arguments it parsed in `args.argv`, so this is right also when the CLI is
    called in-process (from a test), where sys.argv belongs to someone else.
    """
    argv = getattr(args, "argv", None)
    if argv is None:
        argv = sys.argv[1:]
    return " ".join(["usv-lab", *map(shlex.quote, argv)])


def cpu_model() -> str:
    """The processor's name (/proc/cpuinfo's first "model name"; else what `platform` knows): a virtual machine
    can come back on other hardware, and the same code then runs at another speed."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as info:
            names = [line.split(":", 1)[1].strip() for line in info if line.startswith("model name")]
        if names:
            return names[0]
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> list[str]:
    """What a result page says of the machine it was measured on, a line each."""
    return [f"platform: {platform.platform()}", f"CPU: {cpu_model()}", f"os.cpu_count(): {os.cpu_count()}",
            f"Python: {platform.python_implementation()} {sys.version.split()[0]}",
            f"numpy: {np.__version__}"]
