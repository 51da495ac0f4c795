"""Has this camera's view moved? The live picture registered against a reference of the empty room.

A camera bumped by a cleaner, turned by 2 degrees or shifted by 10 cm, goes
on sending clean masks: its background model learns the new view within
seconds. Only the camera host still has the picture, so the worker checks
it: about once a second (``every_s`` of capture time) it registers the
current frame against a reference picture of the room, taken once when the
background model has been learned (the model's background image, people
left out), and sends how far the view has moved with every mask
(``MaskFrame.view_shift_px``); the fusion server turns that into degrees
through the camera's calibration and decides (:mod:`fusion_server.consistency`).

**One measurement** (:func:`register`). Both pictures are made grey and small
(``width_px`` wide, area-averaged: sensor noise and compression average out)
and cut into ``TILES`` (6 x 4). Each tile that shows enough of the room (at
least ``TILE_ROOM`` of it: the current mask's people, dilated, are left out,
and so is what the reference shows nothing of, such as a fisheye's corners
outside its image circle) and has texture is lined up on its own: phase
correlation's translation, refined by OpenCV's enhanced correlation
coefficient (ECC) over the tile's room pixels (a mask that floods, as the
background model's does right after a move, shows no people and is not
used: ``FLOODED``); a tile whose fit stays under
``min_fit`` is dropped. Both measures ignore the light's brightness and
contrast, so lights and daylight do not read as movement. A similarity warp
(a shift, a turn about the picture's axis, a scale: what moving a camera
does to a distant room; nothing shears it) is then fitted to the tiles'
translations by least median of squares, so that a few tiles that changed
for another reason (a chair moved, a person the background model has
absorbed or the mask missed) cannot pull it. The **shift** is the root
mean square of how far that warp moves a 5x5 grid of points over the image,
in pixels of the capture frame: a turn moves every point alike (by about the
focal length times the angle), a shift along the camera's axis moves the
edges (the warp's scale), a roll moves the corners. With fewer than
``min_tiles`` tiles to go on (a dark room, a covered lens, a crowd in front
of the camera) there is no measurement and the previous one stands.

On the tuning worlds an untouched camera reads under 0.13 degree, also in
crowds of 11-12 people (with the masks' own faults), a 2 degree turn 1.5-2.4
degrees and a 10 cm shift 0.6-3.5 (the nearer the room, the more); the lab
recording's untouched cameras read under 0.16 degree (docs/guides/calibrating.md, "Keeping
cameras calibrated").

Pure apart from OpenCV; no clock (time is the frames' capture stamps).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pydantic import Field

from common.settings import Settings

DARK = 12
"""Grey level under which a reference pixel shows nothing (a border, a fisheye's corners)."""
EDGE_PX = 3
"""How far (small-picture pixels) from what shows nothing, and from a person, a pixel must be to count."""
GRID = 5
"""The shift is measured on a GRID x GRID lattice of points over the picture."""
FLOODED = 0.5
"""A mask with more foreground than this share is not people but the background model seeing a changed
view (as right after a move, until it has learned the new one): the picture is measured without it."""
TILES = (6, 4)
"""Tiles across and down, each lined up on its own."""
TILE_ROOM = 0.7
"""A tile is lined up when at least this share of it shows the room."""
TILE_TEXTURE = 3.0
"""... and its room pixels vary by at least this many grey levels (standard deviation)."""


class ViewCheckParams(Settings):
    """Settings of :class:`ViewCheck` (module text), each declared with its range."""

    every_s: float = Field(1.0, ge=0.0, allow_inf_nan=False)
    width_px: int = Field(320, ge=32, le=1024, strict=True)
    min_fit: float = Field(0.7, gt=0.0, lt=1.0)
    min_tiles: int = Field(6, ge=3, strict=True)
    iterations: int = Field(50, ge=1, strict=True)


@dataclass(frozen=True)
class Registration:
    """One measurement: ``shift_px`` (capture pixels, root mean square over the lattice), the
    ``warp`` (2x3 similarity, small-picture pixels, reference onto current picture), the ``tiles``
    lined up and the ``agreeing`` ones (the fit's inliers)."""

    shift_px: float
    warp: np.ndarray
    tiles: int
    agreeing: int


class ViewCheck:
    """Per camera: the reference picture and the latest measured shift (module text).

    ``reference``: a picture of the empty room (BGR or grey ``uint8``, any size), or None to
    take one later with :meth:`set_reference`.
    """

    def __init__(self, params: ViewCheckParams = ViewCheckParams(), reference: np.ndarray | None = None) -> None:
        self.params = params
        self._reference: np.ndarray | None = None
        self._room: np.ndarray | None = None
        self._next_ns: int | None = None
        self.shift_px: float | None = None
        """The latest measured shift (capture pixels), None before the first measurement."""
        self.last: Registration | None = None
        self.measured = 0
        self.skipped = 0
        if reference is not None:
            self.set_reference(reference)

    @property
    def has_reference(self) -> bool:
        return self._reference is not None

    def set_reference(self, picture: np.ndarray) -> None:
        """Take ``picture`` (the empty room) as the view to compare with; forgets the shift."""
        small = _small_grey(picture, self.params.width_px)
        self._reference = small
        room = (small > DARK).astype(np.uint8)
        self._room = cv2.erode(room, _disc(EDGE_PX))
        self.shift_px, self.last, self._next_ns = None, None, None

    def follow(self, segmenter, image: np.ndarray, mask: np.ndarray, fg_fraction: float, relearning: bool,
               stamp_ns: int) -> float | None:
        """:meth:`observe` for a camera segmented by ``segmenter`` (a
        :class:`~camera_worker.segmentation.ForegroundSegmenter`): without a reference yet, the
        model's background image becomes it once the model has learned the room (a background clip,
        or a window of live frames) on a frame that is mostly room (``fg_fraction`` at most 0.2, not
        ``relearning`` after a light change). Returns the latest shift, None until measured."""
        if self._reference is None:
            if not segmenter.learned or fg_fraction > 0.2 or relearning:
                return None
            self.set_reference(segmenter.background_image())
        return self.observe(image, mask, stamp_ns)

    def observe(self, image: np.ndarray, mask: np.ndarray | None, stamp_ns: int) -> float | None:
        """The frame captured at ``stamp_ns`` with its foreground ``mask`` (any size; None: nobody):
        measured when one is due. Returns the latest shift (capture pixels), None until measured."""
        if self._reference is None:
            return None
        stamp_ns = int(stamp_ns)
        if self._next_ns is not None and stamp_ns < self._next_ns:
            return self.shift_px
        self._next_ns = stamp_ns + int(self.params.every_s * 1e9)
        reg = self.measure(image, mask)
        if reg is None:
            self.skipped += 1
        else:
            self.measured += 1
            self.last, self.shift_px = reg, reg.shift_px
        return self.shift_px

    def measure(self, image: np.ndarray, mask: np.ndarray | None) -> Registration | None:
        """One registration of ``image`` against the reference, None when it cannot be trusted."""
        if self._reference is None:
            raise ValueError("no reference picture yet")
        small = _small_grey(image, self.params.width_px)
        if small.shape != self._reference.shape:
            small = cv2.resize(small, self._reference.shape[::-1], interpolation=cv2.INTER_AREA)
        room = self._room.copy()
        if mask is not None and np.count_nonzero(mask) <= FLOODED * np.size(mask):
            people = cv2.resize(np.asarray(mask, dtype=np.uint8), small.shape[::-1], interpolation=cv2.INTER_AREA)
            room[cv2.dilate((people > 0).astype(np.uint8), _disc(EDGE_PX)) > 0] = 0
        p = self.params
        reg = register(self._reference, small, room, min_fit=p.min_fit, min_tiles=p.min_tiles,
                       iterations=p.iterations)
        if reg is None:
            return None
        warp, tiles, agreeing = reg
        scale = np.asarray(image).shape[1] / small.shape[1]
        return Registration(shift_px=lattice_shift(warp, small.shape) * scale, warp=warp, tiles=tiles,
                            agreeing=agreeing)


def register(reference: np.ndarray, current: np.ndarray, room: np.ndarray, *, min_fit: float = 0.7,
             min_tiles: int = 6, iterations: int = 50) -> tuple[np.ndarray, int, int] | None:
    """The similarity warp (2x3) taking ``reference`` onto ``current`` (float32 grey pictures of one size),
    from the translations of the tiles that show the room (``room``: uint8, nonzero where a pixel
    counts) (module text): ``(warp, tiles lined up, tiles agreeing with the warp)``, None with fewer
    than ``min_tiles``."""
    h, w = reference.shape
    nx, ny = TILES
    th, tw = h // ny, w // nx
    window = cv2.createHanningWindow((tw, th), cv2.CV_32F)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, int(iterations), 1e-3)
    centres, moved = [], []
    for j in range(ny):
        for i in range(nx):
            rows, cols = slice(j * th, (j + 1) * th), slice(i * tw, (i + 1) * tw)
            ref, cur, ok = reference[rows, cols], current[rows, cols], room[rows, cols]
            if np.count_nonzero(ok) < TILE_ROOM * ok.size or float(ref[ok > 0].std()) < TILE_TEXTURE:
                continue
            # OpenCV works in place on float32 inputs (phase correlation windows them, ECC smooths
            # them): every call gets its own copies. People are painted over with the room.
            filled = np.where(ok > 0, cur, ref).astype(np.float32)
            (dx, dy), _ = cv2.phaseCorrelate(ref.copy(), filled, window)
            warp = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], np.float32)
            try:
                fit, warp = cv2.findTransformECC(ref.copy(), cur.copy(), warp, cv2.MOTION_TRANSLATION,
                                                 criteria, ok.copy(), 3)
            except cv2.error:  # did not converge
                continue
            if fit < min_fit or not np.all(np.isfinite(warp)):
                continue
            cx, cy = (i + 0.5) * tw, (j + 0.5) * th
            centres.append((cx, cy))
            moved.append((cx + warp[0, 2], cy + warp[1, 2]))
    if len(centres) < min_tiles:
        return None
    warp, inliers = cv2.estimateAffinePartial2D(np.array(centres, np.float32), np.array(moved, np.float32),
                                                  method=cv2.LMEDS)
    if warp is None or not np.all(np.isfinite(warp)):
        return None
    return warp, len(centres), int(np.count_nonzero(inliers))


def lattice_shift(warp: np.ndarray, shape: tuple[int, int]) -> float:
    """Root mean square of how far the 2x3 ``warp`` moves a GRID x GRID lattice over a picture of
    ``shape`` (h, w), in that picture's pixels."""
    h, w = shape
    ys, xs = np.meshgrid((np.arange(GRID) + 0.5) * h / GRID, (np.arange(GRID) + 0.5) * w / GRID, indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    moved = np.asarray(warp, dtype=np.float64) @ pts
    return float(np.sqrt(np.mean(np.sum((moved - pts[:2]) ** 2, axis=0))))


def load_reference(path: str | Path) -> np.ndarray | None:
    """The reference picture kept at ``path`` (None when there is none yet); ValueError when the
    file is there but is not a picture."""
    path = Path(path)
    if not path.exists():
        return None
    picture = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if picture is None or picture.dtype != np.uint8:
        raise ValueError(f"{path}: not an 8-bit picture (delete it to take a new reference view)")
    return picture


def save_reference(path: str | Path, picture: np.ndarray) -> None:
    """Keep ``picture`` at ``path`` (PNG, written beside it first, then renamed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    if not cv2.imwrite(str(tmp), np.asarray(picture)):
        raise OSError(f"{path}: cannot write the reference picture")
    tmp.replace(path)


def _small_grey(picture: np.ndarray, width_px: int) -> np.ndarray:
    picture = np.asarray(picture)
    if picture.dtype != np.uint8 or picture.ndim not in (2, 3):
        raise ValueError(f"a picture must be (H, W) or (H, W, 3) uint8, got {picture.shape} {picture.dtype}")
    grey = cv2.cvtColor(picture, cv2.COLOR_BGR2GRAY) if picture.ndim == 3 else picture
    h, w = grey.shape
    width_px = min(width_px, w)
    size = (width_px, max(8, int(round(h * width_px / w))))
    return cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32)


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
