"""Per-pixel Gaussian-mixture foreground segmentation with shadow removal.

The background model is OpenCV's adaptive Gaussian mixture
(``cv2.createBackgroundSubtractorMOG2``, Stauffer-Grimson mixtures with
Zivkovic's per-pixel choice of the number of modes) with its shadow test
switched on. On top of it this module adds what the voxelwatch pipeline
needs from a camera:

* **Window-based fast start-up.** The model is updated with learning rate
  ``1/n`` on the ``n``-th frame while ``n < window_frames`` (the
  expected-sufficient-statistics phase), then with the settled rate
  ``alpha`` (default ``1/window_frames``, an L-recent window). A background
  clip of the empty room is learned the same way with :meth:`learn`; the live
  frames that follow start at the settled rate, because continuing ``1/n``
  would absorb anyone who sits in view when the live source starts.
* **Shadow removal.** MOG2 marks shadow pixels 127; they are background here.
* **Clean-up.** Morphological opening, then closing, removal of connected
  components smaller than ``min_area_px``, filling of enclosed holes (the
  closing and the smallest area given for a 640x480 frame and scaled to the
  frames' size).
* **Hold regions.** MOG2's learning rate is global, so a person who stays
  still is absorbed into the background after about
  ``-ln(background_ratio) / alpha`` frames (about ``0.105 * window_frames``
  with the defaults). Boxes where a tracked person holds still are protected
  this way: the foreground of the real frame is computed with
  ``learningRate=0`` (no update), then the model is updated with the normal
  rate on a copy of the frame whose hold boxes are replaced by the model's
  own background image (gain-corrected for global brightness changes; both
  refreshed every 8 frames). The model keeps learning everywhere else and
  sees background inside the boxes, so the still person stays foreground
  however long the hold lasts. The cost is a second ``apply`` (about 2.3 ms
  at 640x480 on one core) and a copy on frames that have holds; frames
  without holds pay nothing. (OpenCV's ``apply(image, knownForegroundMask)``
  was tried: it still learns the masked pixels, so it cannot hold.)
* **Sudden light change.** When more than ``light_change_fraction`` of the
  live image (pixels whose background is not black, so a fisheye's corners
  do not count) differs from the background (foreground or shadow, before
  clean-up) and the change covers at least 14/16 of the live cells of a
  4x4 grid (a person close to the lens does not), the model is
  re-initialised (rate 1, the window schedule's ``n = 1``) with its own
  background re-lit: each pixel's most probable background mode times a
  per-channel gain, the median ratio frame/background. Nothing in view at
  that moment is learned -- people, their soft shadows, hold boxes -- and
  the frame is segmented again against the re-lit model, so the mask is
  clean from the frame of the change on (recovery within 0 frames for a
  global change; tested on drawn scenes and on the synthetic house's lamp).
  The next ``relearn_frames`` frames continue the restarted schedule (rates
  1/2, 1/3, ...) with their foreground and shadows masked out of the update.
  A change the gain cannot explain (one lamp lighting one corner) is left to
  the normal rate, like any other static change.
* **Downscaling.** With ``mask_scale < 1`` the frame is reduced (area
  averaging) before segmentation, which is cheaper and gives the smaller
  mask the fusion wants anyway. Sizes in pixels given to the constructor are
  full-resolution pixels and are scaled with it.

Everything here is pure: no clock, no files, no network.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Sequence

import cv2
import numpy as np

from common.settings import check_setting
from common.site import Carving

Box = tuple[int, int, int, int]

DEFAULT_MIN_AREA_PX = 400
"""The smallest component (640x480 pixels) a segmenter keeps unless told, and the size a smaller one
must keep apart from: beside a blob this large it is a piece of someone near (a hand, a shadow's
blotch), not someone far (see :mod:`camera_worker.viewsize`)."""
REFERENCE_AREA_PX = 640 * 480
"""Frame area for which ``open_px``, ``close_px`` and ``min_area_px`` are given; other sizes scale them."""
_RELEARN_FIRST_RATE = 1.0     # the frame that shows a light change re-initialises the model: 1/n with n = 1
_PROTECT_KERNEL = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))   # foreground edges kept out of re-learning
_BG_REFRESH_FRAMES = 8       # hold boxes use a background image at most this many frames old
_LIGHT_GRID = 4               # a light change covers most cells of a 4x4 grid ...
_LIGHT_CELL_FRACTION = 0.25   # ... each cell at least this much changed ...
_LIGHT_MIN_CELLS = 14         # ... in at least this many cells (a person close to the lens covers fewer)
_DEAD_LEVEL = 8               # background pixels at most this bright (a fisheye's corners) never count

__all__ = [
    "Box",
    "ForegroundSegmenter",
    "SegmentStats",
    "SegmenterBase",
    "cleanup_mask",
    "describe_frame",
    "fill_holes",
    "learning_rate_schedule",
    "remove_small_components",
    "scale_box",
]


@dataclass(frozen=True)
class SegmentStats:
    """What happened to one frame.

    ``frame_index`` counts every frame the model has seen (background clip
    included), 1 for the first. Fractions are over the mask's pixels:
    ``fg_fraction`` after clean-up, ``changed_fraction`` (foreground or
    shadow) and ``shadow_fraction`` as the model first saw the frame.
    ``learning_rate`` is the rate the frame was learned with (0 when
    ``learn=False``). ``light_change``: this frame showed a sudden light
    change and it was adopted; ``relearning``: this frame was learned as
    part of a light-change re-learn (the change itself or the window after it).
    """

    frame_index: int
    learning_rate: float
    fg_fraction: float
    changed_fraction: float
    shadow_fraction: float
    components: int
    holds: int
    light_change: bool
    relearning: bool


DEFAULT_WINDOW_S = 500 / 15.0
"""The learning window in seconds: 500 frames at the 15 fps the defaults were
tuned for. A still person is learned into the background after about
``0.105 * window_frames`` frames (3.5 s at 15 fps, but only 1.1 s at 50 fps
with 500 frames, before the tracker's one-second still test can hold them),
so the window is set in seconds and converted at each source's own rate."""


def window_frames_for(fps: float, window_s: float = DEFAULT_WINDOW_S) -> int:
    """The learning window in frames for a source at ``fps``."""
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps!r}")
    return max(1, int(round(window_s * fps)))


def learning_rate_schedule(n: int, *, window_frames: int, alpha: float) -> float:
    """Learning rate for the ``n``-th frame (1-based) of the window schedule.

    ``1/n`` while ``n < window_frames`` (fast start-up), ``alpha`` afterwards;
    never below ``alpha``. ``n = 1`` gives 1: the first frame initialises the model.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if n < window_frames:
        return max(1.0 / n, alpha)
    return alpha


class SegmenterBase:
    """What every segmenter shares: the window schedule, the frames' size, the mask size and the clean-up.

    ``window_frames`` and ``alpha`` set the learning rates (:func:`learning_rate_schedule`);
    ``mask_scale`` reduces the frames before segmentation; ``open_px`` (full-resolution pixels),
    ``close_px`` and ``min_area_px`` (pixels of a 640x480 frame, :data:`REFERENCE_AREA_PX`) and
    ``fill_holes`` set the clean-up (:func:`cleanup_mask`). A subclass stores its own settings,
    then calls :meth:`reset`, whose own version calls this one.
    """

    def __init__(
        self,
        *,
        window_frames: int,
        alpha: float | None,
        mask_scale: float,
        open_px: int,
        close_px: int,
        min_area_px: int,
        fill_holes: bool,
    ) -> None:
        if isinstance(window_frames, bool) or not isinstance(window_frames, int) or window_frames < 1:
            raise ValueError(f"window_frames must be an int >= 1, got {window_frames!r}")
        if alpha is None:
            alpha = 1.0 / window_frames
        if not 0.0 < alpha <= 1.0:
            raise ValueError(f"alpha must be in (0, 1], got {alpha!r}")
        # the site file's carving.mask_scale is the one declaration of its range
        mask_scale = check_setting(Carving, "mask_scale", mask_scale, flag="mask_scale")
        for name, value in (("open_px", open_px), ("close_px", close_px), ("min_area_px", min_area_px)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name} must be an int >= 0, got {value!r}")
        self.window_frames = window_frames
        self.alpha = float(alpha)
        self.mask_scale = float(mask_scale)
        self.fill_holes = bool(fill_holes)
        self._cleanup_px = (int(open_px), int(close_px), int(min_area_px))

    def reset(self) -> None:
        """Forget the frames: the next one starts the window schedule again and sets the frames' size."""
        self._frames = 0            # frames the model has seen
        self._settled = False       # a background clip was learned: live frames use alpha
        self._full_size: tuple[int, int] | None = None   # (W, H) of input frames
        self._dtype: np.dtype | None = None   # the frames' type, where a subclass keeps to one
        self._cleanup: tuple | None = None   # kernels and smallest area for the frames' size, set on the first

    @property
    def frames_seen(self) -> int:
        """Frames the model has been updated with or evaluated on."""
        return self._frames

    @property
    def learned(self) -> bool:
        """Whether the model knows the room: a background clip was learned, or a whole window of live frames."""
        return self._settled or self._frames >= self.window_frames

    @property
    def full_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the input frames, None before the first frame."""
        return self._full_size

    @property
    def mask_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the masks, None before the first frame."""
        if self._full_size is None:
            return None
        return _scaled_size(self._full_size, self.mask_scale)

    def next_learning_rate(self) -> float:
        """The rate :meth:`apply` will use for the next frame (when learning)."""
        if self._settled:
            return self.alpha
        return self._window_rate()

    # -- for subclasses -------------------------------------------------------

    def _window_rate(self) -> float:
        """The window schedule's rate for the next frame (``1/n``, then ``alpha``)."""
        return learning_rate_schedule(self._frames + 1, window_frames=self.window_frames, alpha=self.alpha)

    def _adopt_size(self, size: tuple[int, int], dtype: np.dtype | None = None) -> None:
        """Take ``size = (W, H)`` (and ``dtype``, where the frames must keep to one) from the first
        frame; raise ValueError when a later frame differs."""
        if self._full_size is None:
            self._full_size, self._dtype = size, dtype
        elif size != self._full_size or dtype != self._dtype:
            what, mine, theirs = "frame size", f"{size[0]}x{size[1]}", f"{self._full_size[0]}x{self._full_size[1]}"
            if dtype is not None:
                what, mine, theirs = "frame", f"{mine} {dtype}", f"{theirs} {self._dtype}"
            raise ValueError(f"{what} {mine} differs from the model's {theirs} (reset() to start a new model)")

    def _mask_boxes(self, holds: Iterable[Sequence[int]], shape: tuple[int, ...]) -> list[Box]:
        """Full-resolution hold boxes scaled and clipped to a mask of ``shape`` ``(h, w, ...)``; empty ones dropped."""
        size = (shape[1], shape[0])
        return [b for b in (scale_box(box, self.mask_scale, size) for box in holds) if b is not None]

    def _cleanup_sizes(self) -> tuple:
        """(open kernel, close kernel, smallest component in mask pixels) for the frames' size. The
        opening removes pixel noise and scales with the mask scale only; the closing and the smallest
        component are sizes of the view, given for a 640x480 frame and scaled by the mask's linear
        size against it, so that a person far off or a child is kept or dropped alike at 320x240
        and at 1280x720."""
        if self._cleanup is None:
            w, h = self._full_size
            scale = self.mask_scale * math.sqrt(w * h / float(REFERENCE_AREA_PX))
            open_px, close_px, min_area_px = self._cleanup_px
            self._cleanup = (_kernel(open_px, self.mask_scale), _kernel(close_px, scale),
                             int(math.ceil(min_area_px * scale * scale)),
                             int(math.ceil(max(min_area_px, DEFAULT_MIN_AREA_PX) * scale * scale)))
        return self._cleanup

    def _clean(self, fg_raw: np.ndarray) -> tuple[np.ndarray, int]:
        """:func:`cleanup_mask` with the sizes for the frames' size: ``(mask, components)``."""
        open_k, close_k, min_area, apart_area = self._cleanup_sizes()
        return cleanup_mask(fg_raw, open_kernel=open_k, close_kernel=close_k,
                            min_area_px=min_area, fill=self.fill_holes, apart_area_px=apart_area)

    def _plain_stats(self, rate: float, mask: np.ndarray, fg_raw: np.ndarray, components: int,
                     holds: int) -> SegmentStats:
        """Stats of a frame for a model without shadows or light changes: ``fg_raw`` (0/255, before
        clean-up) is what changed, ``mask`` the cleaned foreground."""
        n_pix = float(mask.size)
        return SegmentStats(
            frame_index=self._frames, learning_rate=rate, fg_fraction=cv2.countNonZero(mask) / n_pix,
            changed_fraction=cv2.countNonZero(fg_raw) / n_pix, shadow_fraction=0.0, components=components,
            holds=holds, light_change=False, relearning=False,
        )


def describe_frame(frame: object) -> str:
    """``shape dtype`` of something offered as a frame, for error messages."""
    return f"{getattr(frame, 'shape', None)} {getattr(frame, 'dtype', type(frame).__name__)}"


class ForegroundSegmenter(SegmenterBase):
    """Adaptive GMM foreground with shadow removal, clean-up and hold regions.

    Frames are ``(H, W, 3) uint8`` BGR images (``(H, W)`` grey is accepted),
    all of the same size. Masks are ``(round(H*s), round(W*s)) uint8`` with
    0 (background) and 255 (foreground), ``s = mask_scale``. Hold boxes are
    ``(x0, y0, x1, y1)`` in full-resolution pixels, ``x1``/``y1`` exclusive.
    ``open_px`` (the opening's width, against pixel noise) is in full-resolution
    pixels; ``close_px`` (the closing's width) and ``min_area_px`` (smallest
    component) are pixels of a 640x480 frame (:data:`REFERENCE_AREA_PX`),
    scaled to the frames' own size, so they mean the same part of the view at
    any resolution. All are scaled by ``mask_scale``.
    """

    def __init__(
        self,
        *,
        window_frames: int = 500,
        alpha: float | None = None,
        n_mixtures: int = 5,
        var_threshold: float = 16.0,
        background_ratio: float = 0.9,
        detect_shadows: bool = True,
        shadow_threshold: float = 0.5,
        mask_scale: float = 1.0,
        open_px: int = 3,
        close_px: int = 7,
        min_area_px: int = DEFAULT_MIN_AREA_PX,
        fill_holes: bool = True,
        light_change_fraction: float | None = 0.45,
        relearn_frames: int = 10,
    ) -> None:
        super().__init__(window_frames=window_frames, alpha=alpha, mask_scale=mask_scale, open_px=open_px,
                         close_px=close_px, min_area_px=min_area_px, fill_holes=fill_holes)
        if not 1 <= n_mixtures <= 16:
            raise ValueError(f"n_mixtures must be in 1..16, got {n_mixtures!r}")
        if not var_threshold > 0:
            raise ValueError(f"var_threshold must be > 0, got {var_threshold!r}")
        if not 0.0 < background_ratio <= 1.0:
            raise ValueError(f"background_ratio must be in (0, 1], got {background_ratio!r}")
        if not 0.0 < shadow_threshold < 1.0:
            raise ValueError(f"shadow_threshold must be in (0, 1), got {shadow_threshold!r}")
        if light_change_fraction is not None and not 0.0 < light_change_fraction <= 1.0:
            raise ValueError(f"light_change_fraction must be in (0, 1] or None, got {light_change_fraction!r}")
        if isinstance(relearn_frames, bool) or not isinstance(relearn_frames, int) or relearn_frames < 0:
            raise ValueError(f"relearn_frames must be an int >= 0, got {relearn_frames!r}")

        self.light_change_fraction = light_change_fraction
        self.relearn_frames = relearn_frames
        self._params = dict(
            n_mixtures=int(n_mixtures), var_threshold=float(var_threshold),
            background_ratio=float(background_ratio), detect_shadows=bool(detect_shadows),
            shadow_threshold=float(shadow_threshold),
        )
        self.reset()

    # -- public ---------------------------------------------------------------

    def reset(self) -> None:
        """Forget the background: the next frame starts the window schedule again."""
        super().reset()
        p = self._params
        self._model = cv2.createBackgroundSubtractorMOG2(
            history=self.window_frames, varThreshold=p["var_threshold"], detectShadows=p["detect_shadows"])
        self._model.setNMixtures(p["n_mixtures"])
        self._model.setBackgroundRatio(p["background_ratio"])
        self._model.setShadowThreshold(p["shadow_threshold"])
        self._model.setShadowValue(127)
        self._relearn_n = 0         # > 0: inside the re-learn window, next rate 1/_relearn_n
        self._bg: np.ndarray | None = None   # cached background image for hold boxes ...
        self._bg_frame = 0
        self._pred: np.ndarray | None = None  # ... and the same times the current gain
        self._pred_frame = -1

    def next_learning_rate(self) -> float:
        """The rate :meth:`apply` will use for the next frame (when learning and not re-learning)."""
        if self._relearn_n:
            return max(1.0 / self._relearn_n, self.alpha)
        return super().next_learning_rate()

    def learn(self, frame: np.ndarray) -> None:
        """Learn one frame of a background clip (an empty room) with the ``1/n`` schedule.

        Live frames given to :meth:`apply` afterwards use the settled rate ``alpha``.
        """
        small = self._prepare(frame)
        self._model.apply(small, learningRate=self._window_rate())
        self._frames += 1
        self._settled = True

    def apply(
        self,
        frame: np.ndarray,
        *,
        holds: Iterable[Sequence[int]] = (),
        learn: bool = True,
    ) -> tuple[np.ndarray, SegmentStats]:
        """Segment one frame and update the model; return ``(mask, stats)``.

        ``holds``: full-resolution boxes ``(x0, y0, x1, y1)`` (exclusive) that
        must not be learned into the background this frame; boxes are clipped
        to the image, empty ones are ignored. ``learn=False`` evaluates the
        frame without changing the model.
        """
        small = self._prepare(frame)
        boxes = self._mask_boxes(holds, small.shape)
        first = self._frames == 0
        rate = self.next_learning_rate() if learn else 0.0
        relearning = learn and self._relearn_n > 0
        # Holds and re-learning need the foreground before the update: detect without learning first.
        selective = learn and not first and (bool(boxes) or relearning)

        raw = self._model.apply(small, learningRate=0.0 if selective else rate)
        if first:
            raw = np.zeros_like(raw)   # a model of one frame has nothing to compare with
        self._frames += 1
        n_pix = float(raw.size)
        changed = cv2.countNonZero(raw) / n_pix

        light_change = learn and not first and self._is_light_change(small, raw, changed)
        if light_change:
            self._adopt_light(small, boxes)
            raw = self._model.apply(small, learningRate=0.0)
            rate = _RELEARN_FIRST_RATE
            self._relearn_n = 2 if self.relearn_frames > 0 else 0
        elif selective:
            # people and shadows (both non-zero) stay out of the re-learning
            protect = cv2.dilate(raw, _PROTECT_KERNEL) if relearning else None
            self._update_selective(small, boxes, protect, rate)
            if relearning:
                self._relearn_n += 1
                if self._relearn_n > self.relearn_frames + 1:
                    self._relearn_n = 0

        fg_raw = cv2.threshold(raw, 200, 255, cv2.THRESH_BINARY)[1]   # 255 foreground, 127 shadow, 0 background
        n_fg_raw = cv2.countNonZero(fg_raw)
        mask, components = self._clean(fg_raw)
        stats = SegmentStats(
            frame_index=self._frames,
            learning_rate=rate,
            fg_fraction=cv2.countNonZero(mask) / n_pix,
            changed_fraction=changed,
            shadow_fraction=(cv2.countNonZero(raw) - n_fg_raw) / n_pix,
            components=components,
            holds=len(boxes),
            light_change=light_change,
            relearning=relearning or light_change,
        )
        return mask, stats

    def background_image(self) -> np.ndarray:
        """The model's current background, ``(h, w, 3) uint8`` BGR at mask resolution."""
        return self._model.getBackgroundImage()

    # -- internals ------------------------------------------------------------

    def _prepare(self, frame: np.ndarray) -> np.ndarray:
        if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim not in (2, 3) \
                or (frame.ndim == 3 and frame.shape[2] not in (1, 3)):
            raise ValueError(f"frame must be an (H, W, 3) or (H, W) uint8 array, got {describe_frame(frame)}")
        size = (int(frame.shape[1]), int(frame.shape[0]))
        self._adopt_size(size)
        if self.mask_scale != 1.0:
            frame = cv2.resize(frame, _scaled_size(size, self.mask_scale), interpolation=cv2.INTER_AREA)
        return frame

    def _is_light_change(self, small: np.ndarray, raw: np.ndarray, changed: float) -> bool:
        """Most of the live image changed, spread over most of it (a person close to the lens is not).

        Live pixels are those whose background is not black: a fisheye's
        corners never change and must not count against a light change.
        """
        if self.light_change_fraction is None or changed <= 0.5 * self.light_change_fraction:
            return False
        bg = self._background(small, fresh=False)
        live = cv2.threshold(bg if bg.ndim == 2 else bg.max(axis=2), _DEAD_LEVEL, 1, cv2.THRESH_BINARY)[1]
        n_live = cv2.countNonZero(live)
        if n_live == 0:
            return False
        moved = cv2.bitwise_and(cv2.threshold(raw, 0, 1, cv2.THRESH_BINARY)[1], live)
        if cv2.countNonZero(moved) / n_live <= self.light_change_fraction:
            return False
        grid = (_LIGHT_GRID, _LIGHT_GRID)
        cell_live = cv2.resize(live.astype(np.float32), grid, interpolation=cv2.INTER_AREA)
        cell_moved = cv2.resize(moved.astype(np.float32), grid, interpolation=cv2.INTER_AREA)
        cells = cell_live >= 0.25
        spread = cells & (cell_moved >= _LIGHT_CELL_FRACTION * cell_live)
        return int(np.count_nonzero(spread)) >= math.ceil(_LIGHT_MIN_CELLS / _LIGHT_GRID ** 2 * np.count_nonzero(cells))

    def _background(self, small: np.ndarray, *, fresh: bool) -> np.ndarray:
        # The background moves at the rate alpha: refreshing it every few frames is plenty,
        # except while re-learning after a light change.
        if fresh or self._bg is None or self._relearn_n or self._frames - self._bg_frame >= _BG_REFRESH_FRAMES:
            # the most probable mode of each pixel only: with the usual ratio the image is a
            # weighted mean of every background mode, shadows learned at a low weight included
            self._model.setBackgroundRatio(1e-3)
            try:
                bg = self._model.getBackgroundImage()
            finally:
                self._model.setBackgroundRatio(self._params["background_ratio"])
            if bg.shape != small.shape:   # grey input: MOG2 keeps a grey model
                bg = bg.reshape(small.shape)
            self._bg, self._bg_frame = bg, self._frames
        return self._bg

    def _update_selective(self, small: np.ndarray, boxes: list[Box], protect: np.ndarray | None,
                          rate: float) -> None:
        """Update with the frame, except hold boxes and ``protect`` pixels, which get the background."""
        bg = self._background(small, fresh=False)
        if self._pred is None or self._pred_frame != self._bg_frame:   # re-lit with the background
            gain = _gain(small, bg, boxes)
            self._pred = bg if gain is None else _scaled(bg, gain)
            self._pred_frame = self._bg_frame
        pred = self._pred
        composite = small.copy()
        for x0, y0, x1, y1 in boxes:
            composite[y0:y1, x0:x1] = pred[y0:y1, x0:x1]
        if protect is not None:
            np.copyto(composite, pred, where=(protect > 0) if small.ndim == 2 else (protect > 0)[..., None])
        self._model.apply(composite, learningRate=rate)

    def _adopt_light(self, small: np.ndarray, boxes: list[Box]) -> None:
        """Re-initialise the model with its own background re-lit by the measured gain.

        The new light is modelled as a per-channel gain on the background
        (each pixel's most probable mode), so nothing in view now -- people,
        their soft shadows, hold boxes -- is learned. Where the background
        was clipped at white, the frame may raise the prediction.
        """
        bg = self._background(small, fresh=True)
        gain = _gain(small, bg, boxes)
        relit = bg if gain is None else _scaled(bg, gain)
        # where the background was clipped at white its true level is unknown: when the light
        # drops, such a pixel may be brighter than the gain predicts, never darker
        clipped = bg >= 250 if bg.ndim == 2 else (bg >= 250).any(axis=2, keepdims=True)
        np.copyto(relit, cv2.max(relit, small), where=np.broadcast_to(clipped, relit.shape))
        self._model.apply(relit, learningRate=_RELEARN_FIRST_RATE)
        self._bg = None


def cleanup_mask(
    mask: np.ndarray,
    *,
    open_kernel: np.ndarray | None,
    close_kernel: np.ndarray | None,
    min_area_px: int,
    fill: bool,
    apart_area_px: int = 0,
) -> tuple[np.ndarray, int]:
    """Open, close, drop components below ``min_area_px`` (and those below ``apart_area_px`` beside a
    larger one, :func:`remove_small_components`), fill enclosed holes.

    ``mask``: ``(H, W) uint8`` 0/255. Returns the cleaned mask (new array)
    and the number of foreground components kept.
    """
    out = mask
    if open_kernel is not None:
        out = cv2.morphologyEx(out, cv2.MORPH_OPEN, open_kernel)
    if close_kernel is not None:
        out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, close_kernel)
    out, components = remove_small_components(out, min_area_px, apart_area_px)
    if fill and components:
        out = fill_holes(out)
    return out, components


def remove_small_components(mask: np.ndarray, min_area_px: int, apart_area_px: int = 0) -> tuple[np.ndarray, int]:
    """Drop 8-connected foreground components with fewer than ``min_area_px`` pixels, and those with
    fewer than ``apart_area_px`` that lie beside a component of at least ``apart_area_px`` (their box,
    grown by its own height or by half the larger one's, whichever is more, meets the larger one's
    box): a piece of someone near (a hand, feet seen below a tabletop), not someone far.

    Returns ``(mask, kept)``: a new ``uint8`` 0/255 mask and the number of components kept.
    """
    if cv2.countNonZero(mask) == 0:
        return np.zeros_like(mask), 0
    # BBDT with 32-bit labels: several times faster than the default on one thread, any component count
    n, labels, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(mask, 8, cv2.CV_32S, cv2.CCL_BBDT)
    area = stats[:, cv2.CC_STAT_AREA]
    keep = area >= max(min_area_px, 1)
    keep[0] = False
    small = np.flatnonzero(keep & (area < apart_area_px))
    if len(small):
        big = np.flatnonzero(area >= apart_area_px)
        big = big[big != 0]
        if len(big):
            # boxes (x, y, width, height): (small, 1) against (1, big)
            boxes = stats[:, [cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT]]
            sx, sy, sw, sh = boxes[small].T[:, :, None]
            bx, by, bw, bh = boxes[big].T[:, None, :]
            # near: within its own height or half the larger one's (feet below a tabletop, a hand)
            g = np.maximum(sh, bh // 2)
            meets = (bx < sx + sw + g) & (sx - g < bx + bw) & (by < sy + sh + g) & (sy - g < by + bh)
            keep[small] = ~meets.any(axis=1)
    kept = int(np.count_nonzero(keep))
    if kept == n - 1:
        return mask.copy(), kept
    lut = np.where(keep, np.uint8(255), np.uint8(0))
    return np.take(lut, labels), kept


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill background regions not 4-connected to the image border; ``(H, W) uint8`` 0/255."""
    h, w = mask.shape
    padded = np.zeros((h + 2, w + 2), np.uint8)
    padded[1:-1, 1:-1] = mask
    cv2.floodFill(padded, None, (0, 0), 255)
    # pixels still 0 after flooding the outside from the border are holes
    return mask | cv2.bitwise_not(padded[1:-1, 1:-1])


def scale_box(box: Sequence[int], scale: float, size: tuple[int, int]) -> Box | None:
    """A full-resolution box ``(x0, y0, x1, y1)`` scaled by ``scale`` and clipped to ``size = (w, h)``.

    The scaled box covers every mask pixel the original touches (floor/ceil).
    Returns None for boxes that are empty after clipping.
    """
    if len(box) != 4:
        raise ValueError(f"hold box must be (x0, y0, x1, y1), got {box!r}")
    x0, y0, x1, y1 = (float(v) for v in box)
    w, h = size
    sx0 = max(0, int(math.floor(x0 * scale)))
    sy0 = max(0, int(math.floor(y0 * scale)))
    sx1 = min(w, int(math.ceil(x1 * scale)))
    sy1 = min(h, int(math.ceil(y1 * scale)))
    if sx1 <= sx0 or sy1 <= sy0:
        return None
    return sx0, sy0, sx1, sy1


def _scaled_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    return max(1, int(round(size[0] * scale))), max(1, int(round(size[1] * scale)))


def _kernel(size_px: int, scale: float) -> np.ndarray | None:
    k = int(round(size_px * scale))
    if k < 2:
        return None
    k |= 1   # odd, so the structuring element is centred
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))


def _gain(frame: np.ndarray, bg: np.ndarray, boxes: list[Box]) -> np.ndarray | None:
    """Per-channel brightness ratio frame/background, the median over an 8-pixel grid outside ``boxes``.

    The median ignores people (a minority of the pixels); dark (< 16) and
    clipped (> 250) pixels are left out. None when every channel is within 2 % of
    one or too few pixels are left.
    """
    step = 8
    f = frame[::step, ::step].astype(np.float32)
    b = bg[::step, ::step].astype(np.float32)
    sel = np.ones(f.shape[:2], bool)
    for x0, y0, x1, y1 in boxes:
        sel[-(-y0 // step):-(-y1 // step), -(-x0 // step):-(-x1 // step)] = False
    channels = 1 if f.ndim == 2 else f.shape[2]
    f = f[sel].reshape(-1, channels)
    b = b[sel].reshape(-1, channels)
    gain = np.ones(channels, np.float32)
    for c in range(channels):
        ok = (b[:, c] >= 16.0) & (b[:, c] <= 250.0) & (f[:, c] <= 250.0)   # no dark or clipped pixels
        if np.count_nonzero(ok) < 64:
            return None
        gain[c] = np.median(f[ok, c] / b[ok, c])
    if np.all(np.abs(gain - 1.0) < 0.02):
        return None
    return gain


def _scaled(image: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """``image * gain`` per channel, saturated to uint8."""
    if image.ndim == 2:
        return cv2.convertScaleAbs(image, alpha=float(gain[0]))
    return cv2.convertScaleAbs(image.astype(np.float32) * gain)
