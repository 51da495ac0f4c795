"""``voxelwatch calibrate``: the command line of the calibration tools (argument parsing and
printing only; the work is in :mod:`.intrinsics`, :mod:`.floor` and :mod:`.write`)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def register(sub) -> None:
    """Add ``calibrate intrinsics`` and ``calibrate floor`` to the umbrella command's subparsers."""
    p = sub.add_parser("calibrate", help="calibrate cameras from a board: intrinsics (chessboard or ChArUco), and "
                                         "poses from a chessboard or ChArUco mat on the floor")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    i = actions.add_parser("intrinsics", help="a camera's lens from a clip of a board (chessboard or ChArUco) moved "
                                              "in front of it")
    i.add_argument("--camera", required=True, help="the camera id (written into the file)")
    i.add_argument("--clip", required=True, help="video file, image folder, or device index / stream URL")
    _board_args(i)
    i.add_argument("--model", choices=("pinhole", "fisheye"), default="pinhole", help="lens model [pinhole]")
    i.add_argument("--out", default=None, help="the intrinsics file: .toml (voxelwatch) or .xml/.yaml/.json (OpenCV) "
                                                "[ID-intrinsics.toml]")
    i.set_defaults(handler=_intrinsics)
    f = actions.add_parser("floor", help="every camera's pose from a board laid on the floor (and set up on a stand "
                                         "where cameras share no place of the floor); writes the site's calibration "
                                         "files")
    f.add_argument("--site", required=True, help="the site TOML file")
    f.add_argument("--clip", action="append", default=[], metavar="CAM=FILE",
                   help="a camera's clip of the board on the floor (default: the camera's source); all clips recorded together")
    f.add_argument("--intrinsics", action="append", default=[], metavar="CAM=FILE",
                   help="a camera's intrinsics file (default: the site's calibration file of the camera)")
    _board_args(f)
    f.add_argument("--plan-points", default=None, metavar="FILE",
                   help="TOML file of board-frame <-> room floor points placing the board in the room")
    f.add_argument("--dry-run", action="store_true", help="print the result, write nothing")
    f.add_argument("--fit-board", action="store_true",
                   help="take a chessboard's corners from the board fitted to each still frame as a whole (for boards "
                        "seen small, their rows a few pixels apart; docs/guides/calibrating.md says when it helps)")
    f.set_defaults(handler=_floor)


def _board_args(p) -> None:
    p.add_argument("--board", default="8x6", help="COLSxROWS: a chessboard's inner corners, or with --charuco the "
                                                  "ChArUco board's squares [8x6]")
    p.add_argument("--square-mm", type=float, default=115.0, help="square size, millimetres [115]")
    p.add_argument("--charuco", default=None, metavar="DICT",
                   help="the board is a ChArUco board (a mat) with markers from this OpenCV dictionary, e.g. 4x4_50; "
                        "a camera may see only part of it, where furniture or the image's edge cuts it")
    p.add_argument("--marker-mm", type=float, default=None,
                   help="ChArUco marker side, millimetres, smaller than the square [0.75 x --square-mm]")


def _parse_board(args: argparse.Namespace):
    """The chessboard or ChArUco board the options describe; ValueError naming the option."""
    from calibrate.board import Board
    from calibrate.charuco import CharucoBoard

    if args.charuco is not None:
        return CharucoBoard.parse(args.board, args.square_mm, args.marker_mm, args.charuco)
    if args.marker_mm is not None:
        raise ValueError("--marker-mm is for a ChArUco board: give --charuco DICT too")
    return Board.parse(args.board, args.square_mm)


def _intrinsics(args: argparse.Namespace) -> int:
    from calibrate.intrinsics import LENS_TILT_95_DEG, calibrate_intrinsics
    from calibrate.write import write_intrinsics

    board = _parse_board(args)
    out = Path(args.out or f"{args.camera}-intrinsics.toml")
    if out.suffix.lower() not in (".toml", ".xml", ".yaml", ".yml", ".json"):
        raise ValueError(f"--out {out}: expected a .toml (voxelwatch) or .xml/.yaml/.json (OpenCV) file name")
    res = calibrate_intrinsics(args.clip, args.camera, board, model=args.model)
    cam = res.camera
    print(f"camera {args.camera}: {cam.model} {cam.width}x{cam.height}, RMS reprojection error {res.rms_px:.3f} px "
          f"over {res.views_used} views")
    print(f"  board found in {res.views_found} of {res.frames_searched} frames searched; left out: "
          f"{res.skipped_small} too small, {res.skipped_blurred} blurred, {res.skipped_duplicate} repeats, "
          f"{res.dropped_outliers} outliers")
    K = cam.K
    print(f"  fx {K[0, 0]:.2f}  fy {K[1, 1]:.2f}  cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f} px; distortion "
          f"[{', '.join(f'{v:.5f}' for v in cam.dist)}]")
    sx, sy = res.centre_sd_px
    print(f"  uncertainty (one standard deviation): fx {res.focal_sd_px:.2f} px, cx {sx:.2f} px, cy {sy:.2f} px: "
          f"the camera's tilt to {res.tilt_95_deg:.3f} degree (95 %); the board spanned {100 * res.board_span:.0f} % "
          "of the image's width (median)")
    if res.rms_px > 1.0:
        print("  WARNING: above 1 px: the board may be bent, blurred or badly lit; record again")
    if res.uncertain:
        print(f"  WARNING: the lens's centre leaves camera {args.camera}'s tilt uncertain by more than "
              f"{LENS_TILT_95_DEG:.2f} degree, which no floor calibration takes back: record again with the board "
              "nearer, spanning half the image's width or more, tilted, in more places")
    write_intrinsics(cam, out, res.centre_sd_px)
    print(f"wrote {out}")
    return 0


def _floor(args: argparse.Namespace) -> int:
    from calibrate.floor import (
        ANGLE_TOLERANCE_DEG, FOCAL_PRIOR, MISFIT_PX, POSITION_TOLERANCE_M, calibrate_floor, find_sightings,
        read_plan_points,
    )
    from calibrate.write import WRITABLE, write_site_calibrations
    from calibrate.intrinsics import LENS_TILT_95_DEG, lens_tilt_95_deg
    from common.calibration import CalibrationError, lens_centre_sd, load_calibration
    from common.site import load_site

    board = _parse_board(args)
    if args.fit_board and args.charuco is not None:
        raise ValueError("--fit-board fits a chessboard to the frames; a ChArUco board's corners are taken as its "
                         "markers name them: leave out --fit-board or --charuco")
    site = load_site(args.site)
    clips = _pairs(args.clip, "--clip", site)
    given = _pairs(args.intrinsics, "--intrinsics", site)
    plan = read_plan_points(args.plan_points) if args.plan_points else None
    for cam_id in site.camera_ids:
        spec = site.camera(cam_id)
        if cam_id not in clips:
            if not spec.source or spec.source.startswith("synthetic"):
                raise ValueError(f"camera {cam_id}: no clip: give --clip {cam_id}=FILE")
            clips[cam_id] = str(site.resolve(spec.source)) if not spec.source.isdigit() and "://" not in spec.source \
                else spec.source
        if spec.format not in WRITABLE and not args.dry_run:
            raise ValueError(f"site file {site.source}: camera {cam_id}: {spec.format} calibrations cannot be "
                             f"written; switch it to one of {', '.join(WRITABLE)}")
    intrinsics, rough, lens_tilt = {}, {}, {}
    for cam_id in site.camera_ids:
        try:
            rough[cam_id] = site.load_camera(cam_id)
        except CalibrationError:
            if cam_id not in given:
                raise
            rough[cam_id] = None
        if cam_id in given:
            path = Path(given[cam_id])
            spec = site.camera(cam_id)
            fmt = "voxelwatch" if path.suffix.lower() == ".toml" else (
                "opencv-fisheye" if spec.format == "opencv-fisheye" else "opencv")
            intrinsics[cam_id] = load_calibration(path, fmt, cam_id, image_size=spec.resolution)
        else:
            intrinsics[cam_id] = rough[cam_id]
            path, fmt = site.calibration_path(cam_id), site.camera(cam_id).format
        sd = lens_centre_sd(path, fmt)
        if sd is not None:
            lens_tilt[cam_id] = lens_tilt_95_deg(intrinsics[cam_id], sd)
        if rough[cam_id] is not None and not _plausible(rough[cam_id]):
            rough[cam_id] = None
    first = site.cameras[0]
    sightings = find_sightings(clips, intrinsics, board, rough, fit_board=args.fit_board)
    result = calibrate_floor(sightings, intrinsics, board, rough=rough, plan_points=plan,
                             placement=(first.origin_m, first.yaw_deg), volume=(site.volume.min_m, site.volume.max_m),
                             lens_tilt_95_deg=lens_tilt)
    print(f"site {site.name}: board {board.describe()}, {result.positions} board position(s), "
          f"{len(site.camera_ids)} cameras")
    ox, oy, _ = result.origin_m
    where = "from the plan points" if plan is not None else "from the site's first camera entry"
    print(f"  board frame in the room ({where}): origin ({ox:.3f}, {oy:.3f}) m, yaw {result.yaw_deg:.2f} deg"
          + (f", plan points fit to {100 * result.plan_residual_m:.1f} cm" if result.plan_residual_m is not None else ""))
    loose, lens, centre = [], [], []
    for cam_id, rep in result.reports.items():
        x, y, z = rep.centre_m
        of_lens = f", the lens's centre {rep.lens_tilt_95_deg:.2f} deg of it" if rep.lens_tilt_95_deg else ""
        detector = "" if math.isnan(rep.detected_px) else f", the detector's own corners {rep.detected_px:.2f} px"
        print(f"  camera {cam_id}: reprojection {rep.mean_px:.2f} px mean, {rep.max_px:.2f} px max over {rep.corners} "
              f"corners ({rep.corners_found - rep.corners} stray left out{detector}) in {rep.positions} position(s); "
              f"at ({x:.2f}, {y:.2f}) m, height {z:.2f} m, within {100 * rep.position_95_m:.1f} cm and "
              f"{rep.total_angle_95_deg:.2f} deg (95 %{of_lens}); sees {100 * rep.seen_share:.0f} % of the volume; "
              f"focal length {100 * rep.focal_change:+.2f} % over the lens file's")
        if not rep.pinned:
            loose.append(cam_id)
        if rep.lens_doubtful:
            lens.append(cam_id)
        if rep.lens_uncertain:
            centre.append(cam_id)
    for note in result.notes:
        print(f"  note: {note}")
    for cam_id in lens:
        rep = result.reports[cam_id]
        print(f"  WARNING: camera {cam_id}'s lens disagrees with the board places (its focal length moved "
              f"{100 * rep.focal_change:+.2f} %, over three times the {100 * FOCAL_PRIOR:g} % a lens file is trusted "
              f"to, or its corners are missed by {rep.mean_px:.2f} px on average, over {MISFIT_PX:g} px): check its "
              "intrinsics (the right file, the image size) and that the board lies flat, or calibrate the lens again "
              "with the board held near the image's edges and corners too")
    for cam_id in centre:
        rep = result.reports[cam_id]
        print(f"  WARNING: camera {cam_id}'s lens leaves its angle uncertain by {rep.total_angle_95_deg:.2f} deg, over "
              f"{ANGLE_TOLERANCE_DEG} deg, though the board places pin it: its lens file's principal point is "
              f"{rep.lens_tilt_95_deg:.2f} deg of it (over {LENS_TILT_95_DEG:.2f} would be warned of by calibrate "
              "intrinsics); calibrate the lens again with the board nearer, spanning half the image's width or more")
    for cam_id in loose:
        print(f"  WARNING: camera {cam_id} may be off by more than {100 * POSITION_TOLERANCE_M:.0f} cm or "
              f"{ANGLE_TOLERANCE_DEG} deg: it sees the board too small or too few times; record again with the board "
              f"also laid nearer to it, where another camera sees it too (on the floor, or on a stand), at places "
              f"spread across its view, near and far")
    if args.dry_run:
        print("dry run: nothing written")
        return 0
    for path, backup in write_site_calibrations(site, result.cameras):
        print(f"wrote {path}" + (f" (the old file kept as {backup.name})" if backup else ""))
    return 0


def _pairs(items, flag: str, site) -> dict[str, str]:
    out = {}
    for item in items:
        cam_id, sep, value = item.partition("=")
        if not sep or not value:
            raise ValueError(f"{flag} {item!r}: expected CAM=FILE")
        site.camera(cam_id)   # a SiteError naming the cameras when unknown
        if cam_id in out:
            raise ValueError(f"{flag}: camera {cam_id} given twice")
        out[cam_id] = value
    return out


def _plausible(cam) -> bool:
    """A rough pose worth using: the camera above the floor, not the identity of an intrinsics file."""
    return bool(cam.center[2] > 0.2 and math.isfinite(cam.center[2]) and cam.R[2, 2] < 0.99)
