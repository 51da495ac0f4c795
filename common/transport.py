"""Zenoh session configuration from the site's ``[zenoh]`` section, and opening a session.

The only module besides the process adapters that imports zenoh. Shared
memory is off unless asked for (bursts were lost with it on), multicast
scouting is off unless asked for (sites without multicast, tests).

Endpoints are checked before zenoh sees them (:func:`check_endpoint`): a
mistyped one stops start-up with one line naming it. :func:`open_session`
opens a session the way every long-running process should: a router that
is not there yet (unreachable, down, or a name that does not resolve) is
one warning line, then retried with back-off while the process still stops
within a second or so of SIGINT/SIGTERM; a port that cannot be listened on
is one clear error. :func:`watch_links` says, once each way, when an open
session loses its last zenoh link and when it has one again.

zenoh's limit on one message is set to :data:`MAX_ZENOH_MESSAGE_BYTES`.

Layers, later ones winning: the ``config`` file (zenoh's own JSON5), the
message size limit, the section's fields and the command line, TLS from
``[zenoh.tls]`` (this host's certificate chosen by its name: ``router``,
``fusion`` or the camera id), the site's access control on a router, and last
the ``settings`` table.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from common.messages import MAX_MESSAGE_BYTES
from common.site import ZenohSettings

if TYPE_CHECKING:
    from common.site import Site


class TransportError(ValueError):
    """A zenoh setting that zenoh refused, or an endpoint that cannot be used; the message names it."""


MAX_ZENOH_MESSAGE_BYTES = 2 * MAX_MESSAGE_BYTES
"""zenoh's own limit on one message (``transport/link/rx/max_message_size``; zenoh's default is
1 GiB) on every session and router of a site: twice the largest message the project sends. zenoh
assembles a whole message before any check of the project sees it, so without the limit a single
put of hundreds of megabytes costs the router and the fusion server that much memory, kept."""

PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")
"""Link protocols an endpoint may name (``protocol/address``)."""
_HOST_PORT = ("tcp", "udp", "tls", "quic", "ws")


def check_endpoint(endpoint: object, *, listen: bool = False) -> str:
    """``endpoint`` unchanged when zenoh could use it, else ValueError naming the problem.

    ``protocol/address[?config][#metadata]``; for tcp, udp, tls, quic and ws
    the address is ``host:port`` or ``[ipv6]:port`` with a port in 1..65535
    (0 too when listening: any free port). Whether the host exists is not
    checked here: a name that does not resolve yet is retried like an
    unreachable router.
    """
    if not isinstance(endpoint, str) or "/" not in endpoint:
        raise ValueError(f"endpoint {_short_repr(endpoint)} is not protocol/address (e.g. tcp/10.0.0.2:7447)")
    proto, _, rest = endpoint.partition("/")
    if proto not in PROTOCOLS:
        raise ValueError(f"endpoint {_short_repr(endpoint)}: unknown protocol {_short_repr(proto)} "
                         f"(known: {', '.join(PROTOCOLS)})")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if not address:
        raise ValueError(f"endpoint {_short_repr(endpoint)} has no address")
    if proto in _HOST_PORT:
        m = re.fullmatch(r"(\[[0-9A-Fa-f:.%\w]+\]|[^\s:/\[\]]+):([0-9]{1,5})", address)
        if m is None:
            raise ValueError(f"endpoint {_short_repr(endpoint)}: the address must be host:port "
                             f"(e.g. {proto}/10.0.0.2:7447)")
        port, lowest = int(m.group(2)), 0 if listen else 1
        if not lowest <= port <= 65535:
            raise ValueError(f"endpoint {_short_repr(endpoint)}: port {port} is not in {lowest}..65535")
    return endpoint


def zenoh_config(
    settings: ZenohSettings | None = None,
    *,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    base_dir: str | Path = ".",
    host: str | None = None,
    tls_cert: str | Path | None = None,
    tls_key: str | Path | None = None,
    access_control: dict | None = None,
    connect_timeout_ms: int = -1,
) -> zenoh.Config:
    """A ``zenoh.Config`` from the site settings, with command-line overrides.

    Relative paths in ``settings`` are relative to ``base_dir`` (the site file's folder).
    With ``settings.tls``, this host's certificate and key are ``tls_cert``/``tls_key`` when
    given, else ``<certs>/<host>.pem`` and ``<certs>/<host>-key.pem``. ``access_control``
    (zenoh's section as a dict, see :func:`common.access.site_acl`) is inserted as given.
    connect_timeout_ms: how long a client's ``zenoh.open`` waits for its router (-1: for
    ever; :func:`open_session` uses a short one and retries). A malformed endpoint raises
    TransportError naming it.
    """
    settings = settings or ZenohSettings()
    base = Path(base_dir)
    values: dict[str, object] = {
        "mode": mode or settings.mode,
        "listen/endpoints": list(listen if listen is not None else settings.listen),
        "connect/endpoints": list(connect if connect is not None else settings.connect),
        "scouting/multicast/enabled": settings.multicast_scouting,
        "transport/shared_memory/enabled": settings.shared_memory,
        "transport/link/rx/max_message_size": MAX_ZENOH_MESSAGE_BYTES,
    }
    for key, is_listen in (("listen/endpoints", True), ("connect/endpoints", False)):
        for endpoint in values[key]:
            try:
                check_endpoint(endpoint, listen=is_listen)
            except ValueError as exc:
                raise TransportError(f"zenoh setting {key} = {_short_repr(values[key])}: {exc}") from None
    if values["mode"] == "client":
        values["connect/timeout_ms"] = int(connect_timeout_ms)  # -1: a client waits for its router
    if settings.tls is not None:
        values.update(tls_values(settings, base_dir=base, host=host, tls_cert=tls_cert, tls_key=tls_key))
    elif tls_cert or tls_key:
        raise TransportError("--tls-cert/--tls-key need a [zenoh.tls] section in the site file (its ca)")
    if access_control is not None:
        values["access_control"] = access_control
    values.update(flatten_settings(settings.settings))
    conf = _base_config(_resolve(base, settings.config)) if settings.config else zenoh.Config()
    return _config(values, conf)


def site_config(
    site: "Site",
    *,
    host: str | None,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    tls_cert: str | Path | None = None,
    tls_key: str | Path | None = None,
    connect_timeout_ms: int = -1,
) -> zenoh.Config:
    """:func:`zenoh_config` for one host of ``site``: paths relative to the site file, and on a
    router of a site with ``[zenoh.tls] access_control`` the site's access control."""
    from common.access import site_acl

    z = site.zenoh
    acl = None
    if (mode or z.mode) == "router" and z.tls is not None and z.tls.access_control:
        acl = site_acl(site.prefix, site.camera_ids, readers=z.tls.readers)
    return zenoh_config(z, mode=mode, listen=listen, connect=connect, base_dir=site.base_dir, host=host,
                        tls_cert=tls_cert, tls_key=tls_key, access_control=acl,
                        connect_timeout_ms=connect_timeout_ms)


def tls_values(
    settings: ZenohSettings,
    *,
    base_dir: str | Path,
    host: str | None,
    tls_cert: str | Path | None = None,
    tls_key: str | Path | None = None,
) -> dict[str, object]:
    """zenoh's ``transport/link/tls/...`` settings for this host; TransportError names a missing file."""
    from common.certs import cert_path, key_path

    tls = settings.tls
    assert tls is not None
    base = Path(base_dir)
    ca = _resolve(base, tls.ca)
    if tls_cert is None and tls_key is None:
        if host is None:
            raise TransportError("[zenoh.tls]: this process has no host name to pick its certificate by: "
                                 "give --tls-cert and --tls-key")
        folder = _resolve(base, tls.certs or ".")
        cert, key = cert_path(folder, host), key_path(folder, host)
    elif tls_cert is None or tls_key is None:
        raise TransportError("give both --tls-cert and --tls-key")
    else:
        cert, key = Path(tls_cert), Path(tls_key)
    for what, path in (("[zenoh.tls] ca", ca), ("this host's certificate", cert), ("this host's key", key)):
        if not path.is_file():
            raise TransportError(f"{what}: {path} not found (voxelwatch certs makes the site's certificates; "
                                 "copy each host's own files to it)")
    return {
        "transport/link/tls/root_ca_certificate": str(ca),
        "transport/link/tls/enable_mtls": True,
        "transport/link/tls/listen_certificate": str(cert),
        "transport/link/tls/listen_private_key": str(key),
        "transport/link/tls/connect_certificate": str(cert),
        "transport/link/tls/connect_private_key": str(key),
    }


def flatten_settings(tree: dict[str, Any], prefix: str = "") -> dict[str, object]:
    """``{"transport": {"link": {"tx": {"lease": 1}}}}`` and ``{"transport/link/tx/lease": 1}`` both
    as ``{"transport/link/tx/lease": 1}``: zenoh settings one leaf at a time."""
    out: dict[str, object] = {}
    for key, value in tree.items():
        path = f"{prefix}{str(key).strip('/')}"
        if isinstance(value, dict) and value:
            out.update(flatten_settings(value, path + "/"))
        else:
            out[path] = value
    return out


def plain_endpoints(settings: ZenohSettings, extra: Sequence[str] = ()) -> list[str]:
    """The endpoints of ``settings`` (and ``extra``) that carry data without TLS (``tcp/``, ``udp/`` ...)."""
    return [e for e in [*settings.listen, *settings.connect, *extra] if not e.startswith(("tls/", "quic/"))]


def open_session(make_config: Callable[[], zenoh.Config], stop: threading.Event, *, who: str,
                 endpoints: Sequence[str] = (), log: logging.Logger | None = None, backoff_s: float = 0.5,
                 max_backoff_s: float = 30.0) -> zenoh.Session | None:
    """Open a zenoh session, retrying with back-off while nothing answers; None once ``stop`` is set.

    make_config: a fresh config per attempt (a client's should give up after a
    second or so: ``zenoh_config(..., connect_timeout_ms=1000)``, so that a
    signal is handled between attempts). who: the process, for the log lines.
    endpoints: where it connects, for the log lines. The first failure is one
    warning; while the router stays away, one line every ``max_backoff_s``.
    TransportError when an endpoint cannot be listened on (a port in use, an
    address not of this host): retrying would not help.
    """
    log = log or logging.getLogger("voxelwatch")
    where = ", ".join(endpoints) if endpoints else "the configured endpoints"
    delay, failures = backoff_s, 0
    while not stop.is_set():
        try:
            session = zenoh.open(make_config())
        except Exception as exc:  # noqa: BLE001 - zenoh reports every failure as ZError
            text = short_error(exc)
            if "listener" in text.lower() or "address already in use" in text.lower():
                raise TransportError(f"cannot listen: {text}") from None
            failures += 1
            if failures == 1:
                log.warning("%s: cannot reach zenoh at %s (%s); retrying with back-off up to %.0f s",
                            who, where, text, max_backoff_s)
            elif delay >= max_backoff_s:
                log.info("%s: still cannot reach zenoh at %s after %d attempts; retrying", who, where, failures)
            if stop.wait(delay):
                break
            delay = min(2 * delay, max_backoff_s)
            continue
        if failures:
            log.info("%s: zenoh reached at %s after %d failed attempts", who, where, failures)
        return session
    return None


def watch_links(session: zenoh.Session, stop: threading.Event, *, who: str, endpoints: Sequence[str],
                log: logging.Logger | None = None, after_s: float = 3.0, period_s: float = 2.0) -> threading.Thread | None:
    """Say when a session that connects to ``endpoints`` has no zenoh link, in one line each way.

    A peer opens even when nothing answers at its endpoints, and a client whose
    router goes away later goes on quietly while zenoh reconnects in the
    background: ``after_s`` after opening, then every ``period_s``, this checks
    for a connected peer or router and logs a warning when there is none (once
    until it changes) and an info line when a link is back. Returns the watching
    thread (a daemon, ending with ``stop``), or None without endpoints."""
    if not endpoints:
        return None
    log = log or logging.getLogger("voxelwatch")
    where = ", ".join(endpoints)

    def linked() -> bool | None:
        try:
            return bool(list(session.info.peers_zid())) or bool(list(session.info.routers_zid()))
        except Exception:  # noqa: BLE001 - the session is closing
            return None

    def watch() -> None:
        was = True  # open_session returned: a client had its router then
        wait = after_s
        while not stop.wait(wait):
            wait = period_s
            now = linked()
            if now is None:
                return
            if was and not now:
                log.warning("%s: no zenoh link to %s (zenoh keeps trying in the background)", who, where)
            elif now and not was:
                log.info("%s: zenoh link to %s is back", who, where)
            was = now

    thread = threading.Thread(target=watch, name="zenoh-links", daemon=True)
    thread.start()
    return thread


def short_error(exc: BaseException, limit: int = 300) -> str:
    """A zenoh error's text without the source locations it carries, at most ``limit`` characters."""
    text = re.sub(r"\s+at /\S+?\.rs:\d+\.?", "", str(exc)).strip()
    return text if len(text) <= limit else text[: limit - 3] + "..."


def private_config() -> zenoh.Config:
    """A peer session's config with multicast scouting and shared memory off and zenoh's
    defaults otherwise (no endpoint to connect to): for a process that talks to itself, such as
    a benchmark publishing into its own session."""
    return _config({"scouting/multicast/enabled": False, "transport/shared_memory/enabled": False})


def free_port() -> int:
    """A TCP port on loopback that nothing listens on now (for local runs and tests)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _short_repr(value: object, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _resolve(base: Path, path: str) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() else base / p


def _base_config(path: Path) -> zenoh.Config:
    """zenoh's own configuration file at ``path``; TransportError with zenoh's reason."""
    if not path.is_file():
        raise TransportError(f"[zenoh] config: {path} not found")
    try:
        return zenoh.Config.from_file(str(path))
    except Exception as exc:  # noqa: BLE001 - zenoh raises ZError for a file it refuses
        raise TransportError(f"[zenoh] config {path}: {exc}") from None


def _config(values: dict[str, object], conf: zenoh.Config | None = None) -> zenoh.Config:
    """``conf`` (a new ``zenoh.Config`` by default) with each ``key: value`` inserted (as JSON);
    TransportError names a refused one."""
    conf = conf if conf is not None else zenoh.Config()
    for key, value in values.items():
        try:
            conf.insert_json5(key, json.dumps(value))
        except Exception as exc:  # noqa: BLE001 - zenoh raises ZError for a value it refuses
            raise TransportError(f"zenoh setting {key} = {value!r}: {exc}") from None
    return conf
