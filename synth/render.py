"""Rendering the synthetic house into one camera, fast enough for live use.

Per camera, once (:class:`CameraRenderer`): the world ray of every pixel
(through the camera's own lens model, so distortion and the fisheye come for
free), the background hit of every ray (room, doorway corridor, furniture)
with its depth, the lit and textured background image, the same hits on a
4x coarser grid for shadows, and a bank of sensor noise.

Per frame (:meth:`CameraRenderer.render`): for each body part (an ellipsoid)
only the rays inside its projected bounding box are intersected, vectorised
in numpy, into a depth buffer; a pixel shows the person when the body is
nearer than the background there (furniture occludes correctly). Shadows:
each coarse background point looks towards the ceiling light; the soft
occlusion of that segment by the body parts, fading with the distance to
the occluder, darkens it (a contact shadow under the feet that widens and
fades further away, on the floor and on nearby walls and furniture). Then
the frame is ``saturate(gain * scene + noise - 32)`` in one OpenCV call,
with the noise taken from the bank at a per-frame random offset.

Every output is a pure function of (room, camera, seed, bodies, gain, frame
key): scratch buffers are reset before use.

Units: world metres; pixels in OpenCV convention (integer = pixel centre).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import cv2
import numpy as np

from common.camera import Camera
from common.memo import BytesMemo, kept_on_disk
from synth.body import FOREARM_PARTS, HEAD_PART, HAIR, PART_MATERIAL, SKIN, Body
from synth.scene import Room
from synth.sensors import (
    RangeModel, ThermalModel, body_temperature_c, range_frame_mm, surface_offsets_k, thermal_frame_ck,
)

NOISE_OFFSET = 32
SHADOW_STRIDE = 4
SHADOW_STRENGTH = 0.55
SHADOW_REACH_M = 1.3
AMBIENT = 0.5
DIFFUSE = 0.65

SURF_FLOOR, SURF_CEILING = 0, 1
SURF_WALL_X0, SURF_WALL_X1, SURF_WALL_Y0, SURF_WALL_Y1 = 2, 3, 4, 5
SURF_CORRIDOR = 6
SURF_FURNITURE = 10
SURF_NONE = -1
_DOOR_SURFACE = {"x0": SURF_WALL_X0, "x1": SURF_WALL_X1, "y0": SURF_WALL_Y0, "y1": SURF_WALL_Y1}
HITS_CACHE_BYTES = 256 * 2**20
"""At most this much of the empty room seen through each camera (:func:`room_hits`) is kept per
process, the least recently used going first: a scenario renders every camera afresh, and casting
a 640x480 camera's rays into the room takes most of a second."""
_hits = BytesMemo(HITS_CACHE_BYTES)
_colours = BytesMemo(HITS_CACHE_BYTES // 4)   # the lit empty room (:func:`room_colour`): a fifth of its hits' bytes
_BOX_CHUNK = 2**19
"""Rays times furniture boxes cast against at once in :func:`raycast_room` (its memory: a few arrays of this many
float64)."""


@dataclass(frozen=True)
class BackgroundHits:
    """Where rays from one origin first hit the empty room.

    t: (N,) float64 distance along the (unit) ray, metres (0 where the ray is invalid).
    surface: (N,) int16 surface code (SURF_*, furniture ``SURF_FURNITURE + box index``).
    normal: (N, 3) float64 unit normal facing the ray origin. point: (N, 3) float64 world.
    """

    t: np.ndarray
    surface: np.ndarray
    normal: np.ndarray
    point: np.ndarray


def raycast_room(room: Room, origin_m, dirs) -> BackgroundHits:
    """Cast rays from ``origin_m`` (3,) (inside the room) along ``dirs`` (N, 3) unit world
    directions (NaN rows allowed) against walls, floor, ceiling, the corridor behind the
    door and the furniture boxes."""
    o = np.asarray(origin_m, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(d), axis=1)
    d = np.where(ok[:, None], d, np.array([0.0, 0.0, -1.0]))
    t, axis = _slab_far(o, d, np.zeros(3), np.asarray(room.size_m, dtype=np.float64))
    neg = np.take_along_axis(d, axis[:, None], axis=1)[:, 0] < 0
    surface = np.select(
        [axis == 2, axis == 0, axis == 1],
        [np.where(neg, SURF_FLOOR, SURF_CEILING), np.where(neg, SURF_WALL_X0, SURF_WALL_X1),
         np.where(neg, SURF_WALL_Y0, SURF_WALL_Y1)],
    ).astype(np.int16)
    normal = _axis_normal(axis, d)
    p = o + t[:, None] * d
    for door in room.doors:
        along = p[:, 1] if door.wall in ("x0", "x1") else p[:, 0]
        through = (surface == _DOOR_SURFACE[door.wall]) & (along >= door.y_range_m[0]) & (
            along <= door.y_range_m[1]) & (p[:, 2] <= door.height_m)
        if through.any():
            tc, ac = _slab_far(o, d[through], np.asarray(door.corridor_min_m), np.asarray(door.corridor_max_m))
            t[through] = tc
            surface[through] = SURF_CORRIDOR
            normal[through] = _axis_normal(ac, d[through])
    if room.boxes:
        lo = np.array([box.min_m for box in room.boxes], dtype=np.float64)
        hi = np.array([box.max_m for box in room.boxes], dtype=np.float64)
        step = max(1, _BOX_CHUNK // len(room.boxes))
        for a in range(0, d.shape[0], step):
            _nearest_box(o, d[a:a + step], lo, hi, t[a:a + step], surface[a:a + step], normal[a:a + step])
    t = np.where(ok, t, 0.0)
    surface = np.where(ok, surface, SURF_NONE).astype(np.int16)
    return BackgroundHits(t=t, surface=surface, normal=normal, point=o + t[:, None] * d)


def room_hits(room: Room, camera: Camera, rays: np.ndarray) -> BackgroundHits:
    """:func:`raycast_room` of ``rays`` ((H, W, 3), ``camera.pixel_rays()`` with the invalid ones
    set to its forward axis) from the camera's centre; the (read-only) result is kept for the next
    renderer of the same room and camera (:data:`HITS_CACHE_BYTES`)."""
    key = _room_key(room, camera)
    return _hits.get(key, lambda: kept_on_disk("room-hits", key, lambda: _cast(room, camera, rays), _hits_arrays,
                                               _hits_of), _hits_bytes)


def room_colour(room: Room, camera: Camera, hits: BackgroundHits) -> np.ndarray:
    """:func:`background_colour` of ``hits`` (:func:`room_hits` of ``room`` and ``camera``), kept like them
    (read-only)."""
    key = _room_key(room, camera)

    def make() -> np.ndarray:
        colour = background_colour(room, hits)
        colour.setflags(write=False)
        return colour

    return _colours.get(key, lambda: kept_on_disk("room-colour", key, make, lambda c: {"colour": c},
                                                  lambda a: a["colour"]), lambda c: c.nbytes)


def _room_key(room: Room, camera: Camera) -> tuple:
    """What the empty room seen through a camera depends on: the room and the camera's fingerprint."""
    return repr(room), camera.fingerprint()


def _cast(room: Room, camera: Camera, rays: np.ndarray) -> BackgroundHits:
    hits = raycast_room(room, camera.center.astype(np.float64), rays.reshape(-1, 3).astype(np.float64))
    for arr in (hits.t, hits.surface, hits.normal, hits.point):
        arr.setflags(write=False)
    return hits


def _hits_arrays(hits: BackgroundHits) -> dict[str, np.ndarray]:
    return {"t": hits.t, "surface": hits.surface, "normal": hits.normal, "point": hits.point}


def _hits_of(arrays: dict[str, np.ndarray]) -> BackgroundHits:
    return BackgroundHits(**arrays)


def _hits_bytes(hits: BackgroundHits) -> int:
    return sum(a.nbytes for a in (hits.t, hits.surface, hits.normal, hits.point))


def background_colour(room: Room, hits: BackgroundHits) -> np.ndarray:
    """(N, 3) float32 lit BGR colour (0..255 scale, may exceed) of background hits."""
    p = hits.point
    s = hits.surface
    n = p.shape[0]
    albedo = np.zeros((n, 3), dtype=np.float64)
    tex = _Textures()
    floor = s == SURF_FLOOR
    albedo[floor] = tex.wood(p[floor, 0], p[floor, 1])
    walls = (s >= SURF_WALL_X0) & (s <= SURF_WALL_Y1)
    if walls.any():
        along = np.where((s[walls] == SURF_WALL_X0) | (s[walls] == SURF_WALL_X1), p[walls, 1], p[walls, 0])
        albedo[walls] = tex.paint(along, p[walls, 2], s[walls])
    albedo[s == SURF_CEILING] = (232, 234, 236)
    corr = s == SURF_CORRIDOR
    if corr.any():
        is_floor = hits.normal[corr, 2] > 0.5
        c = np.where(is_floor[:, None], tex.tiles(p[corr, 0], p[corr, 1]), np.array([150.0, 165.0, 172.0]))
        albedo[corr] = c
    for k, box in enumerate(room.boxes):
        m = s == SURF_FURNITURE + k
        if m.any():
            albedo[m] = tex.fabric(p[m], hits.normal[m], box.colour_bgr)
    for dec in room.decals:
        _apply_decal(albedo, p, s, dec, tex)
    shade = lambert(room, p, hits.normal)
    # The ceiling is lit by light bounced off the floor and walls, not by the lamp under it.
    shade[s == SURF_CEILING] = np.maximum(shade[s == SURF_CEILING], 0.8)
    shade[corr] *= 0.75
    out = albedo * shade[:, None]
    out[s == SURF_NONE] = 0.0
    return out.astype(np.float32)


def lambert(room: Room, points, normals) -> np.ndarray:
    """(N,) float64 shading factor at world points with unit normals under the ceiling light."""
    lvec = np.asarray(room.light_m) - points
    dist = np.linalg.norm(lvec, axis=1)
    cos = np.einsum("ni,ni->n", normals, lvec) / np.maximum(dist, 1e-9)
    return AMBIENT + DIFFUSE * np.clip(cos, 0.0, 1.0) / (1.0 + (dist / 4.0) ** 2) * 1.6


class CameraRenderer:
    """One camera's precomputed view of the empty room and its per-frame renderer.

    Precomputed arrays (H, W = image size): ``rays`` (H, W, 3) float32 world unit rays,
    ``valid`` (H, W) bool pixels with a ray, ``bg_depth`` (H, W) float32 distance to the
    empty room along the ray (0 where invalid), ``bg_points`` (H, W, 3) float32 its world
    point, ``bg_bgr`` (H, W, 3) uint8 the lit, textured empty room.

    camera: the calibrated camera. room: the scene. seed: noise seed.
    noise_std: sensor noise, grey levels per channel. shadows: draw cast shadows.
    """

    def __init__(self, camera: Camera, room: Room, *, seed: int = 0, noise_std: float = 2.5,
                 shadows: bool = True, colour: bool = True) -> None:
        if not (0.0 <= noise_std <= 10.0):
            raise ValueError(f"noise_std must lie in 0..10, got {noise_std}")
        self.camera = camera
        self.room = room
        self.seed = int(seed)
        self.shadows = bool(shadows)
        self.cam_key = zlib.crc32(camera.id.encode("utf-8"))
        H, W = camera.height, camera.width
        self.center = camera.center.astype(np.float64)
        rays = camera.pixel_rays()
        self.valid = np.all(np.isfinite(rays), axis=2)
        rays[~self.valid] = camera.forward.astype(np.float32)
        self.rays = rays
        self._cells = _RayCells.of(rays, self.valid, RAY_CELL_PX)
        dx, dy, dz = rays[..., 0], rays[..., 1], rays[..., 2]
        self.rays6 = np.stack([dx * dx, dy * dy, dz * dz, 2 * dx * dy, 2 * dx * dz, 2 * dy * dz], axis=2)
        hits = room_hits(room, camera, rays)
        depth = hits.t.reshape(H, W).astype(np.float32)
        depth[~self.valid] = 0.0
        self.bg_depth = depth
        self.bg_points = hits.point.reshape(H, W, 3).astype(np.float32)
        self._zbuf = np.full((H, W), np.inf, dtype=np.float32)
        self._part = np.full((H, W), -1, dtype=np.int16)
        self._sensor: _SensorBackground | None = None   # range and thermal models' view, on first use
        self._still: tuple | None = None   # (the bodies' pose, scene, labels) last drawn
        self._still_surfaces: tuple | None = None   # (the bodies' pose, surfaces, labels) last cast
        if not colour:  # silhouettes only (:meth:`labels`)
            return
        look = np.random.default_rng([self.seed, self.cam_key, 11])
        self.white_balance = (1.0 + 0.03 * (2 * look.random(3) - 1)) * (1.0 + 0.04 * (2 * look.random() - 1))
        fwd = camera.forward
        cos_off = np.clip(rays.reshape(-1, 3) @ fwd, 0.0, 1.0).reshape(H, W)
        angle = np.arccos(cos_off)
        self.vignette = (1.0 - 0.22 * (angle / (np.pi / 2)) ** 2).astype(np.float32)
        colour = room_colour(room, camera, hits).reshape(H, W, 3) * self.white_balance[None, None, :]
        colour *= self.vignette[..., None]
        colour[~self.valid] = 0.0
        self.bg_bgr = np.clip(np.rint(colour), 0, 255).astype(np.uint8)
        # Shadows are soft: they are computed on every SHADOW_STRIDE-th pixel and upsampled.
        s = SHADOW_STRIDE
        sub = (slice(s // 2, None, s), slice(s // 2, None, s))
        self.coarse_points = self.bg_points[sub]
        surf = hits.surface.reshape(H, W)[sub]
        self.coarse_valid = (surf >= 0) & (surf != SURF_CEILING) & self.valid[sub]
        bank_rng = np.random.default_rng([self.seed, self.cam_key, 5])
        self._n_px = H * W * 3
        bank = bank_rng.normal(NOISE_OFFSET, noise_std, size=2 * self._n_px)
        self.noise_bank = np.clip(np.rint(bank), 0, 2 * NOISE_OFFSET).astype(np.uint8)

    # ------------------------------------------------------------------ frames

    def noise(self, key: tuple[int, ...]) -> np.ndarray:
        """(H, W, 3) uint8 noise frame (offset :data:`NOISE_OFFSET`) for a frame key."""
        rng = np.random.default_rng([self.seed, self.cam_key, *key])
        off = int(rng.integers(0, self._n_px))
        return self.noise_bank[off: off + self._n_px].reshape(self.camera.height, self.camera.width, 3)

    def background(self, gain: float, key: tuple[int, ...]) -> np.ndarray:
        """(H, W, 3) uint8 BGR frame of the empty room."""
        return cv2.addWeighted(self.bg_bgr, float(gain), self.noise(key), 1.0, -float(NOISE_OFFSET))

    def render(self, bodies: list[Body], gain: float, key: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """One frame.

        bodies: people to draw. gain: scene illumination gain. key: frame key for the noise.
        Returns ``bgr`` (H, W, 3) uint8 and ``labels`` (H, W) uint8: the person id whose body
        is visible at each pixel, 0 for background.
        """
        H, W = self.camera.height, self.camera.width
        if not bodies:
            return self.background(gain, key), np.zeros((H, W), dtype=np.uint8)
        pose = _pose(bodies)
        if self._still is None or self._still[0] != pose:
            # A person holding still is drawn once: the frames differ only by gain and noise.
            self._still = (pose, *self._draw(bodies))
        _, scene, labels = self._still
        return cv2.addWeighted(scene, float(gain), self.noise(key), 1.0, -float(NOISE_OFFSET)), labels.copy()

    def _draw(self, bodies: list[Body]) -> tuple[np.ndarray, np.ndarray]:
        """The noiseless scene (H, W, 3) uint8 at gain 1 and its person ids (H, W) uint8."""
        labels = np.zeros((self.camera.height, self.camera.width), dtype=np.uint8)
        scene = self.bg_bgr.copy()
        plans = [self._plan(b) for b in bodies]
        plans = [p for p in plans if p is not None]
        if self.shadows:
            for body, plan in zip(bodies, plans):
                self._shadow(scene, body)
        self._raycast_all(plans)
        for pi, plan in enumerate(plans):
            self._shade(scene, labels, plan, pi, plans)
        return scene, labels

    def labels(self, bodies: list[Body]) -> np.ndarray:
        """(H, W) uint8 the person id whose body is visible at each pixel (furniture and walls
        occlude), 0 for background: the true silhouettes of :meth:`render` without drawing."""
        labels = np.zeros((self.camera.height, self.camera.width), dtype=np.uint8)
        plans = self._raycast_bodies(bodies)
        for pi, plan in enumerate(plans):
            x0, y0, x1, y1 = plan.roi
            zb = self._zbuf[y0:y1, x0:x1]
            pb = self._part[y0:y1, x0:x1]
            visible = (pb >= pi * 32) & (pb < pi * 32 + 32) & (zb < self.bg_depth[y0:y1, x0:x1])
            labels[y0:y1, x0:x1][visible] = np.uint8(plan.body.person_id)
        return labels

    # ------------------------------------------------------------------ other sensors

    def range_mm(self, bodies: list[Body], key: tuple[int, ...], *, model: RangeModel = RangeModel()) -> np.ndarray:
        """(H, W) uint16 what a time-of-flight camera here measures: range (distance from the
        camera centre along the pixel's ray) of the nearest surface, millimetres, 0 where it
        gives no value (model in :mod:`synth.sensors`). Deterministic per ``key``."""
        return self.range_labels(bodies, key, model=model)[0]

    def range_labels(self, bodies: list[Body], key: tuple[int, ...], *,
                     model: RangeModel = RangeModel()) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`range_mm` and the true person ids per pixel (as :meth:`labels`) from one raycast."""
        surfaces, labels = self._body_surfaces(bodies)
        sb = self._sensor_background()
        r = self.bg_depth.copy()
        refl = sb.reflectance.copy()
        cos = sb.cos.copy()
        for plan, surf in surfaces:
            yy, xx = plan.roi[1] + surf.iy, plan.roi[0] + surf.ix
            r[yy, xx] = surf.t
            refl[yy, xx] = plan.body.shape.colours_bgr[surf.material].mean(axis=1) / 255.0
            cos[yy, xx] = np.abs(np.einsum("ni,ni->n", surf.normal, surf.ray))
        return range_frame_mm(r, refl, cos, self.valid, self._draws(key), model), labels

    def thermal(self, bodies: list[Body], key: tuple[int, ...], *, ambient_c: float = 21.0,
                model: ThermalModel = ThermalModel()) -> np.ndarray:
        """(H, W) uint16 radiometric thermal frame, centi-kelvin (``(t_c + 273.15) * 100``): the
        room at ``ambient_c`` Celsius with its surfaces' offsets, people warmer, sensor noise and
        fixed-pattern noise (model in :mod:`synth.sensors`). Deterministic per ``key``."""
        return self.thermal_labels(bodies, key, ambient_c=ambient_c, model=model)[0]

    def thermal_labels(self, bodies: list[Body], key: tuple[int, ...], *, ambient_c: float = 21.0,
                       model: ThermalModel = ThermalModel()) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`thermal` and the true person ids per pixel (as :meth:`labels`) from one raycast."""
        if not -30.0 <= ambient_c <= 60.0:
            raise ValueError(f"ambient_c must lie in -30..60 C, got {ambient_c!r}")
        surfaces, labels = self._body_surfaces(bodies)
        sb = self._sensor_background()
        amb = np.float32(ambient_c)
        temp = sb.offset_k + amb
        for plan, surf in surfaces:
            yy, xx = plan.roi[1] + surf.iy, plan.roi[0] + surf.ix
            body_c = body_temperature_c(surf.material, plan.body.person_id, self.seed)
            cos = np.abs(np.einsum("ni,ni->n", surf.normal, surf.ray)).astype(np.float32)
            # emissivity falls towards grazing angles: edges look nearer the room's temperature
            temp[yy, xx] = amb + (body_c - amb) * (np.float32(0.8) + np.float32(0.2) * cos)
        draws = self._draws(key)
        return thermal_frame_ck(temp, sb.fixed_k(model), draws[0], model), labels

    # ------------------------------------------------------------------ internals

    def _body_surfaces(self, bodies: list[Body]) -> tuple[list, np.ndarray]:
        """Raycast ``bodies``: [(plan, visible surface)] (not to be changed) and the (H, W) uint8 person ids;
        the bodies of the last frame again (people holding still) are not cast again."""
        pose = _pose(bodies)
        if self._still_surfaces is None or self._still_surfaces[0] != pose:
            self._still_surfaces = (pose, *self._cast_surfaces(bodies))
        _, out, labels = self._still_surfaces
        return out, labels.copy()

    def _cast_surfaces(self, bodies: list[Body]) -> tuple[list, np.ndarray]:
        labels = np.zeros((self.camera.height, self.camera.width), dtype=np.uint8)
        plans = self._raycast_bodies(bodies)
        out = []
        for pi, plan in enumerate(plans):
            surf = self._visible_surface(plan, pi)
            if surf is None:
                continue
            labels[plan.roi[1] + surf.iy, plan.roi[0] + surf.ix] = np.uint8(plan.body.person_id)
            out.append((plan, surf))
        return out, labels

    def _sensor_background(self) -> "_SensorBackground":
        """What the range and thermal models need of the empty room, built on first use."""
        sb = self._sensor
        if sb is None:
            H, W = self.camera.height, self.camera.width
            rays = self.rays.reshape(-1, 3).astype(np.float64)
            hits = room_hits(self.room, self.camera, self.rays)
            cos = np.abs(np.einsum("ni,ni->n", hits.normal, rays)).reshape(H, W).astype(np.float32)
            refl = (room_colour(self.room, self.camera, hits).mean(axis=1) / 255.0).reshape(H, W).astype(np.float32)
            offset = surface_offsets_k(self.room, hits.surface, hits.point, self.seed).reshape(H, W)
            offset[~self.valid] = 0.0
            rng = np.random.default_rng([self.seed, self.cam_key, 43])
            n = H * W
            sb = self._sensor = _SensorBackground(
                reflectance=np.clip(refl, 0.0, 1.0), cos=cos, offset_k=offset,
                pattern=(rng.standard_normal((H, W)).astype(np.float32),
                         rng.standard_normal((1, W)).astype(np.float32)),
                normal_bank=rng.standard_normal(2 * n).astype(np.float32),
                uniform_bank=rng.random(2 * n, dtype=np.float32),
                shape=(H, W))
        return sb

    def _draws(self, key: tuple[int, ...]) -> np.ndarray:
        """(2, H, W) float32 this frame's standard normal and uniform draws (from the sensor banks)."""
        sb = self._sensor_background()
        H, W = sb.shape
        n = H * W
        rng = np.random.default_rng([self.seed, self.cam_key, 53, *key])
        a, b = (int(v) for v in rng.integers(0, n, 2))
        return np.stack([sb.normal_bank[a: a + n].reshape(H, W), sb.uniform_bank[b: b + n].reshape(H, W)])


    def _plan(self, body: Body) -> "_BodyPlan | None":
        cam = self.camera
        ext = body.extents_m
        pts = body.centers_m[:, None, :] + ext[:, None, :] * _BOX_POINTS[None, :, :]
        uv, _ = cam.project(pts.reshape(-1, 3))
        uv = uv.reshape(len(ext), -1, 2)
        finite = np.all(np.isfinite(uv), axis=(1, 2))
        # A part reaching behind the camera or beyond the lens's range may cover anything.
        lo = np.where(finite[:, None], np.min(np.where(np.isfinite(uv), uv, np.inf), axis=1), 0.0)
        hi = np.where(finite[:, None], np.max(np.where(np.isfinite(uv), uv, -np.inf), axis=1),
                      [cam.width - 1, cam.height - 1])
        # Margin covers the lens bending box edges between the sampled points.
        margin = 3.0 if cam.model == "pinhole" else 6.0
        x0 = np.clip(np.floor(lo[:, 0] - margin), 0, cam.width).astype(int)
        y0 = np.clip(np.floor(lo[:, 1] - margin), 0, cam.height).astype(int)
        x1 = np.clip(np.ceil(hi[:, 0] + margin) + 1, 0, cam.width).astype(int)
        y1 = np.clip(np.ceil(hi[:, 1] + margin) + 1, 0, cam.height).astype(int)
        keep = (x1 > x0) & (y1 > y0)
        if not keep.any():
            return None
        if not finite.all():
            # Bound those parts by the cone of rays that can meet them instead of the whole image
            # (a person a step from the camera, under it or behind it): the same hits, found
            # in a fraction of the pixels. The body keeps its plan, found or not.
            cone = self._cells.boxes(body.centers_m[~finite] - self.center, np.linalg.norm(ext[~finite], axis=1))
            x0[~finite], y0[~finite], x1[~finite], y1[~finite] = cone.T
        cast = (x1 > x0) & (y1 > y0)
        roi = ((int(x0[cast].min()), int(y0[cast].min()), int(x1[cast].max()), int(y1[cast].max()))
               if cast.any() else (0, 0, 0, 0))
        inv = body.inverse_axes
        o = np.einsum("pij,pj->pi", inv, self.center[None, :] - body.centers_m)
        return _BodyPlan(body=body, roi=roi, boxes=np.stack([x0, y0, x1, y1], axis=1), keep=cast, inv=inv, o=o)

    def _raycast_bodies(self, bodies: list[Body]) -> list["_BodyPlan"]:
        """Plan and raycast ``bodies`` (those out of view are dropped): the plans, in the order of
        their parts in the depth and part buffers."""
        plans = [p for p in (self._plan(b) for b in bodies) if p is not None]
        self._raycast_all(plans)
        return plans

    def _raycast_all(self, plans: list["_BodyPlan"]) -> None:
        """Clear the depth and part buffers over the plans' regions, then raycast each plan."""
        for plan in plans:
            x0, y0, x1, y1 = plan.roi
            self._zbuf[y0:y1, x0:x1] = np.inf
            self._part[y0:y1, x0:x1] = -1
        for pi, plan in enumerate(plans):
            self._raycast(plan, pi)

    def _raycast(self, plan: "_BodyPlan", pi: int) -> None:
        zbuf, part = self._zbuf, self._part
        for k in np.nonzero(plan.keep)[0]:
            x0, y0, x1, y1 = plan.boxes[k]
            inv, o = plan.inv[k], plan.o[k]
            Q = inv.T @ inv
            q6 = np.array([Q[0, 0], Q[1, 1], Q[2, 2], Q[0, 1], Q[0, 2], Q[1, 2]], dtype=np.float32)
            pvec = (inv.T @ o).astype(np.float32)
            a = self.rays6[y0:y1, x0:x1] @ q6
            b = self.rays[y0:y1, x0:x1] @ pvec
            c = np.float32(o @ o - 1.0)
            disc = b * b - a * c
            hit = disc > 0
            if not hit.any():
                continue
            t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
            zb = zbuf[y0:y1, x0:x1]
            closer = hit & (t > 0) & (t < zb)
            np.copyto(zb, t, where=closer)
            np.copyto(part[y0:y1, x0:x1], np.int16(pi * 32 + k), where=closer)

    def _shade(self, scene: np.ndarray, labels: np.ndarray, plan: "_BodyPlan", pi: int, plans) -> None:
        surf = self._visible_surface(plan, pi)
        if surf is None:
            return
        body = plan.body
        x0, y0 = plan.roi[:2]
        iy, ix, point, normal, material = surf.iy, surf.ix, surf.point, surf.normal, surf.material
        shade = lambert(self.room, point, normal)
        colours = body.shape.colours_bgr[material].astype(np.float64)
        # Cloth texture: faint stripes on shirts across the body, so the colour is not flat.
        colours *= (1.0 + 0.05 * np.sin(40.0 * point[:, 2]))[:, None]
        rgb = colours * shade[:, None] * self.white_balance[None, :] * self.vignette[y0 + iy, x0 + ix][:, None]
        scene[y0 + iy, x0 + ix] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
        labels[y0 + iy, x0 + ix] = np.uint8(body.person_id)

    def _visible_surface(self, plan: "_BodyPlan", pi: int) -> "_Surface | None":
        """The pixels of ``plan``'s body that the depth buffer shows (None: none), with their
        range, world point, unit normal and material (SKIN, HAIR, ...)."""
        x0, y0, x1, y1 = plan.roi
        zb = self._zbuf[y0:y1, x0:x1]
        pb = self._part[y0:y1, x0:x1]
        visible = (pb >= pi * 32) & (pb < pi * 32 + 32) & (zb < self.bg_depth[y0:y1, x0:x1])
        if not visible.any():
            return None
        body = plan.body
        iy, ix = np.nonzero(visible)
        k = pb[iy, ix] - pi * 32
        t = zb[iy, ix].astype(np.float64)
        d = self.rays[y0 + iy, x0 + ix].astype(np.float64)
        u = plan.o[k] + np.einsum("nij,nj->ni", plan.inv[k], d) * t[:, None]
        normal = np.einsum("nji,nj->ni", plan.inv[k], u)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        point = self.center + d * t[:, None]
        material = PART_MATERIAL[k].astype(np.int64)
        head = k == HEAD_PART
        material[head & ((u[:, 2] > 0.3) | ((u[:, 0] < -0.25) & (u[:, 2] > -0.35)))] = HAIR
        hand = np.isin(k, FOREARM_PARTS) & (u[:, 2] < (-0.45 if body.shape.long_sleeves else 1.1))
        material[hand] = SKIN
        return _Surface(iy=iy, ix=ix, t=t, ray=d, point=point, normal=normal, material=material)

    def _shadow(self, scene: np.ndarray, body: Body) -> None:
        cam = self.camera
        s = SHADOW_STRIDE
        lo, hi = body.aabb()
        lo = np.array([lo[0] - SHADOW_REACH_M, lo[1] - SHADOW_REACH_M, 0.0])
        hi = np.array([hi[0] + SHADOW_REACH_M, hi[1] + SHADOW_REACH_M, max(hi[2], 0.3)])
        corners = lo + (hi - lo) * (0.5 + 0.5 * _BOX_POINTS)
        uv, _ = cam.project(corners)
        if not np.all(np.isfinite(uv)):
            cx0, cy0, cx1, cy1 = 0, 0, self.coarse_points.shape[1], self.coarse_points.shape[0]
        else:
            cx0 = int(np.clip(np.floor(uv[:, 0].min() / s) - 1, 0, self.coarse_points.shape[1]))
            cy0 = int(np.clip(np.floor(uv[:, 1].min() / s) - 1, 0, self.coarse_points.shape[0]))
            cx1 = int(np.clip(np.ceil(uv[:, 0].max() / s) + 2, 0, self.coarse_points.shape[1]))
            cy1 = int(np.clip(np.ceil(uv[:, 1].max() / s) + 2, 0, self.coarse_points.shape[0]))
        if cx1 <= cx0 or cy1 <= cy0:
            return
        pts = self.coarse_points[cy0:cy1, cx0:cx1].reshape(-1, 3).astype(np.float64)
        valid = self.coarse_valid[cy0:cy1, cx0:cx1].ravel()
        near = valid & np.all(pts >= lo - 1e-6, axis=1) & np.all(pts <= hi + 1e-6, axis=1)
        idx = np.nonzero(near)[0]
        if idx.size == 0:
            return
        light = np.asarray(self.room.light_m, dtype=np.float64)
        # Only segments to the light that pass near the body's bounding sphere can be shadowed.
        blo, bhi = body.aabb()
        centre, radius = 0.5 * (blo + bhi), 0.5 * float(np.linalg.norm(bhi - blo))
        P = pts[idx]
        D = light - P
        t = np.clip(np.einsum("ni,ni->n", centre - P, D) / np.einsum("ni,ni->n", D, D), 0.0, 1.0)
        passing = np.linalg.norm(P + t[:, None] * D - centre, axis=1) < radius + 0.5
        occ = np.zeros(pts.shape[0])
        occ[idx[passing]] = soft_occlusion(body, P[passing], light)
        occ = occ.reshape(cy1 - cy0, cx1 - cx0)
        rows = np.nonzero((occ > 0.003).any(axis=1))[0]
        cols = np.nonzero((occ > 0.003).any(axis=0))[0]
        if rows.size == 0:
            return
        # Crop to the shadowed cells (plus one for the upsampling) before working at full resolution.
        r0, r1 = max(rows[0] - 1, 0), min(rows[-1] + 2, occ.shape[0])
        c0, c1 = max(cols[0] - 1, 0), min(cols[-1] + 2, occ.shape[1])
        factor = (1.0 - SHADOW_STRENGTH * occ[r0:r1, c0:c1]).astype(np.float32)
        cy0, cx0 = cy0 + r0, cx0 + c0
        cy1, cx1 = cy0 + (r1 - r0), cx0 + (c1 - c0)
        H, W = cam.height, cam.width
        full = cv2.resize(factor, ((cx1 - cx0) * s, (cy1 - cy0) * s), interpolation=cv2.INTER_LINEAR)
        fy0, fx0 = cy0 * s, cx0 * s
        fy1, fx1 = min(cy1 * s, H), min(cx1 * s, W)
        full = full[: fy1 - fy0, : fx1 - fx0]
        # Upsampling blurs across depth edges; keep the shadow on surfaces near the person only.
        bp = self.bg_points[fy0:fy1, fx0:fx1]
        near_px = (bp[..., 0] >= lo[0]) & (bp[..., 0] <= hi[0]) & (bp[..., 1] >= lo[1]) & (bp[..., 1] <= hi[1])
        full = np.where(near_px, full, np.float32(1.0))
        roi = scene[fy0:fy1, fx0:fx1]
        scene[fy0:fy1, fx0:fx1] = np.clip(roi.astype(np.float32) * full[..., None] + 0.5, 0, 255).astype(np.uint8)


MODALITIES = ("colour", "thermal", "infrared", "depth")
"""What a site camera can be (``cameras[].modality``); :func:`frame_for` renders each."""


def _pose(bodies: list[Body]) -> tuple:
    """A hashable value equal for the same people in the same pose."""
    return tuple((b.person_id, b.centers_m.tobytes(), b.axes.tobytes(), b.shape) for b in bodies)


def frame_for(renderer: CameraRenderer, modality: str, bodies: list[Body], key: tuple[int, ...], *,
              gain: float = 1.0, ambient_c: float = 21.0, range_model: RangeModel = RangeModel(),
              thermal_model: ThermalModel = ThermalModel()) -> tuple[np.ndarray, np.ndarray]:
    """One frame of a camera of any modality and its true person ids per pixel.

    ``colour``: (H, W, 3) uint8 BGR (:meth:`CameraRenderer.render`, lit with ``gain``);
    ``infrared``: the same scene as grey, (H, W, 3) uint8 (an active near-infrared camera: no
    colour); ``thermal``: (H, W) uint16 centi-kelvin, the room's air at ``ambient_c`` Celsius;
    ``depth``: (H, W) uint16 range in millimetres, 0 = no value. Labels: (H, W) uint8 person ids,
    0 = nobody. Deterministic per ``key``.
    """
    if modality == "colour":
        return renderer.render(bodies, gain, key)
    if modality == "infrared":
        bgr, labels = renderer.render(bodies, gain, key)
        return cv2.cvtColor(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR), labels
    if modality == "thermal":
        return renderer.thermal_labels(bodies, key, ambient_c=ambient_c, model=thermal_model)
    if modality == "depth":
        return renderer.range_labels(bodies, key, model=range_model)
    raise ValueError(f"modality must be one of {', '.join(MODALITIES)}, got {modality!r}")


def soft_occlusion(body: Body, points_m: np.ndarray, light_m: np.ndarray) -> np.ndarray:
    """(N,) float64 in 0..1: how much ``body`` blocks the ceiling light seen from ``points_m`` (N, 3).

    The segment point -> light is tested against every part in the part's unit-ball frame:
    the closest approach ``r`` (1 = touching the surface) gives a soft edge whose width grows
    with the distance from the point to the occluder, and the darkening fades with it too.
    """
    inv = body.inverse_axes
    P = len(inv)
    pts = np.asarray(points_m, dtype=np.float64)
    # o: point in each part's unit frame; d: segment to the light in that frame (light - point).
    o = (pts @ inv.transpose(0, 2, 1).transpose(1, 0, 2).reshape(3, 3 * P)).reshape(-1, P, 3)
    o -= np.einsum("pij,pj->pi", inv, body.centers_m)[None, :, :]
    lc = np.einsum("pij,pj->pi", inv, light_m[None, :] - body.centers_m)
    d = lc[None, :, :] - o
    od = np.einsum("npi,npi->np", o, d)
    dd = np.einsum("npi,npi->np", d, d)
    oo = np.einsum("npi,npi->np", o, o)
    s = np.clip(-od / np.maximum(dd, 1e-12), 0.0, 1.0)
    r = np.sqrt(np.maximum(oo + 2 * s * od + s * s * dd, 0.0))
    dist = s * np.linalg.norm(light_m[None, :] - pts, axis=1)[:, None]
    w = 0.35 + 1.2 * dist
    edge = np.clip((1.0 + w - r) / (2.0 * w), 0.0, 1.0)
    return np.max(edge * np.exp(-dist / 1.1), axis=1)


# ---------------------------------------------------------------------- helpers


@dataclass(frozen=True)
class _RayCells:
    """The image cut into square cells of ``stride`` pixels: each cell's centre ray (unit,
    float64) and ``spread``, the largest angle (radians) between it and the cell's valid rays,
    so that a cone of rays can be bounded in pixels without a ray per pixel."""

    stride: int
    rays: np.ndarray     # (Hc, Wc, 3)
    spread: np.ndarray   # (Hc, Wc)
    shape: tuple[int, int]

    @classmethod
    def of(cls, rays: np.ndarray, valid: np.ndarray, stride: int) -> "_RayCells":
        H, W = valid.shape
        hc, wc = -(-H // stride), -(-W // stride)
        cy = np.minimum(np.arange(hc) * stride + stride // 2, H - 1)
        cx = np.minimum(np.arange(wc) * stride + stride // 2, W - 1)
        centre = rays[cy][:, cx].astype(np.float64)
        centre /= np.linalg.norm(centre, axis=2, keepdims=True)
        padded = np.zeros((hc * stride, wc * stride, 3))
        padded[:H, :W] = rays
        seen = np.zeros((hc * stride, wc * stride), dtype=bool)
        seen[:H, :W] = valid
        dots = np.einsum("aibjk,abk->aibj", padded.reshape(hc, stride, wc, stride, 3), centre)
        dots = np.where(seen.reshape(hc, stride, wc, stride), dots, 1.0)
        spread = np.arccos(np.clip(dots.min(axis=(1, 3)), -1.0, 1.0))
        return cls(stride, centre, spread, (H, W))

    def boxes(self, offsets: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """(N, 4) int pixel boxes (x0, y0, x1, y1; empty where x1 <= x0) holding every pixel whose
        ray can meet a sphere of radius ``radii[i]`` centred ``offsets[i]`` (N, 3) from the camera
        centre: the whole image where the centre lies in the sphere."""
        H, W = self.shape
        out = np.zeros((len(offsets), 4), dtype=int)
        for i, (off, r) in enumerate(zip(offsets, radii)):
            dist = float(np.linalg.norm(off))
            if dist <= r + 1e-3:
                out[i] = (0, 0, W, H)
                continue
            # within the sphere's half-angle, widened by the cell's spread and a float32 margin
            angle = np.arccos(np.clip(self.rays @ (off / dist), -1.0, 1.0))
            rows, cols = np.nonzero(angle <= np.arcsin(r / dist) + self.spread + 1e-4)
            if len(rows):
                s = self.stride
                out[i] = (cols.min() * s, rows.min() * s, min((cols.max() + 1) * s, W), min((rows.max() + 1) * s, H))
        return out


@dataclass
class _BodyPlan:
    body: Body
    roi: tuple[int, int, int, int]
    boxes: np.ndarray
    keep: np.ndarray
    inv: np.ndarray
    o: np.ndarray


@dataclass
class _SensorBackground:
    """The empty room as the range and thermal models see it: (H, W) float32 reflectance 0..1,
    |cos| of incidence, temperature above the air (K); the fixed-pattern draws (pixel, column);
    banks of standard normal and uniform draws (2 H W float32)."""

    reflectance: np.ndarray
    cos: np.ndarray
    offset_k: np.ndarray
    pattern: tuple[np.ndarray, np.ndarray]
    normal_bank: np.ndarray
    uniform_bank: np.ndarray
    shape: tuple[int, int]
    _fixed: dict = field(default_factory=dict)

    def fixed_k(self, model: ThermalModel) -> np.ndarray:
        """(H, W) float32 the camera's fixed-pattern offsets under ``model``, kelvin."""
        if model in self._fixed:
            return self._fixed[model]
        H, W = self.shape
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        rr = ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
        pixel, column = self.pattern
        fixed = (np.float32(model.fpn_k) * pixel + np.float32(model.column_k) * column
                 + np.float32(model.radial_k) * rr).astype(np.float32)
        self._fixed[model] = fixed
        return fixed


@dataclass
class _Surface:
    """Visible body pixels of one plan: rows/columns inside its roi, range (m), unit rays, world points,
    unit normals (float64) and material codes."""

    iy: np.ndarray
    ix: np.ndarray
    t: np.ndarray
    ray: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    material: np.ndarray


def _box_points() -> np.ndarray:
    """(27, 3) the unit cube's corners, edge midpoints, face centres and centre, in -1..1."""
    g = np.array([-1.0, 0.0, 1.0])
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)


_BOX_POINTS = _box_points()
RAY_CELL_PX = 8   # cell of the rays bounding the parts a lens cannot project (see _RayCells)


def _slab_far(o, d, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Exit distance of rays from inside (or entering) box [lo, hi] and the exit axis."""
    far = []
    for ax in range(3):
        da = d[:, ax]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(da > 0, (hi[ax] - o[ax]) / da, (lo[ax] - o[ax]) / da)
        far.append(np.where(da != 0, t, np.inf))
    tf = np.minimum(np.minimum(far[0], far[1]), far[2])
    axis = np.where(tf == far[0], 0, np.where(tf == far[1], 1, 2))
    return tf, axis


def _slab_near(o, d, lo, hi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entry distance of rays ``d`` (N, 3) into boxes [lo, hi] (K, 3 each), entry axis and whether the
    ray hits the box in front, each (N, K)."""
    tmin, tmax = [], []
    for ax in range(3):
        da = np.where(np.abs(d[:, ax]) < 1e-12, 1e-12, d[:, ax])[:, None]
        t1 = (lo[None, :, ax] - o[ax]) / da
        t2 = (hi[None, :, ax] - o[ax]) / da
        tmin.append(np.minimum(t1, t2))
        tmax.append(np.maximum(t1, t2))
    near = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
    far = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
    axis = np.where(near == tmin[0], 0, np.where(near == tmin[1], 1, 2))
    return near, axis, (near <= far) & (near > 1e-9)


def _nearest_box(o, d, lo, hi, t, surface, normal) -> None:
    """Where a ray ``d`` (N, 3) meets one of the boxes [lo, hi] (K, 3 each) nearer than ``t`` (N,), set
    (in place) ``t``, ``surface`` (``SURF_FURNITURE`` + the box's index) and ``normal`` to that box's;
    of boxes met at the same distance, the first."""
    near, axis, hit = _slab_near(o, d, lo, hi)
    near = np.where(hit, near, np.inf)
    k = np.argmin(near, axis=1)
    rows = np.arange(d.shape[0])
    tn = near[rows, k]
    won = tn < t
    if won.any():
        t[won] = tn[won]
        surface[won] = SURF_FURNITURE + k[won]
        normal[won] = _axis_normal(axis[rows, k][won], d[won])


def _axis_normal(axis: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Unit normals along ``axis`` facing against ``d``."""
    n = np.zeros((axis.shape[0], 3))
    comp = np.take_along_axis(d, axis[:, None], axis=1)[:, 0]
    n[np.arange(axis.shape[0]), axis] = -np.sign(comp)
    return n


def _apply_decal(albedo, p, s, dec, tex) -> None:
    surf = {"floor": SURF_FLOOR, "x0": SURF_WALL_X0, "x1": SURF_WALL_X1, "y0": SURF_WALL_Y0,
            "y1": SURF_WALL_Y1}[dec.surface]
    if dec.surface == "floor":
        u, v = p[:, 0], p[:, 1]
    elif dec.surface in ("x0", "x1"):
        u, v = p[:, 1], p[:, 2]
    else:
        u, v = p[:, 0], p[:, 2]
    u0, v0, u1, v1 = dec.rect_m
    m = (s == surf) & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)
    if not m.any():
        return
    base = np.array(dec.colour_bgr, dtype=np.float64)
    uu, vv = u[m], v[m]
    col = np.repeat(base[None, :], uu.shape[0], axis=0)
    if dec.pattern == "stripes":
        col *= (0.85 + 0.15 * (np.sin(uu * 25.0) > 0))[:, None]
    elif dec.pattern == "frame":
        border = np.minimum.reduce([uu - u0, u1 - uu, vv - v0, v1 - vv]) < 0.04
        col[border] = (40, 45, 50)
        col[~border] *= (0.8 + 0.4 * tex.noise(uu[~border] * 6, vv[~border] * 6))[:, None]
    elif dec.pattern == "window":
        border = (np.minimum.reduce([uu - u0, u1 - uu, vv - v0, v1 - vv]) < 0.05) | (
            np.abs(uu - 0.5 * (u0 + u1)) < 0.025) | (np.abs(vv - 0.5 * (v0 + v1)) < 0.025)
        col[border] = (225, 228, 230)
    albedo[m] = col


class _Textures:
    """Procedural textures from world coordinates (fixed, seed-independent: the house looks the same)."""

    def __init__(self) -> None:
        self.grid = np.random.default_rng(20240305).random((64, 64))

    def noise(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Smooth value noise in 0..1 at (u, v) in grid cells (wraps every 64 cells)."""
        iu = np.floor(u).astype(np.int64)
        iv = np.floor(v).astype(np.int64)
        fu = u - iu
        fv = v - iv
        fu = fu * fu * (3 - 2 * fu)
        fv = fv * fv * (3 - 2 * fv)
        g = self.grid
        a = g[iv % 64, iu % 64]
        b = g[iv % 64, (iu + 1) % 64]
        c = g[(iv + 1) % 64, iu % 64]
        d = g[(iv + 1) % 64, (iu + 1) % 64]
        return (a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv

    def wood(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        width = 0.16
        row = np.floor(y / width).astype(np.int64)
        offset = _hash01(row, 7) * 1.4
        col = np.floor((x + offset) / 1.4).astype(np.int64)
        tone = 0.8 + 0.35 * _hash01(row * 131 + col, 3)
        grain = 0.88 + 0.24 * self.noise(x * 3.0 + row * 5.3, y * 40.0)
        seam = (np.mod(y, width) < 0.006) | (np.mod(x + offset, 1.4) < 0.006)
        base = np.array([70.0, 112.0, 160.0])
        col_bgr = base[None, :] * (tone * grain)[:, None]
        col_bgr[seam] *= 0.55
        return col_bgr

    def tiles(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        grout = (np.mod(x, 0.3) < 0.01) | (np.mod(y, 0.3) < 0.01)
        c = np.repeat(np.array([[128.0, 132.0, 136.0]]), x.shape[0], axis=0)
        c *= (0.9 + 0.2 * self.noise(x * 4, y * 4))[:, None]
        c[grout] = (90.0, 92.0, 95.0)
        return c

    def paint(self, along: np.ndarray, z: np.ndarray, surface: np.ndarray) -> np.ndarray:
        tint = {SURF_WALL_X0: (186, 204, 216), SURF_WALL_X1: (196, 206, 214), SURF_WALL_Y0: (180, 200, 214),
                SURF_WALL_Y1: (192, 210, 220)}
        base = np.zeros((surface.shape[0], 3))
        for code, bgr in tint.items():
            base[surface == code] = bgr
        m = 0.92 + 0.1 * self.noise(along * 1.5, z * 1.5) + 0.04 * self.noise(along * 14 + 17, z * 14 + 5)
        c = base * m[:, None]
        skirting = z < 0.08
        c[skirting] = (222.0, 224.0, 226.0)
        return c

    def fabric(self, p: np.ndarray, normal: np.ndarray, colour) -> np.ndarray:
        base = np.array(colour, dtype=np.float64)
        u = p[:, 0] * np.abs(normal[:, 1] + normal[:, 2]) + p[:, 1] * np.abs(normal[:, 0])
        v = p[:, 2] * (1 - np.abs(normal[:, 2])) + p[:, 1] * np.abs(normal[:, 2])
        m = 0.9 + 0.2 * self.noise(u * 12 + 3, v * 12 + 9)
        top = np.where(normal[:, 2] > 0.5, 1.08, 1.0)
        return base[None, :] * (m * top)[:, None]


def _hash01(a: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic hash of integers to [0, 1)."""
    h = (np.asarray(a, dtype=np.int64) * 73856093 + salt * 19349663) & 0xFFFFFFFF
    h = (h ^ (h >> 13)) * 1274126177 & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFF) / 65536.0
