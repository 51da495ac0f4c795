"""Colour descriptors of people, computed by a camera worker without a pixel leaving it.

The fusion server tells each worker where its tracked people are in that
camera: per person a :class:`~common.messages.PersonRegion`, one image box per
body band (head, torso, legs; :data:`BANDS`) and the person's distance from
the camera. The worker answers with one :class:`~common.messages.Appearance`
per person: for each band, a normalised histogram of the colours of the
*foreground* pixels inside the band's box, leaving out every pixel that lies
in a box of a person nearer the camera (they hide this one there).

The colour space is hue and saturation, with the pixels too grey or too dark
to have a reliable hue in a few bins of brightness of their own
(:func:`colour_bins`): a change of illumination scales all three channels,
which moves neither hue nor saturation, and the grey bins are wide. Each
band's histogram goes on the wire as :data:`N_BINS` bytes summing to about
255, with the number of pixels it counts and the share of its box that no
nearer person covers, so that the receiver can weigh it. A person costs
about 150 bytes a descriptor; the fusion server asks for a few a second
(``fusion_server.identity.AppearanceParams.rate_hz``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = [
    "AppearanceModel",
    "BANDS",
    "BAND_FRACTIONS",
    "GREY_LEVELS",
    "HUE_BINS",
    "N_BINS",
    "colour_bins",
    "describe_people",
    "hellinger",
    "quantise",
    "Resident",
    "View",
]

BANDS = ("head", "torso", "legs")
"""Body bands, top down."""
BAND_FRACTIONS = ((0.86, 1.0), (0.52, 0.86), (0.08, 0.52))
"""Each band's extent as fractions of the person's top height (an upright adult: the
head and neck, the shirt from shoulder to hip, the legs above the shoes)."""
HUE_BINS = 12
SAT_LEVELS = (48, 130)
"""Saturation (OpenCV 0-255) from which a pixel has a hue, and from which it is strongly coloured."""
GREY_LEVELS = (50, 110, 175)
"""Brightness (0-255) edges of the four bins of greys: black, dark, mid, light."""
MIN_VALUE = 40
"""Brightness below which a pixel counts as black whatever its hue."""
N_BINS = HUE_BINS * 2 + len(GREY_LEVELS) + 1
MAX_SAMPLES = 4096
"""Most pixels a band's histogram counts (a regular subsample beyond)."""


def colour_bins(bgr: np.ndarray) -> np.ndarray:
    """The histogram bin of each pixel of ``bgr`` ((N, 3) or (H, W, 3) uint8 BGR).

    Bins ``0 .. 2 * HUE_BINS - 1``: hue (12 sectors) times saturation (moderate,
    strong); the last four: greys by brightness. Returns int64 of the input's
    leading shape.
    """
    shape = bgr.shape[:-1]
    hsv = cv2.cvtColor(np.ascontiguousarray(bgr, dtype=np.uint8).reshape(-1, 1, 3), cv2.COLOR_BGR2HSV).reshape(-1, 3)
    h, s, v = hsv[:, 0].astype(np.int64), hsv[:, 1], hsv[:, 2]
    hue = np.minimum(h * HUE_BINS // 180, HUE_BINS - 1)
    chroma = hue * 2 + (s >= SAT_LEVELS[1])
    grey = 2 * HUE_BINS + np.searchsorted(np.asarray(GREY_LEVELS), v, side="right")
    is_grey = (s < SAT_LEVELS[0]) | (v < MIN_VALUE)
    return np.where(is_grey, grey, chroma).reshape(shape)


def quantise(hist: np.ndarray) -> bytes:
    """``N_BINS`` counts -> ``N_BINS`` bytes summing to about 255 (empty: all zero)."""
    hist = np.asarray(hist, dtype=np.float64)
    total = hist.sum()
    if total <= 0:
        return bytes(N_BINS)
    return np.clip(np.rint(hist * (255.0 / total)), 0, 255).astype(np.uint8).tobytes()


def hellinger(a: np.ndarray, b: np.ndarray) -> float:
    """Hellinger distance of two histograms (any scale; each normalised here), in [0, 1]:
    0 for the same colours, 1 for colours with nothing in common. An empty one gives 1."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    sa, sb = a.sum(), b.sum()
    if sa <= 0 or sb <= 0:
        return 1.0
    bc = float(np.sqrt(a * b).sum() / np.sqrt(sa * sb))
    return float(np.sqrt(max(0.0, 1.0 - min(bc, 1.0))))


def describe_people(
    image: np.ndarray,
    mask: np.ndarray,
    people: Sequence[tuple[float, Sequence[tuple[int, int, int, int]]]],
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per person, the band histograms of the foreground inside its boxes.

    image: (H, W, 3) uint8 BGR frame at capture resolution.
    mask: (h, w) uint8 foreground mask of the same frame, 0 background, at the
        capture resolution or downscaled from it.
    people: per person ``(depth_m, boxes)``: its distance from the camera and
        one ``(x0, y0, x1, y1)`` box per band in capture pixels (exclusive
        ends; an empty box for a band out of view).
    Returns per person ``(hist (3, N_BINS) int64 pixel counts, pixels (3,)
    int64, visible (3,) float64)``: ``visible`` is the share of each band's box
    (inside the image) that no box of a nearer person covers.
    """
    H, W = image.shape[:2]
    mh, mw = mask.shape[:2]
    sx, sy = mw / W, mh / H
    depths = [float(d) for d, _ in people]
    out = []
    for i, (depth, boxes) in enumerate(people):
        nearer = [b for j, (_, bs) in enumerate(people) if depths[j] < depth or (depths[j] == depth and j < i)
                  for b in bs]
        hist = np.zeros((len(BANDS), N_BINS), dtype=np.int64)
        pixels = np.zeros(len(BANDS), dtype=np.int64)
        visible = np.zeros(len(BANDS), dtype=np.float64)
        for k, box in enumerate(boxes[: len(BANDS)]):
            x0, y0, x1, y1 = (max(0, int(box[0])), max(0, int(box[1])), min(W, int(box[2])), min(H, int(box[3])))
            if x1 <= x0 or y1 <= y0:
                continue
            free = np.ones((y1 - y0, x1 - x0), dtype=bool)
            for n in nearer:
                a0, b0, a1, b1 = max(x0, int(n[0])), max(y0, int(n[1])), min(x1, int(n[2])), min(y1, int(n[3]))
                if a1 > a0 and b1 > b0:
                    free[b0 - y0: b1 - y0, a0 - x0: a1 - x0] = False
            visible[k] = float(free.mean())
            if not free.any():
                continue
            # the mask's pixels covering the box, brought to the box's size
            m0x, m0y = int(x0 * sx), int(y0 * sy)
            m1x, m1y = max(m0x + 1, int(np.ceil(x1 * sx))), max(m0y + 1, int(np.ceil(y1 * sy)))
            sub = mask[m0y:m1y, m0x:m1x]
            if sub.size == 0:
                continue
            if sub.shape != free.shape:
                sub = cv2.resize(sub, (x1 - x0, y1 - y0), interpolation=cv2.INTER_NEAREST)
            take = free & (sub > 0)
            ys, xs = np.nonzero(take)
            if len(ys) == 0:
                continue
            if len(ys) > MAX_SAMPLES:
                step = int(np.ceil(len(ys) / MAX_SAMPLES))
                ys, xs = ys[::step], xs[::step]
            bins = colour_bins(image[y0 + ys, x0 + xs])
            hist[k] = np.bincount(bins, minlength=N_BINS)
            pixels[k] = int(take.sum())
        out.append((hist, pixels, visible))
    return out


@dataclass
class AppearanceModel:
    """A person's long-term appearance: per band a normalised colour histogram and
    the number of frames it has learnt; the standing height (metres, NaN unknown)."""

    hist: np.ndarray = field(default_factory=lambda: np.zeros((len(BANDS), N_BINS)))
    frames: np.ndarray = field(default_factory=lambda: np.zeros(len(BANDS)))
    height_m: float = float("nan")
    height_frames: int = 0

    def learn(self, view: "View", learn_rate: float, height_m: float | None) -> None:
        """Take one frame's views (bands without views are left as they are)."""
        for k in range(len(BANDS)):
            if view.weight[k] <= 0:
                continue
            self.frames[k] += 1
            rate = max(learn_rate, 1.0 / self.frames[k])
            self.hist[k] += rate * (view.hist[k] - self.hist[k])
        if height_m is not None and math.isfinite(height_m):
            self.height_frames += 1
            rate = max(learn_rate, 1.0 / self.height_frames)
            self.height_m = height_m if not math.isfinite(self.height_m) else self.height_m + rate * (height_m - self.height_m)

    def mature(self, min_frames: int) -> bool:
        return bool(self.frames[1] >= min_frames or self.frames.sum() >= 2 * min_frames)

    def distance(self, view: "View") -> float | None:
        """Mean Hellinger distance over the bands both hold, weighted by the view's
        weights; None when they share no band."""
        total = weight = 0.0
        for k in range(len(BANDS)):
            if view.weight[k] <= 0 or self.frames[k] <= 0:
                continue
            w = view.weight[k] * min(1.0, self.frames[k] / 3.0)
            total += w * hellinger(self.hist[k], view.hist[k])
            weight += w
        return total / weight if weight > 0 else None

    def as_view(self) -> "View":
        return View(hist=self.hist.copy(), weight=np.minimum(self.frames, 10.0) / 10.0)

    def to_dict(self) -> dict:
        return {"bands": list(BANDS), "hist": np.round(self.hist, 5).tolist(),
                "frames": self.frames.tolist(), "height_m": None if not math.isfinite(self.height_m) else self.height_m,
                "height_frames": self.height_frames}

    @classmethod
    def from_dict(cls, d: Mapping, *, where: str = "appearance model") -> "AppearanceModel":
        try:
            if list(d["bands"]) != list(BANDS):
                raise ValueError(f"bands must be {list(BANDS)}, got {d['bands']!r}")
            hist = np.asarray(d["hist"], dtype=np.float64)
            frames = np.asarray(d["frames"], dtype=np.float64)
            if hist.shape != (len(BANDS), N_BINS) or frames.shape != (len(BANDS),):
                raise ValueError(f"hist must be {len(BANDS)}x{N_BINS} and frames {len(BANDS)} numbers")
            if not (np.all(np.isfinite(hist)) and np.all(hist >= 0) and np.all(frames >= 0)):
                raise ValueError("hist and frames must be finite and non-negative")
            height = d.get("height_m")
            height = float("nan") if height is None else float(height)
            return cls(hist=hist, frames=frames, height_m=height, height_frames=int(d.get("height_frames", 0)))
        except KeyError as exc:
            raise ValueError(f"{where}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None


@dataclass
class View:
    """One frame's views of a body: per band a normalised histogram and a weight in [0, 1]
    (0: no clean view of that band)."""

    hist: np.ndarray
    weight: np.ndarray

    @property
    def empty(self) -> bool:
        return not bool(np.any(self.weight > 0))


@dataclass(frozen=True)
class Resident:
    """A person enrolled in the site: their name and appearance model."""

    name: str
    model: AppearanceModel
