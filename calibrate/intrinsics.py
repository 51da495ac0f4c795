"""Intrinsic calibration from a clip of a board moved in front of one camera.

Up to :data:`MAX_CANDIDATES` frames, spread evenly over the clip, are searched for the board: a
chessboard, which must be seen whole (:func:`~calibrate.board.find_board`), or a ChArUco
board, of which any part showing enough corners counts (:class:`~calibrate.charuco.CharucoFinder`),
so that its views may reach past the image's edges, where a lens bends most.
Views are then picked, sharpest first: a view is skipped when it is blurred (the variance of the
Laplacian over the board below :data:`BLUR_SHARE` of the clip's median) or when it repeats one
already picked (its outline within :data:`DUPLICATE_SHARE` of the image diagonal of that view's:
a chessboard's four outer corners, the bounding box of the corners of a ChArUco view, which may
show any part of the board), so that a board held still for a while counts once and the picked
views spread over positions, distances and tilts. At most :data:`MAX_VIEWS` are kept. OpenCV
then fits a pinhole model (``calibrateCamera``: fx, fy, cx, cy, k1, k2, p1, p2, and k3 where the
views show it, :data:`K3_EVIDENCE`) or the
fisheye model (``fisheye.calibrate``: k1..k4) to the views' corners, each view with its own
number of corners; views whose error is far above the others' are dropped and the fit repeated once.

The fit's own uncertainty is measured from its Jacobian (the corners as noisy as the fit found them):
the principal point's, as a tilt of the camera (:attr:`IntrinsicsResult.tilt_95_deg`), which no floor
calibration can take back, since it trades against the camera's turn. Where it exceeds
:data:`LENS_TILT_95_DEG` the result says so (:attr:`IntrinsicsResult.uncertain`): the board was held too
far for the image (a board spanning a quarter to three fifths of a 320x240 image's width left the
principal point of a 230 px lens 0.5 px uncertain, 0.17 degree; spanning half or more, 0.07 degree).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from calibrate.board import Board, board_area_fraction, find_board, sharpness
from calibrate.charuco import CharucoBoard, CharucoFinder
from calibrate.clips import read_gray
from calibrate.floor import ANGLE_TOLERANCE_DEG
from common.camera import Camera

MIN_VIEWS = 6
MAX_VIEWS = 40
MAX_CANDIDATES = 240
"""Frames searched at most (spread evenly over the clip)."""
MIN_AREA = 0.02
"""A usable view's board covers at least this share of the image."""
BLUR_SHARE = 0.4
DUPLICATE_SHARE = 0.04
OUTLIER_FACTOR = 3.0
K3_EVIDENCE = 10.0
"""k3 is kept when freeing it lowers the squared error by more than this many times the noise variance
(the likelihood-ratio test of one more parameter: chi-square with one degree of freedom, p < 0.002). A
lens whose k3 is not zero (the lab's: -0.03 to -0.07) fitted without it came out with its principal point
1-3 px off (0.2-0.4 degree of tilt at 490 px); a lens without one is fitted the same either way."""
LENS_TILT_95_DEG = ANGLE_TOLERANCE_DEG / math.sqrt(2.0)
"""The most a lens fit may leave a camera's tilt uncertain (95 %): half the variance of the floor
calibration's angle tolerance, the other half left to the floor calibration's own pose."""


class IntrinsicsError(ValueError):
    """A clip that cannot give intrinsics; the message says why and what to do."""


@dataclass(frozen=True)
class IntrinsicsResult:
    """camera: the fitted camera (pose: identity, a placeholder until the floor calibration).
    rms_px: OpenCV's RMS reprojection error. views_used, views_found, frames_searched: counts;
    skipped_blurred, skipped_duplicate, skipped_small, dropped_outliers: why found views were left out.
    centre_sd_px: the principal point's standard deviation (x, y), focal_sd_px the focal length's (fx),
    from the fit's Jacobian; board_span: the median share of the image's width the used views' boards span."""

    camera: Camera
    rms_px: float
    views_used: int
    views_found: int
    frames_searched: int
    skipped_blurred: int
    skipped_duplicate: int
    skipped_small: int
    dropped_outliers: int
    centre_sd_px: tuple[float, float]
    focal_sd_px: float
    board_span: float

    @property
    def tilt_95_deg(self) -> float:
        """How far (95 %) the principal point's uncertainty may tilt the camera, in degrees."""
        return lens_tilt_95_deg(self.camera, self.centre_sd_px)

    @property
    def uncertain(self) -> bool:
        """Whether that tilt exceeds :data:`LENS_TILT_95_DEG`: the board should be held nearer."""
        return self.tilt_95_deg > LENS_TILT_95_DEG


def lens_tilt_95_deg(camera: Camera, centre_sd_px: tuple[float, float]) -> float:
    """How far (95 %, degrees) a principal point as uncertain as ``centre_sd_px`` (one standard deviation, x and
    y) may tilt ``camera``: near the image's centre a pixel is one focal length's worth of radian for every
    model."""
    return math.degrees(1.96 * math.hypot(*centre_sd_px) / float(camera.K[0, 0]))


def calibrate_intrinsics(clip: str, cam_id: str, board: Board | CharucoBoard, *,
                         model: str = "pinhole") -> IntrinsicsResult:
    """Fit ``model`` ('pinhole' or 'fisheye') to the board views of ``clip``; IntrinsicsError or
    ClipError naming the clip when it cannot."""
    if model not in ("pinhole", "fisheye"):
        raise ValueError(f"--model: expected pinhole or fisheye, got {model!r}")
    frames, _ = read_gray(clip, spread=MAX_CANDIDATES)
    if len(frames) > MAX_CANDIDATES:
        frames = [frames[k] for k in np.linspace(0, len(frames) - 1, MAX_CANDIDATES).astype(int)]
    H, W = frames[0].shape[:2]
    find = _finder(board)
    views = []
    for gray in frames:
        found = find(gray)
        if found is not None:
            ids, corners = found
            views.append(_View(ids, corners, sharpness(gray, corners), board_area_fraction(corners, W, H)))
    if not views:
        raise IntrinsicsError(f"clip {clip}: board {board.describe()} not found in any of {len(frames)} frames "
                              f"({_NOT_FOUND_HINT[type(board)]})")
    big = [v for v in views if v.area >= MIN_AREA]
    small = len(views) - len(big)
    if not big:
        raise IntrinsicsError(f"clip {clip}: the board is too small in the image (at most "
                              f"{100 * max(v.area for v in views):.1f} % of it; bring it nearer, to {100 * MIN_AREA:g} % or more)")
    median_sharp = float(np.median([v.sharpness for v in big]))
    sharp = [v for v in big if v.sharpness >= BLUR_SHARE * median_sharp]
    blurred = len(big) - len(sharp)
    picked: list[_View] = []
    diag = float(np.hypot(W, H))
    duplicates = 0
    for view in sorted(sharp, key=lambda v: -v.sharpness):
        outline = _outline(view, board)
        if any(np.linalg.norm(outline - _outline(p, board), axis=1).mean() < DUPLICATE_SHARE * diag for p in picked):
            duplicates += 1
            continue
        if len(picked) < MAX_VIEWS:
            picked.append(view)
    if len(picked) < MIN_VIEWS:
        raise IntrinsicsError(f"clip {clip}: the board was found in only {len(picked)} distinct sharp views "
                              f"(need {MIN_VIEWS}): move it slowly to other places, distances and tilts")
    camera, rms, errs, sd = _fit(picked, board, cam_id, W, H, model)
    keep = errs <= OUTLIER_FACTOR * max(float(np.median(errs)), 0.05)
    dropped = int((~keep).sum())
    if dropped and keep.sum() >= MIN_VIEWS:
        picked = [p for p, k in zip(picked, keep) if k]
        camera, rms, errs, sd = _fit(picked, board, cam_id, W, H, model)
    else:
        dropped = 0
    span = float(np.median([np.ptp(v.corners[:, 0]) / W for v in picked]))
    return IntrinsicsResult(camera=camera, rms_px=rms, views_used=len(picked), views_found=len(views),
                            frames_searched=len(frames), skipped_blurred=blurred, skipped_duplicate=duplicates,
                            skipped_small=small, dropped_outliers=dropped, centre_sd_px=(sd[2], sd[3]),
                            focal_sd_px=sd[0], board_span=span)


@dataclass(frozen=True)
class _View:
    """One frame's board: ids (N,) int into the board's object points, corners (N, 2) float64 pixels,
    the sharpness of the board's box and the share of the image its corners' hull covers."""

    ids: np.ndarray
    corners: np.ndarray
    sharpness: float
    area: float


_NOT_FOUND_HINT = {
    Board: "check --board, light the board evenly, show all of it",
    CharucoBoard: "check --board (squares), --charuco and --marker-mm; light the board evenly",
}


def _finder(board: Board | CharucoBoard) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray] | None]:
    """A function of a grey frame giving the board's ids and corners found in it, or None."""
    if isinstance(board, CharucoBoard):
        return CharucoFinder(board).find
    every = np.arange(board.n)

    def find(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        corners = find_board(gray, board, refine=True)
        return None if corners is None else (every, corners)

    return find


def _outline(view: _View, board: Board | CharucoBoard) -> np.ndarray:
    """(4, 2) pixels saying where a view lies: a chessboard's outer corners; the bounding box of a
    ChArUco view's corners."""
    if isinstance(board, CharucoBoard):
        (x0, y0), (x1, y1) = view.corners.min(axis=0), view.corners.max(axis=0)
        return np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])
    g = view.corners.reshape(board.rows, board.cols, 2)
    return np.array([g[0, 0], g[0, -1], g[-1, 0], g[-1, -1]])


def _fit(views: list[_View], board: Board | CharucoBoard, cam_id: str, W: int, H: int, model: str):
    """(camera, rms, per-view mean error px, standard deviations of fx, fy, cx, cy px)."""
    every = board.object_points()
    if model == "pinhole":
        objs = [every[v.ids].astype(np.float32).reshape(-1, 1, 3) for v in views]
        imgs = [v.corners.astype(np.float32).reshape(-1, 1, 2) for v in views]
        # k3 only when the views show it (K3_EVIDENCE): needlessly free, it trades against k1, k2 and the
        # focal length; OpenCV's RMS is over points, each of two coordinates
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, (W, H), None, None, flags=cv2.CALIB_FIX_K3)
        fit = cv2.calibrateCamera(objs, imgs, (W, H), None, None)
        points = sum(len(o) for o in objs)
        if fit[0] > 0 and points * (rms ** 2 - fit[0] ** 2) > K3_EVIDENCE * fit[0] ** 2:
            rms, K, dist, rvecs, tvecs = fit
        dist = dist.ravel()[:5]
        free = 9 if dist[4] != 0.0 else 8   # fx, fy, cx, cy, k1, k2, p1, p2 (, k3)
    else:
        # OpenCV 5's fisheye fit takes (1, N, 3) and (1, N, 2) views only
        objs = [every[v.ids].reshape(1, -1, 3) for v in views]
        imgs = [v.corners.reshape(1, -1, 2) for v in views]
        # OpenCV 5 moved the fisheye flags (with other values) from cv2.fisheye to cv2
        names = cv2.fisheye if hasattr(cv2.fisheye, "CALIB_FIX_SKEW") else cv2
        flags = names.CALIB_RECOMPUTE_EXTRINSIC | names.CALIB_FIX_SKEW | names.CALIB_USE_INTRINSIC_GUESS
        # started from an equidistant lens, centred, seeing 180 degrees across the shorter side (a
        # ceiling fisheye's circle inside the frame), the longer side (OpenCV 4's own start) or the
        # diagonal (a full-frame fisheye); the fit is local, and from a start far from the truth it
        # lands far off or diverges (a 1280x720 lens of 225 px from OpenCV 4's 407 px start: 7.6 % off,
        # or a negative focal length). The least RMS error of the valid fits wins.
        criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-9)
        fits, why = [], ""
        for f in (min(W, H) / np.pi, max(W, H) / np.pi, float(np.hypot(W, H)) / np.pi):
            K0 = np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
            try:
                fit = cv2.fisheye.calibrate(objs, imgs, (W, H), K0, np.zeros(4), flags=flags, criteria=criteria)
            except cv2.error as exc:
                why = str(exc).strip().splitlines()[-1]
                continue
            K = fit[1]
            if np.isfinite(fit[0]) and np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 \
                    and 0 <= K[0, 2] < W and 0 <= K[1, 2] < H:
                fits.append(fit)
        if not fits:
            raise IntrinsicsError(f"the fisheye fit failed ({why or 'no start gave a lens'}): "
                                  "show the board in more places, nearer the image's edges")
        rms, K, dist, rvecs, tvecs = min(fits, key=lambda fit: fit[0])
        dist = dist.ravel()
        free = 8   # fx, fy, cx, cy, k1..k4
    errs, sd = _errors_and_sd(objs, [v.corners for v in views], K, dist, rvecs, tvecs, model, free)
    K = np.asarray(K, dtype=np.float64)
    K[1, 0] = 0.0
    K[2] = (0.0, 0.0, 1.0)
    camera = Camera(id=cam_id, model=model, width=W, height=H, K=K, dist=np.asarray(dist, dtype=np.float64),
                    R=np.eye(3), t=np.zeros(3))
    return camera, float(rms), errs, sd


def _errors_and_sd(objs, corners, K, dist, rvecs, tvecs, model: str, free: int) -> tuple[np.ndarray, np.ndarray]:
    """Each view's mean corner error (px) and the standard deviations (px) of fx, fy, cx, cy: the Gauss-Newton
    covariance of the fit (its first ``free`` lens parameters and every view's pose), each corner coordinate as
    noisy as the residuals say; both from one projection of every view."""
    rows, resid = [], []
    views = len(objs)
    for k, (o, img, r, t) in enumerate(zip(objs, corners, rvecs, tvecs)):
        if model == "pinhole":
            uv, J = cv2.projectPoints(o.astype(np.float64), r, t, K, dist)
            lens, pose = J[:, 6:6 + free], J[:, :6]   # r, t, fx, fy, cx, cy, k1, k2, p1, p2, k3
        else:
            uv, J = cv2.fisheye.projectPoints(o.astype(np.float64), r, t, K, dist)
            lens, pose = J[:, :free], J[:, 8:14]      # fx, fy, cx, cy, k1..k4, r, t, skew
        block = np.zeros((len(J), free + 6 * views))
        block[:, :free] = lens
        block[:, free + 6 * k:free + 6 * k + 6] = pose
        rows.append(block)
        resid.append(uv.reshape(-1) - img.reshape(-1))
    errs = np.array([np.hypot(*part.reshape(-1, 2).T).mean() for part in resid])
    J = np.concatenate(rows)
    r = np.concatenate(resid)
    dof = max(len(r) - J.shape[1], 1)
    cov = np.linalg.pinv(J.T @ J) * float(r @ r) / dof
    return errs, np.sqrt(np.clip(np.diag(cov)[:4], 0.0, None))
