"""Camera models: world points to pixels and pixels to world rays.

Three models, all with the OpenCV camera frame (x right, y down, z forward)
and the world frame of the design (metres, right-handed, Z up, floor Z = 0):

* ``pinhole``: OpenCV pinhole with 4, 5, 8, 12 or 14 distortion coefficients
  ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]])``.
* ``fisheye``: OpenCV fisheye (equidistant) with ``(k1, k2, k3, k4)``.
* ``tsai``: Tsai's model as used by PETS 2009: radial distortion ``kappa1``
  applied in sensor millimetres, ``undistorted = distorted * (1 + kappa1 r^2)``
  with ``r`` the radius of the distorted sensor point; pixels
  ``u = sx * Xd / dpx + cx``, ``v = Yd / dpy + cy``.

Extrinsics: ``X_cam = R @ X_world + t`` with ``t`` in metres.

Pixel convention (OpenCV): integer coordinates are pixel centres, pixel
``[row i, column j]`` is centred on ``(u, v) = (j, i)`` and covers
``[j - 0.5, j + 0.5)``. ``project`` calls a point valid when it falls in the
hull of the pixel centres, ``0 <= u <= width - 1`` and ``0 <= v <= height - 1``,
so that rounding, flooring or truncating a valid ``uv`` all give an in-range
index; :func:`pixel_index` rounds to the nearest centre.

Strong barrel distortion (k1 around -0.37, as in real wide-angle lenses) is a
polynomial that turns back on itself: points far outside the field of view
would fold back into the image. Each camera computes once the largest
normalised radius ``tan(angle off the optical axis)`` over which its
distortion is monotonic (``max_radius``); ``project`` rejects points beyond it
and ``rays`` returns NaN for pixels that no point within it reaches (the
outer corners of such images). The fisheye model covers directions up to 90
degrees off the optical axis (in front of the camera plane); pixels of wider
lenses beyond that get NaN rays.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from common.memo import BytesMemo, kept_on_disk

MODELS = ("pinhole", "fisheye", "tsai")
PINHOLE_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
MIN_DEPTH_M = 1e-6

_ROT_TOL = 1e-6
RAYS_CACHE_BYTES = 256 * 2**20
"""At most this much of :meth:`Camera.pixel_rays` results is kept per process (the least recently
used go first): a renderer per camera per scenario asks again for the same rays, which take about
half a second per 640x480 camera to undistort."""
_rays = BytesMemo(RAYS_CACHE_BYTES)
_radii = BytesMemo(8 * 4096)   # lens (model, distortion, Tsai parameters) -> max_radius: a lens fit makes a
                               # new lens per step, so the 4096 most recent are kept


@dataclass(frozen=True)
class TsaiIntrinsics:
    """Tsai's intrinsic parameters (PETS 2009 naming).

    focal_mm: effective focal length f, millimetres.
    kappa1: radial distortion, 1/mm^2, ``undistorted = distorted * (1 + kappa1 r_d^2)``.
    dpx, dpy: sensor size of one pixel along x and y, millimetres per pixel
        (PETS' ``dpx`` already includes the ``ncx / nfx`` ratio).
    sx: horizontal scale uncertainty factor (dimensionless).
    cx, cy: principal point, pixels.
    """

    focal_mm: float
    kappa1: float
    dpx: float
    dpy: float
    sx: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("focal_mm", "kappa1", "dpx", "dpy", "sx", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise ValueError(f"TsaiIntrinsics.{name} must be a number, got {value!r}")
            if not np.isfinite(value):
                raise ValueError(f"TsaiIntrinsics.{name} must be finite, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("focal_mm", "dpx", "dpy", "sx"):
            if getattr(self, name) <= 0:
                raise ValueError(f"TsaiIntrinsics.{name} must be positive, got {getattr(self, name)!r}")

    def camera_matrix(self) -> np.ndarray:
        """(3, 3) float64: the linear part of the model as an OpenCV K (no distortion)."""
        return np.array(
            [[self.sx * self.focal_mm / self.dpx, 0.0, self.cx], [0.0, self.focal_mm / self.dpy, self.cy], [0.0, 0.0, 1.0]]
        )


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera. Immutable; arrays are read-only float64 copies.

    id: camera id (non-empty string).
    model: ``'pinhole'`` | ``'fisheye'`` | ``'tsai'``.
    width, height: image size, pixels.
    K: (3, 3) float64 camera matrix (for ``tsai``: ``tsai.camera_matrix()``).
    dist: (n,) float64 distortion: pinhole n in {0, 4, 5, 8, 12, 14}, fisheye n = 4, tsai n = 0.
    R: (3, 3) float64 rotation world -> camera.
    t: (3,) float64 translation, metres: ``X_cam = R @ X_world + t``.
    tsai: Tsai intrinsics when ``model == 'tsai'``, else None.
    """

    id: str
    model: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    tsai: TsaiIntrinsics | None = field(default=None)

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id:
            raise ValueError(f"id must be a non-empty string, got {self.id!r}")
        if self.model not in MODELS:
            raise ValueError(f"camera {self.id}: model must be one of {MODELS}, got {self.model!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"camera {self.id}: {name} must be a positive int, got {value!r}")
            object.__setattr__(self, name, int(value))
        K = _frozen_array(self.id, "K", self.K, (3, 3))
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
            raise ValueError(f"camera {self.id}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {K.tolist()}")
        dist = _frozen_array(self.id, "dist", np.asarray(self.dist, dtype=np.float64).ravel(), None)
        if self.model == "pinhole" and dist.size not in PINHOLE_DIST_LENGTHS:
            raise ValueError(f"camera {self.id}: pinhole dist must have 0, 4, 5, 8, 12 or 14 coefficients, got {dist.size}")
        if self.model == "fisheye" and dist.size != 4:
            raise ValueError(f"camera {self.id}: fisheye dist must have 4 coefficients (k1..k4), got {dist.size}")
        if self.model == "tsai":
            if dist.size != 0:
                raise ValueError(f"camera {self.id}: tsai dist must be empty (distortion is tsai.kappa1), got {dist.size} values")
            if not isinstance(self.tsai, TsaiIntrinsics):
                raise ValueError(f"camera {self.id}: tsai model needs tsai=TsaiIntrinsics(...), got {self.tsai!r}")
            if not np.allclose(K, self.tsai.camera_matrix(), rtol=1e-9, atol=1e-9):
                raise ValueError(f"camera {self.id}: K must equal tsai.camera_matrix() for the tsai model")
        elif self.tsai is not None:
            raise ValueError(f"camera {self.id}: tsai intrinsics given for model {self.model!r}")
        R = _frozen_array(self.id, "R", self.R, (3, 3))
        if np.abs(R @ R.T - np.eye(3)).max() > _ROT_TOL or np.linalg.det(R) < 0:
            raise ValueError(f"camera {self.id}: R must be a rotation (orthonormal, det +1), got {R.tolist()}")
        t = _frozen_array(self.id, "t", np.asarray(self.t, dtype=np.float64).ravel(), (3,))
        for name, value in (("K", K), ("dist", dist), ("R", R), ("t", t)):
            object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ constructors

    @classmethod
    def pinhole(
        cls,
        cam_id: str,
        width: int,
        height: int,
        *,
        fx: float | None = None,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        hfov_deg: float | None = None,
        dist=(),
        R=None,
        t=None,
    ) -> "Camera":
        """A pinhole camera. Give ``fx`` (pixels) or ``hfov_deg``; ``fy`` defaults to ``fx``,
        the principal point to the image centre ``((width - 1) / 2, (height - 1) / 2)``.
        ``R, t`` default to the identity pose (use :func:`look_at`)."""
        K = _make_K(width, height, fx, fy, cx, cy, hfov_deg, fisheye=False)
        return cls(id=cam_id, model="pinhole", width=width, height=height, K=K, dist=np.asarray(dist, dtype=np.float64),
                   R=np.eye(3) if R is None else R, t=np.zeros(3) if t is None else t)

    @classmethod
    def fisheye(
        cls,
        cam_id: str,
        width: int,
        height: int,
        *,
        fx: float | None = None,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        hfov_deg: float | None = None,
        dist=(0.0, 0.0, 0.0, 0.0),
        R=None,
        t=None,
    ) -> "Camera":
        """An OpenCV fisheye camera, ``dist = (k1, k2, k3, k4)``. Give ``fx`` (pixels) or
        ``hfov_deg`` (equidistant: ``fx = (width / 2) / (hfov / 2)`` in radians, ignoring k)."""
        K = _make_K(width, height, fx, fy, cx, cy, hfov_deg, fisheye=True)
        return cls(id=cam_id, model="fisheye", width=width, height=height, K=K, dist=np.asarray(dist, dtype=np.float64),
                   R=np.eye(3) if R is None else R, t=np.zeros(3) if t is None else t)

    @classmethod
    def from_tsai(cls, cam_id: str, width: int, height: int, tsai: TsaiIntrinsics, *, R=None, t=None) -> "Camera":
        """A Tsai-model camera (``t`` in metres)."""
        return cls(id=cam_id, model="tsai", width=width, height=height, K=tsai.camera_matrix(), dist=np.zeros(0),
                   R=np.eye(3) if R is None else R, t=np.zeros(3) if t is None else t, tsai=tsai)

    # ------------------------------------------------------------------ geometry

    @property
    def center(self) -> np.ndarray:
        """(3,) float64 optical centre in the world frame, metres: ``-R^T t``."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> np.ndarray:
        """(3,) float64 unit optical axis direction in the world frame."""
        return self.R[2].copy()

    @cached_property
    def max_radius(self) -> float:
        """Largest normalised radius ``sqrt(x^2 + y^2) / z`` (camera frame) over which the
        distortion is monotonic; ``inf`` when it is monotonic everywhere in front. Depends on the
        lens alone: computed once per lens in a process (a search over a million directions)."""
        lens = (self.model, self.dist.tobytes(), repr(self.tsai))
        return _radii.get(lens, lambda: _max_radius(self), lambda radius: 8)

    def project(self, points_w) -> tuple[np.ndarray, np.ndarray]:
        """World points to pixels.

        points_w: (N, 3) world frame, metres.
        Returns ``uv`` (N, 2) float64 pixels and ``valid`` (N,) bool: in front of the camera
        (z_cam > 1e-6 m), within ``max_radius`` and inside ``[0, width-1] x [0, height-1]``.
        ``uv`` is NaN for points behind the camera or beyond ``max_radius`` and the
        (out-of-image) projection for the others.
        """
        pts = _as_points(points_w, 3, "points_w")
        return self.project_cam(pts @ self.R.T + self.t)

    def project_cam(self, points_c) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`project` for (N, 3) points already in the camera frame (metres)."""
        pc = _as_points(points_c, 3, "points_c")
        z = pc[:, 2]
        front = z > MIN_DEPTH_M
        zs = np.where(front, z, 1.0)
        x = pc[:, 0] / zs
        y = pc[:, 1] / zs
        inside = front & (x * x + y * y <= self.max_radius**2)
        with np.errstate(all="ignore"):
            u, v = self._normalised_to_pixel(np.where(inside, x, 0.0), np.where(inside, y, 0.0))
        u = np.where(inside, u, np.nan)
        v = np.where(inside, v, np.nan)
        valid = inside & (u >= 0) & (u <= self.width - 1) & (v >= 0) & (v <= self.height - 1)
        return np.stack([u, v], axis=1), valid

    def rays(self, uv) -> np.ndarray:
        """Pixels to world ray directions.

        uv: (N, 2) pixels. Returns (N, 3) float64 unit vectors in the world frame (rays start at
        :attr:`center`); rows are NaN for pixels no point within ``max_radius`` projects to.
        """
        return self.rays_cam(uv) @ self.R

    def rays_cam(self, uv) -> np.ndarray:
        """Like :meth:`rays` in the camera frame: (N, 3) float64 unit vectors, z > 0."""
        pix = _as_points(uv, 2, "uv")
        with np.errstate(all="ignore"):
            x, y, ok = self._pixel_to_normalised(pix[:, 0], pix[:, 1])
            d = np.stack([x, y, np.ones_like(x)], axis=1)
            d /= np.linalg.norm(d, axis=1, keepdims=True)
        d[~ok] = np.nan
        return d

    def pixel_rays(self) -> np.ndarray:
        """(height, width, 3) float32 world ray directions through every pixel centre
        (``[i, j]`` through ``(u, v) = (j, i)``); NaN where :meth:`rays` is NaN. A fresh array
        each call; the values are kept for the next camera with the same :meth:`fingerprint`
        (:data:`RAYS_CACHE_BYTES`), and shared with other processes through
        :func:`common.memo.kept_on_disk`."""
        key = self.fingerprint()
        return _rays.get(key, lambda: kept_on_disk("pixel-rays", key, self._pixel_rays, lambda r: {"rays": r},
                                                   lambda stored: stored["rays"]), lambda r: r.nbytes).copy()

    def fingerprint(self) -> tuple:
        """A hashable value equal for cameras of the same model, size, lens, orientation and position (the
        key under which what is computed once per camera is kept)."""
        return (self.model, self.width, self.height, self.K.tobytes(), self.dist.tobytes(), self.R.tobytes(),
                self.t.tobytes(), repr(self.tsai))

    def _pixel_rays(self) -> np.ndarray:
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        uv = np.stack([u.ravel(), v.ravel()], axis=1)
        rays = self.rays(uv).reshape(self.height, self.width, 3).astype(np.float32)
        rays.setflags(write=False)
        return rays

    # ------------------------------------------------------------------ derived cameras

    def with_world(self, R_new_old, t_new_old, scale: float = 1.0) -> "Camera":
        """The same camera expressed in another world frame.

        The new frame is related to the current one by ``X_new = scale * R_new_old @ X_old + t_new_old``
        (``scale`` converts the current length unit to metres when ``t`` was not in metres).
        Then ``X_cam = R R_no^T (X_new - t_no) / scale + t`` in old units, i.e. in metres
        ``X_cam = R' X_new + t'`` with ``R' = R R_no^T`` and ``t' = scale * t - R' t_no``.
        """
        A = np.asarray(R_new_old, dtype=np.float64)
        b = np.asarray(t_new_old, dtype=np.float64).ravel()
        if A.shape != (3, 3) or np.abs(A @ A.T - np.eye(3)).max() > _ROT_TOL or np.linalg.det(A) < 0:
            raise ValueError(f"R_new_old must be a (3, 3) rotation, got {A.tolist()}")
        if b.shape != (3,) or not np.all(np.isfinite(b)):
            raise ValueError(f"t_new_old must be a finite (3,) vector, got {b.tolist()}")
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError(f"scale must be a positive finite number, got {scale!r}")
        R2 = self.R @ A.T
        return self._replace(R=R2, t=scale * self.t - R2 @ b)

    def with_pose(self, R, t) -> "Camera":
        """The same intrinsics with a new world->camera pose ``(R, t)`` (metres)."""
        return self._replace(R=R, t=t)

    def with_distortion(self, dist) -> "Camera":
        """The same camera with the distortion coefficients ``dist`` (its model's, see the class text)."""
        return self._replace(dist=np.asarray(dist, dtype=np.float64))

    def with_focal_scale(self, scale: float) -> "Camera":
        """The same camera with its focal length (``fx``, ``fy`` and the skew) times ``scale``, the principal
        point kept: every pixel moves ``scale`` times as far from it. Not for ``tsai`` lenses."""
        if scale == 1.0:
            return self
        if self.model == "tsai":
            raise ValueError(f"camera {self.id}: a tsai lens's focal length is its focal_mm, not K")
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError(f"scale must be a positive finite number, got {scale!r}")
        K = self.K.copy()
        K[:2, :2] *= scale
        return self._replace(K=K)

    def resized(self, width: int, height: int) -> "Camera":
        """The camera for the image resized to ``width x height`` (as ``cv2.resize(img, (width, height))``).

        With pixel centres on integers, ``u' = sx (u + 0.5) - 0.5`` where ``sx = width / self.width``.
        Distortion coefficients act on normalised coordinates and do not change.
        """
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        sx = width / self.width
        sy = height / self.height
        if self.model == "tsai":
            ts = self.tsai
            tsai = TsaiIntrinsics(focal_mm=ts.focal_mm, kappa1=ts.kappa1, dpx=ts.dpx / sx, dpy=ts.dpy / sy, sx=ts.sx,
                                  cx=sx * (ts.cx + 0.5) - 0.5, cy=sy * (ts.cy + 0.5) - 0.5)
            return self._replace(width=int(width), height=int(height), K=tsai.camera_matrix(), tsai=tsai)
        S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
        return self._replace(width=int(width), height=int(height), K=S @ self.K)

    def scaled(self, sx: float, sy: float | None = None) -> "Camera":
        """The camera for the image scaled by ``sx`` (and ``sy``, default ``sx``): the new size is
        ``round(width * sx) x round(height * sy)`` and the exact scale is new size / old size."""
        sy = sx if sy is None else sy
        if not (np.isfinite(sx) and sx > 0 and np.isfinite(sy) and sy > 0):
            raise ValueError(f"scale factors must be positive, got sx={sx!r}, sy={sy!r}")
        return self.resized(max(1, int(round(self.width * sx))), max(1, int(round(self.height * sy))))

    # ------------------------------------------------------------------ model internals

    def _replace(self, **changes) -> "Camera":
        fields = dict(id=self.id, model=self.model, width=self.width, height=self.height, K=self.K, dist=self.dist,
                      R=self.R, t=self.t, tsai=self.tsai)
        fields.update(changes)
        return Camera(**fields)

    def _normalised_to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates (x/z, y/z) -> pixels."""
        if self.model == "tsai":
            return _tsai_project(self.tsai, x, y)
        if self.model == "fisheye":
            xd, yd = _fisheye_distort(self.dist, x, y)
        else:
            xd, yd = pinhole_distort(self.dist, x, y)
        K = self.K
        return K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]

    def _pixel_to_normalised(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels -> undistorted normalised (x, y) and a bool mask of pixels with a valid preimage."""
        if self.model == "tsai":
            return _tsai_unproject(self.tsai, u, v, self.max_radius)
        K = self.K
        yd = (v - K[1, 2]) / K[1, 1]
        xd = (u - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        if self.model == "fisheye":
            return _fisheye_undistort(self.dist, xd, yd, self.max_radius)
        return _pinhole_undistort(self.dist, xd, yd, self.max_radius)


class MaskCameras:
    """A site's cameras (camera id -> full-resolution camera), each resized to the masks it gets:
    a resized camera is built once per mask size, not once per frame."""

    def __init__(self, cameras: Mapping[str, Camera]) -> None:
        self.cameras = dict(cameras)
        self._sized: dict[tuple[str, int, int], Camera] = {}

    def sized(self, masks: Mapping[str, np.ndarray]) -> dict[str, Camera]:
        """Camera id -> the camera at its mask's size, for the masks of this site's cameras."""
        out = {}
        for c, m in masks.items():
            if c not in self.cameras:
                continue
            h, w = np.shape(m)
            key = (c, w, h)
            if key not in self._sized:
                cam = self.cameras[c]
                self._sized[key] = cam if (cam.width, cam.height) == (w, h) else cam.resized(w, h)
            out[c] = self._sized[key]
        return out


def look_at(center, target, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World->camera ``(R, t)`` for a camera at ``center`` looking at ``target`` (world, metres).

    Camera z points at the target, x to the right and y down in the image, with the image
    "up" along the projection of ``up``. Raises ValueError when the view direction is
    parallel to ``up`` or ``center == target``.
    """
    c = np.asarray(center, dtype=np.float64).ravel()
    z = np.asarray(target, dtype=np.float64).ravel() - c
    u = np.asarray(up, dtype=np.float64).ravel()
    if c.shape != (3,) or z.shape != (3,) or u.shape != (3,):
        raise ValueError("center, target and up must be 3-vectors")
    nz = np.linalg.norm(z)
    if nz == 0:
        raise ValueError("center and target must differ")
    z /= nz
    x = np.cross(z, u)
    nx = np.linalg.norm(x)
    if nx < 1e-9 * max(np.linalg.norm(u), 1e-300):
        raise ValueError(f"up {u.tolist()} is parallel to the view direction {z.tolist()}")
    x /= nx
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ c


def pixel_index(uv) -> np.ndarray:
    """(N, 2) pixels -> (N, 2) int64 ``(column, row)`` of the nearest pixel centre.

    For points ``project`` calls valid the result is always inside the image.
    """
    return np.rint(_as_points(uv, 2, "uv")).astype(np.int64)


def rodrigues_to_matrix(rvec) -> np.ndarray:
    """(3,) Rodrigues rotation vector -> (3, 3) float64 rotation matrix."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return R


def matrix_to_rodrigues(R) -> np.ndarray:
    """(3, 3) rotation matrix -> (3,) float64 Rodrigues vector."""
    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64).reshape(3, 3))
    return rvec.ravel()


# ---------------------------------------------------------------------- helpers


def _frozen_array(cam_id: str, name: str, value, shape) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"camera {cam_id}: {name} must be numeric, got {value!r}") from None
    if shape is not None and arr.shape != shape:
        raise ValueError(f"camera {cam_id}: {name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"camera {cam_id}: {name} must be finite, got {arr.tolist()}")
    arr.setflags(write=False)
    return arr


def _as_points(value, dim: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {arr.shape}")
    return arr


def _make_K(width, height, fx, fy, cx, cy, hfov_deg, *, fisheye: bool) -> np.ndarray:  # noqa: N802 - K, the camera matrix
    if (fx is None) == (hfov_deg is None):
        raise ValueError("give exactly one of fx and hfov_deg")
    if fx is None:
        if not 0 < hfov_deg < (360 if fisheye else 180):
            raise ValueError(f"hfov_deg out of range: {hfov_deg!r}")
        half = np.radians(hfov_deg) / 2
        fx = (width / 2) / (half if fisheye else np.tan(half))
    fy = fx if fy is None else fy
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def pinhole_distort(dist: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distortion (as in cv::projectPoints) on normalised coordinates."""
    if dist.size == 0 or not np.any(dist):
        return x, y
    k = np.zeros(14)
    k[: dist.size] = dist
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y = k
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    # The polynomials below, evaluated in place (the same operations in the same order, so the same
    # bits as the plain expressions in the comments, without a temporary array per operation).
    r2 = x * x
    r2 += y * y                                 # r2 = x^2 + y^2
    radial = _horner(r2, (1.0, k1, k2, k3))     # radial = 1 + r2 (k1 + r2 (k2 + r2 k3))
    if k4 or k5 or k6:
        radial /= _horner(r2, (1.0, k4, k5, k6))
    xy2 = 2 * x
    xy2 *= y                                    # xy2 = 2 x y
    t = np.multiply(x, x)
    t *= 2
    t += r2
    t *= p2
    xd = x * radial
    xd += np.multiply(xy2, p1)
    xd += t                                     # xd = x radial + p1 xy2 + p2 (r2 + 2 x^2)
    np.multiply(y, y, out=t)
    t *= 2
    t += r2
    t *= p1
    yd = y * radial
    yd += t
    yd += np.multiply(xy2, p2)                  # yd = y radial + p1 (r2 + 2 y^2) + p2 xy2
    if s1 or s2 or s3 or s4:
        r4 = r2 * r2
        xd = xd + s1 * r2 + s2 * r4
        yd = yd + s3 * r2 + s4 * r4
    if tau_x != 0 or tau_y != 0:
        T = _tilt_matrix(tau_x, tau_y)
        a = T[0, 0] * xd + T[0, 1] * yd + T[0, 2]
        b = T[1, 0] * xd + T[1, 1] * yd + T[1, 2]
        c = T[2, 0] * xd + T[2, 1] * yd + T[2, 2]
        inv = np.where(c != 0, 1.0 / np.where(c != 0, c, 1.0), 1.0)
        xd, yd = a * inv, b * inv
    return xd, yd


def _horner(r2: np.ndarray, c: tuple) -> np.ndarray:
    """``c0 + r2 (c1 + r2 (c2 + r2 c3))``, a new array."""
    out = r2 * c[3]
    for coef in (c[2], c[1]):
        out += coef
        out *= r2
    out += c[0]
    return out


def _tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's tilted-sensor projection matrix (cv::detail::computeTiltProjectionMatrix)."""
    cx, sx = np.cos(tau_x), np.sin(tau_x)
    cy, sy = np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]])
    rot_y = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]])
    rot_xy = rot_y @ rot_x
    proj_z = np.array([[rot_xy[2, 2], 0, -rot_xy[0, 2]], [0, rot_xy[2, 2], -rot_xy[1, 2]], [0, 0, 1]])
    return proj_z @ rot_xy


def _pinhole_undistort(dist, xd, yd, max_radius) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Invert :func:`pinhole_distort`: OpenCV's fixed-point start, then Newton steps with a
    numerical Jacobian so that the result reprojects to ~1e-12 (normalised units)."""
    if dist.size == 0 or not np.any(dist):
        return xd, yd, np.isfinite(xd) & np.isfinite(yd)
    src = np.stack([xd, yd], axis=1).reshape(-1, 1, 2)
    fin = np.all(np.isfinite(src), axis=2)
    src = np.where(fin[..., None], src, 0.0)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
    start = cv2.undistortPoints(src, np.eye(3), dist, criteria=criteria).reshape(-1, 2)
    x, y = start[:, 0].copy(), start[:, 1].copy()
    xd_all, yd_all = np.broadcast_to(xd, x.shape), np.broadcast_to(yd, y.shape)
    h = 1e-7
    todo = np.arange(x.size)   # points still being refined: a point whose distortion is exact is done
    for _ in range(8):
        xa, ya, xt, yt = x[todo], y[todo], xd_all[todo], yd_all[todo]
        fx, fy = pinhole_distort(dist, xa, ya)
        ex, ey = fx - xt, fy - yt
        exact = (ex == 0.0) & (ey == 0.0)
        if exact.any():
            todo, xa, ya, ex, ey = todo[~exact], xa[~exact], ya[~exact], ex[~exact], ey[~exact]
            if not todo.size:
                break
        ax, ay = pinhole_distort(dist, xa + h, ya)
        bx, by = pinhole_distort(dist, xa - h, ya)
        cx_, cy_ = pinhole_distort(dist, xa, ya + h)
        dx_, dy_ = pinhole_distort(dist, xa, ya - h)
        j11, j21 = (ax - bx) / (2 * h), (ay - by) / (2 * h)
        j12, j22 = (cx_ - dx_) / (2 * h), (cy_ - dy_) / (2 * h)
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) > 1e-12, det, np.nan)
        x[todo] = xa - (j22 * ex - j12 * ey) / det
        y[todo] = ya - (-j21 * ex + j11 * ey) / det
    fx, fy = pinhole_distort(dist, x, y)
    ok = (
        fin.ravel()
        & np.isfinite(x)
        & np.isfinite(y)
        & (np.hypot(fx - xd, fy - yd) < 1e-9)
        & (x * x + y * y <= max_radius**2 * (1 + 1e-9))
    )
    return x, y, ok


def _fisheye_theta_d(dist: np.ndarray, theta: np.ndarray) -> np.ndarray:
    t2 = theta * theta
    k1, k2, k3, k4 = dist
    return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def _fisheye_distort(dist, x, y) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV fisheye: ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``, ``x' = theta_d / r * x``."""
    r = np.hypot(x, y)
    theta = np.arctan(r)
    scale = np.where(r > 1e-15, _fisheye_theta_d(dist, theta) / np.where(r > 1e-15, r, 1.0), 1.0)
    return x * scale, y * scale


def _fisheye_undistort(dist, xd, yd, max_radius) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Invert :func:`_fisheye_distort` by Newton on theta (monotonic on [0, theta_max])."""
    theta_d = np.hypot(xd, yd)
    theta_max = np.arctan(max_radius)
    k1, k2, k3, k4 = dist
    theta = np.minimum(theta_d, theta_max)
    for _ in range(30):
        t2 = theta * theta
        f = _fisheye_theta_d(dist, theta) - theta_d
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        theta = np.clip(theta - f / np.where(df > 1e-12, df, 1e-12), 0.0, theta_max)
    residual = np.abs(_fisheye_theta_d(dist, theta) - theta_d)
    r = np.tan(theta)
    scale = np.where(theta_d > 1e-15, r / np.where(theta_d > 1e-15, theta_d, 1.0), 1.0)
    ok = np.isfinite(theta_d) & (residual < 1e-12) & (theta < np.pi / 2)
    return xd * scale, yd * scale, ok


def _tsai_project(ts: TsaiIntrinsics, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised (x, y) -> pixels, solving ``r_u = r_d (1 + kappa1 r_d^2)`` for r_d."""
    xu = ts.focal_mm * x
    yu = ts.focal_mm * y
    ru = np.hypot(xu, yu)
    rd = _tsai_distorted_radius(ts.kappa1, ru)
    scale = np.where(ru > 1e-300, rd / np.where(ru > 1e-300, ru, 1.0), 1.0)
    xd = xu * scale
    yd = yu * scale
    return ts.sx * xd / ts.dpx + ts.cx, yd / ts.dpy + ts.cy


def _tsai_distorted_radius(k: float, ru: np.ndarray) -> np.ndarray:
    """Solve ``rd + k rd^3 = ru`` for the root on the monotonic branch (rd >= 0)."""
    if k == 0:
        return ru.copy()
    if k > 0:
        # Cardano for rd^3 + p rd + q = 0 with p = 1/k > 0, q = -ru/k: one real root.
        p = 1.0 / k
        q = -ru / k
        a = np.cbrt(-q / 2 + np.sqrt((q / 2) ** 2 + (p / 3) ** 3))
        rd = a - p / (3 * a)
    else:
        rd = ru.copy()  # Newton from rd = ru climbs monotonically to the root below 1/sqrt(-3k)
    for _ in range(3 if k > 0 else 40):
        rd = rd - (rd + k * rd**3 - ru) / (1 + 3 * k * rd**2)
    return rd


def _tsai_unproject(ts: TsaiIntrinsics, u, v, max_radius) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels -> undistorted normalised (x, y): closed form."""
    xd = ts.dpx * (u - ts.cx) / ts.sx
    yd = ts.dpy * (v - ts.cy)
    r2 = xd * xd + yd * yd
    factor = 1 + ts.kappa1 * r2
    x = xd * factor / ts.focal_mm
    y = yd * factor / ts.focal_mm
    ok = np.isfinite(x) & np.isfinite(y)
    if ts.kappa1 < 0:
        ok &= r2 <= 1.0 / (-3.0 * ts.kappa1)
    return x, y, ok


def _max_radius(cam: Camera) -> float:
    """First normalised radius where the distorted radius stops growing, over all directions."""
    if cam.model == "tsai":
        k = cam.tsai.kappa1
        if k >= 0:
            return float("inf")
        rd = 1.0 / np.sqrt(-3.0 * k)
        return float(rd * (1 + k * rd * rd) / cam.tsai.focal_mm)
    if cam.model == "fisheye":
        theta = np.linspace(0.0, np.pi / 2, 20001)[:-1]
        td = _fisheye_theta_d(cam.dist, theta)
        stop = np.nonzero(np.diff(td) <= 0)[0]
        return float(np.tan(theta[stop[0]])) if stop.size else float("inf")
    if cam.dist.size == 0 or not np.any(cam.dist):
        return float("inf")
    theta = np.linspace(0.0, np.radians(89.5), 4001)
    r = np.tan(theta)
    phi = np.linspace(0.0, 2 * np.pi, 256, endpoint=False)
    x = np.cos(phi)[:, None] * r[None, :]
    y = np.sin(phi)[:, None] * r[None, :]
    with np.errstate(all="ignore"):
        xd, yd = pinhole_distort(cam.dist, x, y)
        s = np.hypot(xd, yd)
        grows = np.diff(s, axis=1) > 0
    bad = ~grows
    if not bad.any():
        return float("inf")
    first = np.where(bad.any(axis=1), bad.argmax(axis=1), r.size - 1)
    return float(r[first.min()])
