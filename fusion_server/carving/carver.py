"""The carver: foreground masks of one frame set -> foreground voxels and floor maps.

Stages, kept apart so a benchmark can time each one:

1. :meth:`Carver.distance_stage` - distance images of the inverted masks;
2. :meth:`Carver.octree_stage` - the octree descent (seed paper, Figure 1), or
   :meth:`Carver.dense_stage` - the brute-force oracle that tests every finest voxel;
3. :meth:`Carver.fusion_stage` - at the finest level, the depth cameras' free
   space (:mod:`.freespace`) and the graph cut (:mod:`.graphcut`), when the
   carver uses them;
4. :meth:`Carver.result` - floor maps and the :class:`CarveResult`.

Both carves apply the same vote at the finest level, so the octree result is
always a subset of the dense one (before the fusion stage). It can miss a few voxels the dense carve
keeps (section 2.1.3 of the paper): a child's enclosing circle can reach
outside its parent's circle, so foreground there passes the child's test while
the parent, tested first, failed and was never split; a camera can also see a
child's centre but not its parent's, which changes the parent's vote.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import numpy as np

from common.camera import Camera
from common.settings import default_of, validated
from common.site import Carving
from fusion_server.carving.distance import (
    DistanceImages, distance_images, mask_pixels, needed_votes, observations, tally, vote,
)
from fusion_server.carving.freespace import (
    apply_verdicts, check_depth, depth_verdicts, footprint_depth, footprint_level,
)
from fusion_server.carving.graphcut import graphcut_labels
from fusion_server.carving.lut import HIDDEN, RADIUS_UNITS_PER_PX, CacheReport, load_or_compute_lut
from fusion_server.carving.occlusion import Occluder
from fusion_server.carving.octree import OctreeLayout, descend, level_ijk, octree_layout
from fusion_server.grid import CarveResult, VoxelGrid, floor_maps

__all__ = ["Carver", "DEFAULT_CACHE_DIR", "DEFAULT_VOXEL_SIZES_M", "FUSIONS"]

DEFAULT_CACHE_DIR = "~/.cache/voxelwatch"
DEFAULT_VOXEL_SIZES_M = (0.4, 0.2, 0.1, 0.05)
_DENSE_CHUNK = 1 << 17
FUSIONS = ("vote", "graphcut")
_REGION_DILATION = 1  # the graph cut's region: the voted voxels grown by this many 6-neighbour steps


class Carver:
    """Multi-camera voxel carving over a fixed volume with fixed cameras.

    Keyword arguments:
      cameras: camera id -> :class:`common.camera.Camera` (keys equal the cameras' ids).
      volume_min_m, volume_max_m: (3,) corners of the monitored volume, world frame, metres;
        the finest grid is ``VoxelGrid.from_bounds(min, max, voxel_sizes_m[-1])``.
      grid: instead of the volume, the finest grid itself (its ``voxel_m`` must equal
        ``voxel_sizes_m[-1]``).
      voxel_sizes_m: octree voxel edges, coarse to fine, each half the previous.
      min_cameras: a foreground voxel needs at least this many cameras finding foreground.
      min_ratio: and at least this fraction of the present cameras that see it (h(v)).
      mask_scale: the workers' mask downscale factor; the tables are computed for the
        cameras scaled by it. Masks of any other size still work (scaled lookups).
      cache_dir: directory for the lookup-table cache (``~`` expanded), None for no cache.
      occluders: furniture and walls that hide people (:mod:`fusion_server.carving.occlusion`):
        a camera does not vote on a voxel it sees only through one of them.
      fusion: ``"vote"`` keeps the finest voxels that pass the vote; ``"graphcut"`` labels
        the voted voxels and their 6-neighbours by the graph cut of :mod:`.graphcut`.
      smoothing: the graph cut's Potts weight lambda, >= 0 (0.1: see docs/reference/fusion-server.md;
        the paper's 0.01 is for a data term of another scale).
      free_space: depth images given to :meth:`carve` carve the space in front of the
        measured surfaces (:mod:`.freespace`); False ignores them.

    Building the tables is the slow part (0.2-0.7 s per camera for the 1.1M voxels of an
    8 x 6 x 2.5 m room at 5 cm, about 3 s at 2.5 cm); it happens here, once per calibration
    when a cache directory is given. Attributes ``grid``, ``layout``, ``camera_ids``, ``lut_nbytes`` and
    ``cache_reports`` (camera id -> :class:`CacheReport`) describe the result.

    Not thread-safe: the distance buffer is reused from one frame set to the next.
    """

    def __init__(
        self,
        *,
        cameras: Mapping[str, Camera],
        volume_min_m: Sequence[float] | None = None,
        volume_max_m: Sequence[float] | None = None,
        grid: VoxelGrid | None = None,
        voxel_sizes_m: Sequence[float] = DEFAULT_VOXEL_SIZES_M,
        min_cameras: int = default_of(Carving, "min_cameras"),
        min_ratio: float = default_of(Carving, "min_ratio"),
        mask_scale: float = default_of(Carving, "mask_scale"),
        cache_dir: str | os.PathLike | None = DEFAULT_CACHE_DIR,
        occluders: Sequence[Occluder] = (),
        fusion: str = default_of(Carving, "fusion"),
        smoothing: float = default_of(Carving, "smoothing"),
        free_space: bool = default_of(Carving, "free_space"),
    ) -> None:
        if not isinstance(cameras, Mapping) or not cameras:
            raise ValueError("cameras must be a non-empty mapping of camera id -> Camera")
        for cid, cam in cameras.items():
            if not isinstance(cam, Camera):
                raise ValueError(f"cameras[{cid!r}] must be a Camera, got {type(cam).__name__}")
            if cam.id != cid:
                raise ValueError(f"cameras[{cid!r}] has id {cam.id!r}; keys must equal camera ids")
        if len(cameras) > 255:
            raise ValueError(f"cameras: at most 255 cameras, got {len(cameras)}")
        sizes = _check_voxel_sizes(voxel_sizes_m)
        # the site file's [carving] declares these settings, their ranges and messages: one declaration
        if isinstance(min_cameras, bool) or not isinstance(min_cameras, (int, np.integer)):
            raise ValueError(f"min_cameras must be an int >= 1, got {min_cameras!r}")
        validated(Carving, min_cameras=int(min_cameras), min_ratio=min_ratio, mask_scale=mask_scale, fusion=fusion,
                  smoothing=smoothing, free_space=free_space)
        if min_cameras > len(cameras):
            raise ValueError(f"min_cameras {min_cameras} exceeds the {len(cameras)} cameras: nothing could be carved")
        grid = _make_grid(volume_min_m, volume_max_m, grid, sizes[-1])

        self.grid: VoxelGrid = grid
        self.layout: OctreeLayout = octree_layout(grid.shape, len(sizes))
        self.voxel_sizes_m: tuple[float, ...] = tuple(grid.voxel_m * f for f in self.layout.factors)
        self.min_cameras = int(min_cameras)
        self.min_ratio = float(min_ratio)
        self.mask_scale = float(mask_scale)
        self.fusion = fusion
        self.smoothing = float(smoothing)
        self.free_space = free_space
        self.camera_centres_m: dict[str, np.ndarray] = {cid: np.asarray(cam.center, dtype=np.float64)
                                                        for cid, cam in cameras.items()}
        self.camera_ids: tuple[str, ...] = tuple(cameras)
        self.occluders: tuple[Occluder, ...] = tuple(occluders)
        self.cache_reports: dict[str, CacheReport] = {}
        self.lut_sizes: dict[str, tuple[int, int]] = {}

        n_cams = len(self.camera_ids)
        # (N_L, C): one row per voxel holds all cameras, so one gather per level serves all.
        self._pixel = [np.empty((self.layout.count(L), n_cams), dtype=np.int32) for L in range(self.layout.n_levels)]
        self._radius = [np.empty((self.layout.count(L), n_cams), dtype=np.uint16) for L in range(self.layout.n_levels)]
        for col, cid in enumerate(self.camera_ids):
            cam = cameras[cid]
            if self.mask_scale != 1.0:
                cam = cam.scaled(self.mask_scale)
            lut, report = load_or_compute_lut(cam, grid, self.layout, cache_dir, tuple(occluders))
            self.cache_reports[cid] = report
            self.lut_sizes[cid] = (lut.width, lut.height)
            for level in range(self.layout.n_levels):
                self._pixel[level][:, col] = lut.pixel[level]
                self._radius[level][:, col] = lut.radius_q[level]
            del lut
        # levels holding voxels that some camera sees only partly, behind furniture
        self._hidden = [bool(np.any(p == HIDDEN)) for p in self._pixel]
        self._buffer: np.ndarray | None = None

    # ------------------------------------------------------------------ public

    @property
    def lut_nbytes(self) -> int:
        """Bytes held by the lookup tables of all cameras and levels."""
        return sum(a.nbytes for a in self._pixel) + sum(a.nbytes for a in self._radius)

    def carve(self, masks: Mapping[str, np.ndarray], stamp_ns: int,
              depths: Mapping[str, np.ndarray] | None = None) -> CarveResult:
        """Octree carve of one frame set.

        masks: camera id -> (H, W) uint8 mask (0 background, 255 foreground; > 127 counts)
            or bool; cameras absent from ``masks`` do not vote. Unknown ids raise ValueError.
        stamp_ns: the frame set's capture time.
        depths: camera id -> (H, W) uint16 range in millimetres at its mask's size (distance
            from the camera centre along the pixel's ray, 0 = none), for depth cameras;
            any subset of the cameras in ``masks`` (others are ignored).
        """
        dists = self.distance_stage(masks)
        ijk = self.octree_stage(dists)
        return self.result(self.fusion_stage(ijk, dists, self.depth_stage(masks, depths)), stamp_ns, dists)

    def carve_dense(self, masks: Mapping[str, np.ndarray], stamp_ns: int,
                    depths: Mapping[str, np.ndarray] | None = None) -> CarveResult:
        """The brute-force oracle: every finest voxel tested with the same vote, no octree
        (then the same fusion stage)."""
        dists = self.distance_stage(masks)
        ijk = self.dense_stage(dists)
        return self.result(self.fusion_stage(ijk, dists, self.depth_stage(masks, depths)), stamp_ns, dists)

    def distance_stage(self, masks: Mapping[str, np.ndarray]) -> DistanceImages:
        """Stage 1: distance images of the present cameras (valid until the next call)."""
        dists = distance_images(masks, self.camera_ids, self.lut_sizes, out=self._buffer)
        if self._buffer is None or self._buffer.size < dists.values.size:
            self._buffer = dists.values
        return dists

    def octree_stage(self, dists: DistanceImages) -> np.ndarray:
        """Stage 2: the octree descent. Returns (N, 3) int32 finest indices of foreground voxels."""
        if len(dists.camera_ids) < self.min_cameras:
            return np.zeros((0, 3), dtype=np.int32)
        finest = descend(self.layout, lambda level, idx: self._test(level, idx, dists))
        return level_ijk(finest, self.layout.dims[-1])

    def dense_stage(self, dists: DistanceImages) -> np.ndarray:
        """Stage 2 (oracle): every finest voxel tested. Returns (N, 3) int32 indices, sorted."""
        if len(dists.camera_ids) < self.min_cameras:
            return np.zeros((0, 3), dtype=np.int32)
        pixel, radius = self._pixel[-1], self._radius[-1]
        hits = []
        for lo in range(0, pixel.shape[0], _DENSE_CHUNK):
            hi = min(pixel.shape[0], lo + _DENSE_CHUNK)
            passed = vote(pixel[lo:hi], radius[lo:hi], dists, self.min_cameras, self.min_ratio)
            hits.append(np.flatnonzero(passed) + lo)
        return level_ijk(np.concatenate(hits), self.layout.dims[-1])

    def depth_stage(self, masks: Mapping[str, np.ndarray],
                    depths: Mapping[str, np.ndarray] | None) -> dict[str, np.ndarray]:
        """Stage 2b: camera id -> (K, H, W) uint16 footprint range images
        (:func:`.freespace.footprint_depth`) of the depth cameras present in ``masks``
        (the depth of a camera without a mask is ignored); empty without depths or with
        ``free_space`` off. Unknown ids, other dtypes and other shapes raise ValueError."""
        if not depths or not self.free_space:
            return {}
        out = {}
        for cid, depth in depths.items():
            if cid not in self.camera_centres_m:
                raise ValueError(f"depths[{cid!r}]: unknown camera (known: {sorted(self.camera_ids)})")
            if cid not in masks:
                continue  # the camera is absent from the frame set: it does not vote at all
            out[cid] = footprint_depth(check_depth(cid, depth, np.shape(masks[cid])))
        return out

    def fusion_stage(self, ijk: np.ndarray, dists: DistanceImages, footprints: Mapping[str, np.ndarray], *,
                     fusion: str | None = None, smoothing: float | None = None) -> np.ndarray:
        """Stage 3: the finest voxels the carve keeps, (N, 3) int32, given the voted voxels
        ``ijk`` (N0, 3) and the depth cameras' ``footprints`` (:meth:`depth_stage`).

        With the vote and no depth images, ``ijk`` itself. Otherwise the voted voxels (and,
        for the graph cut, their neighbours) are counted again at the finest level with the
        depth cameras' verdicts, then kept by the vote or labelled by the graph cut.
        ``fusion`` and ``smoothing`` override the carver's own (for benchmarks).
        """
        fusion = self.fusion if fusion is None else fusion
        smoothing = self.smoothing if smoothing is None else smoothing
        if fusion not in FUSIONS:
            raise ValueError(f"fusion must be one of {FUSIONS}, got {fusion!r}")
        if ijk.shape[0] == 0 or (fusion == "vote" and not footprints):
            return ijk
        shape = self.layout.dims[-1]
        linear = np.ravel_multi_index(ijk.T.astype(np.int64), shape)
        if fusion == "vote":
            found, seeing = self.finest_counts(linear, dists, footprints)
            keep = found >= needed_votes(len(dists.columns), self.min_cameras, self.min_ratio)[seeing]
            return ijk[keep]
        region = _dilate(linear, shape, _REGION_DILATION)
        found, seeing = self.finest_counts(region, dists, footprints)
        labels = graphcut_labels(region, found, seeing, shape, n_cameras=len(dists.columns),
                                 min_cameras=self.min_cameras, min_ratio=self.min_ratio, smoothing=smoothing)
        return level_ijk(region[labels], shape)

    def finest_counts(self, linear: np.ndarray, dists: DistanceImages,
                      footprints: Mapping[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(found, seeing)`` (M,) uint8 camera counts of the finest voxels ``linear`` (M,) int64,
        with the depth cameras' verdicts (:mod:`.freespace`) in place of their silhouettes'
        where they measured a range."""
        pixel = np.take(self._pixel[-1], linear, axis=0)
        radius = np.take(self._radius[-1], linear, axis=0)
        hit, seen = observations(pixel, radius, dists, hidden=self._hidden[-1])
        if footprints:
            centres = self.grid.centres(level_ijk(linear, self.layout.dims[-1]))
            for cid, footprint in footprints.items():
                p = dists.camera_ids.index(cid)
                col = self.camera_ids.index(cid)
                n_sizes, h, w = footprint.shape
                lut_w, lut_h = self.lut_sizes[cid]
                px = mask_pixels(pixel[:, col], (lut_w, lut_h), (w, h))
                radius_px = radius[:, col] * (max(w / lut_w, h / lut_h) / RADIUS_UNITS_PER_PX)
                flat = footprint_level(radius_px) * (h * w) + np.maximum(px, 0)
                measured_m = np.where(px >= 0, footprint.ravel()[flat], 0) * 1e-3
                range_m = np.linalg.norm(centres - self.camera_centres_m[cid], axis=1)
                apply_verdicts(hit[:, p], seen[:, p], depth_verdicts(range_m, measured_m, self.grid.voxel_m))
        return tally(hit, seen)

    def result(self, ijk: np.ndarray, stamp_ns: int, dists: DistanceImages) -> CarveResult:
        """Stage 4: floor maps and the carve result."""
        return CarveResult(ijk=ijk, grid=self.grid, floor=floor_maps(ijk, self.grid), stamp_ns=int(stamp_ns),
                           cameras=dists.camera_ids)

    def tables(self, level: int, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The lookup-table rows of voxels ``index`` (M,) int64 of ``level``: ``(pixel, radius_q)``,
        each (M, C) over all cameras in ``camera_ids`` order (:mod:`.lut`: -1 or ``HIDDEN`` where the
        camera does not see the centre clearly; radii in 1/32 pixel of the table's size, ``lut_sizes``)."""
        return np.take(self._pixel[level], index, axis=0), np.take(self._radius[level], index, axis=0)

    def seeing_counts(self, level: int = -1) -> np.ndarray:
        """(N_L,) int: how many cameras see each voxel centre of ``level`` (all cameras)."""
        return np.count_nonzero(self._pixel[level] >= 0, axis=1)

    # ------------------------------------------------------------------ helpers

    def _test(self, level: int, index: np.ndarray, dists: DistanceImages) -> np.ndarray:
        pixel = np.take(self._pixel[level], index, axis=0)
        radius = np.take(self._radius[level], index, axis=0)
        return vote(pixel, radius, dists, self.min_cameras, self.min_ratio, hidden=self._hidden[level])


def _dilate(linear: np.ndarray, shape: tuple[int, int, int], steps: int) -> np.ndarray:
    """(M,) linear indices grown by ``steps`` 6-neighbour steps within ``shape``: sorted, unique."""
    occupied = np.zeros(shape, dtype=bool)
    occupied.ravel()[linear] = True
    for _ in range(steps):
        grown = occupied.copy()
        grown[1:] |= occupied[:-1]
        grown[:-1] |= occupied[1:]
        grown[:, 1:] |= occupied[:, :-1]
        grown[:, :-1] |= occupied[:, 1:]
        grown[:, :, 1:] |= occupied[:, :, :-1]
        grown[:, :, :-1] |= occupied[:, :, 1:]
        occupied = grown
    return np.flatnonzero(occupied)


def _make_grid(volume_min_m, volume_max_m, grid, voxel_m: float) -> VoxelGrid:
    if grid is not None:
        if volume_min_m is not None or volume_max_m is not None:
            raise ValueError("give either grid or volume_min_m/volume_max_m, not both")
        if not isinstance(grid, VoxelGrid):
            raise ValueError(f"grid must be a VoxelGrid, got {type(grid).__name__}")
        if abs(grid.voxel_m - voxel_m) > 1e-9 * voxel_m:
            raise ValueError(f"grid.voxel_m {grid.voxel_m} must equal the finest of voxel_sizes_m, {voxel_m}")
        if np.shape(grid.origin_m) != (3,) or len(grid.shape) != 3 or min(grid.shape) <= 0:
            raise ValueError(f"grid must be 3-D with a positive shape, got {grid.shape}")
        return grid
    if volume_min_m is None or volume_max_m is None:
        raise ValueError("volume_min_m and volume_max_m are required (or give grid)")
    try:
        lo = np.asarray(volume_min_m, dtype=np.float64)
        hi = np.asarray(volume_max_m, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"volume_min_m/volume_max_m must be numbers, got {volume_min_m!r}, {volume_max_m!r}") from None
    if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"volume_min_m/volume_max_m must be finite 3-vectors, got {lo.tolist()}, {hi.tolist()}")
    try:
        return VoxelGrid.from_bounds(lo, hi, voxel_m)
    except ValueError as exc:
        raise ValueError(f"volume_min_m/volume_max_m: {exc}") from None


def _check_voxel_sizes(voxel_sizes_m) -> tuple[float, ...]:
    try:
        sizes = tuple(float(s) for s in voxel_sizes_m)
    except (TypeError, ValueError):
        raise ValueError(f"voxel_sizes_m must be a sequence of numbers, got {voxel_sizes_m!r}") from None
    if not sizes or any(not math.isfinite(s) or s <= 0 for s in sizes):
        raise ValueError(f"voxel_sizes_m must be positive, got {list(sizes)}")
    for a, b in zip(sizes, sizes[1:]):
        if abs(a / b - 2.0) > 1e-6:
            raise ValueError(f"voxel_sizes_m must halve from one level to the next, got {list(sizes)}")
    return sizes
