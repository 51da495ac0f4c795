"""Synthetic rigs and masks for testing and timing the carver, and :func:`measure_carving`.

The masks are exact silhouettes: every pixel's ray (through the full camera
model, distortion included) is intersected with the bodies, vertical
cylinders and axis-aligned boxes in the world frame.

:func:`measure_carving` is the one place in the carving package that reads a
clock; it exists for the project's benchmark command and never prints.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from common.camera import Camera, look_at
from fusion_server.carving.carver import Carver

__all__ = ["Cylinder", "Box", "room_rig", "MaskRenderer", "random_people", "body_voxels", "measure_carving"]


@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder: axis at (x_m, y_m), from z0_m up to z0_m + height_m (world, metres)."""

    x_m: float
    y_m: float
    radius_m: float
    height_m: float
    z0_m: float = 0.0


@dataclass(frozen=True)
class Box:
    """An axis-aligned box between the (3,) corners min_m and max_m (world, metres)."""

    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]


def room_rig(*, n_cameras: int = 5, volume_min_m=(0.0, 0.0, 0.0), volume_max_m=(8.0, 6.0, 2.5), width: int = 640,
             height: int = 480, fisheye: bool = True, mount_m: float = 2.4) -> dict[str, Camera]:
    """Cameras around a room: with ``fisheye`` one ceiling fisheye looking down at the centre
    (id ``ceiling``), the others pinholes spread evenly along the walls starting at a corner,
    0.05 m outside the volume at ``mount_m`` height, looking at the room centre at 0.9 m.
    Pinholes have a slight barrel distortion (k1 = -0.05), the fisheye k1 = 0.02."""
    lo = np.asarray(volume_min_m, dtype=np.float64)
    hi = np.asarray(volume_max_m, dtype=np.float64)
    mid = (lo + hi) / 2
    cams: dict[str, Camera] = {}
    n_walls = n_cameras - (1 if fisheye else 0)
    if n_walls < 0:
        raise ValueError(f"n_cameras must be at least 1 with a fisheye, got {n_cameras}")
    if fisheye:
        centre = np.array([mid[0], mid[1], hi[2] - 0.05])
        R, t = look_at(centre, centre - np.array([0.0, 0.0, 1.0]), up=(0.0, 1.0, 0.0))
        cams["ceiling"] = Camera.fisheye("ceiling", width, height, hfov_deg=200.0, dist=(0.02, 0.0, 0.0, 0.0), R=R, t=t)
    sx, sy = hi[0] - lo[0], hi[1] - lo[1]
    perimeter = 2 * (sx + sy)
    for n in range(n_walls):
        s = perimeter * n / max(n_walls, 1)
        if s < sx:
            x, y = lo[0] + s, lo[1]
        elif s < sx + sy:
            x, y = hi[0], lo[1] + (s - sx)
        elif s < 2 * sx + sy:
            x, y = hi[0] - (s - sx - sy), hi[1]
        else:
            x, y = lo[0], hi[1] - (s - 2 * sx - sy)
        pos = np.array([x, y, mount_m])
        outward = np.sign(pos[:2] - mid[:2]) * (np.isclose(pos[:2], lo[:2]) | np.isclose(pos[:2], hi[:2]))
        pos[:2] += 0.05 * outward
        R, t = look_at(pos, (mid[0], mid[1], 0.9))
        cid = f"cam{n + 1}"
        cams[cid] = Camera.pinhole(cid, width, height, hfov_deg=100.0, dist=(-0.05, 0.0, 0.0, 0.0), R=R, t=t)
    return cams


class MaskRenderer:
    """Exact silhouettes of bodies in a set of cameras (keeps each camera's pixel rays)."""

    def __init__(self, cameras: Mapping[str, Camera]) -> None:
        self.cameras = dict(cameras)
        self._rays = {cid: cam.pixel_rays().reshape(-1, 3) for cid, cam in self.cameras.items()}

    def render(self, bodies: Sequence[Cylinder | Box], camera_ids: Sequence[str] | None = None, *,
               hidden_by: Sequence[Box] = ()) -> dict[str, np.ndarray]:
        """camera id -> (H, W) uint8 mask, 255 where the pixel's ray meets a body in front of the camera
        and before any of ``hidden_by`` (furniture: background that hides the bodies behind it)."""
        out = {}
        for cid in self.cameras if camera_ids is None else camera_ids:
            cam = self.cameras[cid]
            body = self._nearest(cid, bodies)
            wall = self._nearest(cid, hidden_by)
            hit = np.isfinite(body) & (body < wall)
            out[cid] = (hit.reshape(cam.height, cam.width).astype(np.uint8)) * np.uint8(255)
        return out

    def render_depth(self, bodies: Sequence[Cylinder | Box], camera_ids: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """camera id -> (H, W) uint16 range images of a depth camera: millimetres from the
        camera centre to where the pixel's ray enters the nearest body, 0 where it meets none
        (the pixel rays are unit vectors, so the ray parameter is the range)."""
        out = {}
        for cid in self.cameras if camera_ids is None else camera_ids:
            cam = self.cameras[cid]
            body = self._nearest(cid, bodies)
            mm = np.where(np.isfinite(body), np.clip(np.rint(body * 1000.0), 1, 65535), 0)
            out[cid] = mm.reshape(cam.height, cam.width).astype(np.uint16)
        return out

    def _nearest(self, camera_id: str, bodies: Sequence[Cylinder | Box]) -> np.ndarray:
        """(H*W,) float64 ray parameter (metres) at which each of the camera's pixel rays first
        enters one of ``bodies``, inf where it meets none."""
        cam, rays = self.cameras[camera_id], self._rays[camera_id]
        nearest = np.full(rays.shape[0], np.inf)
        for b in bodies:
            np.minimum(nearest, _ray_enter(cam.center, rays, b), out=nearest)
        return nearest


def random_people(n: int, rng: np.random.Generator, *, volume_min_m=(0.0, 0.0, 0.0), volume_max_m=(8.0, 6.0, 2.5),
                  margin_m: float = 0.6) -> list[Cylinder]:
    """``n`` standing people (cylinders of radius 0.2-0.3 m, 1.5-1.9 m tall) at random places
    at least ``margin_m`` from the walls and 0.7 m from each other."""
    lo = np.asarray(volume_min_m, dtype=np.float64) + margin_m
    hi = np.asarray(volume_max_m, dtype=np.float64) - margin_m
    people: list[Cylinder] = []
    while len(people) < n:
        x, y = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
        if all(np.hypot(x - p.x_m, y - p.y_m) > 0.7 for p in people):
            people.append(Cylinder(float(x), float(y), float(rng.uniform(0.2, 0.3)), float(rng.uniform(1.5, 1.9))))
    return people


def body_voxels(carver: Carver, bodies: Sequence[Cylinder | Box]) -> np.ndarray:
    """(nx, ny, nz) bool: finest voxels of ``carver.grid`` whose centre lies inside a body."""
    grid = carver.grid
    nx, ny, nz = grid.shape
    x = grid.origin_m[0] + (np.arange(nx) + 0.5) * grid.voxel_m
    y = grid.origin_m[1] + (np.arange(ny) + 0.5) * grid.voxel_m
    z = grid.origin_m[2] + (np.arange(nz) + 0.5) * grid.voxel_m
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    inside = np.zeros(grid.shape, dtype=bool)
    for b in bodies:
        if isinstance(b, Cylinder):
            inside |= ((X - b.x_m) ** 2 + (Y - b.y_m) ** 2 <= b.radius_m**2) & (Z >= b.z0_m) & (Z <= b.z0_m + b.height_m)
        else:
            lo, hi = np.asarray(b.min_m), np.asarray(b.max_m)
            inside |= (X >= lo[0]) & (X <= hi[0]) & (Y >= lo[1]) & (Y <= hi[1]) & (Z >= lo[2]) & (Z <= hi[2])
    return inside


def measure_carving(carver: Carver, mask_sets: Sequence[Mapping[str, np.ndarray]], *, repeats: int = 3,
                    dense: bool = True, graphcut_smoothing: float | None = 0.01) -> dict[str, float]:
    """Time the carver's stages over ``mask_sets``.

    Each stage of each frame set runs ``repeats`` times and keeps its fastest run (robust
    to other processes sharing the core); the figures are means over the frame sets.
    Returns seconds per frame set for ``distance_s``, ``octree_s``, ``floor_s``,
    ``octree_total_s`` and (with ``dense``) ``dense_s``, ``dense_total_s``; frame sets per
    second ``octree_fps`` / ``dense_fps``; ``voxels`` (mean foreground voxels per set),
    ``dense_voxels``, ``missed_fraction`` (dense voxels the octree missed), ``frames``,
    ``cameras`` and ``lut_bytes``. With ``graphcut_smoothing`` (lambda), the graph cut of the
    octree's voxels is timed too: ``graphcut_s`` (its fusion stage: counting the region at
    the finest level and the cut), ``graphcut_total_s``, ``graphcut_fps`` and
    ``graphcut_voxels``; the octree figures are the vote's.
    """
    if not mask_sets:
        raise ValueError("mask_sets must not be empty")
    cut = graphcut_smoothing is not None
    stages = ["distance_s", "octree_s", "floor_s"] + (["dense_s"] if dense else []) + (["graphcut_s"] if cut else [])
    total = dict.fromkeys(stages, 0.0)
    voxels = dense_voxels = missed = cut_voxels = 0
    for masks in mask_sets:
        best = dict.fromkeys(stages, np.inf)
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            dists = carver.distance_stage(masks)
            t1 = time.perf_counter()
            ijk = carver.octree_stage(dists)
            t2 = time.perf_counter()
            carver.result(ijk, 0, dists)
            t3 = time.perf_counter()
            best["distance_s"] = min(best["distance_s"], t1 - t0)
            best["octree_s"] = min(best["octree_s"], t2 - t1)
            best["floor_s"] = min(best["floor_s"], t3 - t2)
            if dense:
                t4 = time.perf_counter()
                ijk_dense = carver.dense_stage(dists)
                best["dense_s"] = min(best["dense_s"], time.perf_counter() - t4)
            if cut:
                t5 = time.perf_counter()
                ijk_cut = carver.fusion_stage(ijk, dists, {}, fusion="graphcut", smoothing=graphcut_smoothing)
                best["graphcut_s"] = min(best["graphcut_s"], time.perf_counter() - t5)
        voxels += len(ijk)
        if cut:
            cut_voxels += len(ijk_cut)
        if dense:
            dense_voxels += len(ijk_dense)
            missed += len(ijk_dense) - len(ijk)
        for key in stages:
            total[key] += best[key]
    n = len(mask_sets)
    out = {key: float(value / n) for key, value in total.items()}
    out["octree_total_s"] = out["distance_s"] + out["octree_s"] + out["floor_s"]
    out["octree_fps"] = 1.0 / out["octree_total_s"]
    if dense:
        out["dense_total_s"] = out["distance_s"] + out["dense_s"] + out["floor_s"]
        out["dense_fps"] = 1.0 / out["dense_total_s"]
        out["dense_voxels"] = dense_voxels / n
        out["missed_fraction"] = missed / max(dense_voxels, 1)
    if cut:
        out["graphcut_total_s"] = out["octree_total_s"] + out["graphcut_s"]
        out["graphcut_fps"] = 1.0 / out["graphcut_total_s"]
        out["graphcut_voxels"] = cut_voxels / n
    out["voxels"] = voxels / n
    out["frames"] = float(n)
    out["cameras"] = float(len(carver.camera_ids))
    out["lut_bytes"] = float(carver.lut_nbytes)
    return out


# ---------------------------------------------------------------------- helpers


def _ray_enter(origin: np.ndarray, rays: np.ndarray, body: Cylinder | Box) -> np.ndarray:
    """(N,) float: the ray parameter s > 0 where origin + s d enters the body, inf where it
    misses. NaN rays never hit."""
    o = np.asarray(origin, dtype=np.float64)
    d = rays.astype(np.float64)
    with np.errstate(all="ignore"):
        if isinstance(body, Cylinder):
            lo_z, hi_z = _slab(o[2], d[:, 2], body.z0_m, body.z0_m + body.height_m)
            ox, oy = o[0] - body.x_m, o[1] - body.y_m
            a = d[:, 0] ** 2 + d[:, 1] ** 2
            b = 2 * (ox * d[:, 0] + oy * d[:, 1])
            c = ox * ox + oy * oy - body.radius_m**2
            disc = b * b - 4 * a * c
            root = np.sqrt(np.maximum(disc, 0.0))
            vertical = a < 1e-12
            s1 = np.where(vertical, np.where(c <= 0, -np.inf, np.inf), (-b - root) / (2 * np.where(vertical, 1, a)))
            s2 = np.where(vertical, np.where(c <= 0, np.inf, -np.inf), (-b + root) / (2 * np.where(vertical, 1, a)))
            s1 = np.where(~vertical & (disc < 0), np.inf, s1)
            enter = np.maximum.reduce([s1, lo_z, np.zeros_like(s1)])
            leave = np.minimum(s2, hi_z)
        else:
            lo, hi = np.asarray(body.min_m, dtype=np.float64), np.asarray(body.max_m, dtype=np.float64)
            enter = np.zeros(d.shape[0])
            leave = np.full(d.shape[0], np.inf)
            for axis in range(3):
                a_lo, a_hi = _slab(o[axis], d[:, axis], lo[axis], hi[axis])
                enter = np.maximum(enter, a_lo)
                leave = np.minimum(leave, a_hi)
        return np.where((enter <= leave) & np.isfinite(d[:, 0]), enter, np.inf)


def _slab(o: float, d: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters where o + s d lies within [lo, hi] along one axis: (s_lo, s_hi)."""
    flat = np.abs(d) < 1e-12
    inside = lo <= o <= hi
    safe = np.where(flat, 1.0, d)
    t1, t2 = (lo - o) / safe, (hi - o) / safe
    s_lo = np.where(flat, -np.inf if inside else np.inf, np.minimum(t1, t2))
    s_hi = np.where(flat, np.inf if inside else -np.inf, np.maximum(t1, t2))
    return s_lo, s_hi
