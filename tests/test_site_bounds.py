"""Every value ``site check`` accepts starts every process.

For each bounded number of the site file's ``[carving]``, ``[events]`` and ``[identity]``
sections, its cameras (``fps``) and its top level (``residents``, ``utc_offset_hours``), the
values at its bounds (the nearest accepted one for an open bound) and between them are written
into the tiny site; where ``site check`` accepts the file, the fusion server's start-up (its
command line, announcement, pipeline with the carving tables, and the node it serves with) and
the camera worker's (its command line, settings, segmenter and zenoh configuration) must accept
it too, through the functions the two commands run. (The property the issue of
``mask_scale = 0.2`` broke: the site took it and every camera refused to start; a camera ``fps``
near 0 made the server's frame period overflow, so the schema now asks for 0.5 at least.)
"""

from __future__ import annotations

import argparse
import logging
import math
import re

import pytest

from common.settings import bounds_of
from common.site import CameraSpec, Carving, EventSettings, IdentitySettings, Site

SECTIONS = {"carving": Carving, "events": EventSettings, "identity": IdentitySettings,
            "cameras": CameraSpec, "": Site}
"""Where the numbers live: a section's table, every camera's ``[[cameras]]`` (``fps``), the file's top level."""


def _candidates() -> list[tuple[str, str, float | int]]:
    out = []
    for section, model in SECTIONS.items():
        for name, info in model.model_fields.items():
            if info.annotation not in (int, float):
                continue
            low, high = bounds_of(model, name)
            meta = {type(m).__name__ for m in info.metadata}
            if info.annotation is int:
                values = [int(low), int(low) + 1] if math.isfinite(low) else []
            else:
                lo = math.nextafter(low, math.inf) if "Gt" in meta else low
                hi = math.nextafter(high, -math.inf) if "Lt" in meta else high
                if not math.isfinite(lo):
                    continue
                values = [lo, hi, (lo + hi) / 2] if math.isfinite(hi) else [lo, lo * 10 or 1.0]
            out += [(section, name, v) for v in values]
    return out


CANDIDATES = _candidates()


def test_the_candidates_cover_the_settings_that_broke():
    names = {(s, n) for s, n, _ in CANDIDATES}
    assert {("carving", "mask_scale"), ("events", "long_lie_s"), ("identity", "rate_hz"), ("cameras", "fps"),
            ("", "utc_offset_hours"), ("", "residents")} <= names
    assert ("carving", "mask_scale", 0.125) in CANDIDATES


def _with(site_text: str, section: str, name: str, value) -> str:
    """The site file's text with ``[section] name = value`` (the section added when missing; every
    camera's for ``cameras``; before the first table for the top level)."""
    line = f"{name} = {value!r}"
    site_text = re.sub(rf"^{name} = .*\n", "", site_text, flags=re.M)   # the tiny site's own value, if any
    if section == "cameras":
        return site_text.replace("\n[[cameras]]\n", f"\n[[cameras]]\n{line}\n")
    if section == "":
        return f"{line}\n{site_text}"
    if re.search(rf"^\[{section}\]$", site_text, flags=re.M):
        return re.sub(rf"^\[{section}\]$", f"[{section}]\n{line}", site_text, count=1, flags=re.M)
    head, sep, cams = site_text.partition("\n[[cameras]]")
    return f"{head}\n[{section}]\n{line}\n{sep}{cams}"


@pytest.mark.parametrize("section, name, value", CANDIDATES, ids=[f"{s}.{n}={v:g}" for s, n, v in CANDIDATES])
def test_a_value_site_check_accepts_starts_the_fusion_server_and_the_camera_worker(
        tmp_path, lut_cache, section, name, value):
    from tinysite import write_site

    from camera_worker import cli as camera_cli
    from fusion_server import cli as fusion_cli
    from fusion_server.node import FusionNode
    from voxelwatch.cli import _site_check

    site_file, _ = write_site(tmp_path)
    site_file.write_text(_with(site_file.read_text(), section, name, value))
    try:
        _site_check(argparse.Namespace(path=str(site_file), clip=[]))
    except ValueError as exc:
        pytest.skip(f"site check refuses {section}.{name} = {value!r}: {exc}")
    # the fusion server: its command line, then what it checks and builds before zenoh
    args = fusion_cli.build_parser().parse_args(["--site", str(site_file), "--store", str(tmp_path / "ev.sqlite"),
                                                  "--cache-dir", str(lut_cache), "--mode", "client",
                                                  "--connect", "tcp/127.0.0.1:7447"])
    settings = fusion_cli.settings_from_args(args)
    cameras = settings.announce(logging.getLogger("test"))
    FusionNode(settings, settings.build_pipeline(cameras))   # what it serves with once zenoh is open
    # the camera worker: every camera's command line and settings, its segmenter and zenoh configuration
    for cam in cameras:
        cargs = camera_cli.build_parser().parse_args(["--site", str(site_file), "--camera", cam, "--source",
                                                      "synthetic", "--mode", "client", "--connect", "tcp/127.0.0.1:7447"])
        worker, conf, connect = camera_cli._configure(cargs)
        assert worker.cam == cam and connect == ["tcp/127.0.0.1:7447"]
