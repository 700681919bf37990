"""The Zenoh session settings every process of the fleet shares (agents, bridges, launcher, operator tools),
and the session's configuration, made in two layers:

1. the base: the json5 file named by `ZENOH_CONFIG` when it is set (on a boat, the file usv-deploy renders),
   else our settings (the `zenoh` section of the process's YAML);
2. on top, `ZENOH_CONFIG_OVERRIDE`, read as rmw_zenoh reads it: `key/path=json5value` pairs separated by `;`,
   e.g. `mode="client";connect/endpoints=["tcp/10.0.0.2:7447"]`, to change a key or two without a file.
   (A `;` inside a quoted string or brackets belongs to the value: an endpoint's configuration may hold one.)

Certificate and key paths in a file are read relative to the file's own folder (Zenoh itself would read them
relative to the working directory), so a rendered folder can be started from anywhere: `config_from_file`.
A named certificate or key that does not exist is refused before Zenoh sees it.

A bad file or override is a `ConfigError` of one line. Zenoh's own log goes to stderr: errors only, unless
`RUST_LOG` asks for more (`RUST_LOG=zenoh=debug` to debug a boat's link).
"""

from __future__ import annotations

import functools
import json
import os
import re
from typing import Literal

import zenoh
from pydantic import Field

from agent.config import ConfigError, PositiveFloat, StrictModel

FILE_VARIABLE = "ZENOH_CONFIG"
OVERRIDE_VARIABLE = "ZENOH_CONFIG_OVERRIDE"


class ZenohSettings(StrictModel):
    mode: Literal["peer", "client"] = "peer"
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to, e.g. tcp/10.0.0.2:7447")
    listen: list[str] = Field(default_factory=list, description="endpoints to listen on, e.g. tcp/0.0.0.0:7447")
    multicast_scouting: bool = Field(False, description="off by default: explicit endpoints only")
    # A boat's agent may boot before the shore router is up; after the timeout it exits and its service
    # restarts it.
    connect_timeout: PositiveFloat = Field(
        30.0, description="client: seconds to keep trying to reach the router at start-up")


class SessionError(zenoh.ZError):
    """The session could not be opened (an address that cannot be listened on, a router that cannot be
    reached in client mode): one line that says why, without Rust's source locations."""


def open_session(settings: ZenohSettings, wait_for_peers: bool = True) -> zenoh.Session:
    """A Zenoh session configured by `zenoh_config`; SessionError (one line) if Zenoh cannot open it.
    `wait_for_peers=False`: return without waiting to link to the peers gossip names (a tool that must
    answer at once: one frozen peer, which still accepts the TCP connection, would hold it for seconds)."""
    config = zenoh_config(settings)
    if not wait_for_peers:
        config.insert_json5("open/return_conditions/connect_scouted", "false")
    try:
        return zenoh.open(config)
    except zenoh.ZError as error:
        raise SessionError(f"cannot open the Zenoh session: {_reason(error)}") from None


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """The session's zenoh.Config: the ZENOH_CONFIG file or `settings`, then ZENOH_CONFIG_OVERRIDE on top.
    Also starts Zenoh's log, once per process (every session is configured here first)."""
    init_zenoh_log()
    path = os.environ.get(FILE_VARIABLE)
    config = _from_file(path) if path else _from_settings(settings)
    for key, value in override_pairs(os.environ.get(OVERRIDE_VARIABLE, "")):
        try:
            config.insert_json5(key, value)
        except zenoh.ZError as error:
            raise ConfigError(f"{OVERRIDE_VARIABLE}: {key}={value}: {_reason(error)}") from None
    return config


@functools.cache
def init_zenoh_log() -> None:
    """Zenoh's log to stderr: the levels RUST_LOG gives if it is set, else errors only. Zenoh sets its logger
    up once per process, so this runs once (a second call is harmless anyway)."""
    zenoh.init_log_from_env_or("error")


def config_layers(settings_section: str = "the 'zenoh' section") -> list[str]:
    """Where a session's configuration comes from, base first, in words (for --print-config)."""
    path = os.environ.get(FILE_VARIABLE)
    layers = [f"base: the file {FILE_VARIABLE}={path} ({settings_section} is not used)" if path
              else f"base: {settings_section}"]
    pairs = override_pairs(os.environ.get(OVERRIDE_VARIABLE, ""))
    if pairs:
        layers.append(f"then {OVERRIDE_VARIABLE}: " + "; ".join(f"{key}={value}" for key, value in pairs))
    return layers


def override_pairs(text: str) -> list[tuple[str, str]]:
    """The (key path, json5 value) pairs of a ZENOH_CONFIG_OVERRIDE, in order; ConfigError on a part that is
    not `key/path=value`."""
    pairs = []
    for part in _split_outside_values(text):
        if not part.strip():
            continue   # a trailing or doubled ';'
        key, equals, value = part.partition("=")
        if not equals or not key.strip() or not value.strip():
            raise ConfigError(f"{OVERRIDE_VARIABLE}: {part.strip()!r} is not key/path=json5value "
                              "(pairs are separated by ';', e.g. mode=\"client\";scouting/multicast/enabled=false)")
        pairs.append((key.strip(), value.strip()))
    return pairs


def _split_outside_values(text: str) -> list[str]:
    """`text` split at each `;` that is outside quotes and brackets."""
    parts, start, depth, quote, escaped = [], 0, 0, "", False
    for n, char in enumerate(text):
        if escaped:
            escaped = False
        elif quote:
            escaped = char == "\\"
            quote = "" if char == quote else quote
        elif char in "\"'":
            quote = char
        elif char in "[{":
            depth += 1
        elif char in "]}":
            depth = max(0, depth - 1)
        elif char == ";" and depth == 0:
            parts.append(text[start:n])
            start = n + 1
    return [*parts, text[start:]]


TLS_FILES = tuple(f"transport/link/tls/{key}" for key in (
    "root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate", "connect_private_key"))


def config_from_file(path: str | os.PathLike, name: str = FILE_VARIABLE) -> zenoh.Config:
    """A Zenoh configuration file, its TLS file paths made absolute against the file's folder (see above);
    ConfigError of one line, headed `name=path`, if Zenoh refuses the file or a named TLS file is missing."""
    try:
        config = zenoh.Config.from_file(str(path))
    except zenoh.ZError as error:
        raise ConfigError(f"{name}={path}: {_reason(error)}") from None
    folder = os.path.dirname(os.path.abspath(path))
    for key in TLS_FILES:
        value = json.loads(config.get_json(key))
        if not isinstance(value, str) or not value:
            continue
        resolved = os.path.normpath(os.path.join(folder, value))   # an absolute value stays as it is
        if not os.path.isfile(resolved):
            raise ConfigError(f"{name}={path}: {key.rsplit('/', 1)[1]} {value!r} is not a file "
                              f"(looked for {resolved}; relative paths are read from the file's folder)")
        config.insert_json5(key, json.dumps(resolved))
    return config


def _from_file(path: str) -> zenoh.Config:
    return config_from_file(path)


def _from_settings(settings: ZenohSettings) -> zenoh.Config:
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    for field, path, endpoints in (("connect", "connect/endpoints", settings.connect),
                                   ("listen", "listen/endpoints", settings.listen)):
        if endpoints:
            try:
                config.insert_json5(path, json.dumps(endpoints))
            except zenoh.ZError as error:   # a malformed endpoint: one line naming the field, not a traceback
                raise ConfigError(f"zenoh.{field}: {_reason(error)}") from None
    if settings.mode == "client":
        config.insert_json5("connect/timeout_ms", json.dumps(int(settings.connect_timeout * 1000)))
    return config


RUST_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?")   # " at /root/.cargo/.../endpoint.rs:615."


def _reason(error: Exception) -> str:
    """Zenoh's error in one line: what is wrong and where in the json5, without Rust's debug wrapping and
    source location."""
    text = RUST_LOCATION.sub("", str(error))
    inner = re.search(r'msg: "(.*?)", location', text, re.DOTALL) or re.search(r'Str\("(.*?)"\)', text, re.DOTALL)
    if inner:
        text = inner.group(1).replace("\\n", "\n").replace('\\"', '"')
        text = RUST_LOCATION.sub("", text)
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    where = next((line[3:].strip() for line in lines if line.startswith("-->")), None)
    what = next((line[1:].strip() for line in lines if line.startswith("=")), None) or (lines[0] if lines else "?")
    return f"{what} (at {where})" if where else what
