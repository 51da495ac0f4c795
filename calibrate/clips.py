"""Reading calibration clips: a video file, an image folder or a live camera, as grey frames.

Floor clips are cut into still stretches (the board lies still at one place; carrying it to
the next place moves the picture), and each stretch is reduced to its median frame, which
removes most sensor and compression noise before the board is looked for.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
CHANGE_GREY = 12
"""A pixel of the quarter-size image changed between two frames when it moved by more than this (grey levels)."""
STILL_SHARE = 0.001
"""Two frames show a still scene when at most this share of the pixels changed (a board put down or
taken away changes far more; sensor noise far less)."""
MIN_STILL_FRAMES = 3
MEDIAN_FRAMES = 15
LIVE_FRAMES = 150


class ClipError(ValueError):
    """A clip that cannot be read; the message names it."""


@dataclass(frozen=True)
class Still:
    """A still stretch of a clip: frames ``start`` .. ``stop - 1`` and their median (H, W) uint8 frame."""

    start: int
    stop: int
    gray: np.ndarray


def read_gray(clip: str, *, spread: int | None = None) -> tuple[list[np.ndarray], list[int]]:
    """Grey frames of ``clip`` (a video file, an image folder, or a device index / stream URL read for
    :data:`LIVE_FRAMES` frames) and their frame indices; ClipError naming the clip when nothing can be read.
    spread: read about this many frames, evenly spread over a long clip (default every frame)."""
    path = Path(clip)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        step = max(1, -(-len(files) // spread)) if spread else 1
        frames, index = [], []
        for i in range(0, len(files), step):
            img = cv2.imread(str(files[i]), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise ClipError(f"clip {clip}: image {files[i].name} cannot be read")
            frames.append(img)
            index.append(i)
        if not frames:
            raise ClipError(f"clip {clip}: the folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
        return frames, index
    live = clip.isdigit() or "://" in clip
    if not live and not path.is_file():
        raise ClipError(f"clip {clip}: not found")
    cap = cv2.VideoCapture(int(clip) if clip.isdigit() else clip)
    try:
        if not cap.isOpened():
            raise ClipError(f"clip {clip}: OpenCV cannot open it as a video")
        count = 0 if live else int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        step = max(1, -(-count // spread)) if spread and count > 0 else 1
        frames, index, i = [], [], 0
        limit = LIVE_FRAMES if live else 1_000_000
        while len(frames) < limit:
            ok, frame = cap.read()
            if not ok or frame is None:
                break
            if i % step == 0:
                frames.append(frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
                index.append(i)
            i += 1
    finally:
        cap.release()
    if not frames:
        raise ClipError(f"clip {clip}: no frame could be decoded (not a video OpenCV reads, or empty)")
    return frames, index


def still_stretches(frames: list[np.ndarray], index: list[int]) -> list[Still]:
    """The still stretches of at least :data:`MIN_STILL_FRAMES` frames, each with its median frame."""
    if len(frames) < 2:
        return [Still(index[0], index[0] + 1, frames[0])] if frames else []
    small = [cv2.resize(f, (max(1, f.shape[1] // 4), max(1, f.shape[0] // 4)), interpolation=cv2.INTER_AREA).astype(np.int16)
             for f in frames]
    change = [float((np.abs(a - b) > CHANGE_GREY).mean()) for a, b in zip(small, small[1:])]
    out, start = [], 0
    for i in range(1, len(frames) + 1):
        if i == len(frames) or change[i - 1] > STILL_SHARE:
            if i - start >= MIN_STILL_FRAMES:
                picked = frames[start:i]
                if len(picked) > MEDIAN_FRAMES:
                    picked = [picked[k] for k in np.linspace(0, len(picked) - 1, MEDIAN_FRAMES).astype(int)]
                out.append(Still(index[start], index[i - 1] + 1, np.median(np.stack(picked), axis=0).astype(np.uint8)))
            start = i
    return out
