"""Zenoh configuration in layers: the ZENOH_CONFIG file (or our settings), then ZENOH_CONFIG_OVERRIDE on top."""

from __future__ import annotations

import json
import time

import pytest

zenoh = pytest.importorskip("zenoh")

from conftest import free_ports

from agent.config import ConfigError
from agent.runtime.process import print_config
from agent.runtime.zenoh_session import (
    ZenohSettings,
    config_layers,
    init_zenoh_log,
    open_session,
    override_pairs,
    zenoh_config,
)


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch):
    """The caller's own Zenoh variables must not leak into these tests."""
    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
    monkeypatch.delenv("ZENOH_CONFIG_OVERRIDE", raising=False)


def value(config, key: str):
    return json.loads(config.get_json(key))


def test_the_override_changes_a_key_on_top_of_the_file_and_keeps_the_rest(tmp_path, monkeypatch):
    path = tmp_path / "zenoh.json5"
    path.write_text('{mode: "peer", listen: {endpoints: ["tcp/127.0.0.1:7447"]}, scouting: {multicast: {enabled: false}}}')
    monkeypatch.setenv("ZENOH_CONFIG", str(path))
    assert value(zenoh_config(ZenohSettings()), "mode") == "peer"
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", 'mode="client";connect/endpoints=["tcp/10.0.0.2:7447"];')
    config = zenoh_config(ZenohSettings(mode="peer", listen=["tcp/127.0.0.1:9999"]))
    assert value(config, "mode") == "client"
    assert value(config, "connect/endpoints") == ["tcp/10.0.0.2:7447"]
    # The file is the base: its keys stay, and the settings' section is not used at all.
    assert value(config, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert value(config, "scouting/multicast/enabled") is False


def test_without_a_file_the_override_goes_on_top_of_our_settings(monkeypatch):
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", "scouting/multicast/enabled=true")
    config = zenoh_config(ZenohSettings(listen=["tcp/127.0.0.1:9999"]))
    assert value(config, "scouting/multicast/enabled") is True
    assert value(config, "listen/endpoints") == ["tcp/127.0.0.1:9999"]


def test_a_semicolon_inside_a_quoted_value_belongs_to_the_value():
    assert override_pairs('connect/endpoints=["tls/a:7447#x=1;y=2"]; mode = "client" ;;') == [
        ("connect/endpoints", '["tls/a:7447#x=1;y=2"]'), ("mode", '"client"')]


@pytest.mark.parametrize("override, says", [
    ("modeclient", "is not key/path=json5value"),
    ("=\"client\"", "is not key/path=json5value"),
    ("mode=", "is not key/path=json5value"),
    ("mode=client", "expected array, boolean, null, number, object, or string"),   # json5 strings are quoted
    ('mode="clientx"', "unknown variant `clientx`"),
    ("no/such/key=1", "unknown key"),
])
def test_a_malformed_override_is_one_line_naming_the_variable(monkeypatch, override, says):
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", f'listen/endpoints=["tcp/127.0.0.1:1"];{override}')
    with pytest.raises(ConfigError) as raised:
        zenoh_config(ZenohSettings())
    message = str(raised.value)
    assert message.startswith("ZENOH_CONFIG_OVERRIDE: ") and says in message
    assert "\n" not in message and ".rs:" not in message     # no Rust location or multi-line parser dump


def test_a_bad_config_file_is_one_line_naming_it(tmp_path, monkeypatch):
    path = tmp_path / "zenoh.json5"
    path.write_text('{mode: "peer", listen: ')
    monkeypatch.setenv("ZENOH_CONFIG", str(path))
    with pytest.raises(ConfigError, match=f"^ZENOH_CONFIG={path}: ") as raised:
        zenoh_config(ZenohSettings())
    assert "\n" not in str(raised.value)
    monkeypatch.setenv("ZENOH_CONFIG", str(tmp_path / "missing.json5"))
    with pytest.raises(ConfigError, match="No such file"):
        zenoh_config(ZenohSettings())


def test_print_config_names_the_layers(tmp_path, monkeypatch, capsys):
    print_config("usv-agent --vessel 1", ZenohSettings())
    assert "# Zenoh base: the 'zenoh' section below" in capsys.readouterr().out
    monkeypatch.setenv("ZENOH_CONFIG", str(tmp_path / "boat.json5"))
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", 'mode="client"')
    print_config("usv-agent --vessel 1", ZenohSettings())
    shown = capsys.readouterr().out
    assert f"# Zenoh base: the file ZENOH_CONFIG={tmp_path / 'boat.json5'} (the 'zenoh' section below is not used)" in shown
    assert '# Zenoh then ZENOH_CONFIG_OVERRIDE: mode="client"' in shown
    assert config_layers()[0].startswith("base: the file ZENOH_CONFIG=")


def test_zenoh_log_set_up_twice_is_harmless():
    init_zenoh_log()
    init_zenoh_log()
    zenoh.init_log_from_env_or("error")    # Zenoh's own call is idempotent too, whoever called it first


def test_a_real_session_runs_with_the_override_applied(monkeypatch):
    # The settings listen on one port, the override moves the session to another: a peer that connects to
    # the overridden port finds the session there.
    settings_port, override_port = free_ports(2)
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", f'listen/endpoints=["tcp/127.0.0.1:{override_port}"]')
    with open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{settings_port}"])) as session:
        monkeypatch.delenv("ZENOH_CONFIG_OVERRIDE")
        with open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{override_port}"])) as peer:
            deadline = time.monotonic() + 10
            while session.info.zid() not in list(peer.info.peers_zid()) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert session.info.zid() in list(peer.info.peers_zid())
