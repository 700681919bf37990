"""The shore router: a Zenoh session in router mode that boats connect to as clients.

zenohd is not packaged for every registry a boat's PC or a shore laptop can reach, and a router is only a
session with `mode: router`, so the project starts one itself from a Zenoh configuration file (see
deploy/zenoh/). Certificate paths in the file are read from the file's folder, so it starts from any working
directory. It runs until SIGINT or SIGTERM.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from pathlib import Path

import zenoh

from agent.runtime.zenoh_session import config_from_file

# Python runs a signal's handler in the main thread, but the kernel may deliver SIGTERM to any of Zenoh's threads;
# then nothing interrupts a main thread blocked in an untimed wait, and the router never stops (seen in CI: still
# running 15 s after SIGTERM). A timed wait lets the main thread run the pending handler within this many seconds.
SIGNAL_POLL = 0.2


def router_config(config_file: Path | None, listen: list[str]):
    """The router's zenoh.Config: the file if given, else plain TCP on `listen`; mode is always router."""
    config = config_from_file(config_file, "--config") if config_file is not None else zenoh.Config()
    config.insert_json5("mode", json.dumps("router"))
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(listen))
    if config_file is None:
        config.insert_json5("scouting/multicast/enabled", "false")
    return config


def run_router(config_file: Path | None, listen: list[str], ready: threading.Event | None = None,
               stopping: threading.Event | None = None) -> int:
    """Run until SIGINT/SIGTERM (or until `stopping` is set); `ready` is set once the router is up."""
    stopping = stopping or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, lambda *_: stopping.set())
    with zenoh.open(router_config(config_file, listen)) as session:
        print(f"usv-router: running as {session.zid()}, listening on "
              f"{', '.join(listen) if listen else 'the endpoints of ' + str(config_file)}", file=sys.stderr, flush=True)
        if ready is not None:
            ready.set()
        while not stopping.wait(SIGNAL_POLL):
            pass
    print("usv-router: stopped", file=sys.stderr)
    return 0
