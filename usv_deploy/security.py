"""Zenoh configuration for a fleet that only trusts its own certificates.

Every link is mutual TLS against the fleet's CA (see usv_deploy.certs): a process without a certificate
signed by that CA cannot even open a session with the router. On top of that the router runs Zenoh's
access control, which denies everything by default and recognises each client by its certificate's common
name, so that a boat can speak only for itself (`usv/<id>/**`) and only the operator can change the
mission (`mission/**`).

The functions are pure: they return plain dicts that dump to JSON (a subset of JSON5), either whole for
`zenoh.Config.from_json5` or a config file given to `ZENOH_CONFIG`, or piecewise for
`zenoh.Config.insert_json5(path, json.dumps(value))`. Key names are those of zenoh 1.x.

Access control is enforced where the router forwards messages, on the transport of each client, in two
directions: `ingress` is what a client sends to the router, `egress` what the router sends to a client. A
client must therefore be allowed both to declare its subscriber (ingress) and to be sent the samples and
liveliness tokens that match it (egress). A message is allowed only if some allow rule's key expression
includes the message's whole key expression.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from agent.contract import VESSEL_ID_PATTERN

VESSEL_ID = re.compile(VESSEL_ID_PATTERN)
# What every boat may listen to: its fleet mates, the simulator (in trials) and the operator's mission.
FLEET_TOPICS = ["usv/**", "sim/**", "mission/**"]
MISSION_TOPICS = ["mission/**"]
# Declaring interest and receiving what matches it; liveliness queries are answered with tokens.
LISTEN = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
RECEIVE = ["put", "delete", "liveliness_token"]


def check_vessel_id(vessel: str) -> str:
    """The id, or ValueError: it becomes part of a key expression and of a certificate's name."""
    if not isinstance(vessel, str) or not VESSEL_ID.fullmatch(vessel):
        raise ValueError(f"bad vessel id {vessel!r}: expected 1 to 32 of A-Z a-z 0-9 _ -")
    return vessel


def check_name(name: str, what: str) -> str:
    """A certificate name (operator, router) or ValueError: it is also a file name and an ACL subject."""
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.-]{1,64}", name) or name.startswith("."):
        raise ValueError(f"bad {what} name {name!r}: expected 1 to 64 of A-Z a-z 0-9 _ . - (not starting with .)")
    return name


def vessel_subject(vessel: str) -> str:
    """The common name of a vessel's certificate, which is how the router's ACL knows the vessel."""
    return f"vessel-{check_vessel_id(vessel)}"


def tls_settings(certs: Mapping, name: str, listen: bool) -> dict:
    """The `transport/link/tls` section for process `name` (a key of `certs`, as make_certificates returns).

    Both sides check the other's certificate against the fleet CA (mutual TLS). A listener presents its
    certificate as a server, a connector as a client; the server name is checked against the router's
    subjectAltNames (zenoh's default), so connect to a host the router's certificate names.
    """
    own = certs[name]
    role = "listen" if listen else "connect"
    return {
        "root_ca_certificate": str(certs["ca"]["cert"]),
        "enable_mtls": True,
        f"{role}_certificate": str(own["cert"]),
        f"{role}_private_key": str(own["key"]),
    }


def _rule(rule_id: str, messages: list[str], flow: str, key_exprs: list[str]) -> dict:
    return {"id": rule_id, "messages": list(messages), "flows": [flow], "permission": "allow",
            "key_exprs": list(key_exprs)}


def _vessel_rules(vessel: str) -> list[dict]:
    """What one boat may send: samples and its liveliness token under its own key space, nothing else."""
    own = [f"usv/{vessel}/**"]
    return [
        _rule(f"publish-{vessel}", ["put", "delete"], "ingress", own),
        _rule(f"token-{vessel}", ["liveliness_token"], "ingress", own),
    ]


def _fleet_rules() -> list[dict]:
    """What every boat may listen to, in both directions (its declarations in, the matching data out)."""
    return [
        _rule("fleet-listen", LISTEN, "ingress", FLEET_TOPICS),
        _rule("fleet-receive", RECEIVE, "egress", FLEET_TOPICS),
        # The router tells a client where subscribers are so that the client sends only what someone
        # wants (write-side filtering); without this a boat's own publications would stay on the boat.
        _rule("fleet-see-subscribers", ["declare_subscriber"], "egress", ["**"]),
    ]


def _operator_rules() -> list[dict]:
    """The operator publishes the mission and may watch everything."""
    return [
        _rule("operator-publish", ["put", "delete"], "ingress", MISSION_TOPICS),
        _rule("operator-listen", LISTEN, "ingress", ["**"]),
        _rule("operator-receive", RECEIVE + ["declare_subscriber"], "egress", ["**"]),
    ]


def access_control(vessels: list[str], operator: str = "operator") -> dict:
    """The router's `access_control` section: deny by default, allow each vessel and the operator their part.

    Subjects are matched by certificate common name (`vessel-<id>`, `operator`), so it only works on a router
    whose links are TLS with mutual authentication. A client whose name is not listed gets nothing through.
    """
    vessels = [check_vessel_id(v) for v in vessels]
    if len(set(vessels)) != len(vessels):
        raise ValueError(f"vessel ids must be unique: {vessels}")  # rule and subject ids would clash
    check_name(operator, "operator")
    subjects = [{"id": f"cn-{vessel_subject(v)}", "cert_common_names": [vessel_subject(v)]} for v in vessels]
    subjects.append({"id": f"cn-{operator}", "cert_common_names": [operator]})
    rules = _fleet_rules() + _operator_rules()
    policies = [{"id": "operator", "rules": [r["id"] for r in _operator_rules()], "subjects": [f"cn-{operator}"]}]
    fleet_rule_ids = [r["id"] for r in _fleet_rules()]
    for vessel in vessels:
        own = _vessel_rules(vessel)
        rules += own
        policies.append({"id": vessel_subject(vessel), "rules": [r["id"] for r in own] + fleet_rule_ids,
                         "subjects": [f"cn-{vessel_subject(vessel)}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def secure_config(certs: Mapping, name: str, role: str, listen: list[str], connect: list[str],
                  vessels: list[str], operator: str = "operator") -> dict:
    """A complete zenoh config for the router (`role="router"`: TLS listener plus the ACL) or a client.

    Endpoints must be `tls/host:port`; multicast scouting is off (boats reach the router by its address
    only, and a scouted plain-TCP peer must never be able to join). A router that also connects out (to
    another router) gets its connect settings too, but note that the router's certificate is a server
    certificate only.
    """
    # Only routers and clients: peers would find and link to each other directly, where the router's
    # access control cannot see their traffic.
    if role not in ("router", "client"):
        raise ValueError(f"role must be router or client, not {role!r}")
    for endpoint in [*listen, *connect]:
        if not endpoint.startswith("tls/"):
            raise ValueError(f"endpoint {endpoint!r} is not TLS (tls/host:port)")
    if role == "client" and listen:
        raise ValueError("a client does not listen")
    tls: dict = {}
    if listen:
        tls.update(tls_settings(certs, name, listen=True))
    if connect:
        tls.update(tls_settings(certs, name, listen=False))
    config: dict = {
        "mode": role,
        "scouting": {"multicast": {"enabled": False}},
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect)},
        "transport": {"link": {"tls": tls}},
    }
    if role == "router":
        config["access_control"] = access_control(vessels, operator)
    return config
