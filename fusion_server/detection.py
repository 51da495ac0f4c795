"""Top-down 3D blob detection of people in the foreground voxels.

The seed paper's detector (section 2.2.1, Figure 2): the horizontal layers
of the voxel grid are labelled one at a time from the top down, so every
blob is born at its highest voxel and grows downward. When a connected
region of a layer touches two or more blobs from the layer above, the blobs
have met at that layer's height, and two rules decide whether they become
one:

* below ``tau1_m`` they stay apart. People standing close together touch
  at hand, hip or leg height (and through shadows near the floor) while
  their heads and shoulders stay apart;
* above ``tau1_m`` they merge unless they are heads: people standing
  shoulder to shoulder, or two people whose hull fills the space between
  them up to the neck, still carve two tops that each rise ``head_m`` over
  the meeting, ``head_sep_m`` apart on the floor;
* a blob whose top is less than ``tau2_m`` above the meeting point is always
  joined to a neighbour. That is what keeps one seated or lying person whole:
  the knees of a seated person, or the head, hip and feet of a person lying
  on the floor, are born as separate blobs in the top layers and meet low,
  but they rise only a little above the place where they meet. It is also
  what folds a low object that a person touches (a table, a chair that was
  moved) into that person instead of making it a target of its own.

When blobs meet and stay apart, the cells of the meeting region go to the
blob whose cells in the layer above are nearest. A layer's cells look up
across a carving gap of at most ``gap_m`` (holes in the masks at one height
cut a body in two). Blobs under
``min_volume_m3`` are noise and are dropped at the end.

Heights are world Z in metres, floor at Z = 0 (DESIGN.md conventions).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from fusion_server.grid import CarveResult

__all__ = ["BODY_WIDTH_FRAC", "Blob", "body_top_layers", "detect_blobs"]

BODY_WIDTH_FRAC = 0.25
"""A body's top is the top of its highest layer at least this share as wide as its widest (layer
areas as 3-layer running means). The cameras' cones over a body lying on the floor cross above it
and leave a thin tent of hull that rises past a metre over a body 0.3 m high: its layers are a
twentieth as wide as the body, which is not there. A standing person's body top is their chin or
crown (0.80-0.99 of their height, 5th to 95th percentile, on twelve tuning worlds), a lying person's
at most 0.55 of their height in 99 frames in 100 (the hull's top in 86)."""


def body_top_layers(height_profile: np.ndarray, width_frac: float = BODY_WIDTH_FRAC) -> int:
    """Layers from the bottom of the profile up to the top of the body (see :data:`BODY_WIDTH_FRAC`):
    0 for an empty profile. ``height_profile``: (nz,) voxel counts per layer."""
    counts = np.asarray(height_profile, dtype=np.float64)
    if counts.ndim != 1:
        raise ValueError(f"height_profile must be 1-D (nz,), got shape {counts.shape}")
    if not (counts > 0).any():
        return 0
    area = np.convolve(counts, np.ones(3) / 3.0, mode="same") if len(counts) >= 3 else counts
    wide = np.flatnonzero(area >= width_frac * area.max())
    occupied = np.flatnonzero(counts > 0)
    return int(min(wide[-1], occupied[-1])) + 1


@dataclass(frozen=True, eq=False)
class Blob:
    """One detected 3D blob: a person candidate.

    x, y: world metres, centroid of the blob's floor projection weighted by
        the number of voxels in each column (plan-view centre of mass).
    z_top_m: height of the top face of the blob's highest voxel, metres.
    volume_voxels: number of finest-level voxels in the blob.
    ijk: (N, 3) int32 finest-level voxel indices of the blob.
    footprint: (M, 2) int32 floor cells ``(j, i)`` under the blob, unique,
        indexing ``FloorMaps`` arrays.
    height_profile: (nz,) int32, number of the blob's voxels in each height
        layer ``k`` of the grid (layer ``k`` spans
        ``origin_z + [k, k + 1) * voxel_m``).
    bbox_m: (2, 3) float64 world metres, rows are the minimum and maximum
        corners of the blob's voxels' outer faces.
    voxel_m: edge of a voxel, metres.
    """

    x: float
    y: float
    z_top_m: float
    volume_voxels: int
    ijk: np.ndarray
    footprint: np.ndarray
    height_profile: np.ndarray
    bbox_m: np.ndarray
    voxel_m: float

    @property
    def volume_m3(self) -> float:
        return self.volume_voxels * self.voxel_m**3

    @property
    def body_top_m(self) -> float:
        """Height of the top of the blob's body (:data:`BODY_WIDTH_FRAC`): its top less any thin hull over it."""
        highest = int(np.flatnonzero(self.height_profile)[-1]) + 1
        return self.z_top_m - (highest - body_top_layers(self.height_profile)) * self.voxel_m

    @property
    def footprint_area_m2(self) -> float:
        return len(self.footprint) * self.voxel_m**2


def detect_blobs(
    result: CarveResult,
    *,
    tau1_m: float = 1.0,
    tau2_m: float = 0.3,
    min_volume_m3: float = 0.02,
    head_m: float = 0.1,
    head_sep_m: float = 0.3,
    gap_m: float = 0.1,
) -> list[Blob]:
    """Top-down blob analysis of one frame set's foreground voxels.

    tau1_m: blobs meeting at a height above this merge; meeting at or below it
        they stay apart. 1.0 m sits above the hands, hips and forearms of
        adults standing side by side (0.7-1.0 m) and below the shoulders and
        neck (1.3-1.5 m) where one person's head and raised arm join the body.
    tau2_m: a blob whose top is less than this above the meeting height always
        joins a neighbour. 0.3 m covers the knees of a seated person over the
        seat (~0.1-0.15 m), the parts of a lying body (~0.1-0.3 m thick) and
        low furniture touching a person, while two people's heads rise
        0.5 m or more above any contact below ``tau1_m``.
    min_volume_m3: blobs with less volume are noise. 0.02 m^3 (160 voxels at
        5 cm) is a fifth of a carved adult lying down and still above a
        speckle of shadow or a pet.
    head_m, head_sep_m: above ``tau1_m`` blobs meet at the shoulders of
        people standing close together, so there a blob stays apart only
        as a head: its top rises at least ``head_m`` over the meeting and
        lies at least ``head_sep_m`` on the floor from the top of any higher
        blob in the meeting. 0.1 m is two voxels, under the head and neck
        over the shoulders of a child (0.2-0.3 m) and over the hull that
        fills the gap between two heads; 0.3 m keeps a hand raised beside
        the head, or a bump of the hull on it, with its person.
    gap_m: a blob's cells reach down across empty layers of at most this
        height. Holes in the masks at one height cut a carved body
        horizontally (legs below, torso above); 0.1 m joins the parts,
        while a person's head never floats that close over someone else.

    Returns the blobs sorted by decreasing volume.
    """
    for name, value in (("tau1_m", tau1_m), ("tau2_m", tau2_m), ("min_volume_m3", min_volume_m3), ("head_m", head_m),
                        ("head_sep_m", head_sep_m), ("gap_m", gap_m)):
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{name} must be a finite non-negative number, got {value}")
    ijk = np.asarray(result.ijk)
    grid = result.grid
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise ValueError(f"CarveResult.ijk must have shape (N, 3), got {ijk.shape}")
    if len(ijk) == 0:
        return []
    voxel_m = grid.voxel_m
    min_voxels = min_volume_m3 / voxel_m**3 - 1e-9
    ijk, packed = _pack_columns(ijk, min_voxels)
    if len(ijk) == 0:
        return []
    k0 = int(ijk[:, 2].min())
    k1 = int(ijk[:, 2].max())
    occ = np.zeros((k1 - k0 + 1, packed[:, 1].max() + 1, packed[:, 0].max() + 1), dtype=np.uint8)
    occ[ijk[:, 2] - k0, packed[:, 1], packed[:, 0]] = 1
    z_top_of_layer = grid.origin_m[2] + (np.arange(k0, k1 + 1) + 1) * voxel_m

    labels, roots = _TopDown(occ, z_top_of_layer, tau1_m, tau2_m, head_m, head_sep_m, gap_m, voxel_m).run()
    blob_id = roots[labels[ijk[:, 2] - k0, packed[:, 1], packed[:, 0]]]

    order = np.argsort(blob_id, kind="stable")
    _, starts, counts = np.unique(blob_id[order], return_index=True, return_counts=True)
    blobs = []
    for start, count in zip(starts, counts):
        if count < min_voxels:
            continue
        blobs.append(_make_blob(ijk[order[start : start + count]], grid))
    blobs.sort(key=lambda b: (-b.volume_voxels, b.x, b.y))
    return blobs


def _pack_columns(ijk: np.ndarray, min_voxels: float) -> tuple[np.ndarray, np.ndarray]:
    """Drop small column groups and pack the rest side by side.

    A connected set of voxels projects onto a connected set of floor cells,
    so each 8-connected group of occupied floor cells can be analysed on its
    own: groups with fewer than ``min_voxels`` voxels can only hold noise,
    and the others are copied into one small canvas, one cell apart, so the
    layer loop works on the occupied area instead of the whole room.

    Returns (kept ijk (M, 3), packed (M, 2) int ``(column, row)`` in the canvas).
    """
    lo = ijk[:, :2].min(axis=0)
    ij = (ijk[:, :2] - lo).astype(np.intp)
    plan = np.zeros((ij[:, 1].max() + 1, ij[:, 0].max() + 1), dtype=np.uint8)
    plan[ij[:, 1], ij[:, 0]] = 1
    n, lab, stats, _ = cv2.connectedComponentsWithStats(plan, connectivity=8, ltype=cv2.CV_32S)
    group = lab[ij[:, 1], ij[:, 0]]
    keep_group = np.bincount(group, minlength=n) >= min_voxels
    keep_group[0] = False
    keep = keep_group[group]
    ijk, ij, group = ijk[keep], ij[keep], group[keep]
    ids = np.flatnonzero(keep_group)
    if len(ids) == 0:
        return ijk, np.zeros((0, 2), dtype=np.intp)
    x0, y0, w, h = (stats[ids, c] for c in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
    width = max(int(w.max()), int(np.ceil(np.sqrt(((w + 1) * (h + 1)).sum()))))
    ox = np.zeros(n, dtype=np.intp)
    oy = np.zeros(n, dtype=np.intp)
    cx = cy = shelf = 0
    for g, gw, gh in sorted(zip(ids, w, h), key=lambda t: -t[2]):
        if cx + gw > width:
            cx, cy, shelf = 0, cy + shelf + 1, 0
        ox[g], oy[g] = cx - stats[g, cv2.CC_STAT_LEFT], cy - stats[g, cv2.CC_STAT_TOP]
        cx += gw + 1
        shelf = max(shelf, gh)
    packed = np.stack([ij[:, 0] + ox[group], ij[:, 1] + oy[group]], axis=1)
    return ijk, packed


class _TopDown:
    """Layer-by-layer labelling state; one use per frame."""

    def __init__(
        self, occ: np.ndarray, z_top_of_layer: np.ndarray, tau1_m: float, tau2_m: float, head_m: float, head_sep_m: float,
        gap_m: float, voxel_m: float,
    ):
        self.occ = occ
        self.z_top = z_top_of_layer
        self.tau1 = tau1_m
        self.tau2 = tau2_m
        self.head_m = head_m
        self.gap_layers = int(round(gap_m / voxel_m))
        self.head_sep2 = (head_sep_m / voxel_m) ** 2
        self.parent: list[int] = [0]
        self.top_m: list[float] = [0.0]
        self.peak: list[tuple[float, float]] = [(0.0, 0.0)]

    def run(self) -> tuple[np.ndarray, np.ndarray]:
        """Returns (labels (nk, nj, ni) int32, roots (n_ids,) int64 id -> final id)."""
        occ = self.occ
        labels = np.zeros(occ.shape, dtype=np.int32)
        rootmap = np.zeros(1, dtype=np.int32)
        dirty = False
        for k in range(occ.shape[0] - 1, -1, -1):
            layer = occ[k]
            if not layer.any():
                continue
            # a layer with a carving gap under a body (holes in the masks at one height) still
            # touches the body: cells empty in the layer just above look further up, gap_layers at most
            prev = labels[k + 1] if k + 1 < occ.shape[0] else labels[k]
            for g in range(2, self.gap_layers + 2):
                if k + g >= occ.shape[0]:
                    break
                prev = np.where(prev > 0, prev, labels[k + g])
            n, cc, stats, centroids = cv2.connectedComponentsWithStats(layer, connectivity=8, ltype=cv2.CV_32S)
            if dirty:
                rootmap = self._roots().astype(np.int32)
                dirty = False
            elif len(rootmap) < len(self.parent):  # blobs born since are their own roots
                rootmap = np.concatenate([rootmap, np.arange(len(rootmap), len(self.parent), dtype=np.int32)])
            above = rootmap[prev]
            touch = (cc > 0) & (above > 0)
            meets = np.zeros((n, len(self.parent)), dtype=bool)
            meets[cc[touch], above[touch]] = True
            n_above = meets.sum(axis=1)
            assign = np.where(n_above == 1, meets.argmax(axis=1), 0).astype(np.int32)
            for c in np.flatnonzero(n_above[1:] == 0) + 1:
                col, row = centroids[c]
                assign[c] = self._new(float(self.z_top[k]), (float(row), float(col)))
            conflicts = [(c, np.flatnonzero(meets[c])) for c in np.flatnonzero(n_above > 1)]
            cur = assign[cc]
            for c, rs in conflicts:
                dirty |= self._resolve(c, [int(r) for r in rs], cc, stats[c], above, cur, float(self.z_top[k]))
            labels[k] = cur
        return labels, self._roots()

    def _new(self, top_m: float, peak: tuple[float, float]) -> int:
        self.parent.append(len(self.parent))
        self.top_m.append(top_m)
        self.peak.append(peak)
        return len(self.parent) - 1

    def _roots(self) -> np.ndarray:
        """(n_ids,) int64: every id's root, by pointer jumping over the whole parent list at once
        (written back: the same roots, shorter paths)."""
        p = np.asarray(self.parent, dtype=np.int64)
        while True:
            q = p[p]
            if np.array_equal(q, p):
                break
            p = q
        self.parent = p.tolist()
        return p

    def _find(self, i: int) -> int:
        parent = self.parent
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return root

    def _union(self, keep: int, other: int) -> None:
        keep, other = self._find(keep), self._find(other)
        if keep != other:
            self.parent[other] = keep
            if self.top_m[other] > self.top_m[keep]:
                self.top_m[keep], self.peak[keep] = self.top_m[other], self.peak[other]

    def _peak_d2(self, a: int, b: int) -> float:
        (ra, ca), (rb, cb) = self.peak[a], self.peak[b]
        return (ra - rb) ** 2 + (ca - cb) ** 2

    def _reroot(self, ids: np.ndarray) -> np.ndarray:
        values, inverse = np.unique(ids, return_inverse=True)
        roots = np.array([self._find(int(v)) if v else 0 for v in values], dtype=np.int32)
        return roots[inverse].reshape(ids.shape)

    def _resolve(
        self, c: int, roots: list[int], cc: np.ndarray, stat: np.ndarray, above: np.ndarray, cur: np.ndarray,
        z_conn: float,
    ) -> bool:
        """Decide which blobs meeting in component ``c`` (``stat``: its row of OpenCV's component
        stats) merge; label its cells in ``cur``.

        Returns whether any union happened.
        """
        roots = sorted({self._find(r) for r in roots})
        c0, r0 = int(stat[cv2.CC_STAT_LEFT]), int(stat[cv2.CC_STAT_TOP])
        c1, r1 = c0 + int(stat[cv2.CC_STAT_WIDTH]), r0 + int(stat[cv2.CC_STAT_HEIGHT])
        comp = cc[r0:r1, c0:c1] == c
        seeds = self._reroot(np.where(comp, above[r0:r1, c0:c1], 0))
        unions = False
        if len(roots) > 1:
            # Below tau1 a blob rising tau2 over the meeting stands on its own; above it only a head
            # (a height maximum head_m over the meeting, head_sep_m from any higher one) does.
            rise = self.tau2 if z_conn <= self.tau1 + 1e-9 else self.head_m
            tall: list[int] = []
            for r in sorted(roots, key=lambda r: -self.top_m[r]):
                if self.top_m[r] - z_conn < rise - 1e-9:
                    continue
                if z_conn > self.tau1 + 1e-9 and any(self._peak_d2(r, t) < self.head_sep2 for t in tall):
                    continue
                tall.append(r)
            low = [r for r in roots if r not in tall]
            if not tall:
                for r in low[1:]:
                    self._union(low[0], r)
                unions = True
            elif low:
                for r in low:
                    self._union(_nearest_root(seeds, r, tall), r)
                unions = True
        final = sorted({self._find(r) for r in roots})
        if len(final) == 1:
            cur[r0:r1, c0:c1][comp] = final[0]
            return unions
        if unions:
            seeds = self._reroot(seeds)
        # Meeting cells go to the blob whose cells above are nearest.
        _, (ni, nj) = ndimage.distance_transform_edt(seeds == 0, return_indices=True)
        cur[r0:r1, c0:c1][comp] = seeds[ni, nj][comp]
        return unions


def _nearest_root(seeds: np.ndarray, low: int, tall: list[int]) -> int:
    """The tall blob whose seed cells come nearest to the low blob's seed cells."""
    pl = np.argwhere(seeds == low).astype(np.float64)
    best, best_d = tall[0], np.inf
    for t in tall:
        pt = np.argwhere(seeds == t).astype(np.float64)
        d = np.min(((pl[:, None, :] - pt[None, :, :]) ** 2).sum(-1))
        if d < best_d:
            best, best_d = t, d
    return best


def _make_blob(ijk: np.ndarray, grid) -> Blob:
    voxel_m = grid.voxel_m
    ijk = np.ascontiguousarray(ijk, dtype=np.int32)
    centres = grid.centres(ijk)
    nx = grid.shape[0]
    cells = np.unique(ijk[:, 1].astype(np.int64) * nx + ijk[:, 0])
    footprint = np.stack([cells // nx, cells % nx], axis=1).astype(np.int32)
    profile = np.bincount(ijk[:, 2], minlength=grid.shape[2]).astype(np.int32)
    lo = grid.origin_m + ijk.min(axis=0) * voxel_m
    hi = grid.origin_m + (ijk.max(axis=0) + 1) * voxel_m
    return Blob(
        x=float(centres[:, 0].mean()),
        y=float(centres[:, 1].mean()),
        z_top_m=float(hi[2]),
        volume_voxels=int(len(ijk)),
        ijk=ijk,
        footprint=footprint,
        height_profile=profile,
        bbox_m=np.stack([lo, hi]),
        voxel_m=voxel_m,
    )
