"""Zenoh session configuration from the site's ``[zenoh]`` section.

The only module besides the process adapters that imports zenoh. Shared
memory is off unless asked for (bursts were lost with it on), multicast
scouting is off unless asked for (sites without multicast, tests).

Layers, later ones winning: the ``config`` file (zenoh's own JSON5), the
section's fields and the command line, TLS from ``[zenoh.tls]`` (this host's
certificate chosen by its name: ``router``, ``fusion`` or the camera id), the
site's access control on a router, and last the ``settings`` table.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from common.site import ZenohSettings

if TYPE_CHECKING:
    from common.site import Site


class TransportError(ValueError):
    """A zenoh setting that zenoh refused; the message names the setting."""


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
) -> zenoh.Config:
    """A ``zenoh.Config`` from the site settings, with command-line overrides.

    Relative paths in ``settings`` are relative to ``base_dir`` (the site file's folder).
    With ``settings.tls``, this host's certificate and key are ``tls_cert``/``tls_key`` when
    given, else ``<certs>/<host>.pem`` and ``<certs>/<host>-key.pem``. ``access_control``
    (zenoh's section as a dict, see :func:`common.access.site_acl`) is inserted as given.
    """
    settings = settings or ZenohSettings()
    base = Path(base_dir)
    values: dict[str, object] = {
        "mode": mode or settings.mode,
        "listen/endpoints": list(listen if listen is not None else settings.listen),
        "connect/endpoints": list(connect if connect is not None else settings.connect),
        "scouting/multicast/enabled": settings.multicast_scouting,
        "transport/shared_memory/enabled": settings.shared_memory,
    }
    if values["mode"] == "client":
        values["connect/timeout_ms"] = -1  # a client waits for its router instead of failing
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
) -> zenoh.Config:
    """:func:`zenoh_config` for one host of ``site``: paths relative to the site file, and on a
    router of a site with ``[zenoh.tls] access_control`` the site's access control."""
    from common.access import site_acl

    z = site.zenoh
    acl = None
    if (mode or z.mode) == "router" and z.tls is not None and z.tls.access_control:
        acl = site_acl(site.prefix, site.camera_ids, readers=z.tls.readers)
    return zenoh_config(z, mode=mode, listen=listen, connect=connect, base_dir=site.base_dir, host=host,
                        tls_cert=tls_cert, tls_key=tls_key, access_control=acl)


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


def _resolve(base: Path, path: str) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() else base / p


def _base_config(path: Path) -> zenoh.Config:
    """zenoh's own configuration file at ``path``; TransportError with zenoh's reason."""
    if not path.is_file():
        raise TransportError(f"[zenoh] config: {path} not found")
    try:
        return zenoh.Config.from_file(str(path))
    except Exception as exc:  # zenoh raises ZError for a file it refuses
        raise TransportError(f"[zenoh] config {path}: {exc}") from None


def _config(values: dict[str, object], conf: zenoh.Config | None = None) -> zenoh.Config:
    """``conf`` (a new ``zenoh.Config`` by default) with each ``key: value`` inserted (as JSON);
    TransportError names a refused one."""
    conf = conf if conf is not None else zenoh.Config()
    for key, value in values.items():
        try:
            conf.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh raises ZError for a value it refuses
            raise TransportError(f"zenoh setting {key} = {value!r}: {exc}") from None
    return conf
