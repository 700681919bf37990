"""The fleet inventory (one YAML for the whole fleet) and the per-vessel configuration rendered from it.

The inventory says which vessels there are, where each is reached, what hardware each has, and how they talk:
- `topology: peer`: the boats' agents and driver bridges are Zenoh peers on the boat LAN, each listening on
  its own address and connecting to every other vessel's explicitly (no multicast scouting);
- `topology: router`: every process is a client of the shore router (`usv-deploy router`), the only
  listener; boats need a route to the shore, not to each other.
With `tls` set, every link is mutual TLS with the fleet's certificates (`usv-deploy certs`) and the router
enforces who may publish what (usv_deploy/security.py); this needs the router topology.

`render(inventory, vessel, out)` writes what one onboard PC needs: `agent.yaml` (NodeSettings), `driver.yaml`
(DriverSettings), `usv.env` (read by the systemd units in deploy/systemd/) and, with TLS, `zenoh.json5`.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import Field, model_validator

from agent.config import InlineOrFile, StrictModel, deep_merge, load_yaml, parse_mapping
from agent.contract import VesselId
from agent.core.params import AgentParams
from agent.shell.settings import NodeSettings
from driver_bridge.node import DriverSettings
from usv_deploy.security import secure_config

# Agent parameters as an overlay: inline or an AgentParams file (relative to the inventory's folder), checked
# as AgentParams when the inventory is read; only the keys it names go over what is beneath it.
AgentOverlay = Annotated[AgentParams, InlineOrFile(AgentParams)]

CONFIG_ROOT = "/etc/usv"          # where the units look for a vessel's files: /etc/usv/<id>/
LOG_ROOT = "/var/log/usv"         # where the agents write their MCAP logs (the units' LogsDirectory)


class Endpoint(StrictModel):
    address: str = Field(description="IP address or host name on the fleet network")
    port: int = Field(7447, ge=1, le=65535)


class Devices(StrictModel):
    """Serial devices of one boat; a missing one leaves that adapter out of the driver bridge."""

    uwb: str | None = None
    odometry: str | None = None
    camera: str | None = None
    thrusters: str | None = None


class Vessel(Endpoint):
    id: VesselId
    devices: Devices = Devices()
    uwb_node: int | None = Field(None, ge=0, le=255, description="this vessel's LinkTrack node id")
    agent: AgentOverlay = Field(AgentParams(), description="agent parameters of this vessel, over the fleet's")
    driver: dict = Field(default_factory=dict, description="driver settings of this vessel, over the fleet's")


class Inventory(StrictModel):
    fleet: str = Field(description="a name for the fleet, used in file names")
    topology: Literal["peer", "router"] = "peer"
    router: Endpoint | None = Field(None, description="the shore router (topology router)")
    operator: Endpoint | None = Field(None, description="the operator's station")
    # On a boat they are installed in /etc/usv/<id>/certs.
    tls: str | None = Field(None, description="folder of the fleet's certificates (usv-deploy certs), relative to "
                            "the inventory's folder")
    vessels: list[Vessel] = Field(min_length=1)
    agent: AgentOverlay = Field(AgentParams(), description="agent parameters (AgentParams) of every vessel")
    driver: dict = Field(default_factory=dict, description="driver settings (DriverSettings) of every vessel")

    @model_validator(mode="after")
    def _consistent(self) -> Inventory:
        ids = [v.id for v in self.vessels]
        if len(set(ids)) != len(ids):
            raise ValueError(f"vessel ids must be unique: {ids}")
        if self.topology == "router" and self.router is None:
            raise ValueError("topology 'router' needs a router: {address, port}")
        if self.tls is not None and self.topology != "router":
            raise ValueError("tls needs topology 'router' (the router checks the certificates and the access rules)")
        return self

    def vessel(self, vessel_id: str) -> Vessel:
        for vessel in self.vessels:
            if vessel.id == vessel_id:
                return vessel
        raise ValueError(f"vessel {vessel_id!r} is not in the inventory (there: {', '.join(v.id for v in self.vessels)})")


# What a vessel cannot do without each device: a render says so for every device left out.
WITHOUT_DEVICE = {
    "uwb": "no ranges: it cannot localise its neighbours",
    "odometry": "no odometry: it cannot localise anything and stands still",
    "camera": "no bearings: it can never see the target and circles nothing",
    "thrusters": "no thrusters: its commands move nothing",
}


def missing_devices(inventory: Inventory) -> list[str]:
    """One line per device a vessel lacks, saying what that vessel then cannot do."""
    return [f"vessel {vessel.id} has no {name} device: {consequence}"
            for vessel in inventory.vessels for name, consequence in WITHOUT_DEVICE.items()
            if getattr(vessel.devices, name) is None]


def load_inventory(path: str | Path) -> Inventory:
    """The inventory in `path`; its `tls` folder made absolute against the inventory's own folder."""
    inventory = load_yaml(Inventory, path)
    if inventory.tls is not None:
        folder = (Path(path).parent / inventory.tls).resolve()
        inventory = inventory.model_copy(update={"tls": str(folder)})
    return inventory


def _zenoh(inventory: Inventory, vessel: Vessel, port_offset: int) -> dict:
    """The Zenoh settings of one of the vessel's processes (agent: offset 0, driver bridge: offset 1)."""
    if inventory.topology == "router":
        scheme = "tls" if inventory.tls else "tcp"
        return {"mode": "client", "connect": [f"{scheme}/{inventory.router.address}:{inventory.router.port}"]}
    # Peers: each process listens on its own port and connects to every other vessel's processes.
    others = [f"tcp/{v.address}:{v.port + k}" for v in inventory.vessels if v.id != vessel.id for k in (0, 1)]
    own_other = [f"tcp/{vessel.address}:{vessel.port + 1 - port_offset}"]
    return {"mode": "peer", "listen": [f"tcp/{vessel.address}:{vessel.port + port_offset}"],
            "connect": others + own_other}


def agent_settings(inventory: Inventory, vessel: Vessel) -> NodeSettings:
    data = {
        "clock": "wall",
        "zenoh": _zenoh(inventory, vessel, 0),
        "log": f"{LOG_ROOT}/agent-{{vessel}}-{{start}}.mcap",
        "agent": deep_merge(inventory.agent.model_dump(exclude_unset=True), vessel.agent.model_dump(exclude_unset=True)),
    }
    return parse_mapping(NodeSettings, data, f"inventory {inventory.fleet}, vessel {vessel.id}, agent")


def driver_settings(inventory: Inventory, vessel: Vessel) -> DriverSettings:
    data = copy.deepcopy(deep_merge(inventory.driver, vessel.driver))   # filled in below: not the inventory's
    data["zenoh"] = _zenoh(inventory, vessel, 1)
    for name, device in vessel.devices.model_dump().items():
        if device is None:
            data.pop(name, None)
        else:
            data.setdefault(name, {})["device"] = device
    if "uwb" in data:
        # The module's node ids: each vessel's `uwb_node`, so the inventory is the one place they are written.
        nodes = {v.uwb_node: v.id for v in inventory.vessels if v.uwb_node is not None and v.id != vessel.id}
        module = data["uwb"].setdefault("module", {})
        module["peers"] = {**nodes, **module.get("peers", {})}
    return parse_mapping(DriverSettings, data, f"inventory {inventory.fleet}, vessel {vessel.id}, driver")


def render(inventory: Inventory, vessel_id: str, out: Path) -> list[Path]:
    """Write one vessel's files into `out`; returns them."""
    vessel = inventory.vessel(vessel_id)
    out.mkdir(parents=True, exist_ok=True)
    folder = f"{CONFIG_ROOT}/{vessel.id}"
    files = {
        "agent.yaml": yaml.safe_dump(agent_settings(inventory, vessel).model_dump(mode="json"), sort_keys=False),
        "driver.yaml": yaml.safe_dump(driver_settings(inventory, vessel).model_dump(mode="json", exclude_none=True),
                                      sort_keys=False),
    }
    environment = [f"USV_VESSEL={vessel.id}", f"USV_FLEET={inventory.fleet}"]
    if inventory.tls:
        certs = {name: {kind: f"{folder}/certs/{Path(path).name}" for kind, path in paths.items()}
                 for name, paths in _certificate_names(vessel.id).items()}
        connect = [f"tls/{inventory.router.address}:{inventory.router.port}"]
        files["zenoh.json5"] = json.dumps(secure_config(certs, f"vessel-{vessel.id}", "client", [], connect,
                                                        [v.id for v in inventory.vessels]), indent=2)
        environment.append(f"ZENOH_CONFIG={folder}/zenoh.json5")
    files["usv.env"] = "\n".join(environment) + "\n"
    written = []
    for name, text in files.items():
        (out / name).write_text(text)
        written.append(out / name)
    return written


def _certificate_names(vessel_id: str) -> dict[str, dict[str, str]]:
    """The certificate files a vessel's PC holds, as `usv-deploy certs` names them."""
    name = f"vessel-{vessel_id}"
    return {"ca": {"cert": "ca.pem"}, name: {"cert": f"{name}.pem", "key": f"{name}-key.pem"}}


ROUTER_CERTS = ("ca.pem", "router.pem", "router-key.pem", "operator.pem", "operator-key.pem")


def render_router(inventory: Inventory, out: Path, certs_dir: str | None = None) -> tuple[Path, list[str]]:
    """The shore router's Zenoh configuration (`usv-deploy router --config`) and, with TLS, the operator's
    (`operator.json5`, for ZENOH_CONFIG on the operator's station). With TLS, the router's and the operator's
    certificates are copied from the inventory's `tls` folder (or `certs_dir`) into `out/certs/`, which both
    files name relative to themselves: the folder is whole, to be copied as it is (to /etc/usv/router/ for the
    systemd unit) and started from any directory. Returns the router's file and the certificates that were
    not found to copy (to be put in `out/certs/` by hand)."""
    if inventory.router is None:
        raise ValueError("the inventory has no router")
    out.mkdir(parents=True, exist_ok=True)
    listen = [f"{'tls' if inventory.tls else 'tcp'}/0.0.0.0:{inventory.router.port}"]
    vessels = [v.id for v in inventory.vessels]
    missing: list[str] = []
    if inventory.tls:
        missing = _copy_certificates(Path(certs_dir or inventory.tls), out / "certs")
        certs = {"ca": {"cert": "certs/ca.pem"}, "router": {"cert": "certs/router.pem", "key": "certs/router-key.pem"}}
        config = secure_config(certs, "router", "router", listen, [], vessels)
        # The operator's station, a client like the boats, with the one certificate that may change the mission.
        operator = {"ca": certs["ca"], "operator": {"cert": "certs/operator.pem", "key": "certs/operator-key.pem"}}
        connect = [f"tls/{inventory.router.address}:{inventory.router.port}"]
        (out / "operator.json5").write_text(json.dumps(
            secure_config(operator, "operator", "client", [], connect, vessels), indent=2))
    else:
        config = {"mode": "router", "listen": {"endpoints": listen}, "scouting": {"multicast": {"enabled": False}}}
    path = out / "router.json5"
    path.write_text(json.dumps(config, indent=2))
    return path, missing


def _copy_certificates(source: Path, target: Path) -> list[str]:
    """Copy the router's and operator's certificates from `source` into `target` (keys readable by the owner
    only); the names not found in `source`."""
    target.mkdir(parents=True, exist_ok=True)
    missing = []
    for name in ROUTER_CERTS:
        if not (source / name).is_file():
            missing.append(name)
            continue
        shutil.copyfile(source / name, target / name)
        if name.endswith("-key.pem"):
            os.chmod(target / name, 0o600)
    return missing
