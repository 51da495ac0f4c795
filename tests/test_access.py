"""The site's access control (common/access.py) enforced by a real ``voxelwatch router --site``
over TLS with mutual authentication, on loopback.

Every host is its own zenoh session with its own certificate: a session's own
puts reach its own subscribers without passing the router, so each check
watches from another host's session. A refusal is judged against a sentinel:
an allowed message sent after the refused one, on the same key, by a host
that may send it; once the sentinel has arrived the refused one never will.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from common import keys
from common.access import site_acl
from common.certs import make_site_certs
from common.site import load_site
from common.transport import site_config
from tests.procs import ROOT, Proc, free_port, wait_for
from tests.tinysite import write_site

DEPLOY = ROOT / "deploy"


@pytest.fixture(scope="module")
def secured(tmp_path_factory):
    """(site, endpoint): a site of three cameras with [zenoh.tls], its certificates, and its router
    running as a ``voxelwatch router --site`` process on a free loopback port."""
    folder = tmp_path_factory.mktemp("secured")
    site_file, _ = write_site(folder)
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    with site_file.open("a") as f:
        f.write(f'\n[zenoh]\nmode = "client"\nconnect = ["{endpoint}"]\n\n'
                '[zenoh.tls]\nca = "certs/ca.pem"\ncerts = "certs"\nreaders = ["reader", "tablet"]\n')
    site = load_site(site_file)
    make_site_certs(folder / "certs", site=site.name, cameras=site.camera_ids, readers=["reader", "tablet"])
    router = Proc("router", [sys.executable, "-c", "import sys; from voxelwatch.cli import main; sys.exit(main())",
                             "router", "--site", str(site_file), "--listen", endpoint],
                  folder / "router.log", env={"PYTHONPATH": str(ROOT)})
    try:
        wait_for(lambda: "listening" in router.output(), 30, "the router", procs=[router])
        assert "access control for c1, c2, c3" in router.output()
        yield site, endpoint
    finally:
        router.stop()


class Host:
    """One host's session (``name``: fusion, a camera id, a reader name) and what it has heard."""

    def __init__(self, site, name: str) -> None:
        self.site = site
        self.session = zenoh.open(site_config(site, host=name))
        self.lock = threading.Lock()
        self.heard: list[tuple[str, bytes]] = []
        self.tokens: list[str] = []
        self._keep: list = []

    def subscribe(self, *key_exprs: str) -> "Host":
        for ke in key_exprs:
            self._keep.append(self.session.declare_subscriber(ke, self._on_sample))
        return self

    def watch_tokens(self, key_expr: str) -> "Host":
        self._keep.append(self.session.liveliness().declare_subscriber(key_expr, self._on_token, history=True))
        return self

    def got(self, key: str, payload: bytes) -> bool:
        with self.lock:
            return (key, payload) in self.heard

    def keys_heard(self) -> set[str]:
        with self.lock:
            return {k for k, _ in self.heard}

    def _on_sample(self, sample) -> None:
        with self.lock:
            self.heard.append((str(sample.key_expr), sample.payload.to_bytes()))

    def _on_token(self, sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            with self.lock:
                self.tokens.append(str(sample.key_expr))

    def close(self) -> None:
        for item in self._keep:
            item.undeclare()
        self.session.close()


@pytest.fixture()
def hosts(secured):
    site, _ = secured
    opened: dict[str, Host] = {}

    def open_as(name: str) -> Host:
        opened[name] = opened.get(name) or Host(site, name)
        return opened[name]

    yield open_as
    for host in opened.values():
        host.close()


def settle() -> None:
    """Declarations travel through the router before the first put counts."""
    time.sleep(0.5)


def refused(offender: Host, key: str, watcher: Host, allowed: Host, what: str) -> None:
    """``offender`` puts on ``key``; ``watcher`` (subscribed to it) hears ``allowed``'s sentinel
    there and never the offender's message."""
    offender.session.put(key, b"forged")
    allowed.session.put(key, b"sentinel")
    wait_for(lambda: watcher.got(key, b"sentinel"), 10, f"the sentinel on {key} ({what})")
    assert not watcher.got(key, b"forged"), f"{what}: the router let a forged message through on {key}"


# ---------------------------------------------------------------- who may connect


def _client(endpoint: str, ca: Path, cert: Path | None = None, key: Path | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    values = {"mode": "client", "connect/endpoints": [endpoint], "scouting/multicast/enabled": False,
              "transport/link/tls/root_ca_certificate": str(ca), "transport/link/tls/enable_mtls": bool(cert)}
    if cert:
        values.update({"transport/link/tls/connect_certificate": str(cert),
                       "transport/link/tls/connect_private_key": str(key)})
    for k, v in values.items():
        conf.insert_json5(k, json.dumps(v))
    return conf


def test_a_client_without_a_certificate_of_the_site_cannot_connect(secured, tmp_path):
    site, endpoint = secured
    ca = site.resolve("certs/ca.pem")
    with pytest.raises(zenoh.ZError):
        zenoh.open(_client(endpoint, ca))
    other = make_site_certs(tmp_path / "other", site="elsewhere", cameras=["c1"])  # same names, another authority
    with pytest.raises(zenoh.ZError):
        zenoh.open(_client(endpoint, ca, other.folder / "fusion.pem", other.folder / "fusion-key.pem"))
    with pytest.raises(zenoh.ZError):
        zenoh.open(_client(f"tcp/127.0.0.1:{endpoint.rsplit(':', 1)[1]}", ca))  # plain TCP: nothing listens
    with zenoh.open(_client(endpoint, ca, site.resolve("certs/fusion.pem"), site.resolve("certs/fusion-key.pem"))):
        pass  # the site's own certificate does


# ---------------------------------------------------------------- a camera


def test_a_camera_publishes_only_its_own_masks_and_token(secured, hosts):
    site, _ = secured
    p = site.prefix
    fusion = hosts("fusion").subscribe(keys.mask_wildcard(p)).watch_tokens(f"{p}/alive/**")
    reader = hosts("reader").subscribe(keys.tracks_key(p), keys.events_wildcard(p), keys.status_key(p))
    cam1, cam2 = hosts("c1"), hosts("c2").subscribe(keys.hold_key(p, "c2"), keys.look_key(p, "c2"))
    settle()
    cam1.session.put(keys.mask_key(p, "c1"), b"mask")
    wait_for(lambda: fusion.got(keys.mask_key(p, "c1"), b"mask"), 10, "camera c1's own mask at the fusion server")
    refused(cam1, keys.mask_key(p, "c2"), fusion, cam2, "a mask in another camera's name")
    for key in (keys.event_key(p, "fall", 1), keys.tracks_key(p), keys.status_key(p)):
        refused(cam1, key, reader, fusion, "a camera publishing what only the fusion server publishes")
    for key in (keys.hold_key(p, "c2"), keys.look_key(p, "c2")):
        refused(cam1, key, cam2, fusion, "a camera sending another camera holds or look requests")
    cam1.session.liveliness().declare_token(keys.alive_fusion_key(p))
    cam1.session.liveliness().declare_token(keys.alive_camera_key(p, "c2"))
    cam1.session.liveliness().declare_token(keys.alive_camera_key(p, "c1"))
    wait_for(lambda: keys.alive_camera_key(p, "c1") in fusion.tokens, 10, "camera c1's own token")
    time.sleep(0.3)
    assert fusion.tokens == [keys.alive_camera_key(p, "c1")], "a camera declared another process's token"


def test_a_camera_hears_only_its_own_holds_and_looks(secured, hosts):
    site, _ = secured
    p = site.prefix
    fusion, reader = hosts("fusion"), hosts("reader").subscribe(keys.events_wildcard(p), keys.tracks_key(p))
    cam1 = hosts("c1").subscribe(keys.hold_key(p, "c1"), keys.look_key(p, "c1"), keys.hold_key(p, "c2"),
                                 keys.mask_wildcard(p), keys.events_wildcard(p), keys.tracks_key(p), keys.status_key(p))
    cam2 = hosts("c2")
    settle()
    for key in (keys.hold_key(p, "c1"), keys.look_key(p, "c1")):
        fusion.session.put(key, b"for c1")
        wait_for(lambda: cam1.got(key, b"for c1"), 10, f"{key} at camera c1")
    fusion.session.put(keys.hold_key(p, "c2"), b"for c2")
    cam2.session.put(keys.mask_key(p, "c2"), b"c2 mask")
    fusion.session.put(keys.event_key(p, "fall", 3), b"event")
    fusion.session.put(keys.tracks_key(p), b"tracks")
    wait_for(lambda: reader.got(keys.tracks_key(p), b"tracks"), 10, "tracks at the reader")
    time.sleep(0.3)
    assert cam1.keys_heard() == {keys.hold_key(p, "c1"), keys.look_key(p, "c1")}


@pytest.mark.parametrize("which", ["history", "ack"])
def test_only_the_fusion_server_answers_the_history_and_acknowledgements(secured, hosts, which):
    site, _ = secured
    p = site.prefix
    fusion, cam1, tablet = hosts("fusion"), hosts("c1"), hosts("tablet")
    declared = f"{keys.history_key(p)}/**" if which == "history" else keys.ack_wildcard(p)
    asked = f"{keys.history_key(p)}/**" if which == "history" else keys.ack_key(p, "17-fall-2")

    def answer(who: str):
        def on_query(query) -> None:
            with query:
                query.reply(str(query.key_expr), who.encode())
        return on_query

    queryables = [fusion.session.declare_queryable(declared, answer("fusion")),
                  cam1.session.declare_queryable(declared, answer("camera")),
                  tablet.session.declare_queryable(declared, answer("reader"))]
    reader = hosts("reader")
    settle()
    replies = [r.ok.payload.to_bytes() for r in reader.session.get(asked, timeout=5) if r.ok]
    assert replies == [b"fusion"]
    assert [r for r in cam1.session.get(asked, timeout=2) if r.ok and
            r.ok.payload.to_bytes() != b"camera"] == [], f"a camera queried {which}"
    for q in queryables:
        q.undeclare()


# ---------------------------------------------------------------- a reader


def test_a_reader_subscribes_and_queries_but_publishes_nothing(secured, hosts):
    site, _ = secured
    p = site.prefix
    fusion = hosts("fusion").subscribe(keys.mask_wildcard(p))
    tablet = hosts("tablet").subscribe(keys.tracks_key(p), keys.events_wildcard(p), keys.status_key(p))
    cam1 = hosts("c1").subscribe(keys.hold_key(p, "c1"), keys.look_key(p, "c1"))
    reader = hosts("reader").subscribe(keys.mask_wildcard(p), keys.hold_key(p, "c1"))
    settle()
    for key in (keys.event_key(p, "fall", 2), keys.tracks_key(p), keys.status_key(p)):
        refused(reader, key, tablet, fusion, "a reader publishing")
    for key in (keys.hold_key(p, "c1"), keys.look_key(p, "c1")):
        refused(reader, key, cam1, fusion, "a reader sending a camera holds")
    refused(reader, keys.mask_key(p, "c1"), fusion, cam1, "a reader forging a mask")
    tablet.watch_tokens(f"{p}/alive/**")
    reader.session.liveliness().declare_token(keys.alive_camera_key(p, "c3"))
    time.sleep(0.5)
    fusion.session.liveliness().declare_token(keys.alive_fusion_key(p))
    wait_for(lambda: keys.alive_fusion_key(p) in tablet.tokens, 10, "the fusion server's token at a reader")
    time.sleep(0.3)
    assert keys.alive_camera_key(p, "c3") not in tablet.tokens, "a reader declared a camera's token"
    # a reader sees the masks (the installer's page draws them), never a camera's holds (its own forged
    # puts reach only its own subscribers, inside its session)
    assert sorted({h for h in reader.heard if h[1] != b"forged"}) == [(keys.mask_key(p, "c1"), b"sentinel")]


# ---------------------------------------------------------------- the generated rules


def test_the_rules_name_every_camera_and_deny_the_rest(secured):
    site, _ = secured
    acl = site_acl(site.prefix, site.camera_ids, readers=["reader", "tablet"])
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert all(r["permission"] == "allow" for r in acl["rules"])
    names = {n for s in acl["subjects"] for n in s["cert_common_names"]}
    assert names == {"fusion", "camera-c1", "camera-c2", "camera-c3", "reader-reader", "reader-tablet"}
    rule_ids = {r["id"] for r in acl["rules"]}
    assert all(set(pol["rules"]) <= rule_ids for pol in acl["policies"])
    cam_rules = [r for r in acl["rules"] if r["id"].startswith("camera c2 ") and "ingress" in r["flows"]]
    assert {ke for r in cam_rules for ke in r["key_exprs"]} == {
        keys.mask_key(site.prefix, "c2"), keys.alive_camera_key(site.prefix, "c2"),
        keys.hold_key(site.prefix, "c2"), keys.look_key(site.prefix, "c2")}
    with pytest.raises(ValueError):
        site_acl(site.prefix, ["c/1"])


# ---------------------------------------------------------------- a stock zenoh program


def test_a_plain_zenoh_session_from_deploy_reader_json5_reads_an_event(secured, hosts, monkeypatch):
    """deploy/zenoh/reader.json5 as written (certificate paths relative to the working folder),
    only the endpoint changed: zenoh.open with it hears an event the fusion server publishes."""
    site, endpoint = secured
    fusion = hosts("fusion")
    monkeypatch.chdir(site.base_dir)  # where certs/ lies, as the file expects
    conf = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "reader.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    heard: list[tuple[str, str]] = []
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(keys.events_wildcard(site.prefix),
                                         lambda s: heard.append((str(s.key_expr), s.payload.to_string())))
        settle()
        event = '{"v":1,"type":"event","kind":"fall","track":4}'
        pub = fusion.session.declare_publisher(keys.event_key(site.prefix, "fall", 4))
        settle()
        pub.put(event)
        wait_for(lambda: heard, 10, "the event at the stock reader")
        assert heard == [(keys.event_key(site.prefix, "fall", 4), event)]
        pub.undeclare()
        sub.undeclare()
    assert os.path.isfile("certs/reader.pem")


# ---------------------------------------------------------------- peer mode


def test_peers_of_a_secured_site_authenticate_each_other_without_a_router(secured, tmp_path):
    """Peer mode: the fusion host listens over TLS, a camera connects to it with its certificate.
    (No router: nothing enforces the access control; voxelwatch site check warns.)"""
    site, _ = secured
    peer_site = site.model_copy(update={"zenoh": site.zenoh.model_copy(update={"mode": "peer", "connect": []})})
    endpoint = f"tls/localhost:{free_port()}"
    heard: list[str] = []
    with zenoh.open(site_config(peer_site, host="fusion", listen=[endpoint])) as fusion, \
            zenoh.open(site_config(peer_site, host="c1", connect=[endpoint])) as cam:
        sub = fusion.declare_subscriber(keys.mask_wildcard(site.prefix), lambda s: heard.append(str(s.key_expr)))
        settle()
        cam.put(keys.mask_key(site.prefix, "c1"), b"mask")
        wait_for(lambda: heard, 10, "a mask between two peers over TLS")
        sub.undeclare()
