"""What real segmentation does to a true silhouette, for the randomised worlds' mask cameras.

A :class:`MaskFaults` per camera, drawn by :func:`random_faults`, says what
goes wrong in that camera; :func:`degrade` applies it to one frame's true
person mask:

* leftover shadows: part of each person's cast shadow on the floor (from the
  room's ceiling lamp, reaching at most 1.0 m from the feet) stays foreground,
  in blotches;
* ragged edges: the silhouette grows or shrinks by a pixel now and then;
* holes: clothing that matches the background punches holes in the body;
* specks: isolated noise pixels all over the image;
* clutter: a blob that is nobody (a curtain, a screen) in a fixed place for a
  stretch of the recording;
* a dark camera: for a few seconds the picture goes black: the first dark
  frame and the first frame back are all foreground (the background model
  sees everything change) and the frames between are empty;
* a time offset: the camera's frame ``i`` shows the world at frame ``i - lag``
  (applied where the silhouettes are rendered);
* a moved camera (:class:`CameraMove`): from frame ``first`` on the camera
  is rotated or shifted (a cleaner bumped it) while the site keeps its old
  calibration; applied where the silhouettes are rendered (the renderer
  draws through :meth:`CameraMove.apply`'s camera from then on). Never drawn
  by :func:`random_faults`: a test or an evaluation sets it on purpose.

Everything is a pure function of the faults, the frame index and the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.camera import Camera
from synth.body import Body

SHADOW_REACH_M = 1.0


@dataclass(frozen=True)
class Clutter:
    """A false blob: centre and radii as fractions of the image, frames ``[first, last)``."""

    cx: float
    cy: float
    rx: float
    ry: float
    first: int
    last: int


@dataclass(frozen=True)
class CameraMove:
    """A camera knocked out of place from frame ``first`` on: turned by ``rotation_deg`` about
    ``axis`` (camera frame: (0, 1, 0), the image's vertical axis, pans it; (1, 0, 0) tilts it)
    about its optical centre, then its centre moved by ``shift_m`` (world frame, metres)."""

    first: int
    rotation_deg: float = 0.0
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    shift_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if isinstance(self.first, bool) or not isinstance(self.first, (int, np.integer)) or self.first < 0:
            raise ValueError(f"first must be a frame index >= 0, got {self.first!r}")
        axis = np.asarray(self.axis, dtype=np.float64)
        if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
            raise ValueError(f"axis must be a non-zero 3-vector, got {self.axis!r}")
        shift = np.asarray(self.shift_m, dtype=np.float64)
        if shift.shape != (3,) or not np.all(np.isfinite(shift)) or not np.isfinite(self.rotation_deg):
            raise ValueError(f"rotation_deg and shift_m must be finite, got {self.rotation_deg!r}, {self.shift_m!r}")

    def apply(self, camera: Camera) -> Camera:
        """``camera`` as it stands after the move (same intrinsics, new pose)."""
        axis = np.asarray(self.axis, dtype=np.float64)
        rvec = axis / np.linalg.norm(axis) * np.radians(self.rotation_deg)
        turn, _ = cv2.Rodrigues(rvec.reshape(3, 1))
        R = turn @ camera.R
        centre = camera.center + np.asarray(self.shift_m, dtype=np.float64)
        return camera.with_pose(R, -R @ centre)

    def describe(self) -> str:
        parts = []
        if self.rotation_deg:
            parts.append(f"turned {self.rotation_deg:g} deg")
        if any(self.shift_m):
            parts.append(f"shifted {100 * float(np.linalg.norm(self.shift_m)):.0f} cm")
        return f"moved at frame {self.first} ({', '.join(parts) or 'not at all'})"


@dataclass(frozen=True)
class MaskFaults:
    """What goes wrong in one camera's masks (see the module text)."""

    shadow_keep: float = 0.0
    edge_noise: float = 0.0
    holes_per_person: float = 0.0
    specks: float = 0.0
    clutter: tuple[Clutter, ...] = ()
    dark: tuple[int, int] | None = None
    lag_frames: int = 0
    moved: CameraMove | None = None

    def describe(self) -> list[str]:
        """Short names of the faults present, for reports."""
        out = []
        if self.shadow_keep > 0:
            out.append("shadows")
        if self.holes_per_person > 0:
            out.append("holes")
        if self.specks > 0:
            out.append("specks")
        if self.clutter:
            out.append("clutter")
        if self.dark is not None:
            out.append("dark")
        if self.lag_frames:
            out.append(f"lag {self.lag_frames}")
        if self.moved is not None:
            out.append(self.moved.describe())
        return out


def random_faults(rng: np.random.Generator, cam_ids, n_frames: int, fps: float) -> dict[str, MaskFaults]:
    """Faults of every camera of a world: mild ones everywhere, and in some worlds one camera that
    goes dark for 2-6 s and one that runs 1-3 frames behind."""
    cam_ids = list(cam_ids)
    dark_cam = cam_ids[int(rng.integers(len(cam_ids)))] if rng.random() < 0.3 and n_frames > 4 * fps else None
    lag_cam = cam_ids[int(rng.integers(len(cam_ids)))] if rng.random() < 0.3 else None
    out = {}
    for cam in cam_ids:
        clutter = []
        for _ in range(int(rng.integers(0, 3)) if rng.random() < 0.4 else 0):
            first = int(rng.integers(0, max(1, n_frames - 1)))
            clutter.append(Clutter(float(rng.uniform(0.1, 0.9)), float(rng.uniform(0.1, 0.9)),
                                   float(rng.uniform(0.01, 0.05)), float(rng.uniform(0.02, 0.08)), first,
                                   int(min(n_frames, first + rng.integers(int(fps), max(int(fps) + 1, n_frames))))))
        dark = None
        if cam == dark_cam:
            length = int(rng.uniform(2, 6) * fps)
            first = int(rng.integers(0, max(1, n_frames - length)))
            dark = (first, first + length)
        out[cam] = MaskFaults(
            shadow_keep=float(rng.uniform(0.1, 0.6)) if rng.random() < 0.6 else 0.0,
            edge_noise=float(rng.uniform(0.0, 0.5)),
            holes_per_person=float(rng.uniform(0.0, 1.5)) if rng.random() < 0.5 else 0.0,
            specks=float(rng.uniform(0, 40)) if rng.random() < 0.5 else 0.0,
            clutter=tuple(clutter),
            dark=dark,
            lag_frames=int(rng.integers(1, 4)) if cam == lag_cam else 0,
        )
    return out


def degrade(labels: np.ndarray, faults: MaskFaults, frame: int, *, camera: Camera, bodies: list[Body],
            light_m, seed: int) -> np.ndarray:
    """One degraded mask (H, W) uint8 0/255 from the true person ids per pixel ``labels`` (H, W) uint8
    of ``camera`` (at the mask's size) showing ``bodies``."""
    h, w = labels.shape
    if faults.dark is not None and faults.dark[0] <= frame <= faults.dark[1]:
        full = frame in faults.dark
        return np.full((h, w), 255 if full else 0, dtype=np.uint8)
    rng = np.random.default_rng([seed, frame, 0xD1])
    mask = np.where(labels > 0, np.uint8(255), np.uint8(0))
    if faults.shadow_keep > 0 and bodies:
        shadow = _shadows(camera, bodies, light_m, (h, w))
        if shadow.any():
            blot = cv2.resize(rng.random((max(2, h // 16), max(2, w // 16))).astype(np.float32), (w, h),
                              interpolation=cv2.INTER_LINEAR)
            mask[(shadow > 0) & (blot < faults.shadow_keep)] = 255
    if faults.edge_noise > 0 and rng.random() < faults.edge_noise:
        kernel = np.ones((3, 3), np.uint8)
        mask = cv2.dilate(mask, kernel) if rng.random() < 0.5 else cv2.erode(mask, kernel)
    if faults.holes_per_person > 0:
        for pid in np.unique(labels[labels > 0]):
            for _ in range(int(rng.poisson(faults.holes_per_person))):
                ys, xs = np.nonzero(labels == pid)
                k = int(rng.integers(len(xs)))
                size = max(2, int(0.06 * (ys.max() - ys.min() + 1) * rng.uniform(0.4, 1.2)))
                cv2.ellipse(mask, (int(xs[k]), int(ys[k])), (size, max(1, int(size * rng.uniform(0.5, 1.5)))),
                            float(rng.uniform(0, 180)), 0, 360, 0, -1)
    for c in faults.clutter:
        if c.first <= frame < c.last:
            wobble = 1.0 + 0.15 * np.sin(frame * 0.4 + c.cx * 10)
            cv2.ellipse(mask, (int(c.cx * w), int(c.cy * h)), (max(1, int(c.rx * w * wobble)), max(1, int(c.ry * h))),
                        0.0, 0, 360, 255, -1)
    if faults.specks > 0:
        n = int(rng.poisson(faults.specks))
        if n:
            mask[rng.integers(0, h, n), rng.integers(0, w, n)] = 255
    return mask


def _shadows(camera: Camera, bodies: list[Body], light_m, size: tuple[int, int]) -> np.ndarray:
    """(H, W) uint8 255 where a body's floor shadow lies (people themselves included)."""
    h, w = size
    out = np.zeros((h, w), dtype=np.uint8)
    light = np.asarray(light_m, dtype=np.float64)
    for body in bodies:
        pts = (body.centers_m[:, None, :] + 0.7 * body.extents_m[:, None, :] * _CORNERS[None]).reshape(-1, 3)
        pts = pts[pts[:, 2] < light[2] - 0.2]
        if pts.shape[0] < 3:
            continue
        s = light[2] / (light[2] - pts[:, 2])
        floor = light[:2] + (pts[:, :2] - light[:2]) * s[:, None]
        feet = body.pelvis_m[:2]
        off = floor - feet
        n = np.linalg.norm(off, axis=1, keepdims=True)
        floor = feet + off * np.minimum(1.0, SHADOW_REACH_M / np.maximum(n, 1e-9))
        hull = cv2.convexHull(floor.astype(np.float32))[:, 0, :].astype(np.float64)
        uv, ok = camera.project(np.column_stack([hull, np.zeros(len(hull))]))
        if ok.sum() < 3 or not np.all(np.isfinite(uv[ok])):
            continue
        poly = np.round(uv[ok]).astype(np.int32)
        cv2.fillPoly(out, [cv2.convexHull(poly)], 255)
    return out


_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
