"""Calibration boards in the synthetic worlds: a chessboard moved in front of a camera (for its
intrinsics) or laid on the floor at a few places (for the floor calibration), rendered into any
camera of the house or of a random world, so that the calibration commands can be checked
against the cameras' true calibrations.

Rendering (:class:`BoardRenderer`): each pixel is sampled at ``supersample x supersample``
points whose world rays come from the camera's own lens model (computed once per camera); a
sample shows the board where its ray meets the board's plane inside the printed sheet (the
squares and a white border half a square wide) before the empty room's surface behind it
(:class:`common.synth.render.CameraRenderer`), else the room. The samples are averaged, so edges
are anti-aliased as a real sensor sees them, and sensor noise is added.

Board frame (:class:`common.calibrate.board.Board`): inner corner ``(col, row)`` at
``(col, row, 0) * square_m``; the outer square next to corner ``(0, 0)`` is black. Poses are
``(R_wb, t_wb)``: ``X_world = R_wb X_board + t_wb``.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from common.calibrate.board import Board
from common.camera import Camera
from common.synth.render import SURF_FLOOR, CameraRenderer, raycast_room
from common.synth.scene import Room

BLACK, WHITE = 28.0, 220.0
FLOOR_MIN_AREA = 0.006
"""A floor position counts as seen by a camera when the board covers at least this share of its image."""
FLOOR_MAX_SLANT_DEG = 78.0


class BoardRenderer:
    """One camera's renderer of a board over the empty room (or a plain grey background)."""

    def __init__(self, camera: Camera, room: Room | None = None, *, supersample: int = 2, seed: int = 0) -> None:
        self.camera = camera
        self.ss = int(supersample)
        H, W, s = camera.height, camera.width, self.ss
        off = (np.arange(s) + 0.5) / s - 0.5
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        uu = (u[:, :, None, None] + off[None, None, None, :]).repeat(s, axis=2)
        vv = (v[:, :, None, None] + off[None, None, :, None]).repeat(s, axis=3)
        rays = camera.rays(np.stack([uu.ravel(), vv.ravel()], axis=1)).astype(np.float32)
        self.rays = rays.reshape(H, W, s * s, 3)
        self.centre = camera.center
        if room is not None:
            bg = CameraRenderer(camera, room, seed=seed, noise_std=0.0, shadows=False)
            self.background = cv2.cvtColor(bg.bg_bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
            self.bg_depth = bg.bg_depth
        else:
            self.background = np.full((H, W), 110.0, dtype=np.float32)
            self.bg_depth = np.full((H, W), np.inf, dtype=np.float32)
        self.seed = seed

    def _box(self, board: Board, pose):
        """Pixel box (x0, y0, x1, y1) around the printed sheet, from its edges projected; None when out of view."""
        c = _sheet_corners(board, pose)
        edge = np.concatenate([c[k] + np.linspace(0, 1, 40)[:, None] * (c[(k + 1) % 4] - c[k]) for k in range(4)])
        uv, _ = self.camera.project(edge)
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if not len(uv):
            return None
        W, H = self.camera.width, self.camera.height
        x0, y0 = np.clip(np.floor(uv.min(axis=0)).astype(int) - 3, 0, [W, H])
        x1, y1 = np.clip(np.ceil(uv.max(axis=0)).astype(int) + 4, 0, [W, H])
        return None if x1 <= x0 or y1 <= y0 else (int(x0), int(y0), int(x1), int(y1))

    def render(self, board: Board | None, pose=None, *, key: int = 0, noise_std: float = 2.0) -> np.ndarray:
        """(H, W) uint8 grey frame with the board at ``pose`` (None: the empty room); ``key`` picks the noise."""
        img = self.background.copy()
        box = None if board is None else self._box(board, pose)
        if box is not None:
            x0, y0, x1, y1 = box
            rays = self.rays[y0:y1, x0:x1]
            R_wb, t_wb = (np.asarray(a, dtype=np.float64) for a in pose)
            n = R_wb[:, 2]
            denom = rays @ n.astype(np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.float32(n @ (t_wb - self.centre)) / denom
            ok = np.isfinite(s) & (s > 0) & (s <= self.bg_depth[y0:y1, x0:x1, None] + 0.01)
            p = (s[..., None] * rays + (self.centre - t_wb).astype(np.float32)) @ R_wb.astype(np.float32)
            sq = board.square_m
            bx, by = p[..., 0] / sq, p[..., 1] / sq
            on = ok & (bx >= -1.5) & (bx <= board.cols + 0.5) & (by >= -1.5) & (by <= board.rows + 0.5)
            i, j = np.floor(bx) + 1, np.floor(by) + 1
            squares = (i >= 0) & (i <= board.cols) & (j >= 0) & (j <= board.rows)
            value = np.where(squares & (np.mod(i + j, 2) == 0), BLACK, WHITE)
            share = on.mean(axis=2)
            board_value = np.where(on, value, 0.0).sum(axis=2) / np.maximum(on.sum(axis=2), 1)
            img[y0:y1, x0:x1] = img[y0:y1, x0:x1] * (1.0 - share) + board_value * share
        rng = np.random.default_rng([self.seed, key, 7])
        img = img + rng.normal(0.0, noise_std, size=img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def corners_world(board: Board, pose) -> np.ndarray:
    """(N, 3) the board's inner corners in the world for ``pose``."""
    R, t = pose
    return board.object_points() @ np.asarray(R).T + np.asarray(t)


def intrinsics_poses(camera: Camera, board: Board, count: int, rng: np.random.Generator) -> list:
    """``count`` world poses of the board held in front of ``camera``: spread over the image (a 3x3
    grid of aims, then random), covering 25-60 % of its width, tilted up to 40 degrees; every corner
    in view with a margin of 4 % of the image."""
    W, H = camera.width, camera.height
    width_m = (board.cols + 1) * board.square_m
    centre_b = np.array([(board.cols - 1) / 2, (board.rows - 1) / 2, 0.0]) * board.square_m
    poses = []
    tries = 0
    while len(poses) < count and tries < 200 * count:
        tries += 1
        k = len(poses)
        if k < 9:
            u = W * (0.25 + 0.25 * (k % 3)) + rng.normal(0, 0.04 * W)
            v = H * (0.25 + 0.25 * (k // 3)) + rng.normal(0, 0.04 * H)
        else:
            u, v = rng.uniform(0.15, 0.85) * W, rng.uniform(0.15, 0.85) * H
        ray = camera.rays_cam(np.array([[u, v]]))[0]
        if not np.all(np.isfinite(ray)):
            continue
        fill = rng.uniform(0.25, 0.6)
        dist = camera.K[0, 0] * width_m / (fill * W)
        tilt = _rot(0, math.radians(rng.uniform(-40, 40))) @ _rot(1, math.radians(rng.uniform(-40, 40))) @ \
            _rot(2, math.radians(rng.uniform(-20, 20)))
        R_cb = tilt @ np.diag([1.0, -1.0, -1.0])      # the printed face towards the camera
        t_cb = ray / ray[2] * dist - R_cb @ centre_b
        pts_c = board.object_points() @ R_cb.T + t_cb
        uv, valid = camera.project_cam(pts_c)
        m = 0.04 * min(W, H)
        if not valid.all() or uv[:, 0].min() < m or uv[:, 1].min() < m or uv[:, 0].max() > W - 1 - m \
                or uv[:, 1].max() > H - 1 - m:
            continue
        R_wb = camera.R.T @ R_cb
        poses.append((R_wb, camera.R.T @ (t_cb - camera.t)))
    if len(poses) < count:
        raise ValueError(f"camera {camera.id}: could not place {count} board views in front of it")
    return poses


def floor_sees(camera: Camera, room: Room | None, board: Board, pose, *, min_area: float = FLOOR_MIN_AREA) -> bool:
    """Whether ``camera`` sees the whole board lying at ``pose`` on the floor, big enough and not edge-on."""
    pts = _sheet_corners(board, pose)
    uv, valid = camera.project(pts)
    m = 6
    if not valid.all() or uv[:, 0].min() < m or uv[:, 1].min() < m or uv[:, 0].max() > camera.width - 1 - m \
            or uv[:, 1].max() > camera.height - 1 - m:
        return False
    inner, _ = camera.project(corners_world(board, pose))
    hull = cv2.convexHull(inner.astype(np.float32).reshape(-1, 1, 2))
    if cv2.contourArea(hull) < min_area * camera.width * camera.height:
        return False
    d = pts - camera.center
    slant = np.degrees(np.arccos(np.clip(-d[:, 2] / np.linalg.norm(d, axis=1), -1, 1)))
    if slant.max() > FLOOR_MAX_SLANT_DEG:
        return False
    if room is not None:
        dist = np.linalg.norm(d, axis=1)
        hits = raycast_room(room, camera.center, d / dist[:, None])
        if not np.all((hits.surface == SURF_FLOOR) & (np.abs(hits.t - dist) < 0.02)):
            return False
    return True


def floor_positions(cameras: dict[str, Camera], room: Room, board: Board, rng: np.random.Generator, *,
                    max_positions: int = 8, step_m: float = 0.4, min_area: float = FLOOR_MIN_AREA) -> list:
    """Board poses on the floor (Z = 0) that chain every camera: the first is the place most cameras
    see, each next one is seen by a camera already chained and by the most cameras not yet chained.
    ValueError naming the cameras left out when no such chain exists."""
    (x0, y0), (x1, y1) = room.volume_rect_m
    cands = []
    for x in np.arange(x0 + 0.2, x1 - 0.2, step_m):
        for y in np.arange(y0 + 0.2, y1 - 0.2, step_m):
            yaw = rng.uniform(0, 2 * math.pi)
            centre_b = np.array([(board.cols - 1) / 2, (board.rows - 1) / 2, 0.0]) * board.square_m
            R = _rot(2, yaw)
            t = np.array([x, y, 0.0]) - R @ centre_b
            seen = {c for c, cam in cameras.items() if floor_sees(cam, room, board, (R, t), min_area=min_area)}
            if seen:
                cands.append(((R, t), seen))
    if not cands:
        raise ValueError("no floor position is seen by any camera")
    picked = [max(cands, key=lambda c: len(c[1]))]
    chained = set(picked[0][1])
    while chained != set(cameras) and len(picked) < max_positions:
        best = max(cands, key=lambda c: (bool(c[1] & chained) * len(c[1] - chained)))
        if not (best[1] & chained) or not (best[1] - chained):
            break
        picked.append(best)
        chained |= best[1]
    if chained != set(cameras):
        raise ValueError(f"cameras {sorted(set(cameras) - chained)} share no floor position with the others")
    return [p for p, _ in picked]


def write_frames(frames, folder: str | Path) -> Path:
    """Write frames as ``000000.png ...`` into ``folder`` (a clip the calibration commands read)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:06d}.png"), frame)
    return folder


def intrinsics_clip(renderer: BoardRenderer, board: Board, poses, *, frames_per_pose: int = 2):
    """Frames of the board at each pose in turn (each held ``frames_per_pose`` frames)."""
    k = 0
    for pose in poses:
        for _ in range(frames_per_pose):
            yield renderer.render(board, pose, key=k)
            k += 1


def floor_clip(renderer: BoardRenderer, board: Board, poses, *, still_frames: int = 5, gap_frames: int = 2):
    """Frames of the board lying at each floor pose in turn, the empty floor for ``gap_frames`` between
    (the board is being carried), as every camera records it at the same time. A pose of None: the
    camera does not see the board there (the empty floor instead)."""
    k = 0
    for pose in poses:
        for _ in range(gap_frames):
            yield renderer.render(None, key=k)
            k += 1
        for _ in range(still_frames):
            yield renderer.render(None if pose is None else board, pose, key=k)
            k += 1


def _sheet_corners(board: Board, pose) -> np.ndarray:
    """(4, 3) world corners of the printed sheet (squares and border)."""
    R, t = pose
    sq = board.square_m
    lo, hx, hy = -1.5 * sq, (board.cols + 0.5) * sq, (board.rows + 0.5) * sq
    sheet = np.array([[lo, lo, 0.0], [hx, lo, 0.0], [hx, hy, 0.0], [lo, hy, 0.0]])
    return sheet @ np.asarray(R).T + np.asarray(t)


def _rot(axis: int, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    if axis == 0:
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == 1:
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
