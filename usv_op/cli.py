"""`usv-op`: the operator's command line on the shore.

    usv-op status [--once]                      the live fleet in the terminal, refreshed in place
    usv-op hold | resume | start [--vessel ID]  a mission command, then wait for every live agent's answer
    usv-op set radius=8 [yaw_rate=0.1] [direction=cw|ccw] [--vessel ID]
    usv-op view [--port 8765]                   the live fleet in Foxglove (its WebSocket protocol)
    usv-op layout [--vessels 1 2 3 4]           the Foxglove layout for the live view and the logs

A command goes to `mission/all` (or `mission/<ID>`), stamped with the fleet's clock: the sim clock when one
is heard (a simulated fleet), else this computer's clock (a fleet at sea runs on synchronised wall clocks).
Its `seq` is the wall clock in ns and its `session` a random one per invocation: an agent refuses a second
command of the same sender, session and seq while it is within the stamp window (a replay). The command
then waits for each live agent it addresses (liveliness) to answer in its status: exit 0 if every one
applied it, 1 if one refused it or did not answer within --deadline (each is named), 2 on a usage error.

Zenoh: `--connect` endpoints (the shore router, or a vessel's agent on loopback), or the ZENOH_CONFIG file
and ZENOH_CONFIG_OVERRIDE as for every process (agent/runtime/zenoh_session.py).
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import sys
import threading
import time

import zenoh
from pydantic import ValidationError

from agent.config import ConfigError
from agent.contract import (
    CLOCK_KEY,
    LIVELINESS,
    Clock,
    MissionCommand,
    Status,
    decode,
    encode,
    every,
    mission_key,
    vessel_of,
)
from agent.runtime.zenoh_session import SessionError, ZenohSettings, open_session
from usv_op.layout import fleet_layout
from usv_op.view import MAX_VESSELS, serve

CLOCK_LISTEN = 0.5      # s to listen for a sim clock before stamping with the wall clock
DISCOVERY = 1.0         # s to wait for the agents' liveliness tokens
SETTABLE = ("radius", "yaw_rate", "direction")
CLOSE_WAIT = 1.0        # s to wait for the session to close before exiting without it
ONCE_WAIT = 3.0         # s `status --once` waits for a status of every live vessel
RATE_WINDOW = 2.0       # s of statuses the console's tick rate is counted over
LOST_AFTER = 2.0        # s without a status after which the console calls a vessel lost (20 ticks at 10 Hz)


def _settings(args: argparse.Namespace) -> ZenohSettings:
    return ZenohSettings(mode=args.mode, connect=args.connect or [])


def live_vessels(session, wait: float = DISCOVERY) -> set[str]:
    """The vessels whose agent holds its liveliness token now. The replies go to a callback: iterating the
    default channel hung for good once 256 tokens were declared (forged ones, without TLS)."""
    found: set[str] = set()
    done = threading.Event()

    def on_reply(reply) -> None:
        if reply.ok is not None:
            vessel = vessel_of(str(reply.ok.key_expr))
            if vessel is not None:
                found.add(vessel)

    session.liveliness().get(every(LIVELINESS), zenoh.handlers.Callback(on_reply, done.set), timeout=wait)
    done.wait(wait + CLOSE_WAIT)
    return set(found)


def fleet_clock(session):
    """A function giving now in the fleet's clock (ns): the latest sim clock heard within CLOCK_LISTEN carried
    on by the time since it was heard, else the wall clock. A command is stamped just before it goes out: the
    discovery before it may take a second or two (a fleet with many tokens), and a command stamped before
    it would come stale."""
    heard: list[tuple[bytes, float]] = []
    subscriber = session.declare_subscriber(
        CLOCK_KEY, lambda sample: heard.append((sample.payload.to_bytes(), time.monotonic())))
    time.sleep(CLOCK_LISTEN)
    subscriber.undeclare()
    for payload, arrived in reversed(heard):
        clock, _ = decode(Clock, payload)
        if clock is not None:
            return lambda: clock.stamp_ns + round((time.monotonic() - arrived) * 1e9)
    return time.time_ns



def send(session, command: MissionCommand, vessel: str | None, deadline: float, out=print, clock=None) -> int:
    """Publish `command` to `vessel` (None: the fleet) and wait for the answers; the exit code.

    The vessels expected to answer are the live ones: those whose liveliness token this session sees, and
    those the agents' statuses list as their live peers. A vessel whose process is frozen still holds its
    token in the others' sessions until its lease ends, but a session opened now cannot link to it: only
    the others' statuses tell that it should be there."""
    answers: dict[str, tuple[bool, str]] = {}
    peers: set[str] = set()
    addressed: set[str] = set()
    done = threading.Event()

    def on_status(sample) -> None:
        status, _ = decode(Status, sample.payload.to_bytes())
        if status is None:
            return
        peers.update([status.sender, *status.peers])
        for ack in status.mission:
            if ack.sender == command.sender and ack.seq == command.seq:
                answers.setdefault(status.sender, (ack.applied, ack.reason))
        if addressed and addressed <= set(answers):
            done.set()

    subscriber = session.declare_subscriber(every("status"), on_status)
    try:
        live = live_vessels(session)
        heard_from_all = time.monotonic() + DISCOVERY   # a status of each live agent brings its peers
        while not live <= peers and time.monotonic() < heard_from_all:
            time.sleep(0.02)
        live |= peers
        if vessel is not None and vessel not in live:
            out(f"usv-op: no live vessel {vessel!r} (live: {', '.join(sorted(live)) or 'none'})")
            return 2
        addressed.update({vessel} if vessel is not None else live)
        if not addressed:
            out("usv-op: no live vessel to command")
            return 1
        if clock is not None:   # stamped now, after the discovery
            command = command.model_copy(update={"stamp_ns": clock()})
        session.put(mission_key(vessel), encode(command))
        done.wait(deadline)
    finally:
        subscriber.undeclare()
    code = 0
    for name in sorted(addressed):
        if name not in answers:
            out(f"vessel {name}: no answer within {deadline:g} s")
            code = 1
        elif answers[name][0]:
            out(f"vessel {name}: {command.command} applied")
        else:
            out(f"vessel {name}: {command.command} refused: {answers[name][1]}")
            code = 1
    return code


def _command(args: argparse.Namespace, stamp_ns: int) -> MissionCommand:
    values = {}
    for item in getattr(args, "values", None) or []:
        name, equals, text = item.partition("=")
        if not equals or name not in SETTABLE:
            raise ConfigError(f"{item!r}: give {' or '.join(f'{n}=VALUE' for n in SETTABLE)}")
        if name == "direction":
            values[name] = text
            continue
        try:
            values[name] = float(text)
        except ValueError:
            raise ConfigError(f"{item!r}: {text!r} is not a number") from None
    try:
        return MissionCommand(stamp_ns=stamp_ns, seq=time.time_ns(), sender=args.sender, command=args.command,
                              session=secrets.token_hex(8), **values)
    except ValidationError as error:     # one line, the field as the user typed it: 'radius=-3: ...'
        first = error.errors()[0]
        field = ".".join(str(part) for part in first["loc"])
        given = f"{field}={first['input']}" if field in values else field or args.command
        raise ConfigError(f"{given}: {first['msg'][0].lower()}{first['msg'][1:]}") from None


def autopilot(status: Status) -> str:
    """The autopilot's state as its agent last repeated it: mode and arming, 'link lost', and '(N s)' when the
    driver said it more than LOST_AFTER s before the status; '-' without an autopilot (a simulated vessel)."""
    vehicle = status.vehicle
    if vehicle is None:
        return "-"
    said = f"{vehicle.mode} {'armed' if vehicle.armed else 'disarmed'}" if vehicle.linked else "link lost"
    age = (status.stamp_ns - vehicle.stamp_ns) * 1e-9
    return said + (f" ({age:.0f} s)" if status.ticked and age > LOST_AFTER else "")


def status_lines(statuses: dict[str, tuple[float, Status]], live: set[str], now: float,
                 rates: dict[str, float] | None = None) -> list[str]:
    """The fleet as the console shows it: one line per vessel heard or alive. A vessel whose last status is
    more than LOST_AFTER s old is LOST, whatever its liveliness token says (a frozen process keeps it)."""
    rates = rates or {}
    lines = [f"{'vessel':8} {'alive':5} {'age s':>6} {'Hz':>5} {'held':4} {'surge':>6} {'yaw r.':>7} {'refused':>7} "
             f"{'autopilot':16} {'weakest pair':22} last mission command"]
    for vessel in sorted(set(statuses) | live):
        arrived, status = statuses.get(vessel, (None, None))
        if status is None:
            lines.append(f"{vessel:8} {'yes':5} {'-':>6} {'-':>5} {'-':4} {'-':>6} {'-':>7} {'-':>7} {'-':16} {'-':22} "
                         "(no status yet)")
            continue
        refused = sum(v for k, v in status.health.items() if k.startswith("rejected_"))
        last = max(status.mission, key=lambda a: a.stamp_ns, default=None)
        said = "-" if last is None else (f"{last.command} from {last.sender}: "
                                         + ("applied" if last.applied else f"refused ({last.reason})"))
        weakest = status.weakest_pair
        pair = "-" if weakest is None else f"{weakest.neighbour}: {weakest.observability}"
        alive = "LOST" if now - arrived > LOST_AFTER else "yes" if vessel in live else "no"
        lines.append(f"{vessel:8} {alive:5} {now - arrived:6.1f} "
                     f"{rates.get(vessel, 0.0):5.1f} {'HOLD' if status.held else '':4} {status.command[0]:6.2f} "
                     f"{status.command[1]:7.3f} {refused:7d} {autopilot(status)[:16]:16} {pair[:22]:22} {said}")
    return lines


def tick_rate(arrivals: list[float], now: float) -> float:
    """Statuses per second over the last RATE_WINDOW s of arrival times (0 with fewer than two)."""
    recent = [t for t in list(arrivals) if now - t <= RATE_WINDOW]
    return (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] else 0.0


def watch(session, once: bool, period: float = 0.5, out=print, where: str = "the configured endpoints",
          stop: threading.Event | None = None) -> int:
    """The status console: refreshed in place every `period` s until `stop` is set (Ctrl-C through
    `_stop_on_signals`); `once`: print once and exit 0, or exit 1 saying so when no vessel answered at
    `where`. The subscriber is left to the session's close, which `_close` bounds."""
    stop = stop or threading.Event()
    statuses: dict[str, tuple[float, Status]] = {}
    arrivals: dict[str, list[float]] = {}

    def on_status(sample) -> None:
        status, _ = decode(Status, sample.payload.to_bytes())
        if status is not None and status.ticked:
            now = time.monotonic()
            statuses[status.sender] = (now, status)
            recent = arrivals.setdefault(status.sender, [])
            recent.append(now)
            del recent[:max(0, len(recent) - 200)]

    _subscriber = session.declare_subscriber(every("status"), on_status)   # held: dropping it may undeclare
    started = time.monotonic()
    while not stop.is_set():
        live = live_vessels(session, wait=period)
        # the peers that live agents see (a frozen one too), from statuses that are not old themselves
        now = time.monotonic()
        live |= {peer for arrived, status in list(statuses.values()) if now - arrived <= LOST_AFTER
                 for peer in status.peers}
        heard = {v for v, times in list(arrivals.items()) if len(times) >= 3}   # enough for a rate
        if once and not (heard and live <= heard) and time.monotonic() - started < ONCE_WAIT:
            continue   # a new subscription takes a moment to reach every agent
        now = time.monotonic()
        rates = {v: tick_rate(times, now) for v, times in list(arrivals.items())}
        if not statuses and not live:
            if once:
                print(f"usv-op: no fleet reachable at {where}: no agent's status or liveliness token in "
                      f"{ONCE_WAIT:.0f} s", file=sys.stderr)
                return 1
            out(f"\x1b[H\x1b[2Jno fleet reachable at {where} (yet): waiting", end="", flush=True)
            continue
        lines = status_lines(dict(statuses), live, now, rates)
        if once:
            out("\n".join(lines))
            return 0
        out("\x1b[H\x1b[2J" + "\n".join(lines), end="", flush=True)   # home, clear: refresh in place
    out("")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="usv-op", description=__doc__.split("\n\n")[0])
    parser.add_argument("--connect", action="append", help="Zenoh endpoint to connect to (repeatable)")
    parser.add_argument("--mode", choices=("peer", "client"), default="peer", help="Zenoh session mode")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    status = commands.add_parser("status", help="the live fleet, refreshed in place")
    status.add_argument("--once", action="store_true", help="print the fleet once and exit")
    view = commands.add_parser("view", help="serve the live fleet to Foxglove over its WebSocket protocol")
    view.add_argument("--host", default="127.0.0.1", help="address to serve on (0.0.0.0: every interface)")
    view.add_argument("--port", type=int, default=8765, help="port to serve on (0: any free one)")
    view.add_argument("--max-vessels", type=int, default=MAX_VESSELS,
                      help="vessels shown at most (each opens three channels; the first come are kept)")
    layout = commands.add_parser("layout", help="print the Foxglove layout (JSON) for a fleet")
    layout.add_argument("--vessels", nargs="+", default=["1", "2", "3", "4"], help="the fleet's vessel ids")
    for name, text in (("hold", "every addressed vessel stops and keeps station"),
                       ("resume", "circle again after a hold"), ("start", "start (or go on) circling"),
                       ("set", "a new circle: set radius=8 yaw_rate=0.1 direction=cw")):
        sub = commands.add_parser(name, help=text)
        if name == "set":
            sub.add_argument("values", nargs="+", metavar="NAME=VALUE")
        sub.add_argument("--vessel", default=None, help="one vessel's id (default: the whole fleet)")
        sub.add_argument("--deadline", type=float, default=3.0, help="seconds to wait for the answers")
        sub.add_argument("--sender", default="operator", help="the operator's id in the command")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except KeyboardInterrupt:
        # A Ctrl-C before the console's own handler is in place (while the session opens, or during a
        # command's send): one line and the shell's code for it, not a traceback.
        print("usv-op: interrupted", file=sys.stderr)
        return 130


def _run(args: argparse.Namespace) -> int:
    if args.command == "layout":
        try:
            print(json.dumps(json.loads(fleet_layout(args.vessels)), indent=2))
        except ImportError as error:
            print(f"usv-op: {error}", file=sys.stderr)
            return 2
        return 0
    try:
        session = open_session(_settings(args), wait_for_peers=False)
    except (ConfigError, SessionError) as error:
        print(f"usv-op: {' '.join(str(error).split())}", file=sys.stderr)
        return 2
    try:
        if args.command == "status":
            where = ", ".join(args.connect) if args.connect else "the Zenoh configuration's endpoints"
            code = watch(session, args.once, where=where, stop=_stop_on_signals())
        elif args.command == "view":
            code = serve(session, args.host, args.port, _stop_on_signals(), max_vessels=args.max_vessels)
        else:
            clock = fleet_clock(session)
            code = send(session, _command(args, clock()), args.vessel, args.deadline, clock=clock)
    except (ConfigError, ValueError, ImportError) as error:
        print(f"usv-op: {' '.join(str(error).split())}", file=sys.stderr)
        code = 2
    return _close(session, code)


def _stop_on_signals() -> threading.Event:
    """An event SIGINT and SIGTERM set: the live view and the status console stop at their next look, and
    no KeyboardInterrupt lands inside a Zenoh call (once `usv-op status` outlived a Ctrl-C by 20 s)."""
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    return stop


def _close(session, code: int) -> int:
    """Close the session and return `code`; if the close hangs (a frozen peer holds a link open for about
    10 s), exit now with `code`: the command is out and its answers are in."""
    closing = threading.Thread(target=session.close, daemon=True)
    closing.start()
    closing.join(CLOSE_WAIT)
    if closing.is_alive():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
