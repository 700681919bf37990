"""Mutual TLS and access control on real Zenoh sessions over loopback.

One router (in this process, built by usv_deploy.security) serves the whole module; the operator and
vessels 1 and 2 connect to it as clients with certificates from usv_deploy.certs. Every "nothing arrives"
check first sees a positive control arrive on the same subscriber, then waits a further second, so a
broken link cannot pass for a denial.
"""

from __future__ import annotations

import json
import os
import select
import stat
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest
import yaml
import zenoh
from conftest import free_ports, wait_until

pytest.importorskip("cryptography", reason="usv_deploy.certs needs the cryptography package")

from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from agent.runtime.zenoh_session import zenoh_config
from sim_bridge.fleet import free_port
from usv_deploy.certs import make_certificates
from usv_deploy.inventory import Inventory, agent_settings
from usv_deploy.security import access_control, secure_config, tls_settings

VESSELS = ["1", "2"]
SILENCE = 1.0   # how long "nothing arrives" is watched for, once the control has arrived
DEADLINE = 5.0  # the most any positive wait may take
# The tests that open Zenoh sessions (the module's router and clients, or their own) are `slow`; those of the
# certificates and configurations alone are not.
slow = pytest.mark.slow


class Inbox:
    """A subscriber that keeps (key, payload) of what it receives; callbacks only append."""

    def __init__(self, session, key_expr: str, liveliness: bool = False, history: bool = False) -> None:
        self.items: list[tuple[str, str]] = []
        self._lock = threading.Lock()
        if liveliness:
            self._sub = session.liveliness().declare_subscriber(key_expr, self._on_sample, history=history)
        else:
            self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample) -> None:
        with self._lock:
            self.items.append((str(sample.key_expr), sample.payload.to_string()))

    def received(self) -> list[tuple[str, str]]:
        with self._lock:
            return list(self.items)

    def has(self, key: str, payload: str = "") -> bool:
        return (key, payload) in self.received()

    def seen_keys(self) -> set[str]:
        return {key for key, _ in self.received()}

    def close(self) -> None:
        self._sub.undeclare()


def open_session(config: dict):
    return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))


def stamp(label: str) -> str:
    """A payload no other test sends."""
    return f"{label}-{uuid.uuid4().hex[:8]}"


def put_until_received(sender, key: str, inbox: Inbox, label: str) -> str:
    """Send a control message until `inbox` has it: the first one may race the router learning of the
    subscriber, which is the setup's business and not what the tests are about."""
    payload = stamp(label)
    end = time.monotonic() + DEADLINE
    while time.monotonic() < end:
        sender.put(key, payload)
        if wait_until(lambda: inbox.has(key, payload), timeout=0.3):
            return payload
    raise AssertionError(f"control message {key}={payload} never arrived; got {inbox.received()}")


FORBIDDEN = "forbidden"  # payload prefix of every message that must not arrive


def assert_held_back(inbox: Inbox, send_forbidden, control_sender, control_key: str):
    """What `send_forbidden()` sends (payloads starting FORBIDDEN) never reaches `inbox`, though control
    messages on the same subscriber do.

    One control goes first, so the subscriber is surely known to the router before the forbidden message is
    sent (else a broken ACL could pass by that race); one goes after it, and then the second of silence.
    """
    put_until_received(control_sender, control_key, inbox, "control-before")
    send_forbidden()
    put_until_received(control_sender, control_key, inbox, "control-after")

    def leaked() -> list:
        return [item for item in inbox.received() if item[1].startswith(FORBIDDEN)]

    assert not wait_until(leaked, timeout=SILENCE), leaked()


# ----- fixtures -----
@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    """The fleet's certificates (vessels 1, 2 and 3; vessel 3 is left out of the router's ACL)."""
    return make_certificates(tmp_path_factory.mktemp("pki"), VESSELS + ["3"])


@pytest.fixture(scope="module")
def foreign_certs(tmp_path_factory):
    """A complete second PKI: certificates with the right names, signed by a CA the fleet does not trust."""
    return make_certificates(tmp_path_factory.mktemp("foreign"), ["1"])


@pytest.fixture(scope="module")
def router(certs):
    """(session, port) of the shore router: TLS listener on loopback, ACL for vessels 1 and 2."""
    port = free_port()
    config = secure_config(certs, "router", "router", [f"tls/127.0.0.1:{port}"], [], VESSELS)
    session = open_session(config)
    yield session, port
    session.close()


def client(certs, name: str, port: int, host: str = "localhost"):
    """A client session of `name` connected to the router (host must be one of its certificate's SANs)."""
    return open_session(secure_config(certs, name, "client", [], [f"tls/{host}:{port}"], VESSELS))


@pytest.fixture(scope="module")
def fleet(certs, router):
    """Client sessions by name: the operator and vessels 1 and 2 (vessel 2 reaches the router by IP)."""
    _, port = router
    sessions = {"operator": client(certs, "operator", port), "vessel-1": client(certs, "vessel-1", port),
                "vessel-2": client(certs, "vessel-2", port, host="127.0.0.1")}
    yield sessions
    for session in sessions.values():
        session.close()


@pytest.fixture
def inboxes():
    """Inboxes a test opens, closed after it so that module-wide sessions stay clean."""
    opened: list[Inbox] = []
    yield lambda *args, **kwargs: opened.append(Inbox(*args, **kwargs)) or opened[-1]
    for inbox in opened:
        inbox.close()


# ----- certificates -----
def load(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(Path(path).read_bytes())


def common_name(cert: x509.Certificate) -> str:
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


def usages(cert: x509.Certificate) -> list:
    return list(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)


def test_certificates_have_names_usages_and_private_keys(tmp_path):
    paths = make_certificates(tmp_path, ["1", "boat_B-2"], hosts=["shore.example", "192.0.2.7", "localhost"])
    assert set(paths) == {"ca", "router", "vessel-1", "vessel-boat_B-2", "operator"}
    ca = load(paths["ca"]["cert"])
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for name, files in paths.items():
        assert stat.S_IMODE(files["key"].stat().st_mode) == 0o600, name
        assert stat.S_IMODE(files["cert"].stat().st_mode) == 0o644, name
        cert = load(files["cert"])
        if name == "ca":
            continue
        assert common_name(cert) == name
        cert.verify_directly_issued_by(ca)
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    server = load(paths["router"]["cert"])
    assert usages(server) == [ExtendedKeyUsageOID.SERVER_AUTH]
    sans = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert sorted(sans.get_values_for_type(x509.DNSName)) == ["localhost", "shore.example"]
    assert sorted(str(ip) for ip in sans.get_values_for_type(x509.IPAddress)) == ["127.0.0.1", "192.0.2.7"]
    for name in ("vessel-1", "vessel-boat_B-2", "operator"):
        assert usages(load(paths[name]["cert"])) == [ExtendedKeyUsageOID.CLIENT_AUTH], name


@pytest.mark.parametrize("bad", ["", "a/b", "../x", "two words", "x" * 33, "é"])
def test_bad_vessel_id_is_refused_before_anything_is_written(tmp_path, bad):
    with pytest.raises(ValueError, match="vessel id"):
        make_certificates(tmp_path / "pki", ["1", bad])
    assert not (tmp_path / "pki").exists()


def test_configs_load_in_zenoh(certs):
    router_config = secure_config(certs, "router", "router", ["tls/0.0.0.0:7447"], [], VESSELS)
    client_config = secure_config(certs, "vessel-1", "client", [], ["tls/localhost:7447"], VESSELS)
    for config in (router_config, client_config):
        zenoh.Config.from_json5(json.dumps(config))
    assert client_config["transport"]["link"]["tls"] == tls_settings(certs, "vessel-1", listen=False)
    assert router_config["access_control"] == access_control(VESSELS)
    with pytest.raises(ValueError):
        secure_config(certs, "vessel-1", "client", [], ["tcp/localhost:7447"], VESSELS)


# ----- transport -----
@slow
def test_vessel_with_fleet_certificate_connects_and_is_heard(router, fleet, inboxes):
    router_session, _ = router
    for name, session in fleet.items():
        assert wait_until(lambda s=session: len(s.info.routers_zid()) == 1, DEADLINE), name
        assert [str(z) for z in session.info.routers_zid()] == [str(router_session.zid())]
    inbox = inboxes(fleet["vessel-2"], "usv/1/cmd")
    put_until_received(fleet["vessel-1"], "usv/1/cmd", inbox, "cmd-from-1")


def intruder_config(certs, foreign_certs, credentials: str, port: int) -> dict:
    """A peer that trusts the fleet's CA (so the router's certificate is fine) and presents `credentials`:
    the real vessel-1 certificate (the control), none at all, or a vessel-1 certificate from another CA."""
    tls = {"valid": tls_settings(certs, "vessel-1", listen=False),
           "none": {"root_ca_certificate": str(certs["ca"]["cert"])},
           "foreign-ca": tls_settings({"ca": certs["ca"], "vessel-1": foreign_certs["vessel-1"]}, "vessel-1",
                                      listen=False)}[credentials]
    # Peer mode: the session opens whether or not the router lets it in, so what it sees can be asked.
    return {"mode": "peer", "scouting": {"multicast": {"enabled": False}}, "listen": {"endpoints": []},
            "connect": {"endpoints": [f"tls/localhost:{port}"]}, "transport": {"link": {"tls": tls}}}


@slow
@pytest.mark.parametrize("credentials", ["valid", "none", "foreign-ca"])
def test_only_a_fleet_certificate_gets_a_link(certs, foreign_certs, router, fleet, inboxes, credentials):
    _, port = router
    inbox = inboxes(fleet["operator"], "usv/1/**")
    peer = open_session(intruder_config(certs, foreign_certs, credentials, port))
    try:
        if credentials == "valid":
            assert wait_until(lambda: len(peer.info.routers_zid()) == 1, DEADLINE)
            put_until_received(peer, "usv/1/cmd", inbox, "peer-valid")
            return
        # No link during a second, in which a handshake would have had every chance to complete.
        assert not wait_until(lambda: list(peer.info.routers_zid()) or list(peer.info.peers_zid()), SILENCE)
        payload = stamp(f"{FORBIDDEN}-{credentials}")
        assert_held_back(inbox, lambda: peer.put("usv/1/cmd", payload), fleet["vessel-1"], "usv/1/cmd")
    finally:
        peer.close()


@slow
@pytest.mark.parametrize("credentials", ["none", "foreign-ca"])
def test_client_without_fleet_certificate_cannot_open(certs, foreign_certs, router, credentials):
    _, port = router
    config = intruder_config(certs, foreign_certs, credentials, port)
    config["mode"] = "client"  # a client must reach a router to open at all
    with pytest.raises(zenoh.ZError):
        open_session(config)


# ----- access control -----
@slow
def test_vessel_cannot_command_another_vessel(fleet, inboxes):
    vessel_2 = fleet["vessel-2"]
    # A declared publisher takes another path than session.put: it sends only where the router has told
    # it there are subscribers.
    publisher = vessel_2.declare_publisher("usv/1/cmd")

    def forge():
        vessel_2.put("usv/1/cmd", stamp(FORBIDDEN))
        publisher.put(stamp(FORBIDDEN))

    try:
        for watcher in (inboxes(fleet["vessel-1"], "usv/*/cmd"), inboxes(fleet["operator"], "usv/*/cmd")):
            assert_held_back(watcher, forge, vessel_2, "usv/2/cmd")
            assert "usv/1/cmd" not in watcher.seen_keys()
    finally:
        publisher.undeclare()


@slow
def test_only_the_operator_publishes_the_mission(fleet, inboxes):
    watcher = inboxes(fleet["vessel-1"], "mission/**")
    assert_held_back(watcher, lambda: fleet["vessel-2"].put("mission/radius", stamp(FORBIDDEN)),
                     fleet["operator"], "mission/radius")


@slow
def test_the_operator_commands_an_agent_through_the_shore_router(certs, router, tmp_path):
    """usv-op with the operator's certificate, through the TLS router, holds an agent process that connects
    with its vessel's certificate; the agent answers, and usv-op says so."""
    _, port = router
    configs = {}
    for name in ("vessel-1", "operator"):
        configs[name] = tmp_path / f"{name}.json5"
        configs[name].write_text(json.dumps(secure_config(certs, name, "client", [], [f"tls/localhost:{port}"],
                                                          VESSELS)))
    settings = tmp_path / "agent.yaml"
    settings.write_text(yaml.safe_dump({"clock": "wall", "id_check": 0.2, "log": str(tmp_path / "agent.mcap")}))
    agent = subprocess.Popen([sys.executable, "-m", "agent", "--vessel", "1", "--config", str(settings)],
                             env={**os.environ, "ZENOH_CONFIG": str(configs["vessel-1"])},
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        operator_env = {**os.environ, "ZENOH_CONFIG": str(configs["operator"])}
        for _ in range(10):   # until the agent is up and heard through the router
            done = subprocess.run([sys.executable, "-m", "usv_op", "hold", "--deadline", "3"], env=operator_env,
                                  capture_output=True, text=True, timeout=60, check=False)
            if "applied" in done.stdout or agent.poll() is not None:
                break
            time.sleep(0.5)
        assert done.returncode == 0 and done.stdout.strip() == "vessel 1: hold applied", (done.stdout, done.stderr)
    finally:
        agent.terminate()
        _, err = agent.communicate(timeout=30)
    assert agent.returncode == 0, err


@slow
def test_vessel_declares_liveliness_only_for_itself(fleet, inboxes):
    # history: tokens declared before the subscription reached the router are reported too
    watcher = inboxes(fleet["vessel-1"], "usv/*/alive", liveliness=True, history=True)
    forged = fleet["vessel-2"].liveliness().declare_token("usv/1/alive")
    own = fleet["vessel-2"].liveliness().declare_token("usv/2/alive")
    try:
        seen = watcher.seen_keys
        assert wait_until(lambda: "usv/2/alive" in seen(), DEADLINE), watcher.received()
        assert not wait_until(lambda: "usv/1/alive" in seen(), SILENCE), watcher.received()
        alive = [str(reply.ok.key_expr) for reply in fleet["operator"].liveliness().get("usv/*/alive", timeout=2)
                 if reply.ok is not None]
        assert alive == ["usv/2/alive"]
    finally:
        forged.undeclare()
        own.undeclare()


@slow
def test_certificate_not_named_in_the_acl_gets_nothing_through(certs, router, fleet, inboxes):
    _, port = router
    stranger = client(certs, "vessel-3", port)  # signed by the fleet CA, but not in the router's list
    try:
        # TLS lets it in; the ACL does not
        assert wait_until(lambda: len(stranger.info.routers_zid()) == 1, DEADLINE)
        inbox = inboxes(fleet["operator"], "usv/*/cmd")
        assert_held_back(inbox, lambda: stranger.put("usv/3/cmd", stamp(FORBIDDEN)), fleet["vessel-2"], "usv/2/cmd")
    finally:
        stranger.close()


# ----- deployment path -----
@slow
def test_usv_deploy_router_runs_the_secure_config(certs, tmp_path):
    """`python -m usv_deploy router --config FILE` with a file written from secure_config enforces it too."""
    port = free_port()
    config_file = tmp_path / "router.json5"
    config = secure_config(certs, "router", "router", [f"tls/127.0.0.1:{port}"], [], VESSELS)
    config_file.write_text(json.dumps(config, indent=2))
    process = subprocess.Popen([sys.executable, "-m", "usv_deploy", "router", "--config", str(config_file)],
                               stderr=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1])
    sessions = []
    try:
        ready, _, _ = select.select([process.stderr], [], [], 20)
        assert ready and "running as" in process.stderr.readline()
        operator, vessel_1, vessel_2 = sessions = [client(certs, name, port)
                                                   for name in ("operator", "vessel-1", "vessel-2")]
        inbox = Inbox(operator, "usv/*/cmd")
        assert_held_back(inbox, lambda: vessel_2.put("usv/1/cmd", stamp(FORBIDDEN)), vessel_2, "usv/2/cmd")
        put_until_received(vessel_1, "usv/1/cmd", inbox, "via-cli-router")
    finally:
        for session in sessions:
            session.close()
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


# ----- the peer LAN without TLS: what docs/reliability.md says an attacker there can do -----
@slow
def test_without_tls_a_stranger_on_the_boat_lan_publishes_as_any_vessel_and_as_the_operator():
    """The peer topology as `usv-deploy render` writes it, plain TCP: a laptop that can reach one boat's
    port joins the fleet's Zenoh and publishes under any key: a thruster command for vessel 1, a share and
    a liveliness token in vessel 2's name, a mission command. Nothing tells these from the real ones but
    what the payload says of itself; this is why the boats' default is the router with mTLS and the ACL."""
    ports = free_ports(2)
    data = yaml.safe_load((Path(__file__).parents[1] / "deploy" / "fleet.example.yaml").read_text())
    data["vessels"] = [{"id": "1", "address": "127.0.0.1", "port": ports[0]},
                       {"id": "2", "address": "127.0.0.1", "port": ports[1]}]
    fleet_lan = Inventory.model_validate(data)
    boat = agent_settings(fleet_lan, fleet_lan.vessel("1"))
    stranger_config = {"mode": "peer", "scouting": {"multicast": {"enabled": False}},
                       "connect": {"endpoints": [f"tcp/127.0.0.1:{ports[0]}"]}}
    with zenoh.open(zenoh_config(boat.zenoh)) as vessel_1, open_session(stranger_config) as stranger:
        data_inbox = Inbox(vessel_1, "**")
        tokens = Inbox(vessel_1, "usv/*/alive", liveliness=True, history=True)
        token = stranger.liveliness().declare_token("usv/2/alive")
        try:
            for key in ("usv/1/cmd", "usv/2/share", "usv/1/sensor/uwb", "mission/radius"):
                put_until_received(stranger, key, data_inbox, "stranger")
            assert wait_until(lambda: "usv/2/alive" in tokens.seen_keys(), timeout=DEADLINE)
        finally:
            token.undeclare()
            data_inbox.close()
            tokens.close()
