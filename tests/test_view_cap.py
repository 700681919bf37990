"""`usv-op view` against forged senders over real Zenoh: the channels it opens are capped per kind, the rest
dropped, counted and told; the genuine vessel that came first keeps its channel."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time

import pytest
import zenoh

from agent.contract import Status, encode

websockets = pytest.importorskip("websockets.sync.client")
pytest.importorskip("foxglove", reason="usv-op view needs foxglove-sdk")


CAP = 64   # usv-op view's default --max-vessels


def status(sender: str, stamp_ns: int) -> bytes:
    return encode(Status(stamp_ns=stamp_ns, seq=1, sender=sender, phase=0.0, command=(0.0, 0.0)))


@pytest.mark.slow   # usv-op view and a Zenoh session over loopback, about 10 s
def test_forged_senders_cannot_make_the_live_view_open_a_channel_each(tmp_path):
    from agent.runtime.zenoh_session import ZenohSettings, zenoh_config
    from sim_bridge.fleet import free_port

    port = free_port()
    session = zenoh.open(zenoh_config(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"])))
    view = subprocess.Popen([sys.executable, "-m", "usv_op", "--connect", f"tcp/127.0.0.1:{port}", "view",
                             "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = view.stdout.readline()
        url = re.search(r"ws://[0-9.]+:\d+", line)
        assert url, line + view.stderr.read()
        genuine = session.declare_publisher("usv/1/status")
        deadline = time.monotonic() + 10
        for n in range(1000):
            if n % 50 == 0:
                genuine.put(status("1", n))
            session.put(f"usv/forged{n}/status", status(f"forged{n}", n))
            if n % 100 == 0:
                time.sleep(0.05)
        session.put("usv/2/status", status("3", 1))     # a sender that is not its key's vessel: skipped
        time.sleep(1.0)
        topics = set()
        with websockets.connect(url[0], subprotocols=["foxglove.sdk.v1"], open_timeout=10) as client:
            quiet = time.monotonic() + 2.0
            while time.monotonic() < min(quiet, deadline + 10):
                try:
                    frame = client.recv(timeout=0.5)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    message = json.loads(frame)
                    if message["op"] == "advertise":
                        topics |= {c["topic"] for c in message["channels"]}
                        quiet = time.monotonic() + 2.0
    finally:
        view.send_signal(signal.SIGTERM)
        out, err = view.communicate(timeout=20)
        session.close()
    assert view.returncode == 0, err
    assert "usv/1/status" in topics                       # the first vessel heard keeps its channel
    assert len(topics) == CAP, sorted(topics)[:20]        # and no more than the cap
    dropped = int(re.search(rf"(\d+) messages of vessels beyond {CAP} dropped", out)[1])
    assert dropped >= 1000 - CAP, out
    assert re.search(r"1 payloads skipped", out), out
    assert err.count(f"{CAP} vessels have status channels already") == 1, err
