"""Calibration boards in the synthetic worlds: a chessboard or a ChArUco board moved in front of a
camera (for its intrinsics), or a chessboard laid on the floor at a few places (for the floor
calibration), rendered into any camera of the house or of a random world, so that the
calibration commands can be checked against the cameras' true calibrations.

Rendering (:class:`BoardRenderer`): each pixel is sampled at ``supersample x supersample``
points whose world rays come from the camera's own lens model (computed once per camera); a
sample shows the board where its ray meets the board's plane inside the printed sheet (the
squares and a white border half a square wide) before the empty room's surface behind it
(:class:`synth.render.CameraRenderer`), else the room. The samples are averaged, so edges
are anti-aliased as a real sensor sees them, and sensor noise is added. A chessboard's squares
are drawn exactly; a ChArUco sheet is OpenCV's own image of the board
(``CharucoBoard.generateImage``, :data:`SHEET_PX_PER_SQUARE` pixels a square, so that the squares'
edges fall on its pixels' edges) looked up where each sample lands.

Board frames: a chessboard's (:class:`calibrate.board.Board`) has inner corner
``(col, row)`` at ``(col, row, 0) * square_m``, the outer square next to corner ``(0, 0)``
black, and Z out of the printed face; a ChArUco board's
(:class:`calibrate.charuco.CharucoBoard`) is OpenCV's, origin at the sheet's first outer
corner, Y down the sheet and Z into it. Poses are ``(R_wb, t_wb)``: ``X_world = R_wb X_board + t_wb``.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from calibrate.board import Board
from calibrate.charuco import FACE_UP, CharucoBoard
from common.camera import Camera
from common.memo import BytesMemo
from synth.render import SURF_FLOOR, CameraRenderer, raycast_room
from synth.scene import Room

BLACK, WHITE = 28.0, 220.0
BACK = 150.0
"""The grey of a board's blank back (a board on a stand seen from behind)."""
FLOOR_MIN_AREA = 0.006
"""A floor position counts as seen by a camera when the board covers at least this share of its image."""
FLOOR_MAX_SLANT_DEG = 78.0
CHARUCO_FLOOR_CORNERS = 12
"""A ChArUco board on the floor counts as seen by a camera when at least this many of its inner corners
are in view, unhidden and readable (:data:`CHARUCO_MARKER_PX`)."""
CHARUCO_MARKER_PX = 12.0
"""A corner of a ChArUco board counts as readable when the markers beside it are at least this many
pixels across along both of the board's axes (two pixels a cell of a 4x4 marker and its border)."""
SHEET_PX_PER_SQUARE = 64
"""Pixels a square of a ChArUco sheet's image (its markers' bits are a few pixels wide at least)."""
STAND_HEIGHT_M = 1.2
"""The height of the squares' centre of a chessboard set up on a stand (an easel): above most furniture,
so that cameras looking across a furnished room, or level with the room, see it where they share no
place of the floor."""
STAND_TILTS_DEG = (0.0, 35.0)
"""A board on a stand stands upright or leans back by this much (its face turned up towards cameras
high in the corners)."""


VIEW_CACHE_BYTES = 256 * 2**20
"""At most this much of the cameras' supersampled views of the empty room (:class:`BoardRenderer`) is kept
per process, the least recently used going first: a calibration run renders every camera again for each
round of places, and casting a 640x480 camera's samples into the room takes about six seconds."""
_views = BytesMemo(VIEW_CACHE_BYTES)


def _view(camera: Camera, room: Room | None, ss: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(read-only) every sample's ray (H, W, ss * ss, 3), the empty room's grey (H, W) and its depth along every
    sample's ray (H, W, ss * ss) (a plain grey background at infinity without a room)."""
    H, W = camera.height, camera.width
    off = (np.arange(ss) + 0.5) / ss - 0.5
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    uu = (u[:, :, None, None] + off[None, None, None, :]).repeat(ss, axis=2)
    vv = (v[:, :, None, None] + off[None, None, :, None]).repeat(ss, axis=3)
    rays = camera.rays(np.stack([uu.ravel(), vv.ravel()], axis=1)).astype(np.float32)
    if room is not None:
        bg = CameraRenderer(camera, room, seed=seed, noise_std=0.0, shadows=False)
        background = cv2.cvtColor(bg.bg_bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
        # the room's depth along every sample's own ray: a board lying on the floor is as far as the floor
        # along each of them, where the pixel's one depth would hide part of its far squares (seen at a
        # grazing angle a pixel spans tens of centimetres of floor)
        hits = raycast_room(room, camera.center, rays.astype(np.float64))
        depth = hits.t.reshape(H, W, ss * ss).astype(np.float32)
    else:
        background = np.full((H, W), 110.0, dtype=np.float32)
        depth = np.full((H, W, ss * ss), np.inf, dtype=np.float32)
    view = (rays.reshape(H, W, ss * ss, 3), background, depth)
    for a in view:
        a.setflags(write=False)
    return view


class BoardRenderer:
    """One camera's renderer of a board over the empty room (or a plain grey background)."""

    def __init__(self, camera: Camera, room: Room | None = None, *, supersample: int = 2, seed: int = 0) -> None:
        self.camera = camera
        self.ss = int(supersample)
        key = (camera.fingerprint(), repr(room), self.ss, int(seed))
        self.rays, self.background, self.bg_depth = _views.get(key, lambda: _view(camera, room, self.ss, seed),
                                                               lambda v: sum(a.nbytes for a in v))
        self.centre = camera.center
        self.seed = seed
        self._sheets: dict[CharucoBoard, np.ndarray] = {}

    def _box(self, board: Board | CharucoBoard, pose):
        """Pixel box (x0, y0, x1, y1) around the printed sheet, from its edges projected; the whole image when
        part of an edge lies beyond the lens's view (the sheet's visible part may then reach anywhere in
        it); None when out of view."""
        c = _sheet_corners(board, pose)
        edge = np.concatenate([c[k] + np.linspace(0, 1, 40)[:, None] * (c[(k + 1) % 4] - c[k]) for k in range(4)])
        uv, _ = self.camera.project(edge)
        finite = np.all(np.isfinite(uv), axis=1)
        W, H = self.camera.width, self.camera.height
        if not finite.any():
            return None
        if not finite.all():
            return (0, 0, W, H)
        uv = np.clip(uv, -W - H, 2 * (W + H))   # far outside the image: kept from overflowing the int cast
        x0, y0 = np.clip(np.floor(uv.min(axis=0)).astype(int) - 3, 0, [W, H])
        x1, y1 = np.clip(np.ceil(uv.max(axis=0)).astype(int) + 4, 0, [W, H])
        return None if x1 <= x0 or y1 <= y0 else (int(x0), int(y0), int(x1), int(y1))

    def render(self, board: Board | CharucoBoard | None, pose=None, *, key: int = 0,
               noise_std: float = 2.0) -> np.ndarray:
        """(H, W) uint8 grey frame with the board at ``pose`` (None: the empty room); ``key`` picks the noise."""
        img = self.background.copy()
        box = None if board is None else self._box(board, pose)
        if box is not None:
            x0, y0, x1, y1 = box
            rays = self.rays[y0:y1, x0:x1]
            R_wb, t_wb = (np.asarray(a, dtype=np.float64) for a in pose)
            n = R_wb[:, 2]
            denom = rays @ n.astype(np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):   # a fisheye's rays are NaN outside its circle
                s = np.float32(n @ (t_wb - self.centre)) / denom
                p = (s[..., None] * rays + (self.centre - t_wb).astype(np.float32)) @ R_wb.astype(np.float32)
            ok = np.isfinite(s) & (s > 0) & (s <= self.bg_depth[y0:y1, x0:x1] + 0.01)
            sq = board.square_m
            bx, by = p[..., 0] / sq, p[..., 1] / sq
            if isinstance(board, CharucoBoard):
                on, value = self._charuco_value(board, bx, by)
                on &= ok
            else:
                on = ok & (bx >= -1.5) & (bx <= board.cols + 0.5) & (by >= -1.5) & (by <= board.rows + 0.5)
                i, j = np.floor(bx) + 1, np.floor(by) + 1
                squares = (i >= 0) & (i <= board.cols) & (j >= 0) & (j <= board.rows)
                value = np.where(squares & (np.mod(i + j, 2) == 0), BLACK, WHITE)
            if _face_normal(board, R_wb) @ (self.centre - t_wb) < 0:   # seen from behind: the sheet's blank back
                value = np.full_like(value, BACK)
            share = on.mean(axis=2)
            board_value = np.where(on, value, 0.0).sum(axis=2) / np.maximum(on.sum(axis=2), 1)
            img[y0:y1, x0:x1] = img[y0:y1, x0:x1] * (1.0 - share) + board_value * share
        rng = np.random.default_rng([self.seed, key, 7])
        img = img + rng.normal(0.0, noise_std, size=img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def _charuco_value(self, board: CharucoBoard, bx: np.ndarray, by: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(on the sheet, grey level) at board positions ``(bx, by)`` in squares (any shape)."""
        if board not in self._sheets:
            self._sheets[board] = _charuco_sheet(board)
        sheet = self._sheets[board]
        col = np.floor((bx + 0.5) * SHEET_PX_PER_SQUARE)
        row = np.floor((by + 0.5) * SHEET_PX_PER_SQUARE)
        on = (col >= 0) & (col < sheet.shape[1]) & (row >= 0) & (row < sheet.shape[0])
        value = sheet[np.where(on, row, 0).astype(np.intp), np.where(on, col, 0).astype(np.intp)]
        return on, value


def _face_normal(board: Board | CharucoBoard, R: np.ndarray) -> np.ndarray:
    """(3,) the world direction the printed face of a board turned by ``R`` (board -> world) looks to: a
    chessboard's Z, a ChArUco board's minus Z (OpenCV's frame, Z into the sheet)."""
    n = np.asarray(R, dtype=np.float64)[:, 2]
    return -n if isinstance(board, CharucoBoard) else n


def on_stand(board: Board | CharucoBoard, pose) -> bool:
    """Whether the board at ``pose`` stands on a stand rather than lying on the floor (its squares' centre
    over 5 cm up)."""
    return bool(placed_centre(board, pose)[2] > 0.05)


def place_area(camera: Camera, room: Room | None, board: Board | CharucoBoard, pose, *, min_area: float = 0.0) -> float:
    """:func:`stand_area` of a board on a stand (:func:`on_stand`), else :func:`floor_area`."""
    if on_stand(board, pose):
        return stand_area(camera, room, board, pose, min_area=min_area)
    return floor_area(camera, room, board, pose, min_area=min_area)


def corners_world(board: Board | CharucoBoard, pose) -> np.ndarray:
    """(N, 3) the board's inner corners in the world for ``pose``."""
    R, t = pose
    return board.object_points() @ np.asarray(R).T + np.asarray(t)


def intrinsics_poses(camera: Camera, board: Board | CharucoBoard, count: int, rng: np.random.Generator, *,
                     min_in_view: float = 1.0, fill: tuple[float, float] = (0.25, 0.6)) -> list:
    """``count`` world poses of the board held in front of ``camera``: spread over the image (a 3x3
    grid of aims, then random), spanning a share of its width drawn from ``fill`` (held square to the
    camera), tilted up to 40 degrees, the printed face towards the camera.

    min_in_view 1: every corner in view with a margin of 4 % of the image, the board square to the
    optical axis before it is tilted. Below 1 (partial views, for a ChArUco board): the random
    aims reach the image's edges and at least this share of the corners is in view with that
    margin; the board is square to the aim's ray before it is tilted and its distance is taken
    along that ray, as a person holds it up to a fisheye that sees 90 degrees aside."""
    if not 0.0 < min_in_view <= 1.0:
        raise ValueError(f"min_in_view must lie in (0, 1], got {min_in_view!r}")
    partial = min_in_view < 1.0
    W, H = camera.width, camera.height
    width_m, centre_b, facing = _held(board)
    obj = board.object_points()
    poses = []
    tries = 0
    while len(poses) < count and tries < 200 * count:
        tries += 1
        k = len(poses)
        if k < 9:
            u = W * (0.25 + 0.25 * (k % 3)) + rng.normal(0, 0.04 * W)
            v = H * (0.25 + 0.25 * (k // 3)) + rng.normal(0, 0.04 * H)
        elif partial:
            u, v = rng.uniform(0.0, 1.0) * W, rng.uniform(0.0, 1.0) * H
        else:
            u, v = rng.uniform(0.15, 0.85) * W, rng.uniform(0.15, 0.85) * H
        ray = camera.rays_cam(np.array([[u, v]]))[0]
        if not np.all(np.isfinite(ray)):
            continue
        span = rng.uniform(*fill)
        dist = camera.K[0, 0] * width_m / (span * W)
        tilt = _rot(0, math.radians(rng.uniform(-40, 40))) @ _rot(1, math.radians(rng.uniform(-40, 40))) @ \
            _rot(2, math.radians(rng.uniform(-20, 20)))
        if partial:
            R_cb = _towards(ray) @ tilt @ facing
            t_cb = ray * dist - R_cb @ centre_b
        else:
            R_cb = tilt @ facing
            t_cb = ray / ray[2] * dist - R_cb @ centre_b
        uv, valid = camera.project_cam(obj @ R_cb.T + t_cb)
        m = 0.04 * min(W, H)
        with np.errstate(invalid="ignore"):
            inside = valid & (uv[:, 0] >= m) & (uv[:, 1] >= m) & (uv[:, 0] <= W - 1 - m) & (uv[:, 1] <= H - 1 - m)
        if inside.mean() < min_in_view or (not partial and not valid.all()):
            continue
        R_wb = camera.R.T @ R_cb
        poses.append((R_wb, camera.R.T @ (t_cb - camera.t)))
    if len(poses) < count:
        raise ValueError(f"camera {camera.id}: could not place {count} board views in front of it")
    return poses


def floor_sees(camera: Camera, room: Room | None, board: Board, pose, *, min_area: float = FLOOR_MIN_AREA) -> bool:
    """Whether ``camera`` sees the whole board lying at ``pose`` on the floor, big enough and not edge-on."""
    return floor_area(camera, room, board, pose, min_area=min_area) >= min_area


def floor_area(camera: Camera, room: Room | None, board: Board | CharucoBoard, pose, *, min_area: float = 0.0) -> float:
    """The share of ``camera``'s image the board lying at ``pose`` covers (its inner corners' hull), or 0
    when the camera does not see the whole board, sees it edge-on, something in the room hides it, or
    it covers less than ``min_area`` (the room then not looked at). A ChArUco board counts seen in part:
    the hull of its corners in view, unhidden and readable, when there are enough of them
    (:data:`CHARUCO_FLOOR_CORNERS`)."""
    if isinstance(board, CharucoBoard):
        return _charuco_floor_area(camera, room, board, pose, min_area)
    return _sheet_area(camera, room, board, pose, min_area, on_floor=True)


def _charuco_floor_area(camera: Camera, room: Room | None, board: CharucoBoard, pose, min_area: float) -> float:
    R = np.asarray(pose[0], dtype=np.float64)
    pts = corners_world(board, pose)
    uv, valid = camera.project(pts)
    m = 6
    with np.errstate(invalid="ignore"):
        ok = valid & (uv[:, 0] >= m) & (uv[:, 1] >= m) & (uv[:, 0] <= camera.width - 1 - m) & \
            (uv[:, 1] <= camera.height - 1 - m)
    d = pts - camera.center
    dist = np.linalg.norm(d, axis=1)
    ok &= np.degrees(np.arccos(np.clip(-d[:, 2] / dist, -1, 1))) <= FLOOR_MAX_SLANT_DEG
    share = board.marker_m / board.square_m
    for axis in (0, 1):   # the markers' size beside each corner along the board's two axes
        step, _ = camera.project(pts + R[:, axis] * board.square_m)
        with np.errstate(invalid="ignore"):
            ok &= np.nan_to_num(np.linalg.norm(step - uv, axis=1)) * share >= CHARUCO_MARKER_PX
    if ok.sum() < CHARUCO_FLOOR_CORNERS:
        return 0.0
    if room is not None and ok.any():
        hits = raycast_room(room, camera.center, d[ok] / dist[ok, None])
        ok[np.flatnonzero(ok)] = (hits.surface == SURF_FLOOR) & (np.abs(hits.t - dist[ok]) < 0.02)
        if ok.sum() < CHARUCO_FLOOR_CORNERS:
            return 0.0
    hull = cv2.convexHull(uv[ok].astype(np.float32).reshape(-1, 1, 2))
    area = float(cv2.contourArea(hull)) / (camera.width * camera.height)
    return area if area >= min_area else 0.0


def floor_positions(cameras: dict[str, Camera], room: Room, board: Board | CharucoBoard, rng: np.random.Generator, *,
                    max_positions: int = 8, step_m: float = 0.4, min_area: float = FLOOR_MIN_AREA,
                    well_seen: float = 0.0, stand: bool = False) -> list:
    """Board poses on the floor (Z = 0) that chain every camera: the first is the place most cameras
    see, of those the one whose views add up to the most of the cameras' images (the first place is the
    floor frame, and every camera's pose is measured against that place as the cameras see it: a far camera
    turns with any error of its yaw, by its distance from it); each next one is seen by a camera already
    chained and by the most cameras not yet chained.
    With ``well_seen`` > 0, as an installer is told to: each camera whose views so far are all under
    ``well_seen`` times the largest view it can have of a place another camera also sees gets that
    place too. With ``stand`` (a chessboard), where no place on the floor reaches a camera not yet
    chained, the board set up on a stand (:func:`stand_pose`) at a place a chained camera sees too; the
    first place always lies on the floor (it is the floor frame); once the chain stands on a stand, the
    board is also laid flat once in front of each camera that has no floor place yet, where it sees it
    largest, even alone (a place on the floor ties the camera's height and tilt to the floor, which a
    chain through stands leaves to the one floor place at its start). ValueError naming the cameras left
    out when no such chain exists."""
    cands = _floor_candidates(cameras, room, board, rng, step_m, min_area)
    if not cands:
        raise ValueError("no floor position is seen by any camera")
    raised = _stand_candidates(cameras, room, board, rng, 2 * step_m, min_area) if stand else []
    picked = [max(cands, key=lambda c: (len(c[1]), sum(c[2][k] for k in c[1])))]
    chained = set(picked[0][1])
    while chained != set(cameras) and len(picked) < max_positions:
        for pool in (cands, raised):
            best = max(pool, key=lambda c: (bool(c[1] & chained) * len(c[1] - chained)), default=None)
            if best is not None and best[1] & chained and best[1] - chained:
                break
        else:
            break
        picked.append(best)
        chained |= best[1]
    if chained != set(cameras):
        raise ValueError(f"cameras {sorted(set(cameras) - chained)} share no floor position with the others")
    if well_seen > 0.0:
        for c in cameras:
            shared = [k for k in cands + raised if c in k[1] and len(k[1]) >= 2]
            if not shared:
                continue
            best = max(shared, key=lambda k: k[2][c])
            if max(k[2][c] for k in picked) < well_seen * best[2][c] and len(picked) < max_positions:
                picked.append(best)
    if any(on_stand(board, k[0]) for k in picked):
        floor = [k for k in picked if not on_stand(board, k[0])]
        for c in cameras:
            own = [k for k in cands if c in k[1]]
            if own and not any(c in k[1] for k in floor):
                tie = max(own, key=lambda k: k[2][c])
                picked.append(tie)
                floor.append(tie)
    return [p for p, _, _ in picked]


def more_floor_positions(cameras: dict[str, Camera], room: Room, board: Board | CharucoBoard, rng: np.random.Generator,
                         cam_id: str, taken: list, *, count: int = 2, step_m: float = 0.4,
                         min_area: float = FLOOR_MIN_AREA, apart_m: float = 0.5, stand: bool = False,
                         rule: str = "largest", well_seen: float = 0.5) -> list:
    """Up to ``count`` more board poses for camera ``cam_id``, as an installer lays the board again when the
    calibration warns that it is not pinned down, among the places another camera sees too, at least
    ``apart_m`` from the places ``taken`` and from each other (with ``stand``, places with the board on a
    stand count too): with ``rule="largest"``, the places it sees largest; with ``rule="spread"``, of the
    places it sees at least ``well_seen`` times as large as the largest, each the one farthest from every
    place laid so far (spread across its view, near and far: a camera far from every place is pinned by
    how the places it sees lie apart, which places side by side at its nearest edge hardly tell)."""
    if rule not in ("largest", "spread"):
        raise ValueError(f"rule {rule!r}: expected 'largest' or 'spread'")
    centres = [placed_centre(board, p)[:2] for p in taken]
    cands = _floor_candidates(cameras, room, board, rng, step_m, min_area)
    if stand:
        cands += _stand_candidates(cameras, room, board, rng, 2 * step_m, min_area)
    # the places another camera sees too: (pose, its centre on the floor's plan, how large the camera sees it)
    places = [(pose, placed_centre(board, pose)[:2], areas[cam_id]) for pose, seen, areas in cands
              if cam_id in seen and len(seen) >= 2]

    def gap(centre) -> float:
        return min((float(np.linalg.norm(centre - c)) for c in centres), default=math.inf)

    out: list = []
    if rule == "largest":
        for pose, centre, _ in sorted(places, key=lambda k: -k[2]):
            if len(out) >= count:
                break
            if gap(centre) >= apart_m:
                out.append(pose)
                centres.append(centre)
        return out
    largest = max((area for _, _, area in places), default=0.0)
    pool = [k for k in places if k[2] >= well_seen * largest]
    while len(out) < count and pool:
        pose, centre, _ = max(pool, key=lambda k: gap(k[1]))
        if gap(centre) < apart_m:
            break
        out.append(pose)
        centres.append(centre)
    return out


def placed_centre(board: Board | CharucoBoard, pose) -> np.ndarray:
    """(3,) where the board at ``pose`` (world ``(R_wb, t_wb)``) has the centre of its squares."""
    R, t = (np.asarray(a, dtype=np.float64) for a in pose)
    return R @ _board_centre(board) + t


def _board_centre(board: Board | CharucoBoard) -> np.ndarray:
    """(3,) the centre of the board's squares in its own frame."""
    if isinstance(board, CharucoBoard):
        return np.array([board.cols / 2, board.rows / 2, 0.0]) * board.square_m
    return np.array([(board.cols - 1) / 2, (board.rows - 1) / 2, 0.0]) * board.square_m


def floor_pose(board: Board | CharucoBoard, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """The world pose ``(R_wb, t_wb)`` of the board lying face up on the floor, its squares' centre at
    ``(x, y)``, turned ``yaw`` radians (a ChArUco board's frame, Z into the sheet, turned over)."""
    R = _rot(2, yaw)
    if isinstance(board, CharucoBoard):
        R = R @ FACE_UP
    return R, np.array([x, y, 0.0]) - R @ _board_centre(board)


def _floor_candidates(cameras, room, board, rng, step_m: float, min_area: float) -> list:
    """``[(pose, cameras seeing it, camera -> area)]`` over a lattice of the room's floor, each at a random yaw."""
    (x0, y0), (x1, y1) = room.volume_rect_m
    poses = [floor_pose(board, x, y, rng.uniform(0, 2 * math.pi))
             for x in np.arange(x0 + 0.2, x1 - 0.2, step_m) for y in np.arange(y0 + 0.2, y1 - 0.2, step_m)]
    if isinstance(board, CharucoBoard):
        by_camera = {c: [floor_area(cam, room, board, pose, min_area=min_area) for pose in poses]
                     for c, cam in cameras.items()}
    else:
        by_camera = {c: _sheet_areas(cam, room, board, poses, min_area, on_floor=True) for c, cam in cameras.items()}
    cands = []
    for k, pose in enumerate(poses):
        areas = {c: float(by_camera[c][k]) for c in cameras}
        seen = {c for c, a in areas.items() if a >= min_area}
        if seen:
            cands.append((pose, seen, areas))
    return cands


def stand_pose(board: Board, x: float, y: float, yaw: float, tilt_deg: float = 0.0,
               height_m: float = STAND_HEIGHT_M) -> tuple[np.ndarray, np.ndarray]:
    """The world pose ``(R_wb, t_wb)`` of a chessboard set up on a stand: its squares' centre ``height_m``
    above the floor at ``(x, y)``, its printed face towards the floor direction ``yaw`` (radians) and
    leaning back by ``tilt_deg``, its rows level."""
    t = math.radians(tilt_deg)
    normal = np.array([math.cos(yaw) * math.cos(t), math.sin(yaw) * math.cos(t), math.sin(t)])
    x_axis = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    R = np.stack([x_axis, np.cross(normal, x_axis), normal], axis=1)
    return R, np.array([x, y, height_m]) - R @ _board_centre(board)


def stand_area(camera: Camera, room: Room | None, board: Board, pose, *, min_area: float = 0.0) -> float:
    """The share of ``camera``'s image a chessboard on a stand at ``pose`` covers (its inner corners'
    hull), or 0 when the camera does not see the whole sheet from its printed side, sees it edge-on
    (past :data:`FLOOR_MAX_SLANT_DEG`), something in the room stands in front of it, or it covers less
    than ``min_area``."""
    return _sheet_area(camera, room, board, pose, min_area, on_floor=False)


def _sheet_area(camera: Camera, room: Room | None, board: Board, pose, min_area: float, *, on_floor: bool) -> float:
    """The share of the image a chessboard's inner corners' hull covers, or 0 (see :func:`floor_area` and
    :func:`stand_area`). ``on_floor``: the rays to the sheet must meet the floor there (nothing standing on
    or in front of it); else only nothing in front of it."""
    return float(_sheet_areas(camera, room, board, [pose], min_area, on_floor=on_floor)[0])


def _sheet_areas(camera: Camera, room: Room | None, board: Board, poses: list, min_area: float, *,
                 on_floor: bool) -> np.ndarray:
    """:func:`_sheet_area` of each of ``poses`` ((N,) float64), the camera's projections and the rays into
    the room of all of them at once."""
    out = np.zeros(len(poses))
    if not poses:
        return out
    sheets = [_sheet_corners(board, pose) for pose in poses]
    uv, valid = camera.project(np.concatenate(sheets))
    uv, valid = uv.reshape(-1, 4, 2), valid.reshape(-1, 4)
    m = 6
    with np.errstate(invalid="ignore"):
        framed = valid.all(axis=1) & (uv[..., 0].min(axis=1) >= m) & (uv[..., 1].min(axis=1) >= m) & \
            (uv[..., 0].max(axis=1) <= camera.width - 1 - m) & (uv[..., 1].max(axis=1) <= camera.height - 1 - m)
    todo, rays = [], []
    for k in np.flatnonzero(framed):
        R = np.asarray(poses[k][0], dtype=np.float64)
        d = sheets[k] - camera.center
        slant = np.degrees(np.arccos(np.clip(-(d @ R[:, 2]) / np.linalg.norm(d, axis=1), -1, 1)))
        if slant.max() <= FLOOR_MAX_SLANT_DEG:
            todo.append(k)
            rays.append(d)
    if not todo:
        return out
    inner_w = [corners_world(board, poses[k]) for k in todo]
    inner, _ = camera.project(np.concatenate(inner_w))
    n = len(inner_w[0])
    kept = []
    for j, k in enumerate(todo):
        hull = cv2.convexHull(inner[j * n:(j + 1) * n].astype(np.float32).reshape(-1, 1, 2))
        area = float(cv2.contourArea(hull)) / (camera.width * camera.height)
        if area >= min_area:
            out[k] = area
            kept.append(j)
    if room is None or not kept:
        return out
    # nothing in the room (a chair, a table, a wall) stands on or in front of the sheet
    d = np.concatenate([np.concatenate([rays[j], inner_w[j] - camera.center]) for j in kept])
    dist = np.linalg.norm(d, axis=1)
    hits = raycast_room(room, camera.center, d / dist[:, None])
    clear = (hits.surface == SURF_FLOOR) & (np.abs(hits.t - dist) < 0.02) if on_floor else hits.t > dist - 0.02
    per = 4 + n
    for i, j in enumerate(kept):
        if not np.all(clear[i * per:(i + 1) * per]):
            out[todo[j]] = 0.0
    return out


def _stand_free(room: Room, board: Board, pose) -> bool:
    """Whether a board on a stand at ``pose`` stands clear: nothing under its centre down to the floor,
    nothing between its centre and its sheet's corners (furniture, a wall)."""
    centre = placed_centre(board, pose)
    corners = _sheet_corners(board, pose)
    d = np.concatenate([[[0.0, 0.0, -centre[2]]], corners - centre])
    dist = np.linalg.norm(d, axis=1)
    hits = raycast_room(room, centre, d / dist[:, None])
    return bool(np.all(hits.t > dist - 0.02))


def _stand_candidates(cameras, room, board, rng, step_m: float, min_area: float) -> list:
    """``[(pose, cameras seeing it, camera -> area)]`` of a chessboard on a stand over a lattice of the
    room's floor, facing twelve ways at a random start, upright and leaning back
    (:data:`STAND_TILTS_DEG`), kept where it stands clear and two cameras or more see it."""
    if not isinstance(board, Board):
        return []
    (x0, y0), (x1, y1) = room.volume_rect_m
    poses = []
    for x in np.arange(x0 + 0.5, x1 - 0.5, step_m):
        for y in np.arange(y0 + 0.5, y1 - 0.5, step_m):
            start = rng.uniform(0, 2 * math.pi)
            poses += [stand_pose(board, x, y, start + k * math.pi / 6, tilt) for k in range(12) for tilt in STAND_TILTS_DEG]
    # first without the room (cheap), then the room's rays for the places two cameras or more see and where the
    # stand stands clear
    bare = {c: _sheet_areas(cam, None, board, poses, min_area, on_floor=False) for c, cam in cameras.items()}
    seen_bare = np.stack([bare[c] >= min_area for c in cameras]) if cameras else np.zeros((0, len(poses)), bool)
    keep = [k for k in np.flatnonzero(seen_bare.sum(axis=0) >= 2) if _stand_free(room, board, poses[k])]
    roomed = {c: np.zeros(len(poses)) for c in cameras}
    for c, cam in cameras.items():
        seen_by = [k for k in keep if bare[c][k] >= min_area]
        roomed[c][seen_by] = _sheet_areas(cam, room, board, [poses[k] for k in seen_by], min_area, on_floor=False)
    cands = []
    for k in keep:
        areas = {c: float(roomed[c][k]) for c in cameras}
        seen = {c for c, a in areas.items() if a >= min_area}
        if len(seen) >= 2:
            cands.append((poses[k], seen, areas))
    return cands


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


def floor_clip(renderer: BoardRenderer, board: Board | CharucoBoard, poses, *, still_frames: int = 5,
               gap_frames: int = 2):
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


def _sheet_corners(board: Board | CharucoBoard, pose) -> np.ndarray:
    """(4, 3) world corners of the printed sheet (squares and border)."""
    R, t = pose
    sq = board.square_m
    lo = (-0.5 if isinstance(board, CharucoBoard) else -1.5) * sq
    hx, hy = (board.cols + 0.5) * sq, (board.rows + 0.5) * sq
    sheet = np.array([[lo, lo, 0.0], [hx, lo, 0.0], [hx, hy, 0.0], [lo, hy, 0.0]])
    return sheet @ np.asarray(R).T + np.asarray(t)


def _charuco_sheet(board: CharucoBoard) -> np.ndarray:
    """(rows + 1, cols + 1) squares' worth of float32 grey levels: OpenCV's image of the board, black and
    white mapped to the renderer's, with a white border half a square wide; row 0 at Y = -square / 2."""
    px = SHEET_PX_PER_SQUARE
    size = ((board.cols + 1) * px, (board.rows + 1) * px)
    img = board.opencv().generateImage(size, marginSize=px // 2, borderBits=1)
    return (BLACK + (WHITE - BLACK) * img.astype(np.float32) / 255.0).astype(np.float32)


def _held(board: Board | CharucoBoard) -> tuple[float, np.ndarray, np.ndarray]:
    """(width of the squares, metres; (3,) centre of the squares in the board frame; rotation board ->
    camera of the board held square to the optical axis, its printed face towards the camera)."""
    sq = board.square_m
    if isinstance(board, CharucoBoard):
        # OpenCV's frame: X right and Y down the sheet as the camera sees it, Z away from the camera
        return board.cols * sq, _board_centre(board), np.eye(3)
    return (board.cols + 1) * sq, _board_centre(board), np.diag([1.0, -1.0, -1.0])


def _towards(ray: np.ndarray) -> np.ndarray:
    """The rotation turning the optical axis (0, 0, 1) onto the unit ``ray`` (camera frame) about the
    axis square to both (the shortest turn, which adds no roll of its own)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, ray)
    s, c = float(np.linalg.norm(axis)), float(ray @ z)
    if s < 1e-12:
        return np.eye(3)
    a = axis / s
    A = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + s * A + (1.0 - c) * A @ A


def _rot(axis: int, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    if axis == 0:
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == 1:
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
