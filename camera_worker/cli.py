"""``voxelwatch-camera``: one camera worker per camera host.

Parses the command line, reads the site file, opens the zenoh session and
hands plain settings to :func:`camera_worker.worker.run`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from common.shell import (Stopped, add_logging_arguments, add_zenoh_arguments, configure_logging, serve,
                          stop_if_asked, stopped_raises)

log = logging.getLogger("voxelwatch.camera")

DESCRIPTION = """\
voxelwatch camera worker: reads one camera's frames, segments the people in
them with an adaptive Gaussian-mixture background model (shadows removed,
fast start-up, light-change recovery) and publishes one compressed
foreground mask per frame over zenoh on <prefix>/cam/<id>/mask. Raw frames
never leave the host.
"""

EPILOG = """\
sources (--source, or the camera's 'source' in the site file):
  /path/clip.avi          a video file (played at its own rate; --fast: as fast as possible)
  /path/frames/           a folder of images, in name order (at the camera's fps)
  0                       a camera index (V4L2);  /dev/video0  a camera device
  rtsp://host/stream      a stream URL (rtsp, http, https, udp, tcp, rtp, srt, rtmp)
  synthetic[:scenario]    the synthetic house, this camera's view (--seed)
  world:SEED              this camera's view of the randomised world SEED
  Live sources that drop are reopened with back-off (0.5 s doubling to 30 s);
  the worker stays up and reports itself degraded meanwhile.

examples:
  voxelwatch-camera --site home.toml --camera cam1
  voxelwatch-camera --site home.toml --camera cam2 --source rtsp://10.0.0.12/live
  voxelwatch-camera --site lab.toml --camera cam1 --source cam1/video.avi \\
      --background cam1/background.avi --fast --connect tcp/10.0.0.2:7447

exit status: 0 when a recorded source ended or on SIGINT/SIGTERM; 1 when the
source, the background clip or the zenoh session cannot be used; 2 for a bad
site file or option.
"""


def build_parser() -> argparse.ArgumentParser:
    from common import maskcodec

    p = argparse.ArgumentParser(prog="voxelwatch-camera", description=DESCRIPTION, epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--site", required=True, metavar="SITE.toml", help="the site file (cameras, zenoh settings)")
    p.add_argument("--camera", required=True, metavar="ID", help="this worker's camera id in the site file")

    g = p.add_argument_group("source")
    g.add_argument("--source", metavar="S", help="frame source (see below); default: the camera's 'source'")
    g.add_argument("--background", metavar="B",
                   help="recording of the empty room to learn first; default: the camera's 'background'")
    g.add_argument("--no-background", action="store_true", help="ignore the site's background clip")
    g.add_argument("--background-frames", type=int, metavar="N",
                   help="learn at most N frames of the background clip (default: all of it)")
    g.add_argument("--fps", type=float, metavar="HZ",
                   help="frame rate of a recording, overriding its own (default: the file's, else the camera's fps)")
    g.add_argument("--fast", action="store_true", help="play recordings as fast as possible instead of at their rate")
    g.add_argument("--loop", action="store_true", help="play a recording again and again instead of exiting at its end")
    start = g.add_mutually_exclusive_group()
    start.add_argument("--start-ns", type=int, metavar="NS",
                   help="stamp of a recording's first frame (default: now); give every worker the same to replay "
                        "several cameras in step")
    start.add_argument("--start-file", type=Path, metavar="FILE",
                   help="read that stamp from FILE once ready (liveliness token out, background learned), waiting "
                        "for it to be written: how a launcher starts workers in step however long each takes to "
                        "get ready")
    g.add_argument("--seed", type=int, default=0, help="seed of the synthetic house (default 0)")
    g.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")

    g = p.add_argument_group("segmentation")
    g.add_argument("--window-frames", type=int, default=None, metavar="L",
                   help="learning window: rate 1/n for the first L frames, then 1/L "
                        "(default: 33 s at the source's frame rate, 500 frames at 15 fps)")
    g.add_argument("--mask-scale", type=float, metavar="S",
                   help="mask size as a fraction of the frame, 0.125..1 (default: the site's carving.mask_scale)")
    g.add_argument("--min-area-px", type=int, default=None, metavar="PX",
                   help="drop foreground blobs smaller than this, in pixels of a 640x480 frame (scaled to the "
                        "camera's size; default: a quarter of a 1 m child's outline at the farthest floor the "
                        "camera sees in the site's volume, at most 400)")
    g.add_argument("--no-shadows", action="store_true", help="switch the shadow test off (shadows become foreground)")
    g.add_argument("--view-reference", metavar="PNG",
                   help="keep the reference picture of the room in this file, so that a camera moved while its "
                        "worker was down is still noticed (default: the camera's 'view_reference'; delete the "
                        "file after re-aiming and recalibrating the camera)")
    g.add_argument("--no-view-check", action="store_true",
                   help="do not check whether the camera's view has moved")
    g.add_argument("--codec", choices=maskcodec.CODECS, default=maskcodec.DEFAULT_CODEC,
                   help=f"mask codec (default {maskcodec.DEFAULT_CODEC})")

    add_zenoh_arguments(p, host="<camera id>")

    g = add_logging_arguments(p)
    g.add_argument("--stats-period", type=float, default=10.0, metavar="S",
                   help="log counters and per-stage times every S seconds (default 10)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Exit status 0 after a stop (a signal at any moment of start-up included) or the end of a
    recording, 1 when the source or zenoh cannot be used, 2 for a bad site file or option."""
    who = "camera"
    try:
        # from the first instruction: a signal while the modules load (a second or two on a small
        # box) is a stop like any other, said in one line, exit status 0
        with stopped_raises(who=who, log=None):
            args = build_parser().parse_args(argv)
            configure_logging(args.verbose, args.quiet)
            who = f"camera {args.camera}"
            _quiet_opencv()
            try:
                settings, conf, connect = _configure(args)
            except ValueError as exc:   # SiteError, TransportError and bad values carry their own clear message
                print(f"voxelwatch-camera: {exc}", file=sys.stderr)
                return 2
            log.info("%s: %s (%s, foreground blobs from %d px), then zenoh (%s)", who, settings.source,
                     settings.modality, settings.segmenter["min_area_px"],
                     ", ".join(connect) if connect else f"{args.mode or 'site'} mode, scouting")
            from camera_worker.worker import run

            stop_if_asked()   # a signal during the imports: their own handlers may have eaten the exception
            return serve(conf, who=who, endpoints=connect, log=log,
                         work=lambda session, stop: run(session, settings, stop=stop))
    except Stopped as stop:
        configure_logging()   # no-op when set up already
        log.info("%s: %s received while starting, stopping", who, stop.signame)
        return 0


def _configure(args: argparse.Namespace):
    """``(WorkerSettings, a zenoh config factory, the endpoints it connects to)`` from the arguments
    and the site file; ValueError on any problem."""
    from camera_worker.worker import WorkerSettings
    from common.settings import check_setting
    from common.site import Carving, load_site
    from common.transport import site_config

    site = load_site(args.site)
    spec = site.camera(args.camera)
    # paths from the command line are relative to the working directory, paths from the file to the file
    source = args.source if args.source is not None else _from_site(site, spec.source)
    if not source:
        raise ValueError(f"camera {spec.id}: no source: give --source or set cameras[].source in {args.site}")
    if args.no_background:
        background = ""
    else:
        background = args.background if args.background is not None else _from_site(site, spec.background)
    mask_scale = site.carving.mask_scale
    if args.mask_scale is not None:   # the site file's declaration, its one range
        mask_scale = check_setting(Carving, "mask_scale", args.mask_scale, flag="--mask-scale")
    min_area_px = args.min_area_px
    if min_area_px is None:
        from camera_worker.viewsize import min_area_for_site

        min_area_px = min_area_for_site(site, spec.id)
    settings = WorkerSettings(
        cam=spec.id,
        prefix=args.prefix or site.prefix,
        source=source,
        background=background,
        background_frames=args.background_frames,
        fps=args.fps,
        default_fps=spec.fps,
        start_ns=args.start_ns,
        start_file=args.start_file,
        paced=not args.fast,
        loop=args.loop,
        seed=args.seed,
        codec=args.codec,
        segmenter=dict(window_frames=args.window_frames, mask_scale=mask_scale, min_area_px=min_area_px,
                       detect_shadows=not args.no_shadows),
        max_frames=args.max_frames,
        stats_period_s=args.stats_period,
        expected_size=tuple(spec.resolution) if spec.resolution else None,
        modality=spec.modality,
        view_check=not args.no_view_check,
        view_reference=_view_reference(args, site, spec),
    )
    # build the segmenter once here so that a bad value stops start-up with its name
    from camera_worker.segmenters import segmenter_for

    segmenter_for(settings.modality, **settings.segmenter)
    def conf():
        return site_config(site, host=spec.id, mode=args.mode, listen=args.listen, connect=args.connect,
                           tls_cert=args.tls_cert, tls_key=args.tls_key, connect_timeout_ms=1000)

    conf()  # a bad endpoint or a missing certificate stops start-up here, with its name
    connect = list(args.connect if args.connect is not None else site.zenoh.connect)
    return settings, conf, connect


def _view_reference(args: argparse.Namespace, site, spec):
    """The reference picture's file (None: none), checked to be a picture when it exists."""
    from camera_worker.viewcheck import load_reference

    if args.view_reference is not None:
        path = Path(args.view_reference)
    elif spec.view_reference:
        path = site.resolve(spec.view_reference)
    else:
        return None
    load_reference(path)  # ValueError names the file
    return path


def _from_site(site, spec: str) -> str:
    """A source spec from the site file, a relative path made absolute against the file's folder."""
    if not spec or spec.isdigit() or spec.startswith(("synthetic", "world:", "/dev/")) or "://" in spec:
        return spec
    return str(site.resolve(spec))


def _quiet_opencv() -> None:
    """OpenCV's own warnings (failed opens) would repeat what the worker reports more clearly."""
    import cv2

    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    except AttributeError:  # pragma: no cover - builds without the logging module
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
