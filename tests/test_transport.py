"""Zenoh configs: every process's settings come from common.transport, as they were written by hand before."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from common.site import ZenohSettings
from common.transport import TransportError, check_endpoint, open_session, private_config, watch_links, zenoh_config

ROOT = Path(__file__).resolve().parents[1]


def _by_hand(values: dict) -> zenoh.Config:
    conf = zenoh.Config()
    for key, value in values.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


@pytest.mark.parametrize("multicast", [False, True])
def test_router_config_is_the_routers_settings(multicast: bool) -> None:
    conf = zenoh_config(ZenohSettings(multicast_scouting=multicast), mode="router", listen=["tcp/0.0.0.0:7447"])
    assert str(conf) == str(_by_hand({"mode": "router", "listen/endpoints": ["tcp/0.0.0.0:7447"],
                                      "scouting/multicast/enabled": multicast,
                                      "transport/shared_memory/enabled": False}))


def test_default_settings_keep_scouting_and_shared_memory_off() -> None:
    conf = zenoh_config(mode="router", listen=["tcp/127.0.0.1:7000"])
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7000"]


def test_a_client_waits_for_its_router() -> None:
    conf = zenoh_config(mode="client", connect=["tcp/127.0.0.1:7000"])
    assert json.loads(conf.get_json("connect/timeout_ms")) == -1


def test_private_config_turns_off_scouting_and_shared_memory_only() -> None:
    assert str(private_config()) == str(_by_hand({"scouting/multicast/enabled": False,
                                                  "transport/shared_memory/enabled": False}))
    assert json.loads(private_config().get_json("connect/endpoints")) == []


@pytest.mark.parametrize("kwargs, name", [({"mode": "bogus"}, "mode"), ({"listen": ["nowhere"]}, "listen/endpoints")])
def test_a_refused_value_names_the_setting(kwargs: dict, name: str) -> None:
    with pytest.raises(TransportError, match=f"zenoh setting {name} = "):
        zenoh_config(**kwargs)
    assert issubclass(TransportError, ValueError)


@pytest.mark.parametrize("endpoint, listen, problem", [
    ("tpc/127.0.0.1:7447", False, "unknown protocol 'tpc'"),
    ("tcp/127.0.0.1", False, "host:port"),
    ("tcp/127.0.0.1:70000", False, "port 70000"),
    ("tcp/127.0.0.1:0", False, "port 0"),
    ("127.0.0.1:7447", False, "protocol/address"),
    ("tcp/" + "h" * 5000 + ":1:2", False, "host:port"),
])
def test_a_malformed_endpoint_is_named_before_zenoh_sees_it(endpoint, listen, problem) -> None:
    with pytest.raises(ValueError, match=problem) as refused:
        check_endpoint(endpoint, listen=listen)
    assert len(str(refused.value)) < 300
    key = "listen" if listen else "connect"
    with pytest.raises(TransportError, match=f"zenoh setting {key}/endpoints = .*{problem}"):
        zenoh_config(**{key: [endpoint]})


@pytest.mark.parametrize("endpoint", ["tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/router.invalid:7447",
                                      "tcp/127.0.0.1:7447#iface=lo", "unixsock-stream//tmp/zenoh.sock"])
def test_usable_endpoints_pass(endpoint) -> None:
    assert check_endpoint(endpoint) == endpoint
    assert check_endpoint("tcp/0.0.0.0:0", listen=True) == "tcp/0.0.0.0:0"


def _port_in_use() -> tuple[socket.socket, int]:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    return s, s.getsockname()[1]


def test_open_session_retries_an_absent_router_until_stopped_and_refuses_a_busy_port(caplog) -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    stop = threading.Event()
    timer = threading.Timer(2.5, stop.set)
    timer.start()
    began = time.monotonic()
    session = open_session(lambda: zenoh_config(mode="client", connect=[endpoint], connect_timeout_ms=300), stop,
                           who="test", endpoints=[endpoint], backoff_s=0.2)
    assert session is None and time.monotonic() - began < 3.5
    assert sum("cannot reach zenoh" in r.getMessage() for r in caplog.records) == 1
    busy, port = _port_in_use()
    with busy, pytest.raises(TransportError, match="cannot listen"):
        open_session(lambda: zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]), threading.Event(),
                     who="test")


def test_router_on_a_busy_port_is_one_clear_line() -> None:
    busy, port = _port_in_use()
    with busy:
        result = subprocess.run([sys.executable, "-c", "import sys; from common.cli import main; sys.exit(main())",
                                 "router", "--listen", f"tcp/127.0.0.1:{port}"], cwd=ROOT, capture_output=True,
                                text=True, timeout=60)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 1 and len(lines) == 1, result.stderr
    assert f"tcp/127.0.0.1:{port}" in lines[0] and "Address already in use" in lines[0] and ".rs:" not in lines[0]


def _messages(caplog, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if text in r.getMessage()]


def test_a_session_that_loses_its_router_says_so_once_and_when_it_is_back(caplog) -> None:
    import logging

    caplog.set_level(logging.INFO)
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    router = zenoh.open(zenoh_config(mode="router", listen=[endpoint]))
    stop = threading.Event()
    client = open_session(lambda: zenoh_config(mode="client", connect=[endpoint], connect_timeout_ms=1000), stop,
                          who="test", endpoints=[endpoint])
    try:
        watch_links(client, stop, who="test", endpoints=[endpoint], after_s=0.2, period_s=0.2)
        time.sleep(1.0)
        assert _messages(caplog, "no zenoh link") == []
        router.close()
        deadline = time.monotonic() + 10
        while not _messages(caplog, "no zenoh link") and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.0)
        assert _messages(caplog, "no zenoh link") == [f"test: no zenoh link to {endpoint} "
                                                      "(zenoh keeps trying in the background)"]
        router = zenoh.open(zenoh_config(mode="router", listen=[endpoint]))
        deadline = time.monotonic() + 20
        while not _messages(caplog, "is back") and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _messages(caplog, "is back") == [f"test: zenoh link to {endpoint} is back"]
    finally:
        stop.set()
        client.close()
        router.close()
