"""Foreground from a thermal camera: people are warmer than the room.

A per-pixel background model (mean and spread of each pixel's reading) with
what a thermal view needs:

* **Input.** Radiometric ``(H, W) uint16`` frames (centi-kelvin by default,
  ``units_per_k = 100``) or 8-bit views (``(H, W)`` or grey ``(H, W, 3)``
  ``uint8``; ``units_per_k`` defaults to 255 / 25, a 25 K span over the 256
  levels, as :func:`synth.sensors.agc8` with a fixed 15-40 C span gives).
  The model works in kelvin from there on.
* **The room drifts, people do not join it.** Heating and cooling move every
  surface of a room together. Each frame, the reading is compared with
  ``gain * background + offset``, the two fitted robustly (least squares over
  the pixels that look like background, twice, the second time without the
  outliers) on a coarse grid outside the hold boxes; radiometric input fits the
  offset only (``fit_gain=False``), an 8-bit view whose automatic gain moves
  fits both. A pixel is foreground where it is warmer than that prediction by
  more than ``max(min_contrast_k, noise_sigmas * its spread)``.
* **Learning.** A background clip of the empty room is learnt first with
  :meth:`learn` (rate ``1/n``); live frames then learn at ``alpha`` (default
  ``1 / window_frames``) where they show background, and follow the fitted
  drift everywhere. Foreground pixels learn ``fg_rate_factor`` times slower
  (a heater switched on joins the background in minutes; a person sitting
  still stays foreground about ten times as long as the colour model keeps
  them) and hold boxes (tracked still people, as the colour segmenter's)
  follow the drift only: a held person is never learnt in.
* **Clean-up** as :class:`~camera_worker.segmentation.ForegroundSegmenter`:
  opening, closing, small components dropped, holes filled, sizes given for a
  640x480 frame and scaled to the frames' own size; ``mask_scale`` reduces the
  frame (area averaging) first.

Pure: no clock, no files, no network.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import cv2
import numpy as np

from camera_worker.segmentation import DEFAULT_MIN_AREA_PX, SegmenterBase, SegmentStats, _scaled_size, describe_frame

__all__ = ["ThermalSegmenter", "UNITS_PER_K_8BIT", "UNITS_PER_K_16BIT"]

UNITS_PER_K_16BIT = 100.0
"""Radiometric 16-bit frames are centi-kelvin unless told otherwise."""
UNITS_PER_K_8BIT = 255.0 / 25.0
"""8-bit views span 25 K over 256 levels unless told otherwise."""
_FIT_STEP = 4                 # drift fitted on every 4th pixel of every 4th row
_MIN_SIGMA_K = 0.03
_INITIAL_SIGMA_K = 0.15       # spread of a pixel before anything is known


class ThermalSegmenter(SegmenterBase):
    """Warmer-than-the-room foreground with a drifting per-pixel background and hold regions.

    Frames: ``(H, W) uint16`` radiometric, or ``(H, W)`` / ``(H, W, 3)`` ``uint8`` views, all of one
    size and type. Masks: ``(round(H*s), round(W*s)) uint8`` 0/255, ``s = mask_scale``. Hold
    boxes: ``(x0, y0, x1, y1)`` full-resolution pixels, exclusive. ``min_contrast_k``: the least
    excess over the background, kelvin, that is foreground; ``noise_sigmas``: the excess in units
    of the pixel's learnt spread. ``fg_rate_factor``: foreground pixels learn at this fraction of
    the rate. ``units_per_k``: frame units per kelvin (None: 100 for 16-bit, 255/25 for 8-bit).
    ``fit_gain``: fit a gain besides the offset (None: only for 8-bit input).
    """

    def __init__(
        self,
        *,
        window_frames: int = 500,
        alpha: float | None = None,
        min_contrast_k: float = 1.5,
        noise_sigmas: float = 5.0,
        fg_rate_factor: float = 0.1,
        units_per_k: float | None = None,
        fit_gain: bool | None = None,
        mask_scale: float = 1.0,
        open_px: int = 3,
        close_px: int = 7,
        min_area_px: int = DEFAULT_MIN_AREA_PX,
        fill_holes: bool = True,
    ) -> None:
        super().__init__(window_frames=window_frames, alpha=alpha, mask_scale=mask_scale, open_px=open_px,
                         close_px=close_px, min_area_px=min_area_px, fill_holes=fill_holes)
        if not 0.05 <= min_contrast_k <= 30.0:
            raise ValueError(f"min_contrast_k must lie in 0.05..30 K, got {min_contrast_k!r}")
        if not 0.0 <= noise_sigmas <= 20.0:
            raise ValueError(f"noise_sigmas must lie in 0..20, got {noise_sigmas!r}")
        if not 0.0 <= fg_rate_factor <= 1.0:
            raise ValueError(f"fg_rate_factor must lie in 0..1, got {fg_rate_factor!r}")
        if units_per_k is not None and not units_per_k > 0:
            raise ValueError(f"units_per_k must be > 0, got {units_per_k!r}")
        self.min_contrast_k = float(min_contrast_k)
        self.noise_sigmas = float(noise_sigmas)
        self.fg_rate_factor = float(fg_rate_factor)
        self.units_per_k = units_per_k
        self.fit_gain = fit_gain
        self.reset()

    # -- public ---------------------------------------------------------------

    def reset(self) -> None:
        """Forget the background."""
        super().reset()
        self._mean: np.ndarray | None = None     # background, kelvin (mask size)
        self._var: np.ndarray | None = None      # spread squared, kelvin squared
        self._last_fg: np.ndarray | None = None
        self.drift = (1.0, 0.0)                  # last fitted (gain, offset kelvin)

    def background_k(self) -> np.ndarray | None:
        """The background at mask size, ``(h, w) float32`` in the frames' kelvin scale (None before a frame)."""
        return None if self._mean is None else self._mean.copy()

    def learn(self, frame: np.ndarray) -> None:
        """Learn one frame of a background clip (the empty room) with the ``1/n`` schedule."""
        k = self._prepare(frame)
        rate = self._window_rate()
        if self._mean is None:
            self._mean = k.copy()
            self._var = np.full_like(k, _INITIAL_SIGMA_K ** 2)
        else:
            d = k - self._mean
            self._mean += np.float32(rate) * d
            self._var += np.float32(rate) * (d * d - self._var)
        self._frames += 1
        self._settled = True

    def apply(self, frame: np.ndarray, *, holds: Iterable[Sequence[int]] = (),
              learn: bool = True) -> tuple[np.ndarray, SegmentStats]:
        """Segment one frame and update the model; return ``(mask, stats)`` (as the colour segmenter)."""
        k = self._prepare(frame)
        boxes = self._mask_boxes(holds, k.shape)
        first = self._mean is None
        rate = self.next_learning_rate() if learn else 0.0
        if first:
            self._mean = k.copy()
            self._var = np.full_like(k, _INITIAL_SIGMA_K ** 2)
        thr = np.maximum(np.float32(self.min_contrast_k),
                         np.float32(self.noise_sigmas) * np.sqrt(np.maximum(self._var, _MIN_SIGMA_K ** 2)))
        gain, offset = self._fit_drift(k, boxes, thr)
        self.drift = (gain, offset)
        pred = self._mean * np.float32(gain) + np.float32(offset)
        excess = k - pred
        raw = excess > thr
        if first:
            raw[:] = False
        self._frames += 1
        if learn and not first:
            self._update(k, pred, raw, boxes, rate, gain, offset)
        fg_raw = raw.astype(np.uint8) * np.uint8(255)
        mask, components = self._clean(fg_raw)
        self._last_fg = mask
        return mask, self._plain_stats(rate, mask, fg_raw, components, len(boxes))

    # -- internals ------------------------------------------------------------

    def _prepare(self, frame: np.ndarray) -> np.ndarray:
        """The frame at mask size as float32 kelvin (of the frame's own zero)."""
        if not isinstance(frame, np.ndarray) or frame.dtype not in (np.uint8, np.uint16) or frame.ndim not in (2, 3) \
                or (frame.ndim == 3 and frame.shape[2] not in (1, 3)):
            raise ValueError("thermal frame must be an (H, W) uint16 or uint8 array (or grey (H, W, 3) uint8), got "
                             + describe_frame(frame))
        if frame.ndim == 3:
            if frame.dtype != np.uint8:
                raise ValueError("a multi-channel thermal frame must be uint8")
            frame = frame[..., 0]
        size = (int(frame.shape[1]), int(frame.shape[0]))
        self._adopt_size(size, frame.dtype)
        units = self.units_per_k or (UNITS_PER_K_16BIT if frame.dtype == np.uint16 else UNITS_PER_K_8BIT)
        f = frame.astype(np.float32)
        if self.mask_scale != 1.0:
            f = cv2.resize(f, _scaled_size(size, self.mask_scale), interpolation=cv2.INTER_AREA)
        f *= np.float32(1.0 / units)
        return f

    def _fit_gain(self) -> bool:
        return self.fit_gain if self.fit_gain is not None else self._dtype == np.uint8

    def _fit_drift(self, k: np.ndarray, boxes: list, thr: np.ndarray) -> tuple[float, float]:
        """Robust ``k ~ gain * background + offset`` over background-looking pixels of a coarse grid."""
        s = _FIT_STEP
        f = k[::s, ::s].ravel()
        b = self._mean[::s, ::s].ravel()
        t = thr[::s, ::s].ravel()
        sel = np.ones(f.shape[0], bool)
        if boxes or self._last_fg is not None:
            keep = np.ones(k.shape, bool)
            for x0, y0, x1, y1 in boxes:
                keep[y0:y1, x0:x1] = False
            if self._last_fg is not None:
                keep &= self._last_fg == 0
            sel = keep[::s, ::s].ravel()
        if np.count_nonzero(sel) < 32:
            return 1.0, 0.0
        fit_gain = self._fit_gain()
        gain, offset = 1.0, float(np.median(f[sel] - b[sel]))
        for _ in range(2):
            resid = f - (gain * b + offset)
            inl = sel & (np.abs(resid) < np.maximum(t, 3.0 * self.min_contrast_k if _ == 0 else t))
            if np.count_nonzero(inl) < 32:
                break
            if fit_gain:
                bb, ff = b[inl], f[inl]
                var_b = float(np.var(bb))
                if var_b > 1e-6:
                    gain = float(np.cov(bb, ff, bias=True)[0, 1] / var_b)
                    gain = min(max(gain, 0.25), 4.0)
                offset = float(np.mean(ff - gain * bb))
            else:
                offset = float(np.mean(f[inl] - b[inl]))
        return gain, offset

    def _update(self, k, pred, raw, boxes, rate, gain, offset) -> None:
        """Background pixels learn at ``rate``; foreground ones ``fg_rate_factor`` times slower;
        hold boxes follow the fitted drift only."""
        # the background under the fitted drift is where the model should be now
        moved = self._mean * np.float32(gain) + np.float32(offset)
        a = np.full(k.shape, np.float32(rate), np.float32)
        a[raw] *= np.float32(self.fg_rate_factor)
        for x0, y0, x1, y1 in boxes:
            a[y0:y1, x0:x1] = 0.0
        d = k - moved
        # the drift itself is followed at the learning rate by every pixel, held or not
        self._mean += np.float32(rate) * (moved - self._mean) + a * d
        bg = ~raw
        for x0, y0, x1, y1 in boxes:
            bg[y0:y1, x0:x1] = False
        self._var[bg] += np.float32(rate) * (d[bg] * d[bg] - self._var[bg])
