"""``voxelwatch-fusion``: the fusion server process."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from common.shell import (Stopped, add_logging_arguments, add_zenoh_arguments, configure_logging, stop_if_asked,
                          stopped_raises)

if TYPE_CHECKING:
    from fusion_server.settings import FusionSettings

DESCRIPTION = """\
The voxelwatch fusion server: subscribes to every camera's foreground masks,
groups them into frame sets by capture time, carves 3D voxels with an octree
tested by distance transforms, detects and tracks people on the floor plane,
judges posture, dwelling and falls, and publishes on zenoh:

  <prefix>/tracks                   every fused frame: all tracks
  <prefix>/events/<kind>/<track>    each event (JSON text, never dropped)
  <prefix>/history/events           queryable: past events (?since=..;until=..;kind=..)
  <prefix>/status                   per-camera health
  <prefix>/cam/<id>/hold            regions of still people the camera must not learn

Events are written to the local store before they are published, so a
restarted server answers history queries with everything it sent before.
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="voxelwatch-fusion", description=DESCRIPTION,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--site", required=True, type=Path, help="the site TOML file (cameras, volume, hot spots, doors, zenoh)")
    p.add_argument("--store", type=Path, default=None,
                   help="SQLite event store (default: voxelwatch-events.sqlite next to the site file)")
    p.add_argument("--out", type=Path, default=None, help="also write tracks.csv and events.jsonl into this folder")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="where carving lookup tables are cached (default ~/.cache/voxelwatch)")
    p.add_argument("--min-cameras", type=int, default=None,
                   help="fewest cameras a frame set needs to be fused (default: the carving vote's min_cameras)")
    p.add_argument("--exit-after-idle", type=float, default=None, metavar="SECONDS",
                   help="stop when no mask has arrived for this long (for replays and tests)")
    p.add_argument("--max-clock-skew-ms", type=float, default=None, metavar="MS",
                   help="mark a camera skewed when its stamps run this far from the server's clock (default 250)")
    p.add_argument("--free-timeline", action="store_true",
                   help="let the frame-set timeline follow the cameras' stamps instead of this host's clock "
                        "(recordings played faster than real time, e.g. workers run with --fast)")
    add_zenoh_arguments(p, host="fusion")
    add_logging_arguments(p)
    return p


_FLAGS = {"min_cameras": "--min-cameras", "exit_after_idle_s": "--exit-after-idle",
          "max_clock_skew_ms": "--max-clock-skew-ms", "mode": "--mode"}


def settings_from_args(args: argparse.Namespace) -> "FusionSettings":
    """The server's settings from parsed arguments. A bad site file raises its
    :class:`~common.site.SiteError` (a ValueError), any other bad value a ValueError
    naming the command-line flag."""
    from common import keys
    from common.site import load_site

    site = load_site(args.site)   # a bad site file says so before the server's modules are loaded
    from fusion_server.settings import DEFAULT_STORE_NAME, FusionSettings

    prefix = args.prefix or site.prefix
    try:
        keys.validate_prefix(prefix)
    except ValueError as exc:
        raise ValueError(f"--prefix: {exc}") from None
    store = args.store if args.store is not None else Path(args.site).resolve().parent / DEFAULT_STORE_NAME
    extra = {} if args.max_clock_skew_ms is None else {"max_clock_skew_ms": args.max_clock_skew_ms}
    try:
        return FusionSettings(
            site=site, prefix=prefix, store_path=Path(store), out_dir=args.out, mode=args.mode,
            listen=tuple(args.listen) if args.listen is not None else None,
            connect=tuple(args.connect) if args.connect is not None else None,
            tls_cert=args.tls_cert, tls_key=args.tls_key,
            cache_dir=args.cache_dir, min_cameras=args.min_cameras, exit_after_idle_s=args.exit_after_idle,
            free_timeline=bool(args.free_timeline), **extra,
        )
    except ValueError as exc:
        text = str(exc)
        for name, flag in _FLAGS.items():
            if text.startswith((name + " ", name + ":")):
                text = flag + text[len(name):]
        raise ValueError(text) from None


def main(argv: Sequence[str] | None = None) -> int:
    """Exit status 0 after a stop (a signal at any moment, the idle timeout), 2 for a bad site file,
    setting or flag (one line), 1 when zenoh cannot be opened."""
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    log = logging.getLogger("voxelwatch.fusion")
    try:
        with stopped_raises(who="fusion", log=log):
            try:
                settings = settings_from_args(args)
            except ValueError as exc:
                print(f"voxelwatch-fusion: {exc}", file=sys.stderr)
                return 2
            try:
                cameras = settings.announce(log)   # before the server's modules: within a second or so
            except ValueError as exc:
                log.error("%s", exc)
                return 2
            from fusion_server.server import run_forever

            stop_if_asked()   # a signal during the imports: their own handlers may have eaten the exception
            return run_forever(settings, cameras)
    except Stopped:
        return 0


if __name__ == "__main__":
    sys.exit(main())
