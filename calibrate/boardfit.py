"""A chessboard found in an image, fitted to the image as a whole: its pose, through the camera's lens, that
best explains the grey levels of its squares.

The corner detectors place each corner from the few pixels around it. A board lying on the floor far from a
camera that looks across the room shows rows a few pixels apart, and there a corner's pixels are mostly its
neighbours' edges. Every pixel of the board's squares tells where its edges lie, and a flat board has only six
degrees of freedom: on 46 rendered floor views (tuning seeds 0-2, rows 2-11 px apart) the detector's corners
came out 0.04-0.20 px from the truth on average, the fitted board's 0.01-0.10 px, closer in every view.

It is asked for (``calibrate floor --fit-board``), not the default: on the lab's recording, whose black squares
are lighter at their tops and whose white ones are clipped, the fitted corners lie 0.24-0.65 px from the
detector's, which fit a flat board within 0.13-0.22 px, and which of them is nearer the truth the recording
cannot tell (docs/guides/calibrating.md, "Fitting the whole board").

The model of a pixel: the printed checker pattern where the pixel's centre ray meets the board's plane,
blurred by a Gaussian of ``blur_px`` across each edge (the lens's blur and the pixel's own width), times a
contrast and plus a level that each vary linearly across the image (uneven light). The contrast and level
are solved exactly for every pose tried; the pose and the blur by least squares, robust to the pixels a
foot or a chair leg hides. Only the squares inside the outer corners' half-square margin are used: beyond,
the border of the print and the floor are unknown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.special import erf

from calibrate.board import Board, board_pose
from common.camera import Camera

MARGIN_SQUARES = 0.4
"""The fit uses the board within this many squares beyond its outer inner corners (the outer squares reach 1)."""
MIN_PIXELS_PER_SQUARE = 4.0
"""Fewer pixels than this per square used (on average): the view is left as the detector found it."""
MAX_MOVE_PX = 1.0
"""A fit that moves the corners further than this on average from where the detector put them has gone astray
(the detectors are sub-pixel where they find a board at all): the detected corners are kept."""
MAX_PIXELS = 40_000
"""At most this many pixels enter the fit (an even sample of them on a board seen large)."""
BLUR_RANGE_PX = (0.2, 4.0)
_TERMS = range(-2, 4)   # the edges nearest a point that its blurred value depends on (three either side)


@dataclass(frozen=True)
class BoardFit:
    """corners: (N, 2) the fitted board's inner corners, in the order of those given. moved_px: their mean
    distance from those given. blur_px: the fitted blur. rms_before / rms_after: the grey-level misfit of the
    pixels used at the detected and at the fitted pose. pixels: how many were used."""

    corners: np.ndarray
    moved_px: float
    blur_px: float
    rms_before: float
    rms_after: float
    pixels: int


def fit_board(gray: np.ndarray, corners: np.ndarray, board: Board, camera: Camera) -> BoardFit | None:
    """The board whose ``corners`` ((N, 2) pixels in board order, as found by a detector) were found in ``gray``
    ((H, W) uint8) fitted to the image through ``camera``'s lens (its pose is ignored); None where the view has
    too few pixels of its squares to fit, the fit fails, or it strays more than :data:`MAX_MOVE_PX` from the
    detection."""
    if np.any(camera.rays_cam(np.asarray(corners, dtype=np.float64))[:, 2] <= 0):   # a corner behind the lens's plane
        return None
    start = board_pose(camera, board.object_points(), corners)
    if start is None or start[1][2] <= 0:   # no pose, or the board behind the camera
        return None
    region = _Region.around(gray, board, camera, start)
    if region is None or region.count < MIN_PIXELS_PER_SQUARE * (board.cols + 1) * (board.rows + 1):
        return None
    p0 = np.r_[start[0], start[1], math.log(0.5)]
    r0 = region.residuals(p0)
    scale = max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1.0)
    lo = np.r_[np.full(6, -np.inf), math.log(BLUR_RANGE_PX[0])]
    hi = np.r_[np.full(6, np.inf), math.log(BLUR_RANGE_PX[1])]
    try:
        sol = least_squares(region.residuals, p0, bounds=(lo, hi), x_scale="jac", loss="soft_l1", f_scale=scale,
                            max_nfev=200)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if sol.status <= 0 or not np.all(np.isfinite(sol.x)):
        return None
    R, _ = cv2.Rodrigues(sol.x[:3])
    uv, _ = camera.project_cam(board.object_points() @ R.T + sol.x[3:6])
    if not np.all(np.isfinite(uv)):
        return None
    moved = float(np.linalg.norm(uv - corners, axis=1).mean())
    if moved > MAX_MOVE_PX:
        return None
    return BoardFit(corners=uv, moved_px=moved, blur_px=math.exp(sol.x[6]), rms_before=_rms(r0),
                    rms_after=_rms(sol.fun), pixels=region.count)


def refined_corners(gray: np.ndarray, corners: np.ndarray, board: Board, camera: Camera) -> np.ndarray:
    """``corners`` fitted to the image (:func:`fit_board`), or as given where the fit is refused."""
    fit = fit_board(gray, corners, board, camera)
    return corners if fit is None else fit.corners


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r ** 2)))


class _Region:
    """The pixels of a board view the fit uses: their rays, grey levels, and the rectangle around them."""

    def __init__(self, board: Board, rays: np.ndarray, grey: np.ndarray, use: np.ndarray, uv: np.ndarray) -> None:
        self.board = board
        self.rays = rays            # (h, w, 3) camera-frame rays of the rectangle's pixels
        self.use = use              # (h, w) bool, the pixels used
        self.grey = grey[use]
        self.count = int(use.sum())
        u, v = uv[0][use], uv[1][use]
        u, v = (u - u.mean()) / 100.0, (v - v.mean()) / 100.0
        self.light = np.stack([np.ones_like(u), u, v], axis=1)

    @classmethod
    def around(cls, gray: np.ndarray, board: Board, camera: Camera, pose) -> "_Region | None":
        m = MARGIN_SQUARES
        outline = np.array([[-m, -m], [board.cols - 1 + m, -m], [board.cols - 1 + m, board.rows - 1 + m],
                            [-m, board.rows - 1 + m]])
        edge = np.concatenate([outline[k] + np.linspace(0, 1, 40)[:, None] * (outline[(k + 1) % 4] - outline[k])
                               for k in range(4)])
        R, _ = cv2.Rodrigues(pose[0])
        uv, _ = camera.project_cam(np.c_[edge * board.square_m, np.zeros(len(edge))] @ R.T + pose[1])
        if not np.all(np.isfinite(uv)):   # part of it beyond the lens's reach
            return None
        H, W = gray.shape[:2]
        x0, y0 = np.clip(np.floor(uv.min(axis=0)).astype(int) - 2, 0, [W, H])
        x1, y1 = np.clip(np.ceil(uv.max(axis=0)).astype(int) + 3, 0, [W, H])
        if x1 - x0 < 3 or y1 - y0 < 3:
            return None
        v, u = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        rays = camera.rays_cam(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(v.shape + (3,))
        bx, by = _on_board(rays, board, pose[0], pose[1])
        with np.errstate(invalid="ignore"):
            use = (np.isfinite(bx) & np.isfinite(by) & (bx >= -m) & (bx <= board.cols - 1 + m)
                   & (by >= -m) & (by <= board.rows - 1 + m))
        use[[0, -1], :] = False   # the rectangle's rim: no neighbour on one side for the board's local scale
        use[:, [0, -1]] = False
        idx = np.flatnonzero(use)
        if len(idx) > MAX_PIXELS:   # an even sample of a board seen large
            use = np.zeros(use.size, dtype=bool)
            use[idx[:: int(math.ceil(len(idx) / MAX_PIXELS))]] = True
            use = use.reshape(v.shape)
        return cls(board, np.where(np.isfinite(rays), rays, 0.0), gray[y0:y1, x0:x1].astype(np.float64), use, (u, v))

    def residuals(self, p: np.ndarray) -> np.ndarray:
        """Grey-level misfit of the used pixels for ``p`` = (rvec, tvec, log blur_px), with the light's level and
        contrast solved exactly."""
        bx, by = _on_board(self.rays, self.board, p[:3], p[3:6])
        blur = math.exp(p[6])
        # the blur across each family of edges, in squares: the pixel's blur over the board's local scale
        sx = blur * np.hypot(np.gradient(bx, axis=1), np.gradient(bx, axis=0))[self.use]
        sy = blur * np.hypot(np.gradient(by, axis=1), np.gradient(by, axis=0))[self.use]
        pattern = _blurred_square_wave(bx[self.use], sx) * _blurred_square_wave(by[self.use], sy)
        A = np.concatenate([self.light, self.light * pattern[:, None]], axis=1)
        w, *_ = np.linalg.lstsq(A, self.grey, rcond=None)
        return A @ w - self.grey


def _on_board(rays: np.ndarray, board: Board, rvec, tvec) -> tuple[np.ndarray, np.ndarray]:
    """Board coordinates, in squares, where the camera-frame ``rays`` (..., 3) meet the board's plane (NaN where
    they do not, ahead of the camera)."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    t = np.asarray(tvec, dtype=np.float64)
    n = R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n @ t) / (rays @ n)
        s = np.where(s > 0, s, np.nan)
        p = (s[..., None] * rays - t) @ R / board.square_m
    return p[..., 0], p[..., 1]


def _blurred_square_wave(x: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """(-1)^floor(x) blurred by a Gaussian of ``sigma`` (both in squares): half the alternating sum of the
    steps at the nearest edges, three either side."""
    m = np.floor(x)
    out = np.zeros_like(x)
    for j in _TERMS:
        k = m + j
        out += np.where(np.mod(k, 2) == 0, 1.0, -1.0) * erf((x - k) / (np.maximum(sigma, 1e-6) * math.sqrt(2.0)))
    return 0.5 * out
