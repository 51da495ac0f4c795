"""Foreground from a range camera: whatever stands nearer than the empty room.

A range camera (time of flight, a PMD sensor) measures each pixel's range,
``(H, W) uint16`` millimetres, 0 where it has no value. The background is the
empty room's range per pixel; a person is a surface nearer than it. What this
module adds to that:

* **Missing values.** A missing reading is never foreground by itself; one
  next to a nearer reading is taken as part of it
  (``fill_missing``: dark hair and black clothes drop out of a time-of-flight
  image). The background clip (:meth:`DepthSegmenter.learn`) is
  kept, up to ``clip_frames`` frames, and each pixel's background is the
  median of its valid readings, its spread the median absolute deviation
  (robust to the flying pixels at depth edges). A pixel that gave a value in
  fewer than ``min_valid_fraction`` of them (beyond the camera's range, a
  black or glass surface) has no background: any reading there is something
  nearer than the room and is foreground.
* **Flying pixels.** At a depth edge a time-of-flight pixel may read a
  mixture of the near and the far surface, nearer than the background but on
  no surface: a reading with no 8-neighbour within ``max(flying_mm, 3 *
  spread)`` of it is not foreground (``reject_flying``).
* **Range-dependent noise.** A pixel is foreground where it is nearer than its
  background by more than ``max(min_step_mm, noise_sigmas * spread)``, the
  spread at least ``floor_mm + floor_per_m_mm * range_m`` (noise grows with range).
* **Learning.** Live readings that look like background are learnt at
  ``alpha`` (default ``1 / window_frames``); readings farther than the
  background (something that stood in the empty-room clip has gone) are
  adopted at ``far_rate``; foreground pixels learn ``fg_rate_factor`` times
  slower (a chair moved nearer joins the background in minutes, a person
  sitting still stays foreground about ten times as long as the colour model
  keeps them); hold boxes are never learnt.
* **The range travels with the mask.** :attr:`DepthSegmenter.depth_mm` holds the
  last frame's foreground range at the mask size (``(h, w) uint16``, 0 where
  the mask is empty or where a mask pixel came from clean-up rather than
  from a nearer reading), for ``common.maskcodec.encode_depth``.

``mask_scale < 1`` picks pixels (nearest neighbour) rather than averaging:
averaging ranges across an edge invents surfaces that are not there.

Pure: no clock, no files, no network.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import cv2
import numpy as np

from camera_worker.segmentation import DEFAULT_MIN_AREA_PX, SegmenterBase, SegmentStats, _scaled_size, describe_frame

__all__ = ["DepthSegmenter"]

_GAP_KERNEL = cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3))


class DepthSegmenter(SegmenterBase):
    """Nearer-than-the-room foreground of a range camera, with its range, and hold regions.

    Frames: ``(H, W) uint16`` millimetres of range, 0 = no value, all of one size. Masks:
    ``(round(H*s), round(W*s)) uint8`` 0/255. Hold boxes: ``(x0, y0, x1, y1)`` full-resolution
    pixels, exclusive. Other parameters: see the module text.
    """

    def __init__(
        self,
        *,
        window_frames: int = 500,
        alpha: float | None = None,
        min_step_mm: float = 80.0,
        noise_sigmas: float = 4.0,
        floor_mm: float = 5.0,
        floor_per_m_mm: float = 6.0,
        min_valid_fraction: float = 0.1,
        far_rate: float = 0.1,
        fg_rate_factor: float = 0.1,
        clip_frames: int = 64,
        mask_scale: float = 1.0,
        open_px: int = 3,
        close_px: int = 7,
        min_area_px: int = DEFAULT_MIN_AREA_PX,
        fill_holes: bool = True,
        fill_missing: bool = True,
        reject_flying: bool = True,
        flying_mm: float = 150.0,
    ) -> None:
        super().__init__(window_frames=window_frames, alpha=alpha, mask_scale=mask_scale, open_px=open_px,
                         close_px=close_px, min_area_px=min_area_px, fill_holes=fill_holes)
        for name, value, lo, hi in (("min_step_mm", min_step_mm, 1.0, 2000.0), ("noise_sigmas", noise_sigmas, 0.0, 20.0),
                                    ("floor_mm", floor_mm, 0.0, 500.0), ("floor_per_m_mm", floor_per_m_mm, 0.0, 500.0),
                                    ("min_valid_fraction", min_valid_fraction, 0.0, 1.0), ("far_rate", far_rate, 0.0, 1.0),
                                    ("fg_rate_factor", fg_rate_factor, 0.0, 1.0), ("flying_mm", flying_mm, 1.0, 2000.0)):
            if not lo <= value <= hi:
                raise ValueError(f"{name} must lie in {lo:g}..{hi:g}, got {value!r}")
        if isinstance(clip_frames, bool) or not isinstance(clip_frames, int) or not 1 <= clip_frames <= 1000:
            raise ValueError(f"clip_frames must be an int in 1..1000, got {clip_frames!r}")
        self.min_step_mm = float(min_step_mm)
        self.noise_sigmas = float(noise_sigmas)
        self.floor_mm = float(floor_mm)
        self.floor_per_m_mm = float(floor_per_m_mm)
        self.min_valid_fraction = float(min_valid_fraction)
        self.far_rate = float(far_rate)
        self.fg_rate_factor = float(fg_rate_factor)
        self.clip_frames = clip_frames
        self.fill_missing = bool(fill_missing)
        self.reject_flying = bool(reject_flying)
        self.flying_mm = float(flying_mm)
        self.reset()

    # -- public ---------------------------------------------------------------

    def reset(self) -> None:
        """Forget the background."""
        super().reset()
        self._clip: list[np.ndarray] = []
        self._bg: np.ndarray | None = None        # background range, mm (float32, mask size; 0 = none)
        self._sigma: np.ndarray | None = None     # its spread, mm
        self._seen: np.ndarray | None = None      # how often the pixel gives a value, 0..1
        self.depth_mm: np.ndarray | None = None

    def background_mm(self) -> np.ndarray | None:
        """``(h, w) float32`` background range at mask size, 0 where there is none (None before a frame)."""
        self._finish_clip()
        if self._bg is None:
            return None
        return np.where(self._seen >= self.min_valid_fraction, self._bg, 0.0).astype(np.float32)

    def learn(self, frame: np.ndarray) -> None:
        """Learn one frame of a background clip (the empty room); the first ``clip_frames`` are
        kept for a robust median, later ones learnt as live background."""
        r = self._prepare(frame)
        rate = self._window_rate()
        self._frames += 1
        self._settled = True
        if self._bg is None and len(self._clip) < self.clip_frames:
            self._clip.append(r)
            return
        self._finish_clip()
        self._learn(r, np.zeros(r.shape, bool), [], rate)

    def apply(self, frame: np.ndarray, *, holds: Iterable[Sequence[int]] = (),
              learn: bool = True) -> tuple[np.ndarray, SegmentStats]:
        """Segment one frame and update the model; return ``(mask, stats)``; the foreground range
        is in :attr:`depth_mm` afterwards."""
        r = self._prepare(frame)
        boxes = self._mask_boxes(holds, r.shape)
        rate = self.next_learning_rate() if learn else 0.0
        self._finish_clip()
        first = self._bg is None
        if first:
            self._init_from([r])
        valid = r > 0
        known = self._seen >= self.min_valid_fraction
        thr = np.maximum(np.float32(self.min_step_mm), np.float32(self.noise_sigmas) * np.maximum(
            self._sigma, np.float32(self.floor_mm) + np.float32(self.floor_per_m_mm * 1e-3) * self._bg))
        raw = valid & (~known | (r < self._bg - thr))
        if self.reject_flying:
            raw &= _has_close_neighbour(r, np.maximum(np.float32(self.flying_mm), 3.0 * self._sigma))
        if first:
            raw[:] = False
        self._frames += 1
        if learn and not first:
            self._learn(r, raw, boxes, rate, thr)
        fg_raw = raw.astype(np.uint8) * np.uint8(255)
        if self.fill_missing:
            # a gap beside a nearer surface is most likely that surface (dark hair, black clothes)
            gaps = cv2.dilate(fg_raw, _GAP_KERNEL)
            gaps[valid] = 0
            fg_raw |= gaps
        mask, components = self._clean(fg_raw)
        depth = np.zeros(r.shape, np.uint16)
        ship = raw & (mask > 0)
        depth[ship] = np.rint(r[ship]).astype(np.uint16)
        self.depth_mm = depth
        return mask, self._plain_stats(rate, mask, fg_raw, components, len(boxes))

    # -- internals ------------------------------------------------------------

    def _prepare(self, frame: np.ndarray) -> np.ndarray:
        if not isinstance(frame, np.ndarray) or frame.dtype != np.uint16 or frame.ndim != 2:
            raise ValueError(f"range frame must be an (H, W) uint16 array of millimetres, got {describe_frame(frame)}")
        size = (int(frame.shape[1]), int(frame.shape[0]))
        self._adopt_size(size)
        if self.mask_scale != 1.0:
            frame = cv2.resize(frame, _scaled_size(size, self.mask_scale), interpolation=cv2.INTER_NEAREST)
        return frame.astype(np.float32)

    def _finish_clip(self) -> None:
        if self._clip and self._bg is None:
            self._init_from(self._clip)
            self._clip = []

    def _init_from(self, frames: list[np.ndarray]) -> None:
        """Background, spread and valid share from frames of the empty room (median and MAD of valid readings)."""
        stack = np.stack(frames).astype(np.float32)
        stack[stack <= 0] = np.nan
        seen = np.mean(np.isfinite(stack), axis=0).astype(np.float32)
        with np.errstate(all="ignore"):
            import warnings
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(stack, axis=0)
                mad = np.nanmedian(np.abs(stack - med[None]), axis=0) * 1.4826
        self._bg = np.nan_to_num(med, nan=0.0).astype(np.float32)
        self._sigma = np.nan_to_num(mad, nan=0.0).astype(np.float32)
        self._seen = seen

    def _learn(self, r: np.ndarray, raw: np.ndarray, boxes: list, rate: float, thr: np.ndarray | None = None) -> None:
        valid = r > 0
        free = np.ones(r.shape, bool)
        for x0, y0, x1, y1 in boxes:
            free[y0:y1, x0:x1] = False
        self._seen[free] += np.float32(rate) * (valid[free].astype(np.float32) - self._seen[free])
        upd = valid & free
        fresh = upd & (self._bg <= 0)
        self._bg[fresh] = r[fresh]
        upd &= ~fresh
        a = np.full(r.shape, np.float32(rate), np.float32)
        a[raw] *= np.float32(self.fg_rate_factor)
        if thr is not None:
            farther = r > self._bg + thr
            a[farther] = np.float32(max(self.far_rate, rate))
        d = r - self._bg
        self._bg[upd] += a[upd] * d[upd]
        bg = upd & ~raw
        # spread: a running mean absolute deviation (times 1.25: a Gaussian's sigma)
        self._sigma[bg] += np.float32(rate) * (1.2533 * np.abs(d[bg]) - self._sigma[bg])


def _has_close_neighbour(r: np.ndarray, tol_mm: np.ndarray) -> np.ndarray:
    """(h, w) bool: some 8-neighbour of the pixel reads within ``tol_mm`` of it. A reading on a
    surface has such neighbours; a flying pixel (a mixture of the near and the far surface at a
    depth edge) has none."""
    h, w = r.shape
    pad = np.pad(r, 1, mode="constant", constant_values=0.0)
    best = np.full((h, w), np.inf, np.float32)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy == 1 and dx == 1:
                continue
            nb = pad[dy:dy + h, dx:dx + w]
            diff = np.where(nb > 0, np.abs(nb - r), np.float32(np.inf))
            np.minimum(best, diff, out=best)
    return best <= tol_mm
