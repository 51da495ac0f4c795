"""Free space from depth cameras: range images vote on the voxels in front of a surface.

Seed paper 002, eq. 2: a range camera measures, along each pixel's ray, the
distance ``D`` to the first surface, so a voxel whose centre lies nearer than
``D`` on that ray is empty. Silhouettes alone cannot tell this: the rays of
two people seen by two cameras cross in *phantoms*, voxels every silhouette
explains. One depth camera looking at the crossing sees the real person
behind it and carves the phantom away.

Made robust for a real time-of-flight sensor:

* ``D`` is the *nearest* measurement in the voxel's footprint: the smallest
  square of ``FOOTPRINT_HALF_WIDTHS_PX`` about its projected centre that holds
  its enclosing circle. Pixels on a silhouette's edge mix the person with the
  wall behind and read too far, and a voxel at the edge of a person's
  silhouette may project its centre just beside it; the minimum over the
  footprint can only move ``D`` nearer, which makes free space rarer, never a
  real voxel free.
* The tolerance grows with the voxel (its centre lies up to half a diagonal
  from the surface it holds) and with range (ToF noise grows with distance):
  ``tol = sqrt(3)/2 voxel + NOISE_SIGMAS (DEPTH_NOISE_M + DEPTH_NOISE_PER_M D)``.
* A range ``d`` of the voxel centre (Euclidean, from the camera centre):
  ``d < D - tol``: free space, the camera votes background;
  ``D - tol <= d <= D + BODY_DEPTH_M + tol``: the surface, the camera finds the voxel;
  beyond: hidden behind the surface, the camera does not vote.
* ``D = 0`` (no measurement, or background) leaves the silhouette's vote.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = [
    "BEHIND", "BODY_DEPTH_M", "DEPTH_NOISE_M", "DEPTH_NOISE_PER_M", "FREE", "NOISE_SIGMAS", "NO_MEASUREMENT",
    "FOOTPRINT_HALF_WIDTHS_PX", "SURFACE", "apply_verdicts", "footprint_level", "check_depth", "depth_tolerance_m",
    "depth_verdicts", "footprint_depth",
]

DEPTH_NOISE_M = 0.01
"""Range noise at zero range, one sigma, metres."""
DEPTH_NOISE_PER_M = 0.01
"""Growth of the range noise per metre of range (1 % of range, one sigma)."""
NOISE_SIGMAS = 3.0
BODY_DEPTH_M = 0.6
"""How far behind its measured front a body can still hold voxels (a person's depth along a ray)."""

FOOTPRINT_HALF_WIDTHS_PX = (1, 2, 4, 8, 16, 32)
"""Half-widths of the square footprints, pixels; a voxel uses the smallest holding its
enclosing circle (the largest when none does)."""

NO_MEASUREMENT, FREE, SURFACE, BEHIND = 0, 1, 2, 3
_NONE = np.uint16(65535)


def check_depth(cid: str, depth_mm, mask_shape: tuple[int, int]) -> np.ndarray:
    """Validate one depth image: (H, W) uint16 at the mask's shape; ValueError naming the camera."""
    arr = np.asarray(depth_mm)
    if arr.dtype != np.uint16:
        raise ValueError(f"depths[{cid!r}]: expected uint16 millimetres, got {arr.dtype}")
    if arr.shape != tuple(mask_shape):
        raise ValueError(f"depths[{cid!r}]: shape {arr.shape} differs from its mask's {tuple(mask_shape)}")
    return np.ascontiguousarray(arr)


def footprint_depth(depth_mm: np.ndarray) -> np.ndarray:
    """(H, W) uint16 range, millimetres, 0 = no measurement -> (K, H, W) uint16: for each
    half-width ``FOOTPRINT_HALF_WIDTHS_PX[k]``, the nearest measurement in the square of that
    half-width about each pixel, 0 where it holds none."""
    d = np.where(depth_mm == 0, _NONE, depth_mm).astype(np.uint16)
    out = np.empty((len(FOOTPRINT_HALF_WIDTHS_PX),) + d.shape, dtype=np.uint16)
    done = 0
    for k, half in enumerate(FOOTPRINT_HALF_WIDTHS_PX):
        # Grow the previous level's minimum: min over a (2a+1) square then a (2b+1) one is
        # the min over a (2(a+b)+1) square.
        grow = half - done
        kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)
        d = cv2.erode(d, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=int(_NONE))
        done = half
        out[k] = d
    out[out == _NONE] = 0
    return out


def footprint_level(radius_px: np.ndarray) -> np.ndarray:
    """(M,) float enclosing radii, pixels -> (M,) int index into ``FOOTPRINT_HALF_WIDTHS_PX``
    of the smallest square holding each circle (the last when none does)."""
    k = np.searchsorted(np.asarray(FOOTPRINT_HALF_WIDTHS_PX, dtype=np.float64), np.ceil(radius_px))
    return np.minimum(k, len(FOOTPRINT_HALF_WIDTHS_PX) - 1)


def depth_tolerance_m(measured_m: np.ndarray, voxel_m: float) -> np.ndarray:
    """(M,) float: how far in front of a measured range ``measured_m`` a voxel centre can lie
    and still hold the measured surface."""
    return (math.sqrt(3) / 2) * voxel_m + NOISE_SIGMAS * (DEPTH_NOISE_M + DEPTH_NOISE_PER_M * measured_m)


def depth_verdicts(range_m: np.ndarray, measured_m: np.ndarray, voxel_m: float) -> np.ndarray:
    """(M,) int8 verdicts of one depth camera on M voxels.

    range_m: (M,) float, distance from the camera centre to each voxel centre, metres.
    measured_m: (M,) float, the footprint range at each voxel's pixel, 0 for none.
    Returns ``NO_MEASUREMENT``, ``FREE``, ``SURFACE`` or ``BEHIND`` per voxel.
    """
    range_m = np.asarray(range_m, dtype=np.float64)
    measured_m = np.asarray(measured_m, dtype=np.float64)
    tol = depth_tolerance_m(measured_m, voxel_m)
    out = np.full(range_m.shape, SURFACE, dtype=np.int8)
    out[range_m < measured_m - tol] = FREE
    out[range_m > measured_m + BODY_DEPTH_M + tol] = BEHIND
    out[measured_m <= 0] = NO_MEASUREMENT
    return out


def apply_verdicts(hit: np.ndarray, seen: np.ndarray, verdicts: np.ndarray) -> None:
    """Overrule one camera's silhouette observations in place: (M,) bool ``hit`` and ``seen``
    (only where it sees the voxel) by (M,) ``verdicts``."""
    use = seen & (verdicts != NO_MEASUREMENT)
    hit[use & (verdicts == FREE)] = False
    hit[use & (verdicts == SURFACE)] = True
    behind = use & (verdicts == BEHIND)
    hit[behind] = False
    seen[behind] = False
