"""The transport floor of a lockstep tick: what Zenoh and zenoh-python cost the fleet's processes per tick
when the processes do nothing else. A benchmark part of `usv-lab runtime-bench`, not a test.

The message pattern of a lockstep Table II fleet, with payloads of the real messages' sizes and no work on
them: a "bridge" process publishes four sensor messages per vessel and the clock, then waits until every
"agent" has answered; each agent process (one subscriber for its four sensor keys, one for every vessel's
share, one for the clock, as the agent declares them) wakes on the clock and publishes a share, a command
and a status. Each process's CPU per tick (all its threads) is the floor under the real process's; the tick
loop's wall time is the floor under the lockstep real-time factor.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections import Counter

import zenoh

from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
from sim_bridge.fleet import free_port

# Bytes of each payload: about those of the Table II mission's messages.
SIZES = {"sensor": 200, "clock": 150, "share": 700, "cmd": 110, "status": 900}
READY = b"ready"
TICK_DIGITS = 9        # a share's first bytes: the tick it was sent in
STRAGGLERS = 0.3       # s an agent waits after the end for shares still on their way
END = b"end"
START_TIMEOUT = 30.0   # s for every agent process to start and be heard
TICK_TIMEOUT = 2.0     # s a tick waits for its answers
WARM_UP = 50           # ticks run before the measured ones: the agents' links to each other come up meanwhile


def loopback_config(listen: int | None = None, connect: int | None = None):
    """The agents' session settings (`zenoh_config`) on loopback."""
    return zenoh_config(ZenohSettings(listen=[f"tcp/127.0.0.1:{listen}"] if listen is not None else [],
                                      connect=[f"tcp/127.0.0.1:{connect}"] if connect is not None else []))


def agent(vessel: int, port: int, ticks: int, vessels: int) -> None:
    """One agent of the floor (run in its own process): prints its CPU and shares received per measured
    tick as JSON at the end."""
    with zenoh.open(loopback_config(listen=0, connect=port)) as session:   # listening, as agents do: they link up
        tick, ended = threading.Event(), threading.Event()
        shares = [0]
        by_tick: Counter[int] = Counter()   # shares received, by the tick they were sent in

        def take(sample) -> None:
            sample.payload.to_bytes()

        def take_share(sample) -> None:
            by_tick[int(sample.payload.to_bytes()[:TICK_DIGITS])] += 1
            shares[0] += 1

        def on_clock(sample) -> None:
            if sample.payload.to_bytes() == END:
                ended.set()
            tick.set()

        subscribers = [session.declare_subscriber(f"floor/{vessel}/sensor/*", take),
                       session.declare_subscriber("floor/*/share", take_share),
                       session.declare_subscriber("floor/clock", on_clock)]
        share = session.declare_publisher(f"floor/{vessel}/share", allowed_destination=zenoh.Locality.REMOTE)
        cmd = session.declare_publisher(f"floor/{vessel}/cmd")
        status = session.declare_publisher(f"floor/{vessel}/status")
        payloads = {name: b"x" * size for name, size in SIZES.items()}
        while not tick.wait(0.1):   # until the first clock: say so (the bridge may miss a first word)
            status.put(READY)
        done, cpu_started, measured_from, last, cpu, measured = 0, 0.0, None, 0, 0.0, 0
        while not ended.is_set():
            # Measured from the first tick after the warm-up whose tick before brought every other agent's
            # share: the links between the agents are up by then.
            if measured_from is None and done >= WARM_UP and shares[0] - last == vessels - 1:
                measured_from, cpu_started = done, time.process_time()
            last = shares[0]
            tick.clear()
            # Each share says the tick it was sent in: the ones of the measured ticks are counted wherever they
            # come, a share being free to arrive after the receiver has moved on.
            share.put(f"{done:0{TICK_DIGITS}d}".encode() + payloads["share"][TICK_DIGITS:])
            cmd.put(payloads["cmd"])
            status.put(payloads["status"])
            done += 1
            if measured_from is not None and done - measured_from == ticks:   # the measured window ends
                cpu, measured = time.process_time() - cpu_started, ticks
            if not tick.wait(TICK_TIMEOUT):
                break
        if not measured:
            raise RuntimeError(f"transport floor: agent {vessel} never measured {ticks} ticks with every link up")
        time.sleep(STRAGGLERS)
        heard = sum(by_tick[k] for k in range(measured_from, measured_from + ticks))
        for subscriber in subscribers:
            subscriber.undeclare()
    print(json.dumps({"cpu_ms": 1e3 * cpu / measured, "shares": heard / measured}))


def transport_floor(vessels: int = 4, ticks: int = 1000) -> dict[str, float]:
    """Run the floor: the tick loop's wall time and each process's CPU, in milliseconds per tick."""
    port = free_port()
    payloads = {name: b"x" * size for name, size in SIZES.items()}
    with zenoh.open(loopback_config(listen=port)) as session:
        answered = threading.Condition()
        answers: set[str] = set()
        ready: set[str] = set()

        def on_status(sample) -> None:
            with answered:
                (ready if sample.payload.to_bytes() == READY else answers).add(str(sample.key_expr))
                answered.notify_all()

        subscriber = session.declare_subscriber("floor/*/status", on_status)
        sensors = [session.declare_publisher(f"floor/{v}/sensor/{name}")
                   for v in range(vessels) for name in ("odom", "uwb", "bearing", "sonar")]
        clock = session.declare_publisher("floor/clock")
        code = "from lab.benchmarks.transport_floor import agent; agent({}, {}, {}, {})"
        children = [subprocess.Popen([sys.executable, "-c", code.format(v, port, ticks, vessels)],
                                     stdout=subprocess.PIPE, text=True) for v in range(vessels)]
        try:
            with answered:
                if not answered.wait_for(lambda: len(ready) == vessels, timeout=START_TIMEOUT):
                    raise RuntimeError(f"transport floor: {len(ready)} of {vessels} agent processes were heard "
                                       f"within {START_TIMEOUT:.0f} s")
            missed = 0
            # The agents measure `ticks` ticks from the first one with every link up; the second warm-up is
            # the margin for links that come up late.
            for k in range(2 * WARM_UP + ticks):
                if k == WARM_UP:
                    started, cpu_started, missed = time.monotonic(), time.process_time(), 0
                if k == WARM_UP + ticks:
                    wall, cpu = time.monotonic() - started, time.process_time() - cpu_started
                with answered:
                    answers.clear()
                for publisher in sensors:
                    publisher.put(payloads["sensor"])
                clock.put(payloads["clock"])
                with answered:
                    if not answered.wait_for(lambda: len(answers) == vessels, timeout=TICK_TIMEOUT):
                        missed += 1
            clock.put(END)
            agents = [json.loads(child.communicate(timeout=30)[0].strip().splitlines()[-1]) for child in children]
        finally:
            subscriber.undeclare()
            for child in children:
                if child.poll() is None:
                    child.kill()
    return {"loop_ms": 1e3 * wall / ticks, "bridge_cpu_ms": 1e3 * cpu / ticks,
            "agent_cpu_ms": sum(a["cpu_ms"] for a in agents) / len(agents),
            "shares_per_tick": sum(a["shares"] for a in agents) / len(agents), "missed": missed}
