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
from common.transport import (MAX_ZENOH_MESSAGE_BYTES, TransportError, check_endpoint, open_session, private_config,
                              watch_links, zenoh_config)

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
                                      "transport/shared_memory/enabled": False,
                                      "transport/link/rx/max_message_size": MAX_ZENOH_MESSAGE_BYTES}))


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
        result = subprocess.run([sys.executable, "-c", "import sys; from voxelwatch.cli import main; sys.exit(main())",
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
# ---------------------------------------------------------------- zenoh's own settings and TLS from the site


def _site(tmp_path, zenoh_text: str):
    from common.site import load_site
    from tests.tinysite import write_site

    site_file, _ = write_site(tmp_path)
    with site_file.open("a") as f:
        f.write("\n" + zenoh_text)
    return load_site(site_file)


def test_config_file_first_site_fields_over_it_settings_last(tmp_path) -> None:
    (tmp_path / "zenoh.json5").write_text('{ mode: "router", transport: { link: { tx: { lease: 12000 } } },'
                                          ' queries_default_timeout: 7000 }')
    site = _site(tmp_path, '[zenoh]\nmode = "client"\nconfig = "zenoh.json5"\n'
                           '[zenoh.settings]\n"transport/link/tx/lease" = 15000\n'
                           '[zenoh.settings.transport.link.tx]\nkeep_alive = 3\n')
    from common.transport import site_config

    conf = site_config(site, host=None)
    assert json.loads(conf.get_json("mode")) == "client"  # the site's field over the file
    assert json.loads(conf.get_json("queries_default_timeout")) == 7000  # the file's own setting kept
    assert json.loads(conf.get_json("transport/link/tx/lease")) == 15000  # settings last
    assert json.loads(conf.get_json("transport/link/tx/keep_alive")) == 3  # nested tables too


def test_a_setting_zenoh_refuses_and_a_missing_config_file_are_named(tmp_path) -> None:
    from common.transport import site_config

    with pytest.raises(TransportError, match="transport/link/tx/no_such_key"):
        site_config(_site(tmp_path, '[zenoh]\nsettings = {"transport/link/tx/no_such_key" = 1}\n'), host=None)
    (tmp_path / "b").mkdir()
    with pytest.raises(TransportError, match="config.*nowhere.json5.*not found"):
        site_config(_site(tmp_path / "b", '[zenoh]\nconfig = "nowhere.json5"\n'), host=None)


def test_tls_picks_this_hosts_certificate_by_name_and_the_router_gets_the_access_control(tmp_path) -> None:
    from common.certs import make_site_certs
    from common.transport import site_config

    site = _site(tmp_path, '[zenoh]\nmode = "client"\nconnect = ["tls/localhost:7447"]\n'
                           '[zenoh.tls]\nca = "certs/ca.pem"\ncerts = "certs"\n')
    make_site_certs(tmp_path / "certs", site=site.name, cameras=site.camera_ids)
    conf = site_config(site, host="c2")
    tls = json.loads(conf.get_json("transport/link/tls"))
    assert tls["root_ca_certificate"] == str(tmp_path / "certs" / "ca.pem")
    assert tls["enable_mtls"] is True
    assert tls["connect_certificate"] == str(tmp_path / "certs" / "c2.pem")
    assert tls["connect_private_key"] == str(tmp_path / "certs" / "c2-key.pem")
    assert json.loads(conf.get_json("access_control/enabled")) is False  # a client enforces nothing
    router = site_config(site, host="router", mode="router", listen=["tls/localhost:7447"], connect=[])
    acl = json.loads(router.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert json.loads(router.get_json("transport/link/tls/listen_certificate")) == str(tmp_path / "certs" / "router.pem")
    given = site_config(site, host="c2", tls_cert=tmp_path / "certs" / "c1.pem", tls_key=tmp_path / "certs" / "c1-key.pem")
    assert json.loads(given.get_json("transport/link/tls/connect_certificate")) == str(tmp_path / "certs" / "c1.pem")
    with pytest.raises(TransportError, match="this host's certificate: .*c9.pem not found.*voxelwatch certs"):
        site_config(site, host="c9")
    with pytest.raises(TransportError, match="both --tls-cert and --tls-key"):
        site_config(site, host="c2", tls_cert=tmp_path / "certs" / "c1.pem")


def test_tls_options_without_a_tls_section_are_refused(tmp_path) -> None:
    from common.transport import site_config

    with pytest.raises(TransportError, match=r"\[zenoh.tls\]"):
        site_config(_site(tmp_path, '[zenoh]\nmode = "client"\n'), host="c1", tls_cert="a.pem", tls_key="b.pem")


@pytest.mark.parametrize("zenoh_text, warnings", [
    ('[zenoh]\nmode = "client"\nconnect = ["tcp/fusion.local:7447"]\n', ["plain TCP"]),
    ('[zenoh]\nmode = "client"\nconnect = ["tls/fusion.local:7447"]\n[zenoh.tls]\nca = "certs/ca.pem"\n', []),
    ('[zenoh]\nmode = "client"\nconnect = ["tcp/fusion.local:7447"]\n[zenoh.tls]\nca = "certs/ca.pem"\n',
     ["without TLS: tcp/fusion.local:7447"]),
    ('[zenoh]\nmode = "peer"\nlisten = ["tls/0.0.0.0:7447"]\n[zenoh.tls]\nca = "certs/ca.pem"\n', ["peer mode"]),
])
def test_site_check_warns_about_plain_transport(tmp_path, capsys, zenoh_text, warnings) -> None:
    from common.certs import make_site_certs
    from voxelwatch.cli import main

    site = _site(tmp_path, zenoh_text)
    make_site_certs(tmp_path / "certs", site=site.name, cameras=site.camera_ids)
    assert main(["site", "check", str(site.base_dir / "site.toml")]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "WARNING" in line]
    assert len(lines) == len(warnings), lines
    for line, warning in zip(lines, warnings):
        assert warning in line


def test_camera_and_fusion_commands_take_their_certificate_from_the_site_or_the_command_line(tmp_path) -> None:
    from camera_worker import cli as camera_cli
    from common.certs import make_site_certs
    from fusion_server import cli as fusion_cli

    site = _site(tmp_path, '[zenoh]\nmode = "client"\nconnect = ["tls/localhost:7447"]\n'
                           '[zenoh.tls]\nca = "certs/ca.pem"\ncerts = "certs"\n')
    certs = tmp_path / "certs"
    make_site_certs(certs, site=site.name, cameras=site.camera_ids)
    site_file = str(site.base_dir / "site.toml")
    text = Path(site_file).read_text()
    Path(site_file).write_text(text.replace('fps = 30.0\n', 'fps = 30.0\nresolution = [160, 120]\n'))  # the worker needs it

    def camera_cert(*extra: str) -> str:
        args = camera_cli.build_parser().parse_args(["--site", site_file, "--camera", "c3", "--source", "synthetic:demo", *extra])
        _, make_config, _ = camera_cli._configure(args)
        return json.loads(make_config().get_json("transport/link/tls/connect_certificate"))

    assert camera_cert() == str(certs / "c3.pem")
    assert camera_cert("--tls-cert", str(certs / "c1.pem"), "--tls-key", str(certs / "c1-key.pem")) == str(certs / "c1.pem")
    args = fusion_cli.build_parser().parse_args(["--site", site_file, "--tls-cert", str(certs / "fusion.pem"),
                                                 "--tls-key", str(certs / "fusion-key.pem")])
    settings = fusion_cli.settings_from_args(args)
    assert (settings.tls_cert, settings.tls_key) == (certs / "fusion.pem", certs / "fusion-key.pem")


def test_router_of_a_secured_site_without_its_certificate_stops_with_the_path(tmp_path, capsys) -> None:
    from voxelwatch.cli import main

    site = _site(tmp_path, '[zenoh]\nmode = "client"\n[zenoh.tls]\nca = "certs/ca.pem"\ncerts = "certs"\n')
    assert main(["router", "--site", str(site.base_dir / "site.toml"), "--listen", "tls/localhost:1"]) == 2
    err = capsys.readouterr().err
    assert "voxelwatch router: [zenoh.tls] ca:" in err and str(tmp_path / "certs" / "ca.pem") in err
    assert main(["router", "--tls-cert", "a.pem", "--tls-key", "b.pem"]) == 2
    assert "need --site" in capsys.readouterr().err


def test_a_site_with_tls_and_zenoh_settings_is_written_and_read_back_unchanged(tmp_path) -> None:
    from common.site import load_site, write_site

    site = _site(tmp_path, '[zenoh]\nmode = "client"\nconnect = ["tls/fusion.local:7447"]\n'
                           '[zenoh.settings]\n"transport/link/tx/lease" = 15000\n'
                           '[zenoh.tls]\nca = "certs/ca.pem"\nreaders = ["reader", "tablet"]\naccess_control = false\n')
    again = load_site(write_site(site, tmp_path / "copy" / "site.toml"))
    assert again.zenoh == site.zenoh
