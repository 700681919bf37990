"""Deployment: the fleet inventory rendered into each boat's files, --print-config, the systemd units, and the
two Zenoh topologies working as rendered (peers on a LAN, clients of the shore router)."""

from __future__ import annotations

import configparser
import json
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml
import zenoh
from conftest import free_ports, wait_until

from agent.runtime.zenoh_session import config_from_file, zenoh_config
from agent.shell.settings import NodeSettings
from driver_bridge.node import DriverSettings
from sim_bridge.fleet import free_port
from usv_deploy.inventory import (
    LOG_ROOT,
    Inventory,
    agent_settings,
    driver_settings,
    load_inventory,
    missing_devices,
    render,
    render_router,
)
from usv_deploy.router import run_router
from usv_deploy.security import secure_config

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"


def usv_deploy(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "usv_deploy", *args], capture_output=True, text=True, check=False, timeout=120)


def inventory(**changes) -> Inventory:
    data = yaml.safe_load((DEPLOY / "fleet.example.yaml").read_text())
    data.update(changes)
    return Inventory.model_validate(data)


@pytest.mark.slow
def test_the_example_inventory_renders_every_boat(tmp_path):
    result = usv_deploy("render", str(DEPLOY / "fleet.example.yaml"), "--all", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    # Without TLS, render says plainly what anyone on the network can do (one line), and goes on.
    (warning,) = [line for line in result.stderr.splitlines() if "warning" in line]
    assert "no TLS" in warning and "thruster commands" in warning and "Lab use only" in warning
    for vessel in ("1", "2", "3"):
        folder = tmp_path / vessel
        agent = NodeSettings.model_validate(yaml.safe_load((folder / "agent.yaml").read_text()))
        driver = DriverSettings.model_validate(yaml.safe_load((folder / "driver.yaml").read_text()))
        assert agent.clock == "wall" and agent.log == f"{LOG_ROOT}/agent-{{vessel}}-{{start}}.mcap"
        assert agent.agent.control.radius == 20.0                       # the fleet's parameter
        assert agent.zenoh.mode == "peer" and not agent.zenoh.multicast_scouting
        # Every other vessel's agent and driver bridge, explicitly; UWB node ids of the others.
        others = [v for v in ("1", "2", "3") if v != vessel]
        expected = {f"tcp/10.10.0.1{v}:{p}" for v in others for p in (7447, 7448)}
        assert set(agent.zenoh.connect) == expected | {f"tcp/10.10.0.1{vessel}:7448"}
        assert agent.zenoh.listen == [f"tcp/10.10.0.1{vessel}:7447"]
        assert driver.zenoh.listen == [f"tcp/10.10.0.1{vessel}:7448"]
        assert driver.uwb.module.peers == {int(v): v for v in others}
        assert driver.thrusters.hull.max_thrust == 60.0 and driver.camera.camera.width == 1280
        assert (folder / "usv.env").read_text() == f"USV_VESSEL={vessel}\nUSV_FLEET=lake-trial\n"
    # One boat's own parameters go over the fleet's.
    assert yaml.safe_load((tmp_path / "3" / "agent.yaml").read_text())["agent"]["control"]["max_speed"] == 1.2
    assert yaml.safe_load((tmp_path / "1" / "agent.yaml").read_text())["agent"]["control"]["max_speed"] != 1.2


@pytest.mark.slow
def test_print_config_shows_the_effective_settings_without_starting(tmp_path):
    render(inventory(), "2", tmp_path)
    for program, model, name in (("agent", NodeSettings, "agent.yaml"), ("driver_bridge", DriverSettings,
                                                                         "driver.yaml")):
        shown = subprocess.run([sys.executable, "-m", program, "--vessel", "2", "--config", str(tmp_path / name),
                                "--print-config"], capture_output=True, text=True, check=False, timeout=10)
        # Nothing started: started, either would fail here (neither the boat's address 10.10.0.12 nor its
        # serial devices exist on this machine), so exit code 0 says it only printed.
        assert shown.returncode == 0, shown.stderr
        printed = model.model_validate(yaml.safe_load(shown.stdout))
        assert printed == model.model_validate(yaml.safe_load((tmp_path / name).read_text()))
        assert "effective settings" in shown.stdout


@pytest.mark.slow
def test_bad_inventories_are_refused_with_the_reason(tmp_path):
    cases = {
        "duplicate": ({"vessels": [{"id": "1", "address": "a"}, {"id": "1", "address": "b"}]}, "unique"),
        "no router": ({"topology": "router"}, "needs a router"),
        "tls on peers": ({"tls": "certs"}, "tls needs topology 'router'"),
        "bad id": ({"vessels": [{"id": "no spaces", "address": "a"}]}, "vessels.0.id"),
    }
    for name, (change, reason) in cases.items():
        data = yaml.safe_load((DEPLOY / "fleet.example.yaml").read_text()) | change
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump(data))
        result = usv_deploy("render", str(path), "--all", "--out", str(tmp_path / "out"))
        assert result.returncode == 2 and reason in result.stderr and "Traceback" not in result.stderr, name
    result = usv_deploy("render", str(DEPLOY / "fleet.example.yaml"), "--vessel", "9", "--out", str(tmp_path))
    assert result.returncode == 2 and "vessel '9' is not in the inventory" in result.stderr


def test_the_systemd_units_run_the_rendered_files():
    for unit, program, config in (("usv-agent@.service", "usv-agent", "agent.yaml"),
                                  ("usv-driver@.service", "usv-driver", "driver.yaml")):
        parser = configparser.ConfigParser(strict=False, interpolation=None)
        parser.optionxform = str
        parser.read(DEPLOY / "systemd" / unit)
        service = parser["Service"]
        assert service["ExecStart"] == f"/opt/usv/.venv/bin/{program} --vessel %i --config /etc/usv/%i/{config}"
        assert service["EnvironmentFile"] == "/etc/usv/%i/usv.env"          # what render writes
        assert service["Restart"] == "always" and service["KillSignal"] == "SIGTERM"
        assert service["LogsDirectory"] == Path(LOG_ROOT).name
        assert parser["Install"]["WantedBy"] == "multi-user.target"


def test_the_zenoh_topology_files_load():
    modes = {name: json.loads(zenoh.Config.from_file(str(DEPLOY / "zenoh" / f"{name}.json5")).get_json("mode"))
             for name in ("peer-lan", "client-to-router", "router")}
    assert modes == {"peer-lan": "peer", "client-to-router": "client", "router": "router"}


def _exchange(first, second) -> bool:
    """Does a put on one session reach a subscriber on the other?"""
    got = []
    second.declare_subscriber("usv/1/cmd", lambda sample: got.append(sample.payload.to_bytes()))
    publisher = first.declare_publisher("usv/1/cmd")
    return wait_until(lambda: publisher.put(b"x") or bool(got), interval=0.05)


@pytest.mark.slow
def test_peer_topology_as_rendered_links_two_boats():
    ports = free_ports(2)
    fleet = inventory(vessels=[{"id": "1", "address": "127.0.0.1", "port": ports[0]},
                               {"id": "2", "address": "127.0.0.1", "port": ports[1]}])
    one, two = (agent_settings(fleet, fleet.vessel(v)) for v in ("1", "2"))
    with zenoh.open(zenoh_config(one.zenoh)) as first, zenoh.open(zenoh_config(two.zenoh)) as second:
        assert _exchange(first, second)


@pytest.mark.slow
def test_router_topology_as_rendered_links_clients_through_the_router(tmp_path):
    port = free_port()
    fleet = inventory(topology="router", router={"address": "127.0.0.1", "port": port})
    config, missing = render_router(fleet, tmp_path)
    assert missing == []                                   # no TLS: no certificates to copy
    ready, stopping = threading.Event(), threading.Event()
    router = threading.Thread(target=run_router, args=(config, []), kwargs={"ready": ready, "stopping": stopping},
                              daemon=True)
    router.start()
    assert ready.wait(20)
    one, two = (agent_settings(fleet, fleet.vessel(v)) for v in ("1", "2"))
    assert one.zenoh.mode == "client" and one.zenoh.connect == [f"tcp/127.0.0.1:{port}"] and not one.zenoh.listen
    assert driver_settings(fleet, fleet.vessel("1")).zenoh.connect == one.zenoh.connect
    try:
        with zenoh.open(zenoh_config(one.zenoh)) as first, zenoh.open(zenoh_config(two.zenoh)) as second:
            assert wait_until(lambda: list(first.info.routers_zid()))
            assert _exchange(first, second)
    finally:
        stopping.set()
        router.join(10)


def secure_inventory(folder: Path, port: int = 7447, address: str = "10.10.0.1") -> Path:
    """The example TLS inventory copied into `folder` (its `tls: certs` then means `folder/certs`)."""
    data = yaml.safe_load((DEPLOY / "fleet.shore-router.example.yaml").read_text())
    data["router"] = {"address": address, "port": port}
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "fleet.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.slow
def test_a_secure_fleet_renders_tls_configs_and_certificates(tmp_path):
    pytest.importorskip("cryptography")
    inventory_path = secure_inventory(tmp_path)
    made = usv_deploy("certs", "--inventory", str(inventory_path))     # into the inventory's tls folder
    assert made.returncode == 0, made.stderr
    for name in ("ca", "router", "operator", "vessel-1", "vessel-2", "vessel-3"):
        assert (tmp_path / "certs" / f"{name}.pem").exists(), name
    rendered = usv_deploy("render", str(inventory_path), "--all", "--out", str(tmp_path / "rendered"))
    assert rendered.returncode == 0, rendered.stderr
    assert "warning" not in rendered.stderr                   # the boats' default: mTLS and the ACL
    boat = tmp_path / "rendered" / "1"
    assert "ZENOH_CONFIG=/etc/usv/1/zenoh.json5" in (boat / "usv.env").read_text()
    config = json.loads((boat / "zenoh.json5").read_text())
    assert config["mode"] == "client" and config["connect"]["endpoints"] == ["tls/10.10.0.1:7447"]
    tls = config["transport"]["link"]["tls"]
    assert tls["connect_certificate"] == "/etc/usv/1/certs/vessel-1.pem" and tls["enable_mtls"] is True
    assert tls["root_ca_certificate"] == "/etc/usv/1/certs/ca.pem"
    router = json.loads((tmp_path / "rendered" / "router" / "router.json5").read_text())
    assert router["access_control"]["enabled"] and router["access_control"]["default_permission"] == "deny"
    assert router["listen"]["endpoints"] == ["tls/0.0.0.0:7447"]
    # The router's folder is whole: its certificates beside it, named relative to the file.
    assert router["transport"]["link"]["tls"]["listen_private_key"] == "certs/router-key.pem"
    copied = tmp_path / "rendered" / "router" / "certs"
    assert sorted(p.name for p in copied.iterdir()) == sorted(
        ["ca.pem", "router.pem", "router-key.pem", "operator.pem", "operator-key.pem"])
    assert (copied / "router-key.pem").stat().st_mode & 0o077 == 0
    operator = json.loads((tmp_path / "rendered" / "router" / "operator.json5").read_text())
    assert operator["transport"]["link"]["tls"]["connect_certificate"] == "certs/operator.pem"
    for text in ((boat / "zenoh.json5").read_text(), json.dumps(router), json.dumps(operator)):
        zenoh.Config.from_json5(text)                     # each one is a configuration Zenoh accepts
    # The agent and the driver bridge both read the same Zenoh file through ZENOH_CONFIG.
    agent = NodeSettings.model_validate(yaml.safe_load((boat / "agent.yaml").read_text()))
    assert agent.zenoh.connect == ["tls/10.10.0.1:7447"]


@pytest.mark.slow
def test_render_says_which_router_certificates_it_could_not_find(tmp_path):
    inventory_path = secure_inventory(tmp_path)                       # no certificates made
    rendered = usv_deploy("render", str(inventory_path), "--all", "--out", str(tmp_path / "rendered"))
    assert rendered.returncode == 0, rendered.stderr
    assert "ca.pem, router.pem, router-key.pem, operator.pem, operator-key.pem not found in" in rendered.stderr
    assert str(tmp_path / "rendered" / "router" / "certs") in rendered.stderr
    # Started anyway, the router refuses in one line that names the missing file, without a traceback.
    started = usv_deploy("router", "--config", str(tmp_path / "rendered" / "router" / "router.json5"))
    assert started.returncode == 2 and "Traceback" not in started.stderr
    assert "root_ca_certificate 'certs/ca.pem' is not a file" in started.stderr


@pytest.mark.slow
def test_the_secure_router_and_the_operator_start_from_any_directory(tmp_path):
    """As the systemd unit starts it (working directory /), and with the operator's rendered file from another
    directory: the certificate paths are read from each file's folder, not from where the process runs."""
    pytest.importorskip("cryptography")
    port = free_port()
    inventory_path = secure_inventory(tmp_path / "fleet", port=port, address="127.0.0.1")
    assert usv_deploy("certs", "--inventory", str(inventory_path)).returncode == 0
    rendered = usv_deploy("render", str(inventory_path), "--all", "--out", str(tmp_path / "rendered"))
    assert rendered.returncode == 0 and "warning" not in rendered.stderr, rendered.stderr
    folder = tmp_path / "rendered" / "router"
    router = subprocess.Popen([sys.executable, "-m", "usv_deploy", "router", "--config", str(folder / "router.json5")],
                              cwd="/", stderr=subprocess.PIPE, text=True)
    try:
        assert "usv-router: running" in router.stderr.readline()
        # The operator's station (relative paths, read from its file's folder) and vessel 1 with its own
        # certificate: what the operator says under mission/** reaches the vessel through the router.
        vessel_certs = {"ca": {"cert": str(tmp_path / "fleet" / "certs" / "ca.pem")},
                        "vessel-1": {"cert": str(tmp_path / "fleet" / "certs" / "vessel-1.pem"),
                                     "key": str(tmp_path / "fleet" / "certs" / "vessel-1-key.pem")}}
        vessel = secure_config(vessel_certs, "vessel-1", "client", [], [f"tls/127.0.0.1:{port}"], ["1", "2", "3"])
        with zenoh.open(config_from_file(folder / "operator.json5")) as operator, \
                zenoh.open(zenoh.Config.from_json5(json.dumps(vessel))) as boat:
            got = []
            boat.declare_subscriber("mission/all", lambda sample: got.append(sample.payload.to_bytes()))
            assert wait_until(lambda: operator.put("mission/all", b"hold") or bool(got), timeout=20, interval=0.1)
    finally:
        router.terminate()
        assert router.wait(15) == 0


@pytest.mark.slow
def test_the_router_stops_when_sigterm_reaches_one_of_zenohs_threads(tmp_path):
    """The kernel may hand a process's SIGTERM to any thread; Python runs the handler in the main thread. Here
    the signal is aimed at a thread other than the main one, which is what hung a router in CI: it must still
    stop, and say so."""
    port = free_port()
    script = (
        "import signal, sys, threading\n"
        "from usv_deploy.router import run_router\n"
        "ready = threading.Event()\n"
        "def aim():\n"
        "    ready.wait(30)\n"
        "    signal.pthread_kill(threading.get_ident(), signal.SIGTERM)\n"
        "threading.Thread(target=aim, daemon=True).start()\n"
        f"sys.exit(run_router(None, ['tcp/127.0.0.1:{port}'], ready=ready))\n")
    router = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).resolve().parent.parent,
                            capture_output=True, text=True, timeout=60, check=False)
    assert router.returncode == 0, router.stderr
    assert "usv-router: running" in router.stderr and "usv-router: stopped" in router.stderr


@pytest.mark.slow
def test_render_warns_of_each_device_a_vessel_lacks(tmp_path):
    data = yaml.safe_load((DEPLOY / "fleet.example.yaml").read_text())
    del data["vessels"][1]["devices"]["camera"]
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(data))
    rendered = usv_deploy("render", str(path), "--all", "--out", str(tmp_path / "rendered"))
    assert rendered.returncode == 0, rendered.stderr
    assert "warning: vessel 2 has no camera device: no bearings: it can never see the target" in rendered.stderr
    assert "vessel 1 has no" not in rendered.stderr and "vessel 3 has no" not in rendered.stderr
    one = usv_deploy("render", str(path), "--vessel", "1", "--out", str(tmp_path / "one"))
    assert "device" not in one.stderr                   # only the vessel rendered is spoken of
    # Both examples give every boat the four devices.
    for example in ("fleet.example.yaml", "fleet.shore-router.example.yaml"):
        assert missing_devices(load_inventory(DEPLOY / example)) == [], example
