"""The calibration board: its geometry, finding it in an image, and naming its corners the same
way in every camera.

A chessboard of ``cols x rows`` inner corners and ``square_m`` squares. Its frame: origin at
an inner corner, X along the rows (``cols`` corners), Y along the columns, Z = X x Y out of the
printed face; corner ``k = row * cols + col`` lies at ``(col, row, 0) * square_m``, the order
OpenCV's detectors report.

Detectors report the corners starting from any of the four corners of the grid, and may walk it
mirrored. :func:`canonical_order` fixes both where the image alone can tell:

* the mirror: seen from the printed side (Z towards the camera), X turns onto Y
  counter-clockwise on the screen (X to the right, Y up), so a walk the other way round is
  reversed along each row;
* the half turn: when ``cols + rows`` is odd the two ends of the grid differ, one outer corner
  square is black and the opposite one white, and the origin is the inner corner next to the
  black one. When ``cols + rows`` is even the board looks the same turned half round
  (:attr:`Board.symmetric`): which end is the origin must then come from elsewhere (the
  floor calibration uses the cameras' rough poses, or refuses).

Finding a board lying on the floor far from a camera that looks across the room is hard for
the detectors: its squares are thin slivers. :func:`find_board` then looks again in views of
the floor seen from straight above, resampled through the camera's own lens model, with the
camera's rough pose when one is known or with a few guessed pitches, and maps the corners
back into the image. A board set up on a stand, bent by a wide lens near the image's edge, is
looked for again in a view straightened through the lens, looking straight at where the board may
be.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from common.camera import Camera

SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.001)
GUESSED_PITCHES_DEG = (20.0, 35.0, 50.0, 65.0)
"""Downward pitches tried for a camera whose pose is unknown (level cameras to steep corner ones)."""
NADIR_REACH_DEG = 84.0
"""A floor view from above covers the floor within this angle of straight down from the camera."""
VIEW_SIZES_PX = (600, 900, 1400)
"""Longest sides of the floor views from above, pixels."""
GOOD_FIT_PX = 0.25
"""Corners found from above that fit a flat board this well are taken without looking further."""


@dataclass(frozen=True)
class Board:
    """A chessboard: ``cols`` inner corners along a row, ``rows`` along a column, squares of
    ``square_m`` metres."""

    cols: int
    rows: int
    square_m: float

    def __post_init__(self) -> None:
        for name in ("cols", "rows"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 3 <= value <= 40:
                raise ValueError(f"board {name} must be a whole number of inner corners in 3..40, got {value!r}")
        if self.cols == self.rows:
            raise ValueError(f"board {self.cols}x{self.rows}: a square board looks the same turned a quarter round; "
                             "use one with different counts, e.g. 9x6")
        if not (math.isfinite(self.square_m) and 0.005 <= self.square_m <= 1.0):
            raise ValueError(f"board square size must lie in 5..1000 mm, got {self.square_m * 1000:g} mm")

    @classmethod
    def parse(cls, text: str, square_mm: float) -> "Board":
        """``'8x6'`` (inner corners) and the square size in millimetres; ValueError naming the problem."""
        parts = str(text).lower().split("x")
        if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
            raise ValueError(f"--board: expected inner corners as COLSxROWS, e.g. 8x6, got {text!r}")
        return cls(int(parts[0]), int(parts[1]), float(square_mm) / 1000.0)

    @property
    def size(self) -> tuple[int, int]:
        """OpenCV's pattern size ``(cols, rows)``."""
        return (self.cols, self.rows)

    @property
    def n(self) -> int:
        return self.cols * self.rows

    @property
    def symmetric(self) -> bool:
        """The board looks the same turned half round (``cols + rows`` even)."""
        return (self.cols + self.rows) % 2 == 0

    def object_points(self) -> np.ndarray:
        """(N, 3) float64 inner corners in the board frame, metres, row-major."""
        col, row = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.stack([col.ravel(), row.ravel(), np.zeros(self.n)], axis=1) * self.square_m

    def half_turn(self, corners: np.ndarray) -> np.ndarray:
        """The same corners named from the other end of the grid (the board turned half round)."""
        return np.asarray(corners)[::-1].copy()

    def describe(self) -> str:
        return f"{self.cols}x{self.rows} inner corners, {self.square_m * 1000:g} mm squares"


def find_board(gray: np.ndarray, board: Board, *, camera: Camera | None = None, thorough: bool = False,
               rough_pose: tuple[np.ndarray, np.ndarray] | None = None, refine: bool = False) -> np.ndarray | None:
    """The board's inner corners in ``gray`` ((H, W) uint8), (N, 2) float64 pixels in
    :func:`canonical_order`, or None.

    thorough: also try the image doubled and, with ``camera`` (its intrinsics; its pose is ignored),
    views of the floor from above: through ``rough_pose`` (world -> camera ``(R, t)``, the floor at
    Z = 0) when given, else at guessed pitches, and views straightened towards each candidate window;
    with ``camera`` every way is tried and the set that best fits a flat board through the lens is kept (a 9x6
    mat of 250 mm squares with patchy far squares, seen by a 320x240 wide lens, was taken from the image as is
    0.64 px off a flat board, 8 px from the truth with its ends swapped; doubled, 0.15 px off a flat board and
    0.17 px from the truth. On 42 rendered floor views of tuning seeds 2 and 3 the best of every way came out
    0.078 px from the truth on average, 0.133 at worst, where the first within 0.25 px of a flat board came out
    0.104 and 0.236: the best never further than the first).

    refine: the sector detector's corners refined by the gradient search (``cornerSubPix``), for a
    board held up close. On rendered boards held up to pinholes the detector's own corners fitted
    focal lengths 0.1-0.4 % long and the refined ones within 0.1 % but for strong barrels; on boards
    lying on the floor, their squares small or thin, the refined corners were further from the truth
    (0.15-0.45 px rms against 0.08-0.26).
    """
    corners = _find_direct(gray, board, exhaustive=False, refine=refine)
    if thorough and camera is None:
        if corners is None:
            corners = _find_direct(gray, board, exhaustive=False, scale=2)
    elif thorough:
        # of every way of looking, the set that best fits a flat board through the lens: a detector can take a grid
        # off the board's squares that no flat board explains, and its corners of a board seen small scatter
        best, best_fit = None, math.inf
        for find in (lambda: corners, lambda: _find_direct(gray, board, exhaustive=False, scale=2),
                     lambda: _find_from_above(gray, board, camera, rough_pose),
                     lambda: _find_straightened(gray, board, camera)):
            found = find()
            fit = math.inf if found is None else planar_residual_px(found, board, camera)
            if found is not None and (best is None or fit < best_fit):
                best, best_fit = found, fit
        corners = best
    if corners is None:
        return None
    return canonical_order(corners, board, gray)


def canonical_order(corners: np.ndarray, board: Board, gray: np.ndarray) -> np.ndarray:
    """``corners`` (N, 2) reordered so that X turns counter-clockwise onto Y on the screen and, for a board
    that is not :attr:`Board.symmetric`, the origin is the inner corner next to the black corner square."""
    grid = np.asarray(corners, dtype=np.float64).reshape(board.rows, board.cols, 2)
    if _turn(grid) > 0:
        grid = grid[:, ::-1]
    if not board.symmetric:
        H, _ = cv2.findHomography(_grid_xy(board), grid.reshape(-1, 2))
        if H is not None:
            first = _mean_grey(gray, H, -0.5, -0.5)
            last = _mean_grey(gray, H, board.cols - 0.5, board.rows - 0.5)
            if first > last:
                grid = grid[::-1, ::-1]
    return grid.reshape(-1, 2).copy()


def board_area_fraction(corners: np.ndarray, width: int, height: int) -> float:
    """Share of the image covered by the hull of the inner corners."""
    hull = cv2.convexHull(np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2))
    return float(cv2.contourArea(hull)) / float(width * height)


def sharpness(gray: np.ndarray, corners: np.ndarray) -> float:
    """Variance of the Laplacian inside the board's bounding box: low for a blurred view."""
    x0, y0 = np.floor(np.min(corners, axis=0)).astype(int)
    x1, y1 = np.ceil(np.max(corners, axis=0)).astype(int)
    h, w = gray.shape[:2]
    roi = gray[max(y0, 0):min(y1 + 1, h), max(x0, 0):min(x1 + 1, w)]
    if roi.size < 16:
        return 0.0
    return float(cv2.Laplacian(roi, cv2.CV_64F).var())


# ---------------------------------------------------------------------- helpers


def _find_direct(gray: np.ndarray, board: Board, *, exhaustive: bool, scale: int = 1,
                 refine: bool = False) -> np.ndarray | None:
    img = gray if scale == 1 else cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY | (cv2.CALIB_CB_EXHAUSTIVE if exhaustive else 0)
    found, corners = cv2.findChessboardCornersSB(img, board.size, flags=flags)
    if not found:
        found, corners = cv2.findChessboardCorners(
            img, board.size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return None
        refine = True
    if refine:
        win = _subpix_window(corners.reshape(-1, 2), board)
        corners = cv2.cornerSubPix(img, np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 1, 2),
                                   (win, win), (-1, -1), SUBPIX_CRITERIA)
    pts = corners.reshape(-1, 2).astype(np.float64)
    # pixel centres are whole numbers at both scales: u = scale * (u0 + 0.5) - 0.5
    return (pts + 0.5) / scale - 0.5


def _subpix_window(corners: np.ndarray, board: Board) -> int:
    grid = corners.reshape(board.rows, board.cols, 2)
    step = min(np.linalg.norm(np.diff(grid, axis=0), axis=2).min(), np.linalg.norm(np.diff(grid, axis=1), axis=2).min())
    return int(max(2, min(11, step / 3)))


def _find_from_above(gray, board: Board, camera: Camera, rough_pose) -> np.ndarray | None:
    """Corners found in views from above (:func:`_find_resampled`)."""
    windows = _candidate_windows(gray)
    views = ((R, w) for R in _downward_rotations(camera, rough_pose) for w in windows)
    return _find_resampled(gray, board, camera, views)


def _find_straightened(gray, board: Board, camera: Camera) -> np.ndarray | None:
    """Corners found in pinhole views through the lens looking straight at each candidate window (a board
    on a stand near the edge of a wide lens, its rows bent)."""
    views = []
    for window in _candidate_windows(gray):
        x0, y0, x1, y1 = window
        ray = camera.rays_cam(np.array([[(x0 + x1) / 2.0, (y0 + y1) / 2.0]]))[0]
        if np.all(np.isfinite(ray)):
            views.append((_facing(ray / np.linalg.norm(ray)), window))
    return _find_resampled(gray, board, camera, views)


def _find_resampled(gray, board: Board, camera: Camera, views) -> np.ndarray | None:
    """Corners found in pinhole views ``(R_view, window)`` (:func:`_view_from_above`) at a few sizes; the
    detectors' sub-pixel accuracy varies from one resampling to the next, so the set that best fits a flat
    board (:func:`planar_residual_px`) is kept (the first one under :data:`GOOD_FIT_PX` at once)."""
    best, best_fit = None, math.inf
    for R_view, window in views:
        for size in VIEW_SIZES_PX:
            maps = _view_from_above(camera, R_view, window, size)
            if maps is None:
                continue
            mx, my = maps
            view = cv2.remap(gray, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            corners = _find_direct(view, board, exhaustive=False)
            if corners is None:
                continue
            uv = np.stack([_bilinear(mx, corners), _bilinear(my, corners)], axis=1)
            if not np.all(np.isfinite(uv)) or np.any(uv < 0):
                continue
            fit = planar_residual_px(uv, board, camera)
            if fit < best_fit:
                best, best_fit = uv, fit
            if best_fit < GOOD_FIT_PX:
                return best
    return best


def _facing(ray: np.ndarray) -> np.ndarray:
    """Rotation camera frame -> a virtual camera whose optical axis is the unit ``ray`` (camera frame), its
    x axis kept as level with the camera's as it can be."""
    x = np.cross([0.0, 1.0, 0.0], ray)
    if np.linalg.norm(x) < 1e-9:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(ray, x), ray])


def board_pose(camera: Camera, obj: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Board -> camera ``(rvec, tvec)`` from ``corners`` (N, 2) of the board points ``obj`` (N, 3), through the
    camera's own lens model: ``solvePnP`` (IPPE, then iterative) on the corners' normalised lens coordinates, so
    pinhole, fisheye and Tsai lenses are handled alike; None where a corner has no ray or no pose solves."""
    rays = camera.rays_cam(np.asarray(corners, dtype=np.float64))
    if not np.all(np.isfinite(rays)):
        return None
    norm = (rays[:, :2] / rays[:, 2:3]).reshape(-1, 1, 2)
    o = np.asarray(obj, dtype=np.float64).reshape(-1, 1, 3)
    ok, rvec, tvec = cv2.solvePnP(o, norm, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    ok, rvec, tvec = cv2.solvePnP(o, norm, np.eye(3), None, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    return rvec.ravel(), tvec.ravel()


def planar_residual_px(corners: np.ndarray, board: Board, camera: Camera) -> float:
    """Mean distance (pixels) between ``corners`` (N, 2, in detector order) and the best flat grid
    through them: a homography from the grid to the lens's undistorted coordinates, projected back."""
    rays = camera.rays_cam(corners)
    if not np.all(np.isfinite(rays)):
        return math.inf
    norm = rays[:, :2] / rays[:, 2:3]
    H, _ = cv2.findHomography(_grid_xy(board), norm, 0)
    if H is None:
        return math.inf
    g = np.concatenate([_grid_xy(board), np.ones((board.n, 1))], axis=1) @ H.T
    uv, valid = camera.project_cam(g / g[:, 2:3])
    if not valid.all():
        return math.inf
    return float(np.linalg.norm(uv - corners, axis=1).mean())


def _candidate_windows(gray: np.ndarray, count: int = 2) -> list[tuple[int, int, int, int]]:
    """Up to ``count`` image boxes ``(x0, y0, x1, y1)`` dense in saddle points (where four squares
    meet), densest first, each grown by half its size: where a board may lie."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    ixx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3)
    iyy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
    ixy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3)
    saddle = np.maximum(ixy * ixy - ixx * iyy, 0.0)
    strong = (saddle > np.percentile(saddle, 99.0)).astype(np.float32)
    h, w = gray.shape[:2]
    k = max(15, (min(h, w) // 12) | 1)
    density = cv2.boxFilter(strong, -1, (k, k))
    out = []
    for _ in range(count):
        peak = float(density.max())
        if peak <= 0.02:
            break
        y, x = np.unravel_index(int(np.argmax(density)), density.shape)
        _, labels = cv2.connectedComponents((density > 0.3 * peak).astype(np.uint8))
        ys, xs = np.nonzero(labels == labels[y, x])
        x0, x1, y0, y1 = xs.min(), xs.max(), ys.min(), ys.max()
        gx, gy = (x1 - x0) // 2 + k, (y1 - y0) // 2 + k
        out.append((max(0, x0 - gx), max(0, y0 - gy), min(w, x1 + gx), min(h, y1 + gy)))
        density[labels == labels[y, x]] = 0.0
    return out


def _downward_rotations(camera: Camera, rough_pose):
    """Rotations camera frame -> a virtual camera looking straight down at the floor."""
    if rough_pose is not None:
        R_wc = np.asarray(rough_pose[0], dtype=np.float64)  # world -> camera
        x_w = R_wc[0].copy()
        x_w[2] = 0.0
        if np.linalg.norm(x_w) > 1e-6:
            x_w /= np.linalg.norm(x_w)
            z_w = np.array([0.0, 0.0, -1.0])
            y_w = np.cross(z_w, x_w)
            R_vw = np.stack([x_w, y_w, z_w])   # world -> virtual
            yield R_vw @ R_wc.T
            return                              # a rough pose is near enough: no guessing
    for pitch in GUESSED_PITCHES_DEG:
        a = math.radians(90.0 - pitch)        # turn the view down about the camera's x axis
        c, s = math.cos(a), math.sin(a)
        yield np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _view_from_above(camera: Camera, R_view: np.ndarray, window, size_px: int):
    """(map_x, map_y) float32 of a pinhole view with rotation ``R_view`` (camera -> view) framing
    what the camera sees in ``window`` (x0, y0, x1, y1), ``size_px`` across; None
    when the window looks too far from straight down."""
    x0, y0, x1, y1 = window
    v, u = np.mgrid[y0:y1:4, x0:x1:4].astype(np.float64)
    rays = camera.rays_cam(np.stack([u.ravel(), v.ravel()], axis=1)) @ R_view.T
    ok = np.all(np.isfinite(rays), axis=1) & (rays[:, 2] > math.cos(math.radians(NADIR_REACH_DEG)))
    if ok.sum() < 20:
        return None
    xy = rays[ok, :2] / rays[ok, 2:3]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    f = size_px / max(hi[0] - lo[0], hi[1] - lo[1], 1e-9)
    W, H = int((hi[0] - lo[0]) * f) + 1, int((hi[1] - lo[1]) * f) + 1
    if min(W, H) < 32:
        return None
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.stack([lo[0] + xx.ravel() / f, lo[1] + yy.ravel() / f, np.ones(W * H)], axis=1) @ R_view
    uv, valid = camera.project_cam(d)
    uv[~valid] = -1.0
    return uv[:, 0].reshape(H, W).astype(np.float32), uv[:, 1].reshape(H, W).astype(np.float32)


def _bilinear(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    out = cv2.remap(img, pts[:, 0].astype(np.float32).reshape(-1, 1), pts[:, 1].astype(np.float32).reshape(-1, 1),
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
    return out.ravel().astype(np.float64)


def _grid_xy(board: Board) -> np.ndarray:
    col, row = np.meshgrid(np.arange(board.cols), np.arange(board.rows))
    return np.stack([col.ravel(), row.ravel()], axis=1).astype(np.float64)


def _turn(grid: np.ndarray) -> float:
    """Sum of image cross products X x Y over the grid (x right, y down): negative when X turns
    counter-clockwise onto Y on the screen, as seen from the printed side."""
    dx = grid[:-1, 1:] - grid[:-1, :-1]
    dy = grid[1:, :-1] - grid[:-1, :-1]
    return float(np.sum(dx[..., 0] * dy[..., 1] - dx[..., 1] * dy[..., 0]))


def _mean_grey(gray: np.ndarray, H: np.ndarray, col: float, row: float) -> float:
    """Mean grey level in the middle of the square centred at grid position (col, row)."""
    offs = np.array([[dx, dy] for dx in (-0.2, 0.0, 0.2) for dy in (-0.2, 0.0, 0.2)])
    pts = cv2.perspectiveTransform((offs + (col, row)).reshape(-1, 1, 2), H).reshape(-1, 2)
    h, w = gray.shape[:2]
    ij = np.rint(pts).astype(int)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    if not ok.any():
        return 128.0
    return float(gray[ij[ok, 1], ij[ok, 0]].mean())
