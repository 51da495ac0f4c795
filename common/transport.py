"""Zenoh session configuration from the site's ``[zenoh]`` section.

The only module besides the process adapters that imports zenoh. Shared
memory is off unless asked for (bursts were lost with it on), multicast
scouting is off unless asked for (sites without multicast, tests).
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import zenoh

from common.site import ZenohSettings


class TransportError(ValueError):
    """A zenoh setting that zenoh refused; the message names the setting."""


def zenoh_config(
    settings: ZenohSettings | None = None,
    *,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
) -> zenoh.Config:
    """A ``zenoh.Config`` from the site settings, with command-line overrides."""
    settings = settings or ZenohSettings()
    values = {
        "mode": mode or settings.mode,
        "listen/endpoints": list(listen if listen is not None else settings.listen),
        "connect/endpoints": list(connect if connect is not None else settings.connect),
        "scouting/multicast/enabled": settings.multicast_scouting,
        "transport/shared_memory/enabled": settings.shared_memory,
    }
    if values["mode"] == "client":
        values["connect/timeout_ms"] = -1  # a client waits for its router instead of failing
    return _config(values)


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


def _config(values: dict[str, object]) -> zenoh.Config:
    """A ``zenoh.Config`` with each ``key: value`` inserted (as JSON); TransportError names a refused one."""
    conf = zenoh.Config()
    for key, value in values.items():
        try:
            conf.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh raises ZError for a value it refuses
            raise TransportError(f"zenoh setting {key} = {value!r}: {exc}") from None
    return conf
