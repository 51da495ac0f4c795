"""Floor calibration: every camera's pose from a board laid on the floor.

The board lies still at one place or more, seen by every camera at once or by a few at a time;
the clips are recorded together (they start at the same moment, at the same rate), so the still
stretches of different cameras that overlap in time show the same board position
(:mod:`calibrate.clips`).

1. Per camera and still stretch: the board's corners (:func:`~calibrate.board.find_board`,
   with the floor seen from above through the camera's rough pose when the site has one); on
   request, a chessboard's then from the board fitted to the still frame as a whole through the
   lens (:mod:`calibrate.boardfit`: every pixel of its squares, where the detector places
   each corner from the few pixels around it).
2. Orientation: corners are named the same way in every camera (:mod:`calibrate.board`);
   a board that looks the same turned half round is oriented in each camera by the cameras'
   rough poses (the site's present calibrations), which only need to be right to within a
   quarter turn; without them such a board is refused when two cameras must share it.
3. Per sighting: ``solvePnP`` (IPPE, then iterative) on the corners' normalised lens
   coordinates, so pinhole, fisheye and Tsai lenses are handled alike by their own model.
4. Chaining: the first board position is the floor frame (origin at its first inner corner, X
   along its rows, Z up out of the floor); cameras and board positions are placed in turn through
   the sightings they share (breadth first). Cameras that no chain reaches are named. A position
   whose board's centre the chain puts over :data:`RAISED_M` above the floor stood on a stand (set up
   where cameras share no place of the floor): its whole pose is kept; the others lie on the floor.
5. Bundle adjustment (``scipy.optimize.least_squares``, soft-L1 loss with a 1 px scale) over
   every camera pose (6 values), every camera's focal length (held to its lens file's by a prior,
   :data:`FOCAL_PRIOR`: the board places at known distances apart pin it down better than a board
   clip held up close), every pinhole lens's k3 (held to its lens file's by :data:`LENS_CORNER_PX`:
   the floor board is seen near the image's corners, where a lens clip seldom reaches) and every other
   board position, which lies on the same floor (x, y, yaw)
   or, on a stand, anywhere (6 values), minimising the corners' reprojection error in pixels
   through each lens model. A camera's view of one position that the other views outvote (a board
   partly hidden, found a square off) is left out and the chain adjusted again: the views explained
   worst are each left out in turn, and one is wrong when the chain adjusted without it misses it by
   far (:data:`WRONG_SIGHTING_PX`) while its camera's other views come back within the noise
   (:func:`_outvoted_sighting`); the view explained worst with it in need not be the wrong one, as the
   adjustment spreads a wrong view's error over its camera's other views.
   Each camera's 95 % bounds on its position and orientation come from the adjustment's covariance
   (:func:`pose_uncertainty`): how precisely its views of the board pin it down.
6. Placement in the room: floor-plan points (board-frame floor coordinates <-> room coordinates,
   two or more) give a rotation about Z and a shift (least squares, no scale); without them the
   board frame sits where the site's first camera's ``origin_m``/``yaw_deg`` put its calibration frame.
"""

from __future__ import annotations

import hashlib
import math
import tomllib
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from calibrate.board import Board, board_area_fraction, board_pose, find_board
from calibrate.boardfit import refined_corners
from calibrate.charuco import FACE_UP, CharucoBoard, CharucoFinder
from calibrate.clips import read_gray, still_stretches
from common.camera import Camera, matrix_to_rodrigues, pinhole_distort, rodrigues_to_matrix

MIN_FLOOR_AREA = 0.0015
"""A board on the floor must cover at least this share of the image (0.15 %, about 22 x 22 px at 640 x 480)."""
CLIP_SPREAD = 900
STRAY_PX = 1.5
"""A corner that misses the board's own best pose by more than this and by four times the sighting's
median error is a stray detection (a corner snapped to a neighbouring edge) and is left out."""
WRONG_SIGHTING_PX = 2.0
"""A camera's view of one board position that the poses adjusted without it miss by more than this on average
(and by four times the median view), while the camera's other views agree with them, is left out: a board
partly hidden by furniture can be found with its corners a square off."""
NOISE_FLOOR_PX = 0.25
"""The least corner noise assumed for the calibration's error bounds (pixels): a fit that leaves less
is not trusted to be that precise (a corner error a view's corners share moves its pose without showing
in the residuals; with this floor the bounds covered the tuning worlds' rendered boards)."""
POSITION_TOLERANCE_M = 0.02
"""A camera's calibrated centre should be within this of the truth (the fusion's targets rest on it)."""
ANGLE_TOLERANCE_DEG = 0.3
"""And its orientation within this (the moved-camera alarm's view tolerance)."""
FOCAL_PRIOR = 0.002
"""How far (one standard deviation, a share) a lens file's focal length is taken to be from the truth. The
adjustment refines each camera's focal length from the board places, held to the lens file's by this, so
that the bounds carry the lens's own error: a focal length 0.2 % long puts a camera 5 m from the board
1 cm too far along its view. ``calibrate intrinsics`` fitted the tuning worlds' rendered board clips
within 0.03-0.27 % (30 views). Tsai lenses keep theirs."""
RADIAL = (0, 1, 4)
"""Where k1, k2 and k3 sit in a pinhole lens's distortion coefficients (OpenCV's order)."""
FREED = (2,)
"""The radial terms the adjustment refines (indices into :data:`RADIAL`): k3 alone, the term that moves the
image's edges and corners and hardly its middle, which a lens clip pins down well. Freeing k1 and k2 as well
traded them against the focal length and widened every camera's bounds."""
LENS_CORNER_PX = 3.0
"""How far (one standard deviation, pixels) a pinhole lens file's k3 is taken to move the image's farthest corner
from the truth. The adjustment refines it from the board places (:data:`FREED`), held to the lens file's by
this: a lens clip that never showed the board near the image's corners leaves the lens there to
extrapolation (a lab lens whose k3 of -0.031 the clip could not tell from none came out 15 px off at the
corners, 1-2 px where the floor board lay, and its camera 26 cm off), while the floor board, laid around the
room, is seen there. On tuning seed 6's lab rig with every lens file fitted inside 60 % of its corner
radius, 2 px left cam2 1.6 cm off, 3 px 0.7 cm and 5 px 1.1 cm (2.8 cm held)."""
MAX_SUSPECTS = 6
"""At most this many views are left out in turn to find one the others outvote (:func:`_outvoted_sighting`)."""
MISFIT_PX = 1.0
"""A camera whose board corners the adjusted calibration misses by more than this on average (four times the
corners' least noise, :data:`NOISE_FLOOR_PX`) is not described by its lens file where it sees the board: its
bounds, which take the errors for noise, do not hold for it."""
ROUGH_BOARD_Z_M = 0.6
"""By the site's present (rough) calibrations, a board lying on the floor is within this of it; one higher
stood on a stand."""
RAISED_M = 0.3
"""A board position whose squares' centre the chain puts higher than this above the floor stood on a stand
(an easel) and keeps its whole pose (a board on the floor, seen small and far, comes out a few centimetres
off the floor at most; on a stand its centre is half a metre up or more)."""
ROUGH_AGREE_M = 1.2


class FloorError(ValueError):
    """Clips that cannot give the cameras' poses; the message says why and what to do."""


@dataclass(frozen=True)
class Sighting:
    """One camera's view of one board position: (N, 2) corners, the frames it covers."""

    cam_id: str
    start: int
    stop: int
    corners: np.ndarray
    area: float
    position: int = -1
    keep: np.ndarray | None = None
    """(N,) bool: corners used (None: all)."""
    ids: np.ndarray | None = None
    """(N,) the corners' indices into the board's points (a ChArUco board seen in part); None: every
    corner, in board order (a chessboard)."""
    detected: np.ndarray | None = None
    """(N, 2) the detector's own corners where ``corners`` come from the board fitted to the frame as a whole
    (:mod:`calibrate.boardfit`); None: ``corners`` are the detector's."""

    @property
    def kept(self) -> np.ndarray:
        return np.ones(len(self.corners), dtype=bool) if self.keep is None else self.keep

    def points(self, obj: np.ndarray) -> np.ndarray:
        """(N, 3) the board points (``obj``, every corner of the board) its corners show."""
        return obj if self.ids is None else obj[self.ids]


def floor_points(board: Board | CharucoBoard) -> np.ndarray:
    """(N, 3) the board's inner corners in its floor frame, Z up out of the printed face: a chessboard's
    own frame; a ChArUco board's is OpenCV's (Z into the sheet) turned over about X, so that Y runs up
    the sheet from its first row and the corners lie at negative Y."""
    obj = board.object_points()
    return obj @ FACE_UP.T if isinstance(board, CharucoBoard) else obj


@dataclass(frozen=True)
class CameraReport:
    """What the calibration says about one camera (room frame, metres)."""

    cam_id: str
    positions: int
    corners: int
    """Corners used (all but stray ones, see :data:`STRAY_PX`)."""
    corners_found: int
    mean_px: float
    max_px: float
    mean_all_px: float
    """Mean error over every corner found, stray ones included."""
    centre_m: tuple[float, float, float]
    seen_share: float
    position_95_m: float = float("nan")
    """How far the camera's centre may lie from the one found (95 % bound, metres, relative to the
    first board position), from the bundle adjustment's covariance (see :func:`pose_uncertainty`)."""
    angle_95_deg: float = float("nan")
    """The same for its orientation (degrees)."""
    focal_change: float = 0.0
    """The focal length the adjustment found over the lens file's, less one (0.003: 0.3 % longer)."""
    lens_change_px: float = 0.0
    """How far the adjustment's radial distortion moved the image's corners from the lens file's (pixels)."""
    detected_px: float = float("nan")
    """Mean distance (pixels, over the corners used) of the calibrated board's corners from the detector's own,
    where the floor views' corners come from the board fitted to the frame as a whole (NaN: they are the
    detector's): a check of the calibration against corners that fit did not place."""
    lens_tilt_95_deg: float = 0.0
    """How far (95 %, degrees) the lens file's principal point leaves the camera's tilt uncertain, from the lens
    fit's own uncertainty when the file carries it (0: it does not). The board places cannot take it back (a
    principal point off by a pixel turns the camera as a pixel's turn would), so it adds to
    :attr:`angle_95_deg`, the board places' own bound, in :attr:`total_angle_95_deg`."""

    @property
    def total_angle_95_deg(self) -> float:
        """The orientation's bound with the lens's: the two independent, their variances added."""
        return math.hypot(self.angle_95_deg, self.lens_tilt_95_deg)

    @property
    def pinned(self) -> bool:
        """Whether the board places' bounds lie within :data:`POSITION_TOLERANCE_M` and :data:`ANGLE_TOLERANCE_DEG`
        (else more places near the camera pin it better)."""
        return self.position_95_m <= POSITION_TOLERANCE_M and self.angle_95_deg <= ANGLE_TOLERANCE_DEG

    @property
    def lens_uncertain(self) -> bool:
        """Whether, the board places pinning the camera, its lens's principal point takes the orientation's bound
        past :data:`ANGLE_TOLERANCE_DEG` (the lens wants calibrating again, the board held nearer)."""
        return self.pinned and self.total_angle_95_deg > ANGLE_TOLERANCE_DEG

    @property
    def lens_doubtful(self) -> bool:
        """Whether its lens file disagrees with the board places: its focal length moved over three times the
        prior (:data:`FOCAL_PRIOR`), or its corners are missed by over :data:`MISFIT_PX` on average."""
        return abs(self.focal_change) > 3 * FOCAL_PRIOR or self.mean_px > MISFIT_PX

    @property
    def warned(self) -> bool:
        """Whether ``calibrate floor`` warns of it (:attr:`pinned`, :attr:`lens_doubtful`, :attr:`lens_uncertain`)."""
        return not self.pinned or self.lens_doubtful or self.lens_uncertain


@dataclass
class FloorResult:
    """cameras: camera id -> camera in the room frame. board_cameras: the same in the board frame."""

    cameras: dict[str, Camera]
    board_cameras: dict[str, Camera]
    reports: dict[str, CameraReport]
    positions: int
    origin_m: tuple[float, float, float]
    yaw_deg: float
    plan_residual_m: float | None = None
    notes: list[str] = field(default_factory=list)
    sightings: list[Sighting] = field(default_factory=list)


def find_sightings(clips: dict[str, str], intrinsics: dict[str, Camera], board: Board | CharucoBoard,
                   rough: dict[str, Camera | None], *, fit_board: bool = False,
                   looked: dict[tuple, tuple] | None = None) -> list[Sighting]:
    """Every camera's board sightings, one per still stretch of its clip in which the board is found;
    FloorError when a camera never sees it or sees it too small; ClipError for a clip that cannot be read.
    fit_board: a chessboard's corners from the board fitted to the still frame as a whole
    (:mod:`calibrate.boardfit`), the detector's kept in :attr:`Sighting.detected`.
    looked: what was found in still frames looked at before, by camera and frame; a caller that looks
    again at clips grown by more places (the board laid again where a camera was warned of) passes the
    same dict, and only the new stills are searched (a thorough search of a still the board is not in
    takes seconds)."""
    out: list[Sighting] = []
    finder = CharucoFinder(board) if isinstance(board, CharucoBoard) else None
    for cam_id, clip in clips.items():
        cam = intrinsics[cam_id]
        frames, index = read_gray(clip, spread=CLIP_SPREAD)
        h, w = frames[0].shape[:2]
        if (w, h) != (cam.width, cam.height):
            raise FloorError(f"clip {clip}: frames are {w}x{h} but camera {cam_id} is calibrated for "
                             f"{cam.width}x{cam.height}")
        pose = None if rough.get(cam_id) is None else (rough[cam_id].R, rough[cam_id].t)
        found, small = [], []
        for still in still_stretches(frames, index):
            if looked is None:
                ids, corners, detected = _find_floor_board(still.gray, board, finder, cam, pose, fit_board)
            else:
                key = (cam_id, fit_board, hashlib.blake2b(still.gray.tobytes(), digest_size=16).digest())
                if key not in looked:
                    looked[key] = _find_floor_board(still.gray, board, finder, cam, pose, fit_board)
                ids, corners, detected = (None if a is None else a.copy() for a in looked[key])
            if corners is None:
                continue
            area = board_area_fraction(corners, w, h)
            (found if area >= MIN_FLOOR_AREA else small).append(Sighting(cam_id, still.start, still.stop, corners, area,
                                                                         ids=ids, detected=detected))
        if not found and small:
            raise FloorError(f"clip {clip}: the board is too small in camera {cam_id} "
                             f"({100 * max(s.area for s in small):.2f} % of the image, need {100 * MIN_FLOOR_AREA:g} %): "
                             "lay it nearer to the camera or use bigger squares")
        if not found:
            hint = ("check --board, --charuco and --marker-mm; lying still, evenly lit, its markers large enough to "
                    "read" if isinstance(board, CharucoBoard) else
                    "check --board and --square-mm; the whole board must be in view, lying still, evenly lit")
            raise FloorError(f"clip {clip}: board {board.describe()} not found by camera {cam_id} ({hint})")
        out.extend(found)
    return out


def _find_floor_board(gray: np.ndarray, board: Board | CharucoBoard, finder: CharucoFinder | None, cam: Camera,
                      rough_pose, fit_board: bool = False
                      ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """(ids or None for every corner, (N, 2) corners, the detector's own corners or None where they are the
    corners) of the board in one still frame, or (None, None, None). A
    chessboard is looked for thoroughly (:func:`~calibrate.board.find_board`) and, with ``fit_board``, the
    board found fitted to the frame as a whole (:func:`~calibrate.boardfit.refined_corners`); a ChArUco board by
    its markers (``finder``, the board's), in the frame and, where they are too small to read, in the
    frame doubled."""
    if finder is None:
        detected = find_board(gray, board, camera=cam, thorough=True, rough_pose=rough_pose)
        if detected is None or not fit_board:
            return None, detected, None
        corners = refined_corners(gray, detected, board, cam)
        return None, corners, None if corners is detected else detected
    found = finder.find(gray)
    if found is None:
        big = cv2.resize(gray, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
        found = finder.find(big)
        if found is not None:   # pixel centres are whole numbers at both scales
            found = (found[0], (found[1] + 0.5) / 2 - 0.5)
    return (None, None, None) if found is None else (*found, None)


def calibrate_floor(sightings: list[Sighting], intrinsics: dict[str, Camera], board: Board | CharucoBoard, *,
                    rough: dict[str, Camera | None] | None = None, plan_points=None,
                    placement: tuple[tuple[float, float, float], float] = ((0.0, 0.0, 0.0), 0.0),
                    volume: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
                    lens_tilt_95_deg: dict[str, float] | None = None) -> FloorResult:
    """Camera poses from the sightings (see the module text).

    intrinsics: camera id -> camera whose lens model is used (pose ignored). rough: camera id -> the
    camera's rough pose (room frame), or None. plan_points: (K, 4) rows ``board_x, board_y, room_x,
    room_y`` (metres), K >= 2, or None. placement: ``(origin_m, yaw_deg)`` of the board frame in the
    room without plan points. volume: ``(min_m, max_m)``, for the share of it each camera sees.
    lens_tilt_95_deg: camera id -> how far its lens file's principal point leaves its tilt uncertain
    (:attr:`CameraReport.lens_tilt_95_deg`), for the cameras whose lens files say.
    """
    rough = rough or {}
    cam_ids = list(intrinsics)
    sightings = _number_positions(sightings)
    notes: list[str] = []
    sightings = _orient(sightings, intrinsics, board, rough, notes)
    obj = floor_points(board)
    poses = {id(s): _pnp(intrinsics[s.cam_id], s.points(obj), s.corners) for s in sightings}
    sightings = [_drop_stray_corners(s, intrinsics[s.cam_id], s.points(obj), poses.pop(id(s)), poses)
                 for s in sightings]
    centre_b = obj.mean(axis=0)
    _first_on_floor(sightings, poses, obj, rough)
    while True:
        cams0, boards0, raised = _chain(sightings, poses, cam_ids, centre_b)
        cams_bf, focal, lenses, boards, spread, view_err = _adjust(sightings, intrinsics, obj, cams0, boards0, raised)
        wrong = _outvoted_sighting(sightings, view_err, intrinsics, obj, poses, cam_ids, centre_b)
        if wrong is None:
            break
        rest = [s for s in sightings if s is not wrong]
        notes.append(f"camera {wrong.cam_id}'s view of board position {wrong.position + 1} (frames {wrong.start}-"
                     f"{wrong.stop}) disagreed with the others and was left out (the board partly hidden, or its "
                     f"corners found a square off)")
        sightings = rest
    board_cameras = {c: _adjusted_camera(intrinsics[c], focal[c], lenses.get(c), cams_bf[c]) for c in cam_ids}
    moved = {c: lens_change_px(intrinsics[c], board_cameras[c]) if c in lenses else 0.0 for c in cam_ids}
    for c in sorted(lenses):
        if moved[c] > LENS_CORNER_PX:
            notes.append(f"camera {c}: the board places bent its lens {moved[c]:.1f} px at the image's corners from its "
                         "lens file's (k3); the clip it was fitted from showed the board too little near them, and "
                         "the calibration written carries the lens as the board places have it")
    for p in sorted(raised):
        R_wb, t_wb = boards[p]
        tilt = math.degrees(math.acos(min(1.0, abs(float(R_wb[2, 2])))))
        notes.append(f"board position {p + 1} stood {float((R_wb @ centre_b + t_wb)[2]):.2f} m above the floor, "
                     f"{tilt:.0f} degrees from lying flat (on a stand): its whole pose was fitted")
    residual = None
    if plan_points is not None:
        (origin, yaw_deg), residual = fit_plan(plan_points)
    else:
        origin, yaw_deg = placement
    R_place = _rz(yaw_deg)
    cameras = {c: cam.with_world(R_place, np.asarray(origin, dtype=np.float64)) for c, cam in board_cameras.items()}
    reports = {}
    for c in cam_ids:
        errs, kept, detected = _errors(sightings, c, board_cameras[c], boards, obj)
        checked = kept & np.isfinite(detected)
        centre = tuple(float(v) for v in cameras[c].center)
        share = _seen_share(cameras[c], volume) if volume is not None else float("nan")
        reports[c] = CameraReport(c, len({s.position for s in sightings if s.cam_id == c}), int(kept.sum()), kept.size,
                                  float(errs[kept].mean()), float(errs[kept].max()), float(errs.mean()), centre, share,
                                  *spread.get(c, (float("nan"), float("nan"))), focal_change=focal[c] - 1.0,
                                  lens_change_px=moved[c],
                                  detected_px=float(detected[checked].mean()) if checked.any() else math.nan,
                                  lens_tilt_95_deg=(lens_tilt_95_deg or {}).get(c, 0.0))
    n_pos = len({s.position for s in sightings})
    return FloorResult(cameras=cameras, board_cameras=board_cameras, reports=reports, positions=n_pos,
                       origin_m=tuple(float(v) for v in origin), yaw_deg=float(yaw_deg), plan_residual_m=residual,
                       notes=notes, sightings=sightings)


def fit_plan(points) -> tuple[tuple[tuple[float, float, float], float], float]:
    """``((origin_m, yaw_deg), rms residual m)`` of the rotation about Z and shift taking board-frame
    floor points to room points: (K, 4) rows ``board_x, board_y, room_x, room_y``, K >= 2."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 4)
    a, b = p[:, :2], p[:, 2:]
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    A, B = a - ca, b - cb
    yaw = math.atan2(float(np.sum(A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0])), float(np.sum(A * B)))
    R = _rz(math.degrees(yaw))[:2, :2]
    t = cb - R @ ca
    residual = float(np.sqrt(np.mean(np.sum((a @ R.T + t - b) ** 2, axis=1))))
    return ((float(t[0]), float(t[1]), 0.0), math.degrees(yaw)), residual


def read_plan_points(path: str | Path) -> np.ndarray:
    """A floor-plan points file (TOML)::

        # the first board position's floor coordinates (metres, board frame) -> the room's
        points = [
          { board = [0.0, 0.0], room = [2.10, 1.35] },
          { board = [0.805, 0.0], room = [2.91, 1.35] },
        ]

    Returns (K, 4) float64; ValueError naming the file and the entry."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"plan points file {path}: not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"plan points file {path}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"plan points file {path}: not valid TOML: {exc}") from None
    points = doc.get("points")
    if not isinstance(points, list) or len(points) < 2:
        raise ValueError(f"plan points file {path}: points: expected a list of at least 2 {{ board = [x, y], room = [x, y] }}")
    rows = []
    for i, item in enumerate(points):
        try:
            row = [float(v) for v in (*item["board"], *item["room"])]
            if len(row) != 4 or not all(math.isfinite(v) for v in row) or any(isinstance(v, bool) for v in row):
                raise ValueError
        except (TypeError, KeyError, ValueError):
            raise ValueError(f"plan points file {path}: points[{i}]: expected {{ board = [x, y], room = [x, y] }} "
                             f"in metres, got {item!r}") from None
        rows.append(row)
    arr = np.array(rows)
    if np.ptp(arr[:, :2], axis=0).max() < 0.2:
        raise ValueError(f"plan points file {path}: points: the board points must lie at least 0.2 m apart")
    return arr


# ---------------------------------------------------------------------- steps


def _number_positions(sightings: list[Sighting]) -> list[Sighting]:
    """Sightings of different cameras that overlap in time show one board position; positions are
    numbered by their first frame. A camera with two stretches in one position keeps the longer."""
    order = sorted(range(len(sightings)), key=lambda i: (sightings[i].start, sightings[i].cam_id))
    parent = list(range(len(sightings)))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a in range(len(sightings)):
        for b in range(a + 1, len(sightings)):
            sa, sb = sightings[a], sightings[b]
            if sa.cam_id != sb.cam_id and min(sa.stop, sb.stop) - max(sa.start, sb.start) > 0:
                parent[root(a)] = root(b)
    groups: dict[int, list[int]] = {}
    for i in order:
        groups.setdefault(root(i), []).append(i)
    out = []
    for pos, members in enumerate(sorted(groups.values(), key=lambda m: min(sightings[i].start for i in m))):
        best: dict[str, Sighting] = {}
        for i in members:
            s = sightings[i]
            if s.cam_id not in best or s.stop - s.start > best[s.cam_id].stop - best[s.cam_id].start:
                best[s.cam_id] = s
        out.extend(replace(s, position=pos) for s in best.values())
    return out


def _orient(sightings, intrinsics, board: Board, rough, notes: list[str]) -> list[Sighting]:
    """Name a symmetric board's corners from the same end in every camera that shares a position."""
    if isinstance(board, CharucoBoard) or not board.symmetric:
        return sightings   # the markers, or the odd count, name every corner
    obj = board.object_points()
    out = []
    for pos in sorted({s.position for s in sightings}):
        group = [s for s in sightings if s.position == pos]
        if len(group) == 1 and group[0].cam_id not in {c for c, r in rough.items() if r is not None}:
            out.extend(group)
            continue
        missing = [s.cam_id for s in group if rough.get(s.cam_id) is None]
        if missing:
            raise FloorError(
                f"board {board.cols}x{board.rows} looks the same turned half round, and camera(s) "
                f"{', '.join(missing)} have no rough pose to tell its ends apart: use a board with one odd count "
                f"(e.g. {board.cols + 1}x{board.rows}), or give the site calibrations that place the cameras roughly")
        axes, centres = [], []
        for s in group:
            R, t = _pnp(intrinsics[s.cam_id], obj, s.corners)
            r = rough[s.cam_id]
            R_wb = r.R.T @ R               # board -> rough world
            centre_b = obj.mean(axis=0)
            centres.append(r.R.T @ (R @ centre_b + t - r.t))
            axes.append(R_wb[:, 0])
        centres = np.array(centres)
        if float(np.median(centres[:, 2])) > ROUGH_BOARD_Z_M:   # by the rough poses: on a stand
            raise FloorError(
                f"board {board.cols}x{board.rows} looks the same turned half round: set up on a stand (board position "
                f"{pos + 1}) its ends cannot be told apart; use a board with one odd count (e.g. "
                f"{board.cols + 1}x{board.rows})")
        bad = [s.cam_id for s, c in zip(group, centres) if abs(c[2]) > ROUGH_BOARD_Z_M
               or np.linalg.norm(c[:2] - np.median(centres[:, :2], axis=0)) > ROUGH_AGREE_M]
        if bad:
            raise FloorError(
                f"board {board.cols}x{board.rows} looks the same turned half round, and the site's present calibration "
                f"of {', '.join(bad)} is too far off to tell its ends apart (the board would not lie on the floor "
                f"where the other cameras see it): use a board with one odd count (e.g. {board.cols + 1}x{board.rows})")
        # the first camera's board X axis nearest the room's +X; the others follow it
        first = axes[0] if axes[0][0] >= 0 else -axes[0]
        for s, a in zip(group, axes):
            if np.dot(a, first) < 0:
                s = replace(s, corners=board.half_turn(s.corners),
                            detected=None if s.detected is None else board.half_turn(s.detected))
            out.append(s)
    notes.append("the symmetric board's ends were told apart by the site's present calibrations")
    return out


def _first_on_floor(sightings, poses, obj, rough) -> None:
    """FloorError when the cameras' present calibrations put the first board position, which defines the
    floor frame, well off the floor (set up on a stand); nothing to check without them. poses: id of a
    sighting -> its board -> camera (R, t)."""
    heights = []
    for s in sightings:
        r = rough.get(s.cam_id) if s.position == 0 else None
        if r is not None:
            R, t = poses[id(s)]
            heights.append(float((r.R.T @ (R @ s.points(obj).mean(axis=0) + t - r.t))[2]))
    if heights and float(np.median(heights)) > ROUGH_BOARD_Z_M:
        first = min(s.start for s in sightings if s.position == 0)
        raise FloorError(f"the first board position (from frame {first}) stood about {float(np.median(heights)):.1f} m "
                         "above the floor by the site's present calibrations: lay the board flat on the floor first "
                         "(it defines the floor frame), then set it up on a stand where the cameras share no place "
                         "of the floor")


def _outvoted_sighting(sightings, errs: list[float], intrinsics, obj, poses, cam_ids, centre_b) -> Sighting | None:
    """A view the others outvote (a board partly hidden by furniture, found with its corners a square off),
    or None. The adjustment spreads a wrong view's error over its camera's other views, the more so the fewer
    places the camera sees, so the view it explains worst need not be the wrong one: each view above four
    times the median view's error (``errs``, px), worst first, whose camera sees the board elsewhere, whose
    position another camera sees and without which the chain holds, is left out in turn and the chain
    adjusted without it. It is wrong when that adjustment misses it by over :data:`WRONG_SIGHTING_PX` and
    four times the median view, while its camera's other views come within :data:`MISFIT_PX`, four times
    the median, or a quarter of its own miss (a view half a board off, its ends swapped, beside one a
    little off where a stray corner was kept: tuning seed 0's cam6, 47 px against 1.4 px). Of the views
    found wrong so, the one whose camera's other views come closest for its miss is named: a right view
    left out leaves the wrong one in, and a camera seeing three places takes a wrong view and a right one
    with a little error each, where the wrong view left out leaves almost none."""
    median = float(np.median(errs))
    found = []
    for k in sorted((k for k, e in enumerate(errs) if e > 4.0 * median), key=lambda k: -errs[k])[:MAX_SUSPECTS]:
        s = sightings[k]
        rest = [r for r in sightings if r is not s]
        if not any(r.cam_id == s.cam_id for r in rest) or not any(r.position == s.position for r in rest):
            continue
        try:
            cams0, boards0, raised = _chain(rest, poses, cam_ids, centre_b)
        except FloorError:
            continue
        cams, focal, lenses, boards, _, rest_err = _adjust(rest, intrinsics, obj, cams0, boards0, raised, bounds=False)
        cam = _adjusted_camera(intrinsics[s.cam_id], focal[s.cam_id], lenses.get(s.cam_id), cams[s.cam_id])
        R_wb, t_wb = boards[s.position]
        uv, _ = cam.project(s.points(obj)[s.kept] @ R_wb.T + t_wb)
        missed = float(np.nan_to_num(np.linalg.norm(uv - s.corners[s.kept], axis=1), nan=1e3).mean())
        floor = 4.0 * float(np.median(rest_err))
        own = [e for r, e in zip(rest, rest_err) if r.cam_id == s.cam_id]
        if missed > max(WRONG_SIGHTING_PX, floor) and max(own) <= max(MISFIT_PX, floor, missed / 4.0):
            found.append((max(own) / missed, s))
    return min(found, key=lambda f: f[0])[1] if found else None


def _drop_stray_corners(s: Sighting, cam: Camera, obj, pose, poses) -> Sighting:
    """The sighting without stray corners (see :data:`STRAY_PX`), its pose solved again into ``poses``."""
    R, t = pose
    uv, _ = cam.project_cam(obj @ R.T + t)
    err = np.nan_to_num(np.linalg.norm(uv - s.corners, axis=1), nan=1e3)
    keep = err <= max(STRAY_PX, 4.0 * float(np.median(err)))
    if keep.sum() < 0.75 * len(keep):
        keep[:] = True   # not a few strays: keep everything and let the errors show it
    if not keep.all():
        pose = _pnp(cam, obj[keep], s.corners[keep])
    out = replace(s, keep=None if keep.all() else keep)
    poses[id(out)] = pose
    return out


def _pnp(cam: Camera, obj: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Board -> camera (R, t) from corners, through the camera's own lens model (:func:`board_pose`)."""
    pose = board_pose(cam, obj, corners)
    if pose is None:
        if not np.all(np.isfinite(cam.rays_cam(corners))):
            raise FloorError(f"camera {cam.id}: board corners lie where its lens model has no rays (check the "
                             "intrinsics)")
        raise FloorError(f"camera {cam.id}: the board's pose cannot be solved from its corners")
    return rodrigues_to_matrix(pose[0]), pose[1]


def _chain(sightings, poses, cam_ids, centre_b: np.ndarray):
    """Initial camera poses (board frame -> camera (R, t)), board positions (board -> floor frame (R, t))
    and the positions that stood on a stand (:data:`RAISED_M`; ``centre_b`` (3,) the squares' centre in the
    board frame), by breadth-first placement from position 0; FloorError naming the cameras no chain
    reaches."""
    seen = {s.cam_id for s in sightings}
    missing = [c for c in cam_ids if c not in seen]
    if missing:
        raise FloorError(f"camera(s) {', '.join(missing)}: no board sighting")
    cams: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    boards: dict[int, tuple[np.ndarray, np.ndarray]] = {0: (np.eye(3), np.zeros(3))}   # board -> world
    raised: set[int] = set()
    queue = deque([("pos", 0)])
    while queue:
        kind, key = queue.popleft()
        for s in sightings:
            R_cb, t_cb = poses[id(s)]
            if kind == "pos" and s.position == key and s.cam_id not in cams:
                R_wb, t_wb = boards[key]
                R = R_cb @ R_wb.T
                cams[s.cam_id] = (R, t_cb - R @ t_wb)
                queue.append(("cam", s.cam_id))
            elif kind == "cam" and s.cam_id == key and s.position not in boards:
                R_cw, t_cw = cams[key]
                R_wb = R_cw.T @ R_cb
                t_wb = R_cw.T @ (t_cb - t_cw)
                if (R_wb @ centre_b + t_wb)[2] > RAISED_M:   # on a stand: as it stood
                    boards[s.position] = (R_wb, t_wb)
                    raised.add(s.position)
                else:
                    yaw = math.atan2(R_wb[1, 0], R_wb[0, 0])   # onto the floor: keep the turn about Z
                    boards[s.position] = (_rz(math.degrees(yaw)), np.array([t_wb[0], t_wb[1], 0.0]))
                queue.append(("pos", s.position))
    cut = [c for c in cam_ids if c not in cams]
    if cut:
        linked = sorted(cams)
        raise FloorError(f"camera(s) {', '.join(cut)} share no board position with {', '.join(linked)} (the cameras "
                         "that see the first one): lay the board where one of them and one of these see it at once, "
                         "on the floor or set up on a stand")
    return cams, boards, raised


def _adjust(sightings, intrinsics, obj, cams0, boards0, raised: set[int] = frozenset(), *, bounds: bool = True):
    cam_ids = sorted(cams0)
    pos_ids = sorted(p for p in boards0 if p != 0)
    x0 = []
    for c in cam_ids:
        R, t = cams0[c]
        x0 += [*matrix_to_rodrigues(R), *t]
    pi = {}
    for p in pos_ids:
        R, t = boards0[p]
        pi[p] = len(x0)
        x0 += [*matrix_to_rodrigues(R), *t] if p in raised else [t[0], t[1], math.atan2(R[1, 0], R[0, 0])]
    ci = {c: 6 * k for k, c in enumerate(cam_ids)}
    # each camera's focal length as the log of its scale over the lens file's (Tsai lenses: held)
    free = [c for c in cam_ids if intrinsics[c].model != "tsai"]
    fi = {c: len(x0) + k for k, c in enumerate(free)}
    # each pinhole lens's refined radial terms (FREED: k3) as changes to its lens file's
    bent = [c for c in cam_ids if intrinsics[c].model == "pinhole"]
    ki = {c: len(x0) + len(free) + len(FREED) * k for k, c in enumerate(bent)}
    dist0 = {c: _padded(intrinsics[c].dist) for c in bent}
    reach = {c: LENS_CORNER_PX / (intrinsics[c].K[0, 0] * _corner_radius(intrinsics[c]) ** (3.0 + 2.0 * np.arange(3)))[
        list(FREED)] for c in bent}
    x0 = np.array(x0 + [0.0] * (len(free) + len(FREED) * len(bent)))
    groups = [(ci[s.cam_id], pi.get(s.position), fi.get(s.cam_id), ki.get(s.cam_id), intrinsics[s.cam_id],
               s.corners[s.kept], s.points(obj)[s.kept]) for s in sightings]

    stands = {pi[p] for p in raised}

    def unpack_board(x, j):
        if j is None:
            return np.eye(3), np.zeros(3)
        if j in stands:
            return rodrigues_to_matrix(x[j:j + 3]), x[j + 3:j + 6].copy()
        return _rz(math.degrees(x[j + 2])), np.array([x[j], x[j + 1], 0.0])

    def residuals(x):
        out = []
        for c, j, f, k, cam, uv, pts in groups:
            R_wb, t_wb = unpack_board(x, j)
            R_cw = rodrigues_to_matrix(x[c:c + 3])
            pc = (pts @ R_wb.T + t_wb) @ R_cw.T + x[c + 3:c + 6]
            if k is None:
                proj, _ = cam.project_cam(pc)
            else:
                proj = _project_bent(cam, _bent(dist0[cam.id], x[k:k + len(FREED)]), pc)
            if f is not None:   # the lens's pixels scale about the principal point with the focal length
                proj = cam.K[:2, 2] + math.exp(x[f]) * (proj - cam.K[:2, 2])
            out.append(np.nan_to_num(proj - uv, nan=1e3).ravel())
        # the prior, in pixels of the corners' least noise, so that the bounds weigh it as one of them
        out.append(np.array([x[fi[c]] for c in free]) / FOCAL_PRIOR * NOISE_FLOOR_PX)
        out.extend(x[ki[c]:ki[c] + len(FREED)] / reach[c] * NOISE_FLOOR_PX for c in bent)
        return np.concatenate(out)

    # which parameters each residual depends on: its view's camera, board place, focal length and k3; a prior's
    # own parameter. The finite differences then perturb many independent parameters at once.
    rows = sum(2 * len(g[5]) for g in groups) + len(free) + len(FREED) * len(bent)
    sparsity = lil_matrix((rows, len(x0)), dtype=np.int8)
    r = 0
    for c, j, f, k, cam, uv, pts in groups:
        cols = [*range(c, c + 6)]
        if j is not None:
            cols += range(j, j + (6 if j in stands else 3))
        if f is not None:
            cols.append(f)
        if k is not None:
            cols += range(k, k + len(FREED))
        sparsity[r:r + 2 * len(uv), cols] = 1
        r += 2 * len(uv)
    for col in [fi[c] for c in free] + [ki[c] + i for c in bent for i in range(len(FREED))]:
        sparsity[r, col] = 1
        r += 1
    sol = least_squares(residuals, x0, method="trf", loss="soft_l1", f_scale=1.0, x_scale="jac", max_nfev=200,
                        jac_sparsity=sparsity)
    x = sol.x
    cams = {c: (rodrigues_to_matrix(x[ci[c]:ci[c] + 3]), x[ci[c] + 3:ci[c] + 6].copy()) for c in cam_ids}
    focal = {c: math.exp(x[fi[c]]) if c in fi else 1.0 for c in cam_ids}
    lenses = {c: _bent(dist0[c], x[ki[c]:ki[c] + len(FREED)]) for c in bent}
    boards = {0: (np.eye(3), np.zeros(3)), **{p: unpack_board(x, pi[p]) for p in pos_ids}}
    sizes = [2 * len(g[5]) for g in groups]
    spread = {} if not bounds else pose_uncertainty(
        sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac), np.asarray(sol.fun), x,
        {c: ci[c] for c in cam_ids}, views=sizes,
        prior_rows=len(free) + len(FREED) * len(bent))
    # each view's mean corner error (px) at the solution, from the residuals the fit already has
    fun = sol.fun[:sum(sizes)]
    view_err = [float(np.hypot(*part.reshape(-1, 2).T).mean()) for part in np.split(fun, np.cumsum(sizes)[:-1])]
    return cams, focal, lenses, boards, spread, view_err


def _adjusted_camera(lens: Camera, focal: float, dist: np.ndarray | None, pose) -> Camera:
    """The lens file's camera as the adjustment found it: its focal length times ``focal``, its distortion
    ``dist`` (None: the file's), at ``pose`` (board frame -> camera (R, t))."""
    if dist is not None:
        lens = lens.with_distortion(dist)
    return lens.with_focal_scale(focal).with_pose(*pose)


def _padded(dist: np.ndarray) -> np.ndarray:
    """A pinhole lens's distortion coefficients with room for k3 (at least five)."""
    return np.concatenate([dist, np.zeros(max(0, 5 - dist.size))])


def _bent(dist: np.ndarray, change: np.ndarray) -> np.ndarray:
    """``dist`` (padded) with ``change`` added to the radial terms the adjustment refines (:data:`FREED`)."""
    out = dist.copy()
    out[[RADIAL[i] for i in FREED]] += change
    return out


def _project_bent(cam: Camera, dist: np.ndarray, pc: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of camera-frame points ``pc`` (in front) through ``cam``'s pinhole lens with the
    distortion ``dist``."""
    z = np.where(pc[:, 2] > 1e-6, pc[:, 2], np.nan)
    xd, yd = pinhole_distort(dist, pc[:, 0] / z, pc[:, 1] / z)
    K = cam.K
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


def _frame_pixels(cam: Camera) -> np.ndarray:
    """(8, 2) the image's corners and the middles of its edges (pixels)."""
    w, h = cam.width - 1, cam.height - 1
    return np.array([[0, 0], [w, 0], [0, h], [w, h], [w / 2, 0], [w / 2, h], [0, h / 2], [w, h / 2]], dtype=float)


def _corner_radius(cam: Camera) -> float:
    """The normalised radius (undistorted, through the lens file) of the image's farthest corner, or of
    the farthest edge point the lens reaches."""
    rays = cam.rays_cam(_frame_pixels(cam))
    r = np.hypot(rays[:, 0], rays[:, 1]) / rays[:, 2]
    return float(np.nanmax(r)) if np.any(np.isfinite(r)) else 1.0


def lens_change_px(before: Camera, after: Camera) -> float:
    """How far (pixels) the image's corners and the middles of its edges move from ``before``'s lens to
    ``after``'s, at the same focal length: what the floor calibration changed of a lens file's distortion."""
    px = _frame_pixels(before)
    uv = _project_bent(before, after.dist, before.rays_cam(px))
    moved = np.linalg.norm(uv - px, axis=1)
    return float(np.nanmax(moved)) if np.any(np.isfinite(moved)) else 0.0


def pose_uncertainty(jac: np.ndarray, residuals: np.ndarray, x: np.ndarray, offsets: dict[str, int], *,
                     views: list[int] | None = None, prior_rows: int = 0, noise_floor_px: float = NOISE_FLOOR_PX,
                     samples: int = 400, seed: int = 0) -> dict[str, tuple[float, float]]:
    """Per camera ``(position_95_m, angle_95_deg)``: how far its centre and its orientation may be from
    the solution, 95 % of the time, when each view's corners carry the noise the fit left in that view
    (the root mean square of its residuals, at least ``noise_floor_px``). The covariance is the
    weighted Gauss-Newton one, ``(J^T W J)^-1`` with ``W`` one over each residual's noise squared, over
    every parameter (the other cameras and the board positions are uncertain too), relative to the
    first board position; it is sampled and each sample's camera centre and rotation compared with
    the solution's. A camera that sees the board small, far, only edge-on or blurred gets a wide
    bound: the bound says where to lay the board again. jac: (M, P) at ``x`` (P,); residuals: (M,)
    pixels; views: the number of residuals of each view in order (None: one view), followed by
    ``prior_rows`` residuals of priors already in units of ``noise_floor_px`` (their noise); offsets:
    camera id -> index of its Rodrigues vector and translation (6 values) in ``x``."""
    m, n = jac.shape
    if m <= n:
        return {c: (float("inf"), float("inf")) for c in offsets}
    sigma = np.full(m, noise_floor_px)
    start = 0
    for size in (views or [m - prior_rows]):
        part = residuals[start:start + size]
        sigma[start:start + size] = max(noise_floor_px, float(np.sqrt(np.mean(part ** 2))) * math.sqrt(m / (m - n)))
        start += size
    jw = jac / sigma[:, None]
    try:
        cov = np.linalg.pinv(jw.T @ jw, rcond=1e-12, hermitian=True)
    except np.linalg.LinAlgError:
        return {c: (float("inf"), float("inf")) for c in offsets}
    rng = np.random.default_rng(seed)
    out = {}
    for c, k in offsets.items():
        block = cov[k:k + 6, k:k + 6]
        w, v = np.linalg.eigh(0.5 * (block + block.T))
        draws = rng.standard_normal((samples, 6)) * np.sqrt(np.clip(w, 0.0, None)) @ v.T + x[k:k + 6]
        R0 = rodrigues_to_matrix(x[k:k + 3])
        c0 = -R0.T @ x[k + 3:k + 6]
        dist, turn = np.empty(samples), np.empty(samples)
        for i, d in enumerate(draws):
            R = rodrigues_to_matrix(d[:3])
            dist[i] = np.linalg.norm(-R.T @ d[3:] - c0)
            cosang = (np.trace(R @ R0.T) - 1.0) / 2.0
            turn[i] = math.degrees(math.acos(max(-1.0, min(1.0, cosang))))
        out[c] = (float(np.quantile(dist, 0.95)), float(np.quantile(turn, 0.95)))
    return out


def _errors(sightings, cam_id, cam: Camera, boards, obj) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every corner's error (px), whether it was used, and its error against the detector's own corner (NaN for
    the views that have none, :attr:`Sighting.detected`)."""
    errs, kept, detected = [], [], []
    for s in sightings:
        if s.cam_id == cam_id:
            R_wb, t_wb = boards[s.position]
            uv, _ = cam.project(s.points(obj) @ R_wb.T + t_wb)
            errs.append(np.nan_to_num(np.linalg.norm(uv - s.corners, axis=1), nan=1e3))
            kept.append(s.kept)
            detected.append(np.full(len(uv), np.nan) if s.detected is None else
                            np.nan_to_num(np.linalg.norm(uv - s.detected, axis=1), nan=1e3))
    return np.concatenate(errs), np.concatenate(kept), np.concatenate(detected)


def _seen_share(cam: Camera, volume) -> float:
    lo, hi = (np.asarray(v, dtype=np.float64) for v in volume)
    step = max(float(np.max(hi - lo)) / 40.0, 0.05)
    axes = [np.arange(a + step / 2, b, step) for a, b in zip(lo, hi)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    _, valid = cam.project(pts)
    return float(valid.mean()) if len(pts) else float("nan")


def _rz(yaw_deg: float) -> np.ndarray:
    a = math.radians(yaw_deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
