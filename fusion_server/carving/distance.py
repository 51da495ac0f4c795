"""Distance images of the masks and the per-voxel camera vote.

Section 2.1.3 of the seed paper: instead of counting foreground pixels inside
a voxel's projection, each mask is turned once per frame into a distance
image (every pixel holds its distance to the nearest foreground pixel), so
"is there foreground within the enclosing circle" becomes one lookup at the
projected centre compared with the circle's radius. OpenCV's
``distanceTransform(DIST_L2, 3)`` is the 3x3 chamfer with the paper's
0.955 / 1.3693 weights.

The vote combines the cameras with the visibility ratio h(v) of the
heterogeneous-fusion seed (002): among the cameras present in the frame set
that see the voxel (centre visible, and not only through furniture the site
describes: :mod:`fusion_server.carving.occlusion`), ``found`` of them have
foreground within its circle; the voxel passes when ``found >= min_cameras``
and ``found / seeing >= min_ratio``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from fusion_server.carving.lut import HIDDEN, RADIUS_UNITS_PER_PX

__all__ = [
    "DistanceImages", "distance_images", "vote", "observations", "tally", "needed_votes", "mask_pixels",
    "FOREGROUND_THRESHOLD",
]

FOREGROUND_THRESHOLD = 127  # mask values above this are foreground (MOG2 marks shadows 127)
_RATIO_EPS = 1e-9
_FAR = np.float32(1e30)  # distance in an image without foreground: finite, so scaling it cannot overflow


@dataclass(frozen=True, eq=False)
class DistanceImages:
    """The distance images of the cameras present in one frame set, packed in one buffer.

    values: (L,) float32; camera ``p``'s image of ``sizes[p]`` (width, height) occupies
        ``values[offsets[p] : offsets[p] + w * h]`` row-major, and ``values[offsets[p] - 1]``
        is NaN, so that a LUT pixel of -1 (not visible) reads NaN and never passes.
    camera_ids: ids of the present cameras, in LUT column order.
    columns: (P,) int64 LUT columns of those cameras.
    offsets: (P,) int32 (int64 for huge buffers) start of each camera's image in ``values``.
    sizes: per present camera, the mask size (width, height).
    lut_sizes: per present camera, the size the LUT pixels refer to (width, height).
    """

    values: np.ndarray
    camera_ids: tuple[str, ...]
    columns: np.ndarray
    offsets: np.ndarray
    sizes: tuple[tuple[int, int], ...]
    lut_sizes: tuple[tuple[int, int], ...]

    def image(self, p: int) -> np.ndarray:
        """(H, W) float32 view of the ``p``-th present camera's distance image."""
        w, h = self.sizes[p]
        o = int(self.offsets[p])
        return self.values[o : o + w * h].reshape(h, w)


def distance_images(masks: Mapping[str, np.ndarray], camera_ids: Sequence[str],
                    lut_sizes: Mapping[str, tuple[int, int]], out: np.ndarray | None = None) -> DistanceImages:
    """Distance transforms of the inverted masks of the cameras present in ``masks``.

    masks: camera id -> (H, W) uint8 (foreground > 127) or bool mask, any size.
    camera_ids: all known cameras in LUT column order; unknown ids in ``masks`` raise ValueError.
    lut_sizes: camera id -> (width, height) of its LUT pixels.
    out: an optional float32 buffer reused when large enough (the result then views it).
    """
    known = {cid: col for col, cid in enumerate(camera_ids)}
    for cid in masks:
        if cid not in known:
            raise ValueError(f"masks[{cid!r}]: unknown camera (known: {sorted(known)})")
    present = [cid for cid in camera_ids if cid in masks]
    checked = [_as_mask(cid, masks[cid]) for cid in present]
    sizes = tuple((m.shape[1], m.shape[0]) for m in checked)
    offsets = np.zeros(len(present), dtype=np.int64)
    total = 0
    for p, (w, h) in enumerate(sizes):
        total += 1
        offsets[p] = total
        total += w * h
    total += 1
    if total < 2**31:
        offsets = offsets.astype(np.int32)  # int32 LUT pixels + int32 offsets stay int32
    values = out[:total] if out is not None and out.dtype == np.float32 and out.ndim == 1 and out.size >= total \
        else np.empty(total, dtype=np.float32)
    inverted = None
    for p, mask in enumerate(checked):
        w, h = sizes[p]
        o = int(offsets[p])
        values[o - 1] = np.nan
        if inverted is None or inverted.shape != mask.shape:
            inverted = np.empty_like(mask)
        # distanceTransform measures the distance to the nearest zero pixel: zero the foreground.
        cv2.threshold(mask, FOREGROUND_THRESHOLD, 255, cv2.THRESH_BINARY_INV, dst=inverted)
        view = values[o : o + w * h].reshape(h, w)
        if cv2.countNonZero(inverted) == w * h:
            view.fill(_FAR)  # no foreground at all (OpenCV would write FLT_MAX)
        else:
            cv2.distanceTransform(inverted, cv2.DIST_L2, 3, dst=view)
    values[total - 1] = np.nan
    return DistanceImages(
        values=values,
        camera_ids=tuple(present),
        columns=np.array([known[c] for c in present], dtype=np.int64),
        offsets=offsets,
        sizes=sizes,
        lut_sizes=tuple(tuple(int(x) for x in lut_sizes[c]) for c in present),
    )


def vote(pixel: np.ndarray, radius_q: np.ndarray, dists: DistanceImages, min_cameras: int,
         min_ratio: float, *, hidden: bool = False) -> np.ndarray:
    """Which voxels hold foreground by the multi-camera vote.

    pixel: (M, C) int32 LUT rows of the voxels for all C known cameras (-1: not visible;
        with ``hidden``, ``HIDDEN``: partly hidden by furniture, counts as seeing and finding).
    radius_q: (M, C) uint16 (or float32) enclosing radii in 1/32 pixel, same layout.
    Returns (M,) bool.
    """
    if dists.columns.size == 0:
        return np.zeros(pixel.shape[0], dtype=bool)
    found, seeing = tally(*observations(pixel, radius_q, dists, hidden=hidden))
    return found >= needed_votes(len(dists.columns), min_cameras, min_ratio)[seeing]


def observations(pixel: np.ndarray, radius_q: np.ndarray, dists: DistanceImages, *,
                 hidden: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel and present camera, whether the camera finds foreground and whether it sees it.

    pixel, radius_q: as for :func:`vote`, (M, C) over all known cameras.
    Returns ``(hit, seen)``, each (M, P) bool over the P present cameras in ``dists`` order
    (``hit`` implies ``seen``).
    """
    cols = dists.columns
    if cols.size != pixel.shape[1] or np.any(cols != np.arange(pixel.shape[1])):
        pixel = pixel[:, cols]
        radius_q = radius_q[:, cols]
    pixel, radius_q = _rescale(pixel, radius_q, dists)
    # A pixel of -1 reads the NaN before the camera's image: never a hit.
    hit = np.take(dists.values, pixel + dists.offsets) * RADIUS_UNITS_PER_PX <= radius_q
    seen = pixel >= 0
    if hidden:
        behind = pixel == HIDDEN
        hit |= behind
        seen |= behind
    return hit, seen


def tally(hit: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, P) bool hits and sightings -> ``(found, seeing)``, (M,) uint8 camera counts: the
    numerator and denominator of the visibility ratio h(v)."""
    if hit.shape[1] == 0:
        zeros = np.zeros(hit.shape[0], dtype=np.uint8)
        return zeros, zeros.copy()
    # Column sums: much faster than a reduction along a short inner axis.
    found = hit[:, 0].astype(np.uint8)
    seeing = seen[:, 0].astype(np.uint8)
    for p in range(1, hit.shape[1]):
        found += hit[:, p]
        seeing += seen[:, p]
    return found, seeing


def mask_pixels(pixel: np.ndarray, lut_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """(M,) int LUT pixels of one camera (``lut_size`` (width, height)) -> flat pixels of an
    image of ``size`` (width, height): the pixel holding the scaled centre; negatives kept."""
    if tuple(size) == tuple(lut_size):
        return pixel
    (w, h), (lw, lh) = size, lut_size
    seen = pixel >= 0
    v, u = np.divmod(pixel, lw)
    us = np.minimum(((u + 0.5) * (w / lw)).astype(np.int64), w - 1)
    vs = np.minimum(((v + 0.5) * (h / lh)).astype(np.int64), h - 1)
    return np.where(seen, vs * w + us, pixel)


def needed_votes(n_cameras: int, min_cameras: int, min_ratio: float) -> np.ndarray:
    """(n_cameras + 1,) uint8: votes needed by a voxel that ``s`` cameras see, indexed by ``s``:
    ``max(min_cameras, ceil(min_ratio * s))``; never reachable when ``s < min_cameras``."""
    s = np.arange(n_cameras + 1)
    need = np.maximum(min_cameras, np.ceil(min_ratio * s - _RATIO_EPS)).astype(np.int64)
    return np.minimum(need, 255).astype(np.uint8)


# ---------------------------------------------------------------------- helpers


def _as_mask(cid: str, mask) -> np.ndarray:
    arr = np.asarray(mask)
    if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"masks[{cid!r}]: expected a non-empty (H, W) array, got shape {arr.shape}")
    if arr.dtype == np.bool_:
        arr = arr.view(np.uint8) * np.uint8(255)
    elif arr.dtype != np.uint8:
        raise ValueError(f"masks[{cid!r}]: expected uint8 or bool, got {arr.dtype}")
    return np.ascontiguousarray(arr)


def _rescale(pixel: np.ndarray, radius_q: np.ndarray, dists: DistanceImages):
    """Map LUT pixels/radii to masks of another size (nearest pixel of the scaled centre;
    radius times the larger scale factor). Exact up to half a LUT pixel."""
    scaled = [p for p, (size, lut) in enumerate(zip(dists.sizes, dists.lut_sizes)) if size != lut]
    if not scaled:
        return pixel, radius_q
    pixel = pixel.copy()
    radius_q = radius_q.astype(np.float32)
    for p in scaled:
        (w, h), (lw, lh) = dists.sizes[p], dists.lut_sizes[p]
        pixel[:, p] = mask_pixels(pixel[:, p], (lw, lh), (w, h))
        radius_q[:, p] *= max(w / lw, h / lh)
    return pixel, radius_q
