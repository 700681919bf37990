"""The command line every vessel process shares (the agent and the driver bridge): --vessel, --config, --print-config;
`startup_error`, the one line a process says when it cannot start; `stop_on_signals`, how the agent and both
bridges stop; and `guard_stderr`, which keeps a console that cannot be written (a full disk) from ending the
process that writes to it."""

from __future__ import annotations

import argparse
import faulthandler
import signal
import sys
import threading
from pathlib import Path

import yaml
from pydantic import TypeAdapter, ValidationError

from agent.config import ConfigError, StrictModel, parse_mapping, read_yaml
from agent.contract import VesselId
from agent.runtime.zenoh_session import config_layers, zenoh_config

# After SIGINT or SIGTERM a process has this long to finish (its last tick, its log, Zenoh's teardown) before it
# writes every thread's stack to stderr and exits with code 1. Shorter than the launcher's own deadline
# (sim_bridge.fleet.STOP_SECONDS), so that the stacks are written before the launcher's SIGKILL would come; and
# it holds when nobody is left to send that SIGKILL (the launcher killed outright, systemd told to wait).
STOP_DEADLINE = 8.0
STACKS_SIGNAL = signal.SIGUSR1   # `kill -USR1 PID`: every thread's Python stack to stderr, and the process goes on


def stop_on_signals(stopping: threading.Event, deadline: float = STOP_DEADLINE) -> None:
    """SIGINT and SIGTERM set `stopping` and start the deadline to stop by; SIGUSR1 and a fatal signal (SIGSEGV,
    SIGABRT...) write every thread's stack to stderr. The stack dumps and the deadline run in faulthandler's C
    code, so they work while Python's threads are stuck in native code holding the GIL. Call from the main
    thread of a process's entry point only: the deadline ends the whole process."""
    faulthandler.enable(file=sys.stderr, all_threads=True)
    faulthandler.register(STACKS_SIGNAL, file=sys.stderr, all_threads=True)

    def stop(signum, frame):
        if not stopping.is_set():
            faulthandler.dump_traceback_later(deadline, exit=True, file=sys.stderr)
        stopping.set()

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, stop)


class UnfailingStream:
    """A text stream (stderr) whose writes never raise: a console on a full disk, or a pipe nobody reads any
    more, loses the line (counted in `lost`) rather than ending the process from inside its error handling."""

    def __init__(self, stream) -> None:
        self._stream = stream
        self.lost = 0

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except (OSError, ValueError):     # ENOSPC, EDQUOT, EPIPE...; ValueError: the stream was closed
            self.lost += 1
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except (OSError, ValueError):
            self.lost += 1

    def __getattr__(self, name: str):
        return getattr(self._stream, name)    # fileno() (faulthandler's), isatty(), encoding...


def guard_stderr() -> None:
    """Make sys.stderr an UnfailingStream (once): every process calls it first thing in its main."""
    if not isinstance(sys.stderr, UnfailingStream):
        sys.stderr = UnfailingStream(sys.stderr)


def print_config(what: str, settings: StrictModel) -> None:
    """The settings a process would run with, as YAML, and the layers its Zenoh configuration is made of."""
    print(f"# {what}: effective settings")
    for layer in config_layers("the 'zenoh' section below"):
        print(f"# Zenoh {layer}")
    print(yaml.safe_dump(settings.model_dump(mode="json"), sort_keys=False), end="")


def vessel_process(prog: str, description: str, model: type[StrictModel], argv: list[str] | None,
                   add_arguments=None, config_required: bool = False, params_key: str | None = None):
    """The command line of a vessel's process: --vessel, --config, --print-config, with `params_key` --params
    (a file that becomes that field of the settings), and what `add_arguments` adds. Returns (arguments,
    settings) to run with, or an exit code once it has said why not (a bad id, a bad file) or printed the
    configuration."""
    guard_stderr()
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--vessel", required=True, help="this vessel's id (1-32 of A-Z a-z 0-9 _ -)")
    parser.add_argument("--config", required=config_required, default=None,
                        help=f"settings YAML ({model.__name__})" + ("" if config_required else "; default: defaults"))
    parser.add_argument("--print-config", action="store_true",
                        help="print the effective settings (defaults filled in) and exit without starting")
    if params_key is not None:
        parser.add_argument("--params", default=None,
                            help=f"an AgentParams file (as configs/agent.yaml, or what `fit-noise` writes): the "
                                 f"settings' `{params_key}`, in place of theirs")
    if add_arguments is not None:
        add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        TypeAdapter(VesselId).validate_python(args.vessel)
    except ValidationError as error:
        print(f"{prog}: invalid --vessel {args.vessel!r}: {error.errors()[0]['msg']}", file=sys.stderr)
        return 2
    try:
        data = read_yaml(args.config) if args.config else {}
        if params_key is not None and args.params and isinstance(data, (dict, type(None))):
            data = {**(data or {}), params_key: str(Path(args.params).resolve())}
        settings = parse_mapping(model, data, args.config or "<defaults>",
                                 Path(args.config).parent if args.config else None)
        zenoh_config(settings.zenoh)   # a bad ZENOH_CONFIG file or override: one line now, not a traceback later
    except ConfigError as error:
        print(f"{prog}: {error}", file=sys.stderr)
        return 2
    if args.print_config:
        print_config(f"{prog} --vessel {args.vessel}", settings)
        return 0
    return args, settings


def startup_error(prog: str, vessel: str, error: BaseException) -> int:
    """What a vessel's process met while starting (a log it cannot write, a Zenoh session it cannot open, a
    vessel id already taken), in one line as the configuration errors are told; the exit code, 2."""
    text = " ".join(str(error).split()) or type(error).__name__
    print(f"{prog} {vessel}: {text}", file=sys.stderr)
    return 2
