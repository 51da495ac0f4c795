"""Which blobs are people: the set of candidates that explains the masks, phantoms refused.

Where the cones of different people seen by different cameras cross, the
visual hull holds volume where nobody stands: a phantom. Every camera that
sees a phantom sees foreground there, so the carving vote cannot refuse it;
but the foreground it sees is already some real person's. Seen from the
cameras, a phantom explains nothing that the people do not.

:func:`explain_blobs` is the greedy silhouette cover of visual-hull people
counting: each candidate blob is projected into every camera's mask (the
voxels of its body splatted at their projected size: for an upright blob
those near its top's column, so that hull volume hanging on to a person
claims nothing for them); candidates are taken one by one (lazily,
:func:`greedy_cover`),
the one that covers the most foreground not yet covered by those accepted
first, and a candidate is accepted only when, in at least ``min_cameras``
cameras, at least ``min_new`` of the foreground it covers is foreground that
no accepted candidate covers. The rest are phantoms (or duplicates of a
person already accepted).

The cameras see the bodies in depth order. An upright candidate whose
foreground in a camera is covered by a body taken before it, standing
nearer that camera, is hidden there, not explained away: a person seated
behind a table of others, or standing behind someone, is judged on what
the camera can show of them. A candidate refused may so pass once a body
in front of it is taken; the refused are offered again. Low candidates are
not judged so: a piece of hull or a leg behind a body is hidden the same
way, and a person lying behind someone rarely shows in two cameras.

Last, an accepted low, small blob next to an accepted upright person's top
is a fragment of that person (legs carved apart from the body where
furniture hides them from some cameras), not a person of its own.

Masks at any resolution: each camera is resized to its mask. Pure: no clock,
no I/O.
"""

from __future__ import annotations

import heapq
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from common.camera import Camera, MaskCameras
from fusion_server.detection import Blob
from fusion_server.grid import VoxelGrid

MIN_NEW = 0.2
"""Share of a candidate's covered foreground that must be its own, per camera."""
SPLAT_STEP = 2
"""Blobs are projected through cells of SPLAT_STEP voxels along each axis (10 cm at 5 cm voxels)."""
MAX_POINTS = 400
"""At most this many cells of a blob are projected (every n-th, the splats grown to match)."""
CORE_RADIUS_M = 0.35
"""An upright blob claims foreground only through its voxels this close, on the floor, to its top."""
CORE_MIN_TOP_M = 1.0
"""A blob whose top is higher than this is upright (a person standing, walking or seated), ..."""
LYING_MAX_TOP_M = 0.8
"""... unless its body's top (:attr:`~fusion_server.detection.Blob.body_top_m`) is no higher than
this: a body lying on the floor (under half a metre high, carved a little thicker) under a tent of
hull a metre high, which claimed through the tent's top alone would explain little of itself and
be refused as a phantom. A seated adult's shoulders stay above it."""
FRAGMENT_MAX_M3 = 0.05
"""A low blob smaller than this (half a carved adult lying down), ..."""
FRAGMENT_RADIUS_M = 0.45
"""... closer than this on the floor to the top of an accepted upright person, is a piece of that person."""
HIDDEN_MARGIN_M = 0.3
"""A body taken this much nearer a camera than an upright candidate hides the pixels they share from it."""
MIN_SEEN = 0.3
"""A camera speaks for a candidate only where it sees (does not hide) at least this share of what it covers."""
MAX_ROUNDS = 4
"""Rounds of the cover: candidates refused are offered again while a round takes someone."""


@dataclass(frozen=True)
class Explanation:
    """The verdict on a frame's blobs: ``people`` and ``phantoms`` (in the order decided), and per
    accepted blob the cameras where it covers foreground of its own."""

    people: list[Blob]
    phantoms: list[Blob]
    own_cameras: dict[int, tuple[str, ...]]


class BlobExplainer:
    """:func:`explain_blobs` for one site's cameras, keeping each camera resized to the masks it gets
    (a resized camera is built once per mask size, not once per frame)."""

    def __init__(self, cameras: Mapping[str, Camera], *, min_cameras: int = 2, min_new: float = MIN_NEW) -> None:
        if not 0.0 < min_new <= 1.0:
            raise ValueError(f"min_new must lie in (0, 1], got {min_new!r}")
        if isinstance(min_cameras, bool) or not isinstance(min_cameras, int) or min_cameras < 1:
            raise ValueError(f"min_cameras must be an int >= 1, got {min_cameras!r}")
        self.cameras = dict(cameras)
        self.min_cameras = min_cameras
        self.min_new = float(min_new)
        self._sized = MaskCameras(self.cameras)

    def explain(self, blobs: Sequence[Blob], masks: Mapping[str, np.ndarray], grid: VoxelGrid) -> "Explanation":
        """Split ``blobs`` into people and phantoms by how they explain ``masks`` (module text)."""
        return _explain(blobs, masks, self._sized.sized(masks), grid, self.min_cameras, self.min_new)


def explain_blobs(
    blobs: Sequence[Blob],
    masks: Mapping[str, np.ndarray],
    cameras: Mapping[str, Camera],
    grid: VoxelGrid,
    *,
    min_cameras: int = 2,
    min_new: float = MIN_NEW,
) -> Explanation:
    """Split ``blobs`` into people and phantoms by how they explain ``masks`` (see the module text).

    masks: camera id -> (H, W) uint8 mask (> 127 foreground). cameras: camera id -> full-resolution
    camera (resized here to each mask). grid: the voxel grid the blobs index. With fewer cameras
    than ``min_cameras`` nothing can be told apart and every blob is kept.
    """
    return BlobExplainer(cameras, min_cameras=min_cameras, min_new=min_new).explain(blobs, masks, grid)


def _explain(blobs, masks, cams: Mapping[str, Camera], grid: VoxelGrid, min_cameras: int, min_new: float):
    used = list(cams)
    if len(blobs) < 2 or len(used) < min_cameras:
        return Explanation(list(blobs), [], {id(b): tuple(used) for b in blobs})
    fg = {c: np.asarray(masks[c]) > 127 for c in used}
    # per blob and camera: the splat's box, its covered-foreground pixels (bool within the box), their
    # count and the body's median depth from that camera
    cores = [_core(b, grid) for b in blobs]
    splats = [{c: _splat(core, cams[c], grid, fg[c]) for c in used} for core in cores]
    hideable = [upright(b) for b in blobs]
    accepted = greedy_cover(splats, {c: fg[c].shape for c in used}, min_cameras=min_cameras, min_new=min_new,
                            hideable=hideable)
    accepted = _without_fragments(accepted, blobs, grid)
    taken = {k for k, _ in accepted}
    return Explanation([blobs[k] for k, _ in accepted], [b for k, b in enumerate(blobs) if k not in taken],
                       {id(blobs[k]): cams for k, cams in accepted})


def greedy_cover(
    splats: Sequence[Mapping[str, tuple | None]],
    shapes: Mapping[str, tuple[int, int]],
    *,
    min_cameras: int,
    min_new: float,
    hideable: Sequence[bool] | None = None,
) -> list[tuple[int, tuple[str, ...]]]:
    """The greedy silhouette cover: which candidates are people, in the order taken.

    splats: per candidate, camera id -> ``((y0, y1, x0, x1), hit, n_hit[, depth])`` (the foreground its
    projection covers: a bool box of the mask and its pixel count; with ``hideable``, also the
    candidate's median depth from that camera) or None. shapes: camera id -> (H, W) of its mask. The
    candidate covering the most foreground not yet covered is taken first, if in at least
    ``min_cameras`` cameras at least ``min_new`` of what it covers is not yet covered; ties go to the
    lower index. Returns ``(candidate index, cameras where it covers its own)`` per person.

    What a candidate covers anew only shrinks as others are taken, so its last count bounds it from
    above (lazy greedy): only the candidate on top of the queue is counted again. Without
    ``hideable``, one that fails the per-camera test can never pass it later: the same choices as
    counting every candidate anew at every step, without the quadratic cost in a crowd.

    hideable: per candidate, whether the depth order speaks for it (:func:`new_cover`): its pixels
    that a body taken before covers from HIDDEN_MARGIN_M or more nearer the camera are hidden, not
    evidence against it. A candidate refused may then pass once the bodies in front of it are taken,
    so the refused are offered again, while a round takes someone, up to MAX_ROUNDS rounds.
    """
    covered = {c: np.zeros(shape, dtype=bool) for c, shape in shapes.items()}
    nearest = None if hideable is None else {c: np.full(shape, np.inf, dtype=np.float32) for c, shape in shapes.items()}
    accepted: list[tuple[int, tuple[str, ...]]] = []
    pending = list(range(len(splats)))
    for _ in range(1 if hideable is None else MAX_ROUNDS):
        heap = [(-sum(s[2] for s in splats[k].values() if s is not None), k) for k in pending]
        heapq.heapify(heap)
        refused, taken_before = [], len(accepted)
        while heap:
            _, k = heapq.heappop(heap)
            depth_order = nearest if hideable is not None and hideable[k] else None
            new_total, cams_ok = new_cover(splats[k], covered, min_new, depth_order)
            if len(cams_ok) < min_cameras:
                refused.append(k)  # a phantom, or a duplicate of someone taken (or hidden, for now)
                continue
            if heap and (-new_total, k) > heap[0]:
                heapq.heappush(heap, (-new_total, k))  # another may now cover more: count it first
                continue
            accepted.append((k, tuple(cams_ok)))
            for c, s in splats[k].items():
                if s is not None:
                    (y0, y1, x0, x1), hit = s[0], s[1]
                    covered[c][y0:y1, x0:x1] |= hit
                    if nearest is not None:
                        box = nearest[c][y0:y1, x0:x1]
                        box[hit] = np.minimum(box[hit], s[3])
        # only a hideable candidate can pass later: for the others what is new only shrinks
        pending = sorted(k for k in refused if hideable is not None and hideable[k])
        if len(accepted) == taken_before or not pending:
            break
    return accepted


def new_cover(splat: Mapping[str, tuple | None], covered: Mapping[str, np.ndarray], min_new: float,
              nearest: Mapping[str, np.ndarray] | None = None) -> tuple[int, list[str]]:
    """What one candidate covers that ``covered`` (camera id -> (H, W) bool) does not: the pixel count
    over all cameras, and the cameras where it is at least ``min_new`` of what the candidate covers.

    nearest: camera id -> (H, W) depth of the nearest body taken at each pixel (inf where none). Then
    the pixels a body at least HIDDEN_MARGIN_M nearer the camera covers are hidden from it: the share
    is of what it covers less what is hidden, and a camera that sees less than MIN_SEEN of what it
    covers cannot speak for it at all. Where a phantom is hidden, a few stray pixels of its own at the
    rim of the body in front would otherwise be share enough."""
    new_total, cams_ok = 0, []
    for c, s in splat.items():
        if s is None:
            continue
        (y0, y1, x0, x1), hit, n_hit = s[0], s[1], s[2]
        new = int(np.count_nonzero(hit & ~covered[c][y0:y1, x0:x1]))
        new_total += new
        seen = n_hit
        if nearest is not None:
            seen -= int(np.count_nonzero(hit & (nearest[c][y0:y1, x0:x1] < s[3] - HIDDEN_MARGIN_M)))
            if seen < MIN_SEEN * n_hit:
                continue  # the camera sees too little of it to speak for it (nor against it)
        if new >= min_new * seen:
            cams_ok.append(c)
    return new_total, cams_ok


# ---------------------------------------------------------------------- helpers


def _without_fragments(accepted: list[tuple[int, tuple[str, ...]]], blobs: Sequence[Blob],
                       grid: VoxelGrid) -> list[tuple[int, tuple[str, ...]]]:
    """``accepted`` less the fragments: low blobs of less than FRAGMENT_MAX_M3 within FRAGMENT_RADIUS_M
    on the floor of an accepted upright blob's top. Where one person's legs or arm are carved apart
    from their body (hidden from some cameras, holes in a mask), the piece covers foreground of its
    own in two cameras like a person would; a person low enough and small enough to be that piece
    (a crouching child) would stand inside the other's body."""
    tops = np.array([_top_xy(blobs[k], grid) for k, _ in accepted if upright(blobs[k])]).reshape(-1, 2)
    if not len(tops):
        return accepted
    keep = []
    for k, cams in accepted:
        b = blobs[k]
        if not upright(b) and b.volume_m3 < FRAGMENT_MAX_M3:
            if np.min(np.hypot(tops[:, 0] - b.x, tops[:, 1] - b.y)) < FRAGMENT_RADIUS_M:
                continue
        keep.append((k, cams))
    return keep


def _top_ij(blob: Blob) -> np.ndarray:
    """(2,) float grid indices (i, j) of the middle of the blob's two highest layers."""
    k = blob.ijk[:, 2]
    return blob.ijk[k >= k.max() - 1, :2].mean(axis=0)


def _top_xy(blob: Blob, grid: VoxelGrid) -> tuple[float, float]:
    """World (x, y) of the middle of the blob's two highest layers."""
    i, j = _top_ij(blob)
    x, y = grid.floor_xy(np.array([[j, i]]))[0]
    return float(x), float(y)


def upright(blob: Blob) -> bool:
    """Whether ``blob`` is an upright body (:data:`CORE_MIN_TOP_M`, :data:`LYING_MAX_TOP_M`)."""
    return blob.z_top_m > CORE_MIN_TOP_M and blob.body_top_m > LYING_MAX_TOP_M


def _core(blob: Blob, grid: VoxelGrid) -> np.ndarray:
    """(N, 3) int voxel indices of the blob's body: for an upright blob (:func:`upright`) the
    voxels within CORE_RADIUS_M on the floor of its highest column, so that hull volume hanging on
    to a person (where cones cross beside them) claims no foreground for them; a low blob whole."""
    ijk = blob.ijk
    if not upright(blob):
        return ijk
    d2 = ((ijk[:, :2] - _top_ij(blob)) ** 2).sum(axis=1)
    return ijk[d2 <= (CORE_RADIUS_M / grid.voxel_m) ** 2]


def _splat(ijk: np.ndarray, cam: Camera, grid: VoxelGrid, fg: np.ndarray):
    """The projection of voxels ``ijk`` (N, 3) into ``cam``: ((y0, y1, x0, x1), covered foreground (bool, box-sized),
    its pixel count, the voxels' median depth from the camera in metres), or None when it covers no foreground
    in the image."""
    keys = _unique_cells(ijk)
    pts = grid.centres(_cells(keys))
    uv, ok = cam.project(pts)
    if not ok.any():
        return None
    uv = uv[ok]
    depth = (pts[ok] @ cam.R.T + cam.t)[:, 2]
    # the splat's radius: half the diagonal of a sampled cell, at the blob's median depth
    spacing = grid.voxel_m * SPLAT_STEP * max(1.0, (len(keys) / MAX_POINTS) ** (1 / 3))
    f = float(cam.K[0, 0])
    median_depth = float(np.median(depth))
    radius = int(np.clip(round(f * spacing * 0.87 / max(median_depth, 0.1)), 1, 40))
    h, w = fg.shape
    px = np.clip(np.round(uv).astype(np.int64), 0, [w - 1, h - 1])
    x0, y0 = max(int(px[:, 0].min()) - radius, 0), max(int(px[:, 1].min()) - radius, 0)
    x1, y1 = min(int(px[:, 0].max()) + radius + 1, w), min(int(px[:, 1].max()) + radius + 1, h)
    img = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    img[px[:, 1] - y0, px[:, 0] - x0] = 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    hit = (cv2.dilate(img, kernel) > 0) & fg[y0:y1, x0:x1]
    n_hit = int(np.count_nonzero(hit))
    return None if n_hit == 0 else ((y0, y1, x0, x1), hit, n_hit, median_depth)


def _unique_cells(ijk: np.ndarray) -> np.ndarray:
    """(M,) int64 keys of the SPLAT_STEP-coarse cells holding the blob's voxels, sorted."""
    c = np.asarray(ijk, dtype=np.int64) // SPLAT_STEP
    return np.unique((c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2])


def _cells(keys: np.ndarray) -> np.ndarray:
    """(M, 3) int64 fine indices of the centres of at most MAX_POINTS of the coarse cells ``keys``
    (every n-th in key order when there are more)."""
    if len(keys) > MAX_POINTS:
        keys = keys[:: int(np.ceil(len(keys) / MAX_POINTS))]
    mask = (1 << 21) - 1
    c = np.stack([keys >> 42, (keys >> 21) & mask, keys & mask], axis=1)
    return c * SPLAT_STEP + SPLAT_STEP // 2
