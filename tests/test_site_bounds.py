"""Every value ``site check`` accepts starts every process.

Every bounded number of the site schema is found by walking the :class:`~common.site.Site` model
through its tables, optional tables and arrays of tables (``[carving]``, ``[events]``,
``[identity]``, ``[zenoh]``, ``[view]``, ``[notify]`` with ``[notify.mqtt]``,
``[[notify.webhooks]]`` and ``[notify.email]``, every ``[[cameras]]``, the top level), so that a
number declared later is covered too; a list of bounded numbers (``carving.voxel_sizes_m``)
counts by its elements, and is given as a list of one. The values at each number's bounds (the
nearest accepted one for an open bound) and between them are written into the tiny site; where
``site check`` accepts the file, every process must start with it, through the functions its
command runs before it opens zenoh or a socket:

* the fusion server: its command line, settings, announcement, pipeline with the carving
  tables, and the node it serves with;
* every camera worker: its command line, settings, segmenter and zenoh configuration;
* the live view: its command line, token and address, zenoh configuration, and the view it
  serves with;
* the notifier: its command line, channels, zenoh configuration, outbox and notifier;
* the zenoh router: its command line and configuration.

(The property the issue of ``mask_scale = 0.2`` broke: the site took it and every camera refused
to start; a camera ``fps`` near 0 made the server's frame period overflow, so the schema now asks
for 0.5 at least.)
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import math
import threading
import tomllib
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import pytest
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from common.settings import bounds_in
from common.site import Site

ENDPOINT = "tcp/127.0.0.1:7447"

VOLUME = {"min_m": [1.3, 1.3, 0.6], "max_m": [1.7, 1.7, 1.0]}
"""The tiny site's volume shrunk to a 0.4 m cube at the middle of its room, which its cameras look
at: the finest voxel the schema takes (5 mm) makes half a million voxels there, not the room's 144
million."""

TABLES = {
    "view": {"token": "a-view-token-for-tests"},
    "notify": {
        "outbox": "notify-outbox.sqlite",
        "mqtt": {"host": "127.0.0.1"},
        "webhooks": [{"url": "http://127.0.0.1:9/hook"}],
        "email": {"host": "127.0.0.1", "sender": "voxelwatch@example.org", "to": ["nurse@example.org"]},
    },
}
"""What the tiny site adds so that every process has something to start: the view's token and one
notification channel of each kind (each table's numbers then reach the site file)."""


@dataclass(frozen=True)
class Bounded:
    """A bounded number of the site schema."""

    path: tuple[str, ...]
    """Where it lives: ``("notify", "webhooks", "timeout_s")`` (in every table of an array of tables)."""
    kind: type
    """``int`` or ``float``."""
    low: float
    high: float
    """The lowest and highest values the schema accepts (``-inf``/``inf`` where it declares none)."""
    element: bool
    """An element of a list of numbers."""

    @property
    def name(self) -> str:
        return ".".join(self.path)

    def values(self) -> list:
        """The values at the bounds and between them (a list of one of each for an element)."""
        lo, hi = self.low, self.high
        if not math.isfinite(lo) and not math.isfinite(hi):
            return []
        if math.isfinite(lo) and math.isfinite(hi):
            values = [lo, hi, (lo + hi) // 2 if self.kind is int else (lo + hi) / 2]
        elif math.isfinite(lo):
            values = [lo, lo + 1 if self.kind is int else lo * 10 if lo > 0 else lo + 1.0]
        else:
            values = [hi, hi - 1 if self.kind is int else hi / 10 if hi < 0 else hi - 1.0]
        values = [self.kind(v) for v in values]
        return [[v] for v in values] if self.element else values


def bounded_numbers(model: type[BaseModel] = Site, path: tuple[str, ...] = ()) -> Iterator[Bounded]:
    """Every bounded number of ``model`` and of the models it holds, in declaration order."""
    for name, info in model.model_fields.items():
        if not info.exclude:
            yield from _numbers(info.annotation, list(info.metadata), (*path, name), element=False)


def _numbers(annotation: Any, metadata: list, path: tuple[str, ...], *, element: bool) -> Iterator[Bounded]:
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is Annotated:
        more = [m for a in annotation.__metadata__ for m in (a.metadata if isinstance(a, FieldInfo) else [a])]
        yield from _numbers(args[0], metadata + more, path, element=element)
    elif origin in (typing.Union, types.UnionType):   # an optional table or number
        for arg in args:
            yield from _numbers(arg, metadata, path, element=element)
    elif origin is list:   # an array of tables, or a list of numbers
        yield from _numbers(args[0], [], path, element=True)
    elif isinstance(annotation, type) and issubclass(annotation, BaseModel):
        yield from bounded_numbers(annotation, path)
    elif annotation in (int, float):
        low, high = _limits(annotation, metadata)
        if math.isfinite(low) or math.isfinite(high):
            yield Bounded(path, annotation, low, high, element)


def _limits(kind: type, metadata: list) -> tuple[float, float]:
    """The lowest and highest values of ``kind`` that the constraints in ``metadata`` accept: the
    schema's range (:func:`~common.settings.bounds_in`), an open end moved to the nearest value inside."""
    low, high = bounds_in(metadata)
    if any(getattr(m, "gt", None) == low for m in metadata):
        low = low + 1 if kind is int else math.nextafter(low, math.inf)
    if any(getattr(m, "lt", None) == high for m in metadata):
        high = high - 1 if kind is int else math.nextafter(high, -math.inf)
    return low, high


NUMBERS = list(bounded_numbers())
CANDIDATES = [(number.name, value) for number in NUMBERS for value in number.values()]


def _show(value) -> str:
    return f"[{', '.join(_show(v) for v in value)}]" if isinstance(value, list) else f"{value:g}"


def test_the_candidates_cover_the_settings_that_broke():
    names = {name for name, _ in CANDIDATES}
    assert {"carving.mask_scale", "events.long_lie_s", "identity.rate_hz", "cameras.fps", "utc_offset_hours",
            "residents"} <= names
    assert ("carving.mask_scale", 0.125) in CANDIDATES
    # and the sections found by the walk: the view, the notifier's channels, a list's elements
    assert {"view.trail_s", "notify.retry_max_s", "notify.mqtt.port", "notify.webhooks.timeout_s", "notify.email.port",
            "carving.voxel_sizes_m"} <= names
    assert ("notify.mqtt.port", 65535) in CANDIDATES and ("notify.email.port", 1) in CANDIDATES
    assert ("carving.voxel_sizes_m", [0.005]) in CANDIDATES and ("carving.voxel_sizes_m", [2.0]) in CANDIDATES


def _write_site(folder: Path, name: str | None = None, value=None) -> Path:
    """The tiny site written into ``folder``, its volume :data:`VOLUME`, with :data:`TABLES`, and
    with the number ``name`` (dotted) set to ``value`` (in every table of an array of tables)."""
    from tinysite import write_site

    site_file, _ = write_site(folder)
    data = tomllib.loads(site_file.read_text())
    data["volume"] = dict(VOLUME)
    data.update(copy.deepcopy(TABLES))
    if name is not None:
        _put(data, name.split("."), value)
    site_file.write_text(_toml(data))
    return site_file


def _put(table: dict, path: list[str], value) -> None:
    head, *rest = path
    if not rest:
        table[head] = value
        return
    node = table.setdefault(head, {})
    for item in node if isinstance(node, list) else [node]:
        _put(item, rest, value)


def _toml(table: dict, name: str = "") -> str:
    """``table`` as TOML text: its values, then its tables and arrays of tables."""
    def is_tables(v) -> bool:
        return isinstance(v, list) and bool(v) and all(isinstance(i, dict) for i in v)

    text = "".join(f"{k} = {_toml_value(v)}\n" for k, v in table.items() if not isinstance(v, dict) and not is_tables(v))
    for key, v in table.items():
        full = f"{name}.{key}" if name else key
        if isinstance(v, dict):
            text += f"\n[{full}]\n{_toml(v, full)}"
        elif is_tables(v):
            text += "".join(f"\n[[{full}]]\n{_toml(item, full)}" for item in v)
    return text


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, list):
        return f"[{', '.join(_toml_value(v) for v in value)}]"
    return json.dumps(value)


def _site_check_accepts(site_file: Path) -> str:
    """"" when ``voxelwatch site check`` accepts the file, else its refusal."""
    from voxelwatch.cli import _site_check

    try:
        _site_check(argparse.Namespace(path=str(site_file), clip=[]))
    except ValueError as exc:
        return str(exc) or type(exc).__name__
    return ""


def test_site_check_accepts_a_value_of_every_bounded_number(tmp_path):
    """Else the tiny site lacks what that number's table needs, and its candidates prove nothing."""
    assert _site_check_accepts(_write_site(tmp_path)) == ""
    unproven = []
    for number in NUMBERS:
        refusals = [_site_check_accepts(_write_site(tmp_path, number.name, v)) for v in number.values()]
        if all(refusals):
            unproven.append(f"{number.name}: {refusals[0]}")
    assert not unproven, unproven


@pytest.mark.parametrize("name, value", CANDIDATES, ids=[f"{n}={_show(v)}" for n, v in CANDIDATES])
def test_a_value_site_check_accepts_starts_every_process(tmp_path, lut_cache, name, value):
    site_file = _write_site(tmp_path, name, value)
    refusal = _site_check_accepts(site_file)
    if refusal:
        pytest.skip(f"site check refuses {name} = {value!r}: {refusal}")
    cameras = _start_fusion(site_file, tmp_path, lut_cache)
    _start_cameras(site_file, cameras)
    _start_view(site_file)
    _start_notifier(site_file)
    _start_router(site_file)


def _start_fusion(site_file: Path, tmp_path: Path, lut_cache: Path) -> list[str]:
    """The fusion server's command line, then what it checks and builds before zenoh; its cameras."""
    from fusion_server import cli as fusion_cli
    from fusion_server.node import FusionNode

    args = fusion_cli.build_parser().parse_args(["--site", str(site_file), "--store", str(tmp_path / "ev.sqlite"),
                                                  "--cache-dir", str(lut_cache), "--mode", "client",
                                                  "--connect", ENDPOINT])
    settings = fusion_cli.settings_from_args(args)
    cameras = settings.announce(logging.getLogger("test"))
    FusionNode(settings, settings.build_pipeline(cameras))   # what it serves with once zenoh is open
    return list(cameras)


def _start_cameras(site_file: Path, cameras: list[str]) -> None:
    """Every camera's command line and settings, its segmenter and zenoh configuration."""
    from camera_worker import cli as camera_cli

    for cam in cameras:
        args = camera_cli.build_parser().parse_args(["--site", str(site_file), "--camera", cam, "--source",
                                                     "synthetic", "--mode", "client", "--connect", ENDPOINT])
        worker, _, connect = camera_cli._configure(args)
        assert worker.cam == cam and connect == [ENDPOINT]


def _start_view(site_file: Path) -> None:
    """``voxelwatch view``: its command line, token and address, zenoh configuration, then the view it
    serves with once zenoh is open (no session yet: nothing is declared before :meth:`View.start`)."""
    from view import cli as view_cli
    from view.server import View
    from voxelwatch.cli import build_parser

    args = build_parser().parse_args(["view", "--site", str(site_file), "--mode", "client", "--connect", ENDPOINT])
    assert args.handler is view_cli._view
    site, host, port, token = view_cli._configure(args)
    _, endpoints = view_cli._zenoh_config(site, prefix=args.prefix, mode=args.mode, connect=args.connect,
                                          tls_cert=args.tls_cert, tls_key=args.tls_key)
    assert (host, port, endpoints) == ("127.0.0.1", 8080, [ENDPOINT])
    View(None, site, token=token, prefix=args.prefix).close()


def _start_notifier(site_file: Path) -> None:
    """``voxelwatch notify``: its command line, zenoh configuration and channels, then its outbox,
    notifier and one dispatcher per channel (not started: they would connect)."""
    from notify import cli as notify_cli
    from notify.channel import Dispatcher
    from notify.service import Notifier, open_outbox
    from voxelwatch.cli import build_parser

    args = build_parser().parse_args(["notify", "--site", str(site_file), "--mode", "client", "--connect", ENDPOINT])
    assert args.handler is notify_cli._notify
    site, _, endpoints, channels, outbox_path = notify_cli._configure(args)
    assert endpoints == [ENDPOINT] and len(channels) == 3
    outbox = open_outbox(site, outbox_path)
    try:
        Notifier(site, outbox, channels)
        for channel in channels:
            Dispatcher(channel, outbox, threading.Event())
    finally:
        for channel in channels:
            channel.close()
        outbox.close()


def _start_router(site_file: Path) -> None:
    """``voxelwatch router --site``: its command line and zenoh configuration."""
    from voxelwatch import cli as vw_cli

    args = vw_cli.build_parser().parse_args(["router", "--site", str(site_file)])
    assert args.handler is vw_cli._router
    _, listen, _ = vw_cli._router_config(args)
    assert listen == ["tcp/0.0.0.0:7447"]
