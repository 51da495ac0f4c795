"""Furniture and walls that hide people: which cameras cannot see a voxel.

A camera votes on a voxel when its centre projects into the image. But a
person crouching behind a sofa, sitting at a table or walking past a kitchen
counter is hidden from some of the cameras that see that place on the floor,
and those cameras show background there. In the vote (``found / seeing >=
min_ratio``) they count against the person, and a person hidden from two of
five cameras is carved away. The site file describes the furniture and
walls that hide people (``[[occluders]]``: a convex floor polygon between two
heights); a camera whose line of sight to a voxel's centre passes through one
of them does not see that voxel, so it neither votes for it nor against it.

Each occluder's floor polygon is shrunk by ``margin_m`` before the test, so
that a line of sight grazing its side is still seen (its heights are kept:
a table top is a few centimetres thick). A voxel inside an occluder is seen
by no camera and is never carved; one whose centre lies above its top (a
person sitting on the sofa's seat) is not inside.

Pure: no clock, no I/O.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from common.site import is_convex

__all__ = ["Occluder", "blocked", "occluders_digest", "MARGIN_M"]

MARGIN_M = 0.05
"""Occluders' floor polygons are shrunk by this much (one finest voxel): only a clear line of sight through them counts."""


@dataclass(frozen=True)
class Occluder:
    """A solid that hides what is behind it: a convex floor polygon (world metres, any winding)
    extruded from ``z_min_m`` to ``z_max_m``."""

    name: str
    polygon_m: tuple[tuple[float, float], ...]
    z_min_m: float
    z_max_m: float

    def __post_init__(self) -> None:
        poly = np.asarray(self.polygon_m, dtype=np.float64)
        if poly.ndim != 2 or poly.shape[0] < 3 or poly.shape[1] != 2 or not np.all(np.isfinite(poly)):
            raise ValueError(f"occluder {self.name!r}: polygon_m must be 3 or more finite (x, y) points")
        if not (np.isfinite(self.z_min_m) and np.isfinite(self.z_max_m) and self.z_min_m < self.z_max_m):
            raise ValueError(f"occluder {self.name!r}: needs z_min_m < z_max_m, got {self.z_min_m}, {self.z_max_m}")
        if not is_convex(self.polygon_m):
            raise ValueError(f"occluder {self.name!r}: polygon_m must be convex (split other shapes into convex parts)")


def blocked(center_m: np.ndarray, points_m: np.ndarray, occluders: Sequence[Occluder],
            margin_m: float = MARGIN_M) -> np.ndarray:
    """(N,) bool: whether the segment from ``center_m`` (3,) (a camera's centre) to each of
    ``points_m`` (N, 3) passes through one of ``occluders`` (their floor polygons shrunk by
    ``margin_m``), or ends inside one."""
    c = np.asarray(center_m, dtype=np.float64).reshape(3)
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(p), dtype=bool)
    if not len(p):
        return out
    d = p - c
    # each segment's bounding box, one contiguous row per axis; an occluder's candidates are narrowed
    # axis by axis, most of them gone after the first
    box_lo, box_hi = np.minimum(p, c).T.copy(), np.maximum(p, c).T.copy()
    for occ in occluders:
        poly = np.asarray(occ.polygon_m, dtype=np.float64)
        lo, hi = [*poly.min(axis=0), occ.z_min_m], [*poly.max(axis=0), occ.z_max_m]
        idx = np.flatnonzero((box_hi[0] >= lo[0]) & (box_lo[0] <= hi[0]) & ~out)
        for axis in (1, 2):
            idx = idx[(box_hi[axis, idx] >= lo[axis]) & (box_lo[axis, idx] <= hi[axis])]
        if len(idx):
            out[idx] = _through(c, d[idx], occ, margin_m)
    return out


def occluders_digest(occluders: Sequence[Occluder], margin_m: float = MARGIN_M) -> str:
    """A short hash of the occluders' geometry (empty string when there are none): what tables
    computed with them depend on."""
    if not occluders:
        return ""
    h = hashlib.sha256(f"occlusion-v1 margin {margin_m!r}".encode())
    for occ in occluders:
        h.update(np.asarray(occ.polygon_m, dtype="<f8").tobytes())
        h.update(np.array([occ.z_min_m, occ.z_max_m], dtype="<f8").tobytes())
    return h.hexdigest()[:16]


# ---------------------------------------------------------------------- helpers


def _through(c: np.ndarray, d: np.ndarray, occ: Occluder, margin: float) -> np.ndarray:
    """Segments ``c + t d``, t in [0, 1], that meet the prism over the shrunk polygon: the interval
    of t inside every half-space (the slab in Z and one per polygon edge) is not empty."""
    lo = np.zeros(len(d))
    hi = np.ones(len(d))
    _clip(lo, hi, c[2] - occ.z_min_m, d[:, 2])  # z - z_min >= 0
    _clip(lo, hi, occ.z_max_m - c[2], -d[:, 2])  # z_max - z >= 0
    poly = np.asarray(occ.polygon_m, dtype=np.float64)
    area2 = np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    if area2 < 0:
        poly = poly[::-1]
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        e = b - a
        length = float(np.hypot(*e))
        if length == 0.0:
            continue
        n = np.array([-e[1], e[0]]) / length  # inward normal of a counter-clockwise polygon
        # n . (c + t d - a) - m >= 0
        _clip(lo, hi, float(n @ (c[:2] - a)) - margin, d[:, :2] @ n)
    return lo < hi


def _clip(lo: np.ndarray, hi: np.ndarray, g0: float, g1: np.ndarray) -> None:
    """Narrow [lo, hi] to the t where ``g0 + t * g1 >= 0`` (in place)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -g0 / g1
    rising = g1 > 0
    falling = g1 < 0
    np.maximum(lo, np.where(rising, t, -np.inf), out=lo)
    np.minimum(hi, np.where(falling, t, np.inf), out=hi)
    if g0 < 0:  # where g1 == 0 the constraint does not depend on t: never met
        hi[g1 == 0] = -np.inf
