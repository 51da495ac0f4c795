"""Intrinsic calibration from a clip of a board moved in front of one camera.

Up to :data:`MAX_CANDIDATES` frames, spread evenly over the clip, are searched for the board
(:func:`~common.calibrate.board.find_board`).
Views are then picked, sharpest first: a view is skipped when it is blurred (the variance of the
Laplacian over the board below :data:`BLUR_SHARE` of the clip's median) or when it repeats one
already picked (its four outer corners within :data:`DUPLICATE_SHARE` of the image diagonal of
that view's), so that a board held still for a while counts once and the picked views spread
over positions, distances and tilts. At most :data:`MAX_VIEWS` are kept. OpenCV then fits a
pinhole model (``calibrateCamera``: fx, fy, cx, cy, k1, k2, p1, p2, k3) or the fisheye model
(``fisheye.calibrate``: k1..k4); views whose error is far above the others' are dropped and
the fit repeated once.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.calibrate.board import Board, board_area_fraction, find_board, sharpness
from common.calibrate.clips import read_gray
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
K3_RMS_PX = 0.3
"""Above this RMS error without k3, the fit is tried again with k3 free."""


class IntrinsicsError(ValueError):
    """A clip that cannot give intrinsics; the message says why and what to do."""


@dataclass(frozen=True)
class IntrinsicsResult:
    """camera: the fitted camera (pose: identity, a placeholder until the floor calibration).
    rms_px: OpenCV's RMS reprojection error. views_used, views_found, frames_searched: counts;
    skipped_blurred, skipped_duplicate, skipped_small, dropped_outliers: why found views were left out."""

    camera: Camera
    rms_px: float
    views_used: int
    views_found: int
    frames_searched: int
    skipped_blurred: int
    skipped_duplicate: int
    skipped_small: int
    dropped_outliers: int


def calibrate_intrinsics(clip: str, cam_id: str, board: Board, *, model: str = "pinhole") -> IntrinsicsResult:
    """Fit ``model`` ('pinhole' or 'fisheye') to the board views of ``clip``; IntrinsicsError or
    ClipError naming the clip when it cannot."""
    if model not in ("pinhole", "fisheye"):
        raise ValueError(f"--model: expected pinhole or fisheye, got {model!r}")
    frames, _ = read_gray(clip, spread=MAX_CANDIDATES)
    if len(frames) > MAX_CANDIDATES:
        frames = [frames[k] for k in np.linspace(0, len(frames) - 1, MAX_CANDIDATES).astype(int)]
    H, W = frames[0].shape[:2]
    views = []
    for gray in frames:
        corners = find_board(gray, board)
        if corners is not None:
            views.append((corners, sharpness(gray, corners), board_area_fraction(corners, W, H)))
    if not views:
        raise IntrinsicsError(f"clip {clip}: board {board.describe()} not found in any of {len(frames)} frames "
                              "(check --board, light the board evenly, show all of it)")
    big = [v for v in views if v[2] >= MIN_AREA]
    small = len(views) - len(big)
    if not big:
        raise IntrinsicsError(f"clip {clip}: the board is too small in the image (at most "
                              f"{100 * max(v[2] for v in views):.1f} % of it; bring it nearer, to {100 * MIN_AREA:g} % or more)")
    median_sharp = float(np.median([v[1] for v in big]))
    sharp = [v for v in big if v[1] >= BLUR_SHARE * median_sharp]
    blurred = len(big) - len(sharp)
    picked: list[np.ndarray] = []
    diag = float(np.hypot(W, H))
    duplicates = 0
    for corners, _, _ in sorted(sharp, key=lambda v: -v[1]):
        outer = _outer(corners, board)
        if any(np.linalg.norm(outer - _outer(p, board), axis=1).mean() < DUPLICATE_SHARE * diag for p in picked):
            duplicates += 1
            continue
        if len(picked) < MAX_VIEWS:
            picked.append(corners)
    if len(picked) < MIN_VIEWS:
        raise IntrinsicsError(f"clip {clip}: the board was found in only {len(picked)} distinct sharp views "
                              f"(need {MIN_VIEWS}): move it slowly to other places, distances and tilts")
    camera, rms, errs = _fit(picked, board, cam_id, W, H, model)
    keep = errs <= OUTLIER_FACTOR * max(float(np.median(errs)), 0.05)
    dropped = int((~keep).sum())
    if dropped and keep.sum() >= MIN_VIEWS:
        camera, rms, errs = _fit([p for p, k in zip(picked, keep) if k], board, cam_id, W, H, model)
    else:
        dropped = 0
    return IntrinsicsResult(camera=camera, rms_px=rms, views_used=len(picked) - dropped, views_found=len(views),
                            frames_searched=len(frames), skipped_blurred=blurred, skipped_duplicate=duplicates,
                            skipped_small=small, dropped_outliers=dropped)


def _outer(corners: np.ndarray, board: Board) -> np.ndarray:
    g = corners.reshape(board.rows, board.cols, 2)
    return np.array([g[0, 0], g[0, -1], g[-1, 0], g[-1, -1]])


def _fit(views: list[np.ndarray], board: Board, cam_id: str, W: int, H: int, model: str):
    """(camera, rms, per-view mean error px)."""
    obj = board.object_points().astype(np.float32)
    if model == "pinhole":
        objs = [obj.reshape(-1, 1, 3) for _ in views]
        imgs = [v.astype(np.float32).reshape(-1, 1, 2) for v in views]
        # k3 only when it clearly helps: with few views it trades against k1, k2 and the focal length
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, (W, H), None, None, flags=cv2.CALIB_FIX_K3)
        if rms > K3_RMS_PX:
            fit = cv2.calibrateCamera(objs, imgs, (W, H), None, None)
            if fit[0] < 0.9 * rms:
                rms, K, dist, rvecs, tvecs = fit
        dist = dist.ravel()[:5]
        errs = []
        for v, r, t in zip(views, rvecs, tvecs):
            uv, _ = cv2.projectPoints(obj, r, t, K, dist)
            errs.append(np.linalg.norm(uv.reshape(-1, 2) - v, axis=1).mean())
    else:
        objs = [obj.reshape(1, -1, 3).astype(np.float64) for _ in views]
        imgs = [v.reshape(1, -1, 2).astype(np.float64) for v in views]
        flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
        criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-9)
        try:
            rms, K, dist, rvecs, tvecs = cv2.fisheye.calibrate(objs, imgs, (W, H), np.eye(3), np.zeros(4), flags=flags,
                                                               criteria=criteria)
        except cv2.error as exc:
            raise IntrinsicsError(f"the fisheye fit failed ({str(exc).strip().splitlines()[-1]}): "
                                  "show the board in more places, nearer the image's edges") from None
        dist = dist.ravel()
        errs = []
        for v, r, t in zip(views, rvecs, tvecs):
            uv, _ = cv2.fisheye.projectPoints(obj.reshape(1, -1, 3).astype(np.float64), r, t, K, dist)
            errs.append(np.linalg.norm(uv.reshape(-1, 2) - v, axis=1).mean())
    K = np.asarray(K, dtype=np.float64)
    K[1, 0] = 0.0
    K[2] = (0.0, 0.0, 1.0)
    camera = Camera(id=cam_id, model=model, width=W, height=H, K=K, dist=np.asarray(dist, dtype=np.float64),
                    R=np.eye(3), t=np.zeros(3))
    return camera, float(rms), np.asarray(errs)
