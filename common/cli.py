"""``voxelwatch``: the umbrella command.

Each subcommand lives in its own small function that parses nothing but its
own arguments and hands plain values to the library.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence

DESCRIPTION = """\
voxelwatch: multi-camera 3D sensing of people at home.

Camera hosts segment their own video and publish compressed foreground masks
over zenoh; one fusion server carves them into voxels, tracks people, judges
posture, dwelling and falls, and publishes tracks and events.
"""

EPILOG = """\
examples:
  voxelwatch site check deploy/site.toml      validate a site file and its calibrations
  voxelwatch router --listen tcp/0.0.0.0:7447  a zenoh router for client-mode hosts
  voxelwatch camera --help                    the camera worker (same as voxelwatch-camera)
  voxelwatch fusion --help                    the fusion server (same as voxelwatch-fusion)
"""


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="voxelwatch", description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for register in _SUBCOMMANDS:
        register(sub)
    argv = list(sys.argv[1:] if argv is None else argv)
    # camera and fusion hand every remaining argument to their own parsers
    if argv and argv[0] in _PASSTHROUGH:
        return _PASSTHROUGH[argv[0]]()(argv[1:])
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except ValueError as exc:  # configuration problems carry their own clear message
        print(f"voxelwatch {args.command}: {exc}", file=sys.stderr)
        return 2


def _camera_main() -> Callable[[Sequence[str]], int]:
    from camera_worker.cli import main as camera_main

    return camera_main


def _fusion_main() -> Callable[[Sequence[str]], int]:
    from fusion_server.cli import main as fusion_main

    return fusion_main


_PASSTHROUGH: dict[str, Callable[[], Callable[[Sequence[str]], int]]] = {
    "camera": _camera_main,
    "fusion": _fusion_main,
}


def _register_passthrough(sub) -> None:
    sub.add_parser("camera", help="run one camera worker (voxelwatch-camera)", add_help=False)
    sub.add_parser("fusion", help="run the fusion server (voxelwatch-fusion)", add_help=False)


def _register_site(sub) -> None:
    p = sub.add_parser("site", help="check a site file and its calibrations")
    p.add_argument("action", choices=["check"], help="check: validate the file and load every calibration")
    p.add_argument("path", help="the site TOML file")
    p.set_defaults(handler=_site_check)


def _site_check(args: argparse.Namespace) -> int:
    from common.site import load_site

    site = load_site(args.path)
    cameras = site.load_cameras()
    print(f"site {site.name}: prefix {site.prefix}, volume {list(site.volume.min_m)} .. {list(site.volume.max_m)} m")
    for cam_id, cam in cameras.items():
        x, y, z = cam.center
        print(f"  camera {cam_id}: {cam.model} {cam.width}x{cam.height}, centre ({x:.2f}, {y:.2f}, {z:.2f}) m")
    print(f"  {len(site.hotspots)} hot spots, {len(site.doors)} doors")
    return 0


def _register_router(sub) -> None:
    p = sub.add_parser("router", help="run a zenoh router (for client-mode hosts)")
    p.add_argument("--listen", action="append", default=None, help="endpoint to listen on (repeatable), default tcp/0.0.0.0:7447")
    p.add_argument("--multicast-scouting", action="store_true", help="answer multicast scouting")
    p.set_defaults(handler=_router)


def _router(args: argparse.Namespace) -> int:
    import json
    import signal
    import threading

    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps(args.listen or ["tcp/0.0.0.0:7447"]))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(args.multicast_scouting)))
    conf.insert_json5("transport/shared_memory/enabled", "false")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    with zenoh.open(conf):
        print(f"voxelwatch router listening on {', '.join(args.listen or ['tcp/0.0.0.0:7447'])}", flush=True)
        stop.wait()
    return 0


_SUBCOMMANDS: list[Callable] = [_register_site, _register_router, _register_passthrough]
