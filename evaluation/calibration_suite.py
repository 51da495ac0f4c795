"""The calibration commands on randomised worlds: how close the calibrated cameras come to the true ones.

``python -m evaluation.calibration_suite --seeds 1000-1009 [--lenses] [--out DIR]`` takes each world of
:mod:`synth.world` (its room, its rig of two to eight cameras, pinholes of 320x240 to
1280x720 and ceiling fisheyes) and calibrates it as an installer would:

1. with ``--lenses``, each camera's lens from a clip of a board moved in front of it
   (:func:`synth.board.intrinsics_poses`): a 9x6 chessboard of 140 mm through pinholes,
   a 7x5-square ChArUco board of 140 mm through fisheyes, many of its views only partly in the
   image (a chessboard bent that much by the lens is not found), 30 views each (about a minute of
   holding the board still at places), the board spanning a quarter to three fifths of the image's
   width (:data:`HELD`), and recorded again nearer (:data:`NEARER`) where the command warns that the
   lens's centre leaves the camera's tilt uncertain (a camera it still warns of counts as warned);
   without it the true lenses, which the floor calibration still refines
   (:data:`calibrate.floor.FOCAL_PRIOR`);
2. the floor: a 9x6 chessboard of 140 mm (or, where the command refuses it because no chain of
   places reaches every camera, a floor mat of 250 mm squares, then a ChArUco mat of the same size
   that counts where a camera reads only part of it, then the 140 mm chessboard set up on a stand
   where no place of the floor chains a camera: :data:`FLOOR_BOARDS`) laid at the places the installer's instructions lead to
   (:func:`synth.board.floor_positions` with ``well_seen``: a chain of places seen by two
   cameras or more, starting from the place most cameras see, of those the one they see largest (it
   is the floor frame), plus, for each camera that saw the board only small, a
   place it sees as large as it can among those another camera also sees), every camera recording every place (a camera
   sees what its lens and the room let it see), the room's own floor texture around it; the
   cameras' present calibrations 3 degrees and 22 cm off (to tell the board's ends apart), the
   first place's corners as plan points;
3. :func:`calibrate.floor.calibrate_floor` on the corners found, as the command runs it;
4. as the command's warning tells the installer: for each camera whose bounds exceed the targets,
   the board laid at two more places that camera sees well (at least :data:`WELL_SEEN` times as large
   as it can; another camera too), each as far as it can be from the places laid so far (spread
   across its view, near and far), and the whole calibration recorded again, up to
   :data:`HEED_ROUNDS` times while the command still warns (``--no-heed``: the first result stands).

Per camera it reports the position error (cm) and the angle error (degrees) against the world's
true camera, and the bounds the calibration itself gave (its 95 % uncertainty, which the command
prints and warns on); in total the share of cameras within 2 cm and 0.3 degree, and whether every
camera outside them was warned about (its bounds, or its lens disagreeing with the board places:
:attr:`calibrate.floor.CameraReport.warned`). A world whose room no chain of board places reaches (every
camera must see a place with another) is counted as refused, with the command's reason.

Seeds below 1000 are for tuning; figures are reported on 1000 and up.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from calibrate.board import Board
from calibrate.charuco import CharucoBoard
from calibrate.floor import ANGLE_TOLERANCE_DEG, POSITION_TOLERANCE_M, floor_points

WELL_SEEN = 0.5
"""A camera whose views of the board are all under this share of the largest it can have gets that place;
the places laid again for a camera the command warns of are seen at least this share as large as it can."""
PLACE_AREAS = (0.006, 0.003)
"""The board places an installer can use: seen by a camera when the board covers this share of its
image; the larger first, the smaller where no chain of larger ones reaches every camera (twice what
the finder takes at least, :data:`calibrate.floor.MIN_FLOOR_AREA`, so that the views that
chain the cameras are found). A world no chain of them reaches is reported as refused: its room is
too large for the board."""
FLOOR_BOARDS = ((Board(9, 6, 0.14), False), (Board(9, 6, 0.25), False),
                (CharucoBoard(10, 7, 0.25, 0.1875, "4x4_50"), False), (Board(9, 6, 0.14), True))
"""The floor boards, each tried where the one before cannot chain the cameras, and whether it may be set up
on a stand: an A0-sized 9x6 chessboard (1.4 x 1 m); a chessboard mat of 250 mm squares (2.5 x 1.75 m) for a
large room or cameras far apart; a ChArUco mat of the same size (10x7 squares, 4x4 markers of 187.5 mm),
which counts where a camera sees it only in part, for a room whose furniture or cameras' views leave no
place seen whole by two; the A0 chessboard again, first on the floor, then on a stand
(:func:`synth.board.stand_pose`, its centre 1.2 m up) where no place of the floor reaches a camera:
cameras level with the room, or looking across furniture, see the air above the floor together."""
LENS_VIEWS = {"pinhole": 30, "fisheye": 30}
HELD = (0.25, 0.6)
"""The share of the image's width the board spans in the lens clip, as an installer first holds it."""
NEARER = (0.45, 0.85)
"""And as the installer holds it when ``calibrate intrinsics`` warns that the lens's centre is uncertain
(the warning asks for half the image's width or more)."""
HEED_ROUNDS = 3
"""How many times the installer records again for the cameras the command still warns of (each time two
more places for each, where it has not been laid yet). A camera far from every place is pinned by how far apart
the places it sees lie, and each round spreads them further: on the PETS rig (tuning world 12, corners exact
with 0.1 px of noise) view3, 34-40 m from them, came 1.41 cm from the truth after two rounds, 1.03 cm after three."""


def angle_between_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (degrees) of the rotation taking ``Rb`` to ``Ra``."""
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def plan_points(board, pose) -> np.ndarray:
    """(4, 4) rows ``board_x, board_y, room_x, room_y``: the board's outer inner corners where they lie."""
    from synth.board import corners_world

    b = floor_points(board)
    w = corners_world(board, pose)
    cols = board.cols - 1 if isinstance(board, CharucoBoard) else board.cols   # inner corners along a row
    k = [0, cols - 1, board.n - cols, board.n - 1]
    return np.concatenate([b[k, :2], w[k, :2]], axis=1)


def rough_cameras(cameras) -> dict:
    """The cameras as a site's present, rough calibration might have them: 3 degrees and 22 cm off."""
    a = math.radians(3.0)
    turn = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return {c: cam.with_world(turn, np.array([0.2, -0.1, 0.0])) for c, cam in cameras.items()}


def fit_lens(true, folder: Path, seed: int):
    """(lens, whether the command still warns of it, how far its principal point may tilt the camera (95 %,
    degrees; 0 for a lens kept)): the camera's lens from a rendered board clip, as
    ``calibrate intrinsics`` fits it, recorded again with the board nearer (:data:`NEARER`) where the
    command warns that the fit leaves the camera's tilt uncertain; a Tsai lens (the PETS rig's) is kept,
    as the command fits no Tsai model."""
    from calibrate.intrinsics import calibrate_intrinsics
    from synth.board import BoardRenderer, intrinsics_clip, intrinsics_poses, write_frames

    if true.model == "tsai":
        return true, False, 0.0
    if true.model == "fisheye":
        board, views, reach = CharucoBoard(7, 5, 0.14, 0.105, "5x5_100"), LENS_VIEWS["fisheye"], 0.4
    else:
        board, views, reach = Board(9, 6, 0.14), LENS_VIEWS["pinhole"], 1.0
    res = None
    for k, fill in enumerate((HELD, NEARER)):
        poses = intrinsics_poses(true, board, views, np.random.default_rng([seed, k] if k else seed),
                                 min_in_view=reach, fill=fill)
        clip = write_frames(intrinsics_clip(BoardRenderer(true, None, seed=seed), board, poses, frames_per_pose=1),
                            folder / f"take{k + 1}")
        res = calibrate_intrinsics(str(clip), true.id, board, model=true.model)
        if not res.uncertain:
            break
    return res.camera, res.uncertain, res.tilt_95_deg


def run_world(seed: int, work: Path, *, lenses: bool = False, heed: bool = True, fit_board: bool = False
              ) -> dict[str, Any]:
    """One world calibrated (module text); returns per camera its errors and bounds. ``heed``: when the
    calibration warns of a camera, lay the board at two more places it sees well, spread across its view, and
    calibrate again.
    ``fit_board``: the floor views' corners from the board fitted to each still frame as a whole."""
    from synth.world import random_world

    world = random_world(seed)
    t0 = time.perf_counter()
    intrinsics = dict(world.cameras)
    uncertain, tilt = [], {}
    if lenses:
        for k, (c, true) in enumerate(world.cameras.items()):
            intrinsics[c], doubt, tilt[c] = fit_lens(true, work / f"lens-{c}", seed * 100 + k)
            if doubt:
                uncertain.append(c)
    refusals = []
    for k, (board, stand) in enumerate(FLOOR_BOARDS):
        out = _floor_world(world, intrinsics, board, work / f"board{k}", heed=heed, stand=stand, lens_tilt=tilt,
                           fit_board=fit_board)
        out["refused_with"] = refusals
        if "error" not in out:
            break
        refusals.append(f"{_board_name(board, stand)}: {out['error']}")
    for c in uncertain:
        if c in out["cameras"]:
            out["cameras"][c]["lens_uncertain"] = True
            out["cameras"][c]["warned"] = True
    out["seconds"] = time.perf_counter() - t0
    return out


def _floor_world(world, intrinsics, board, work: Path, *, heed: bool, stand: bool = False,
                 lens_tilt: dict[str, float] | None = None, fit_board: bool = False) -> dict[str, Any]:
    from calibrate.floor import FloorError
    from synth.board import floor_positions, more_floor_positions, on_stand

    seed = world.seed
    out: dict[str, Any] = {"seed": seed, "rig": world.rig, "board": _board_name(board, stand), "cameras": {},
                           "warned_first": []}
    poses = None
    for min_area in PLACE_AREAS:   # a large room, or far cameras: places seen smaller
        try:
            poses = floor_positions(world.cameras, world.room, board, np.random.default_rng(seed), min_area=min_area,
                                    well_seen=WELL_SEEN, stand=stand)
            break
        except ValueError as exc:
            why = str(exc)
    try:
        if poses is None:
            raise FloorError(f"no chain of board places: {why}")
        looked: dict = {}   # the stills of the places laid so far, searched once
        result = _calibrate(world, intrinsics, board, poses, work / "floor", lens_tilt, fit_board, looked)
        warned = [c for c, rep in result.reports.items() if not rep.pinned]
        out["warned_first"] = warned
        rounds = HEED_ROUNDS if heed else 0
        for k in range(rounds):
            if not warned:
                break
            rng = np.random.default_rng([seed, 1 + k])
            before = len(poses)
            for c in warned:
                poses = poses + more_floor_positions(world.cameras, world.room, board, rng, c, poses,
                                                     min_area=min_area, stand=stand, rule="spread",
                                                     well_seen=WELL_SEEN)
            if len(poses) == before:
                break   # nowhere left to lay it for them
            result = _calibrate(world, intrinsics, board, poses, work / f"floor-again{k + 1}", lens_tilt, fit_board,
                                looked)
            warned = [c for c, rep in result.reports.items() if not rep.pinned]
            out["heed_rounds"] = k + 1
    except FloorError as exc:
        out["error"] = str(exc)
        return out
    out["places"] = len(poses)
    out["stand_places"] = sum(1 for pose in poses if on_stand(board, pose))
    for c, true in world.cameras.items():
        got, rep = result.cameras[c], result.reports[c]
        out["cameras"][c] = {
            "model": true.model, "size": f"{true.width}x{true.height}",
            "position_cm": 100 * float(np.linalg.norm(got.center - true.center)),
            "angle_deg": angle_between_deg(got.R, true.R),
            "bound_cm": 100 * rep.position_95_m, "bound_deg": rep.total_angle_95_deg,
            "lens_tilt_deg": rep.lens_tilt_95_deg,
            "reprojection_px": rep.mean_px, "board_views": rep.positions, "warned": rep.warned,
        }
    return out


def _calibrate(world, intrinsics, board, poses, folder: Path, lens_tilt: dict[str, float] | None = None,
               fit_board: bool = False, looked: dict | None = None):
    """Every camera records the board at every place; the floor calibration of what they found (``looked``:
    :func:`calibrate.floor.find_sightings`'s stills already searched)."""
    from calibrate.floor import calibrate_floor, find_sightings
    from synth.board import BoardRenderer, floor_clip, write_frames

    clips = {c: str(write_frames(floor_clip(BoardRenderer(cam, world.room, seed=world.seed), board, poses), folder / c))
             for c, cam in world.cameras.items()}
    sightings = find_sightings(clips, intrinsics, board, rough_cameras(world.cameras), fit_board=fit_board,
                               looked=looked)
    return calibrate_floor(sightings, intrinsics, board, plan_points=plan_points(board, poses[0]),
                           lens_tilt_95_deg=lens_tilt)


def _board_name(board, stand: bool = False) -> str:
    kind = "ChArUco mat" if isinstance(board, CharucoBoard) else "chessboard"
    return f"{kind} of {1000 * board.square_m:.0f} mm squares{', on the floor and on a stand' if stand else ''}"


def _on_target(v: dict) -> bool:
    """Whether a camera's figures lie within 2 cm and 0.3 degree of the truth."""
    return v["position_cm"] < 100 * POSITION_TOLERANCE_M and v["angle_deg"] < ANGLE_TOLERANCE_DEG


def summarise(results: list[dict]) -> dict[str, Any]:
    """Cameras within the targets, the worst errors, and whether the bounds warned of every miss."""
    cams = [c for r in results for c in r["cameras"].values()]
    within = [c for c in cams if _on_target(c)]
    warned = [c for c in cams if c["warned"]]
    missed_unwarned = [c for c in cams if c not in within and c not in warned]
    return {
        "worlds": len(results), "refused_worlds": sum(1 for r in results if "error" in r),
        "warned_first": sum(len(r["warned_first"]) for r in results), "cameras": len(cams),
        "within_target": len(within), "warned": len(warned), "outside_target_unwarned": len(missed_unwarned),
        "worst_position_cm": max((c["position_cm"] for c in cams), default=None),
        "worst_angle_deg": max((c["angle_deg"] for c in cams), default=None),
        "worst_unwarned_position_cm": max((c["position_cm"] for c in cams if c not in warned), default=None),
        "worst_unwarned_angle_deg": max((c["angle_deg"] for c in cams if c not in warned), default=None),
    }


def main(argv: list[str] | None = None) -> int:
    from evaluation.world_suite import parse_seeds

    p = argparse.ArgumentParser(prog="python -m evaluation.calibration_suite", description=__doc__.split("\n")[0])
    p.add_argument("--seeds", required=True, help="e.g. 1000-1009 (below 1000: tuning seeds)")
    p.add_argument("--lenses", action="store_true", help="fit every lens from a rendered clip first")
    p.add_argument("--out", type=Path, default=None, help="keep the rendered clips here (default: a temporary folder)")
    p.add_argument("--json", type=Path, default=None, help="write every world's figures here")
    p.add_argument("--no-heed", action="store_true", help="do not lay the board again for cameras the calibration "
                                                           "warns of")
    p.add_argument("--fit-board", action="store_true", help="floor views' corners from the board fitted to each "
                                                             "still frame as a whole (calibrate floor --fit-board)")
    args = p.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        p.error(str(exc))
    results = []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            work = (args.out / f"seed-{seed}") if args.out else Path(tmp)
            r = run_world(seed, work, lenses=args.lenses, heed=not args.no_heed, fit_board=args.fit_board)
        results.append(r)
        _report(r)
    total = summarise(results)
    print(f"calibration, seeds {args.seeds}{' (lenses fitted)' if args.lenses else ''}"
          f"{' (boards fitted to the frames)' if args.fit_board else ''}: {total}")
    if args.json is not None:
        import json

        args.json.write_text(json.dumps({"worlds": results, "total": total}, indent=1) + "\n", encoding="utf-8")
    return 0


def _report(r: dict) -> None:
    if "error" in r:
        print(f"  world {r['seed']} ({r['rig']}): refused: {r['error']}", flush=True)
        return
    rounds = f" ({r['heed_rounds']} rounds)" if r.get("heed_rounds", 0) > 1 else ""
    again = f", board laid again for {', '.join(r['warned_first'])}{rounds}" if r["warned_first"] else ""
    stands = f" ({r['stand_places']} on a stand)" if r.get("stand_places") else ""
    print(f"  world {r['seed']} ({r['rig']}, {r['board']}, {r['places']} board places{stands}{again}, "
          f"{r['seconds']:.0f} s):", flush=True)
    for c, v in r["cameras"].items():
        flag = "" if _on_target(v) else "  OUTSIDE"
        warn = ("  (warned: lens)" if v.get("lens_uncertain") else "  (warned)") if v["warned"] else ""
        print(f"    {c} {v['model']} {v['size']}: position {v['position_cm']:.2f} cm, angle {v['angle_deg']:.3f} deg; "
              f"bounds {v['bound_cm']:.2f} cm, {v['bound_deg']:.3f} deg; {v['reprojection_px']:.2f} px over "
              f"{v['board_views']} place(s){flag}{warn}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
