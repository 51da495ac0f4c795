"""Per-camera lookup tables: where each octree voxel projects and how large it looks.

Cameras are fixed, so items 1 and 2 of the seed paper's Figure 1 (project the
centre and corners of every voxel on every level, keep an enclosing circle)
run once per calibration and volume. For every voxel of every level a
:class:`CameraLut` keeps

* ``pixel``: (N,) int32 flat index ``v * width + u`` of the pixel nearest to
  the projected centre (the (u, v) pixel coordinates and the visibility flag
  in 4 bytes); ``-1`` when the centre is not visible (behind the lens, beyond
  the distortion's valid range or outside the image), or hidden by an
  occluder (:mod:`fusion_server.carving.occlusion`; on coarse levels a
  partly hidden voxel holds ``HIDDEN``, -2: the camera counts as finding
  foreground in it, so that the finer levels decide);
* ``radius_q``: (N,) uint16 radius of the circle about the projected centre
  that encloses the projections of the voxel's 8 corners, in 1/32 pixel,
  rounded up. The corners go through the full camera model, so lens
  distortion is honoured. ``RADIUS_UNBOUNDED`` (65535, 2048 px) when a corner
  cannot be projected (behind the lens or beyond the distortion's valid
  range): the circle then covers the whole image, so the camera rules the
  voxel out only when its mask is empty. (Fixed point rather than float16:
  same size, and comparing against it is several times faster.)

That is 6 bytes per voxel and camera: 5.8 MB per camera for the 960 000
finest voxels of an 8 x 6 x 2.5 m room at 5 cm, about 6.6 MB with the coarser
levels.

:func:`compute_lut` is pure. :func:`load_or_compute_lut` adds a disk cache
(``np.savez``) keyed by a hash of the calibration, the volume and the octree;
an unreadable or mismatching file is recomputed and rewritten, and an
unwritable cache directory only costs the recomputation.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.camera import Camera
from fusion_server.carving.occlusion import Occluder, blocked, occluders_digest
from fusion_server.carving.octree import OctreeLayout, level_ijk
from fusion_server.grid import VoxelGrid

__all__ = [
    "CameraLut", "CacheReport", "HIDDEN", "LUT_FORMAT", "RADIUS_UNITS_PER_PX", "RADIUS_UNBOUNDED", "lut_key", "compute_lut",
    "load_or_compute_lut",
]

LUT_FORMAT = 3
HIDDEN = -2
"""A coarse voxel's pixel when the camera sees part of it only through an occluder: counts as found."""
RADIUS_UNITS_PER_PX = 32
RADIUS_UNBOUNDED = 65535
_LATTICE_CHUNK = 1 << 21  # lattice points projected at once: bounds the temporaries to ~100 MB


@dataclass(frozen=True, eq=False)
class CameraLut:
    """Projection tables of one camera for every octree level.

    width, height: image size the pixel indices refer to.
    pixel: per level, (N_L,) int32 ``v * width + u`` of the nearest pixel to the centre, -1 if not visible.
    radius_q: per level, (N_L,) uint16 enclosing-circle radius in 1/32 pixel, rounded up
        (``RADIUS_UNBOUNDED``: cannot be bounded).
    key: the cache key this table was computed for (:func:`lut_key`).
    """

    width: int
    height: int
    pixel: tuple[np.ndarray, ...]
    radius_q: tuple[np.ndarray, ...]
    key: str

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.pixel) + sum(a.nbytes for a in self.radius_q)

    def visible(self, level: int) -> np.ndarray:
        """(N_L,) bool: the voxel centre is in front of the lens and inside the image."""
        return self.pixel[level] >= 0

    def radius_px(self, level: int) -> np.ndarray:
        """(N_L,) float64 enclosing-circle radii in pixels, inf where unbounded."""
        q = self.radius_q[level]
        return np.where(q == RADIUS_UNBOUNDED, np.inf, q / RADIUS_UNITS_PER_PX)

    def uv(self, level: int) -> np.ndarray:
        """(N_L, 2) int16 ``(u, v)`` pixel of each voxel centre, (-1, -1) where not visible."""
        p = self.pixel[level]
        v, u = np.divmod(p, self.width)
        out = np.stack([u, v], axis=1).astype(np.int16)
        out[p < 0] = -1
        return out


@dataclass(frozen=True)
class CacheReport:
    """What :func:`load_or_compute_lut` did.

    status: ``'hit'`` (read from the cache), ``'miss'`` (computed and written),
        ``'corrupt'`` (the cached file was unreadable or did not match: recomputed, rewritten),
        ``'unwritable'`` (computed; the cache could not be written), ``'disabled'`` (no cache).
    path: the cache file, None when disabled.
    detail: the error behind ``'corrupt'`` / ``'unwritable'``, else empty.
    """

    status: str
    path: Path | None
    detail: str = ""


def lut_key(camera: Camera, grid: VoxelGrid, layout: OctreeLayout, occluders: Sequence[Occluder] = ()) -> str:
    """Hex sha256 of everything the tables depend on: camera model, image size, K, dist,
    R, t (and Tsai intrinsics), the grid origin, finest voxel and shape, the octree factors
    and the occluders (none: the same key as tables without them)."""
    h = hashlib.sha256()
    h.update(f"voxelwatch-lut-v{LUT_FORMAT}|r/{RADIUS_UNITS_PER_PX}|{camera.model}|{camera.width}x{camera.height}|".encode())
    for arr in (camera.K, camera.dist, camera.R, camera.t, grid.origin_m, [grid.voxel_m]):
        a = np.ascontiguousarray(arr, dtype="<f8")
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    if camera.tsai is not None:
        ts = camera.tsai
        h.update(np.array([ts.focal_mm, ts.kappa1, ts.dpx, ts.dpy, ts.sx, ts.cx, ts.cy], dtype="<f8").tobytes())
    h.update(f"|{tuple(grid.shape)}|{layout.factors}".encode())
    digest = occluders_digest(occluders)
    if digest:
        h.update(f"|occluders {digest}".encode())
    return h.hexdigest()


def compute_lut(camera: Camera, grid: VoxelGrid, layout: OctreeLayout,
                occluders: Sequence[Occluder] = ()) -> CameraLut:
    """Project every voxel of every level through ``camera`` (pure, no cache). A voxel whose
    centre the camera sees only through one of ``occluders`` is not visible (pixel -1)."""
    if tuple(grid.shape) != layout.grid_shape:
        raise ValueError(f"layout is for grid shape {layout.grid_shape}, grid has {tuple(grid.shape)}")
    pixels, radii = [], []
    for level, factor in enumerate(layout.factors):
        pix, rad = _project_level(camera, grid.origin_m, grid.voxel_m * factor, layout.dims[level])
        if occluders:
            _hide(pix, camera, grid.origin_m, grid.voxel_m * factor, layout.dims[level], occluders,
                  finest=level == len(layout.factors) - 1)
        pixels.append(pix)
        radii.append(rad)
    return CameraLut(width=camera.width, height=camera.height, pixel=tuple(pixels), radius_q=tuple(radii),
                     key=lut_key(camera, grid, layout, occluders))


def load_or_compute_lut(camera: Camera, grid: VoxelGrid, layout: OctreeLayout,
                        cache_dir: str | os.PathLike | None,
                        occluders: Sequence[Occluder] = ()) -> tuple[CameraLut, CacheReport]:
    """The tables of ``camera`` from ``cache_dir`` when cached, else computed (and cached).

    The file is ``<cache_dir>/lut-v<format>-<key[:32]>.npz``; it is written atomically
    (temporary file then rename). Never raises for cache problems: see :class:`CacheReport`.
    """
    key = lut_key(camera, grid, layout, occluders)
    if cache_dir is None:
        return compute_lut(camera, grid, layout, occluders), CacheReport("disabled", None)
    path = Path(cache_dir).expanduser() / f"lut-v{LUT_FORMAT}-{key[:32]}.npz"
    status, detail = "miss", ""
    if path.exists():
        try:
            return _read(path, key, camera, layout), CacheReport("hit", path)
        except Exception as exc:  # noqa: BLE001 - any unreadable file means: recompute
            status, detail = "corrupt", f"{path}: {type(exc).__name__}: {exc}"
    lut = compute_lut(camera, grid, layout, occluders)
    try:
        _write(path, lut)
    except OSError as exc:
        why = f"{path}: {type(exc).__name__}: {exc}"
        return lut, CacheReport("unwritable", path, f"{detail}; {why}" if detail else why)
    return lut, CacheReport(status, path, detail)


# ---------------------------------------------------------------------- helpers


def _hide(pixel: np.ndarray, camera: Camera, origin_m: np.ndarray, size_m: float, dims: tuple[int, int, int],
          occluders: Sequence[Occluder], *, finest: bool) -> None:
    """Mark (in place) the voxels of one level that ``camera`` sees through an occluder. On the
    finest level, by the line of sight to the centre (the vote looks at the centre): not visible
    (-1). On coarser levels, when the line to the centre or to any of the 8 corners is blocked:
    ``HIDDEN``, a camera that cannot rule the voxel out (part of it may be behind the counter)
    and so counts as finding foreground there; the children decide."""
    seen = np.flatnonzero(pixel >= 0)
    offsets = [(0.5, 0.5, 0.5)] if finest else [(0.5, 0.5, 0.5)] + [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    for lo in range(0, len(seen), _LATTICE_CHUNK):
        idx = seen[lo:lo + _LATTICE_CHUNK]
        corner = np.asarray(origin_m, dtype=np.float64) + level_ijk(idx, dims) * size_m
        hidden = np.zeros(len(idx), dtype=bool)
        for off in offsets:
            todo = np.flatnonzero(~hidden)
            if not len(todo):
                break
            hidden[todo] = blocked(camera.center, corner[todo] + np.asarray(off) * size_m, occluders)
        pixel[idx[hidden]] = -1 if finest else HIDDEN


def _project_level(camera: Camera, origin_m: np.ndarray, size_m: float, dims: tuple[int, int, int]):
    """(pixel int32, radius_q uint16) for the voxels of one level, chunked over X slabs."""
    nx, ny, nz = dims
    n = nx * ny * nz
    pixel = np.full(n, -1, dtype=np.int32)
    radius = np.zeros(n, dtype=np.uint16)
    if n == 0:
        return pixel, radius
    slab = (ny + 1) * (nz + 1)
    step = max(1, _LATTICE_CHUNK // slab)
    jj, kk = np.meshgrid(np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    for i0 in range(0, nx, step):
        i1 = min(nx, i0 + step)
        ni = i1 - i0
        # Corner lattice of the chunk: (ni + 1, ny + 1, nz + 1) points shared by neighbouring voxels.
        ii = np.arange(i0, i1 + 1, dtype=np.float64)
        lattice = np.empty((ni + 1, ny + 1, nz + 1, 3))
        lattice[..., 0] = origin_m[0] + ii[:, None, None] * size_m
        lattice[..., 1] = origin_m[1] + jj[None] * size_m
        lattice[..., 2] = origin_m[2] + kk[None] * size_m
        corner_uv, _ = camera.project(lattice.reshape(-1, 3))
        cu = corner_uv[:, 0].reshape(ni + 1, ny + 1, nz + 1)
        cv = corner_uv[:, 1].reshape(ni + 1, ny + 1, nz + 1)
        del lattice, corner_uv
        centres = np.empty((ni, ny, nz, 3))
        centres[..., 0] = origin_m[0] + (np.arange(i0, i1) + 0.5)[:, None, None] * size_m
        centres[..., 1] = origin_m[1] + (jj[None, :-1, :-1] + 0.5) * size_m
        centres[..., 2] = origin_m[2] + (kk[None, :-1, :-1] + 0.5) * size_m
        centre_uv, valid = camera.project(centres.reshape(-1, 3))
        del centres
        uc = centre_uv[:, 0].reshape(ni, ny, nz)
        vc = centre_uv[:, 1].reshape(ni, ny, nz)
        r2 = np.zeros((ni, ny, nz))
        du, dv = np.empty_like(r2), np.empty_like(r2)
        for a in (0, 1):
            for b in (0, 1):
                for c in (0, 1):
                    # r2 = max(r2, du^2 + dv^2), in place
                    np.subtract(cu[a : a + ni, b : b + ny, c : c + nz], uc, out=du)
                    np.subtract(cv[a : a + ni, b : b + ny, c : c + nz], vc, out=dv)
                    du *= du
                    dv *= dv
                    du += dv
                    # np.maximum propagates NaN: an unprojectable corner makes the radius NaN.
                    np.maximum(r2, du, out=r2)
        r = np.sqrt(r2).ravel()
        valid = valid & np.isfinite(uc.ravel()) & np.isfinite(vc.ravel())
        r = np.where(np.isnan(r), np.inf, r)
        lo, hi = i0 * ny * nz, i1 * ny * nz
        u = np.rint(np.where(valid, uc.ravel(), 0.0)).astype(np.int64)
        v = np.rint(np.where(valid, vc.ravel(), 0.0)).astype(np.int64)
        pixel[lo:hi] = np.where(valid, v * camera.width + u, -1)
        radius[lo:hi] = _quantise_radius(np.where(valid, r, 0.0))
    return pixel, radius


def _quantise_radius(r: np.ndarray) -> np.ndarray:
    """float64 pixels -> uint16 units of 1/32 pixel, rounded up (the circle must still enclose
    the corners); inf and radii beyond the range saturate to RADIUS_UNBOUNDED."""
    q = np.ceil(np.minimum(r, RADIUS_UNBOUNDED) * RADIUS_UNITS_PER_PX)
    return np.minimum(q, RADIUS_UNBOUNDED).astype(np.uint16)


def _read(path: Path, key: str, camera: Camera, layout: OctreeLayout) -> CameraLut:
    with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as data:
        stored = str(data["key"])
        if stored != key:
            raise ValueError(f"key {stored[:12]}... does not match {key[:12]}...")
        width, height = int(data["width"]), int(data["height"])
        if (width, height) != (camera.width, camera.height):
            raise ValueError(f"image size {width}x{height} does not match {camera.width}x{camera.height}")
        pixels, radii = [], []
        for level in range(layout.n_levels):
            pix = np.asarray(data[f"pixel_{level}"])
            rad = np.asarray(data[f"radius_{level}"])
            n = layout.count(level)
            if pix.dtype != np.int32 or pix.shape != (n,) or rad.dtype != np.uint16 or rad.shape != (n,):
                raise ValueError(f"level {level}: arrays {pix.dtype}{pix.shape}/{rad.dtype}{rad.shape}, expected ({n},)")
            if n and (pix.min() < HIDDEN or pix.max() >= width * height):
                raise ValueError(f"level {level}: pixel index out of range")
            pixels.append(pix)
            radii.append(rad)
    return CameraLut(width=width, height=height, pixel=tuple(pixels), radius_q=tuple(radii), key=key)


def _write(path: Path, lut: CameraLut) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"key": np.array(lut.key), "width": np.array(lut.width), "height": np.array(lut.height)}
    for level, (pix, rad) in enumerate(zip(lut.pixel, lut.radius_q)):
        arrays[f"pixel_{level}"] = pix
        arrays[f"radius_{level}"] = rad
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
