"""The fusion server's output files: ``tracks.csv`` and ``events.jsonl``; per-camera mask overlays.

Both are the run files of :mod:`common.runfiles`, which the evaluation
reads too, so a live run can be scored like a replay:

* ``tracks.csv``: one row per confirmed track per fused frame (``person``: the
  enrolled resident's name, empty for anyone else);
* ``events.jsonl``: one ``Event.to_dict()`` object per line.

Each frame's rows and each event go out in one ``write`` followed by a
flush, so a server that is killed loses nothing it had written. Files are
opened for appending: a restarted server carries on after the last complete
line (a partial last line, cut by a kill in mid-write, is trimmed first), and
an existing ``tracks.csv`` must carry the expected header.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from common.messages import Event
from common.runfiles import EVENTS_FILE, TRACK_HEADER, TRACKS_FILE, event_line, write_track_rows

# the file names stay importable from here
__all__ = [
    "EVENTS_FILE",
    "TRACKS_FILE",
    "EventsWriter",
    "RunOutputs",
    "TracksWriter",
]


class TrackRow(Protocol):
    """What a track row needs (``pipeline.TrackOutput`` has it)."""

    id: int
    x: float
    y: float
    z_top: float
    posture: str
    person: str | None  # the enrolled resident's name, None for anyone else


class TracksWriter:
    """Appends fused frames to a tracks CSV, one flush per frame.

    path: the CSV file; created with its header (and folder) when absent or
    empty. ValueError names the file when it cannot be opened or its header
    is not :data:`common.runfiles.TRACK_HEADER`.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fh = _open_append(self.path, header=TRACK_HEADER)
        self.rows_written = 0

    def write_frame(self, frame: int, stamp_ns: int, tracks: Iterable[TrackRow]) -> int:
        """Append one row per track of frame ``frame``; returns the number of rows.

        Tracks with a non-finite position or height are left out (the
        format has no place for them).
        """
        rows = []
        for t in tracks:
            x, y, z = float(t.x), float(t.y), float(t.z_top)
            if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
                rows.append((frame, stamp_ns, int(t.id), x, y, z, t.posture, getattr(t, "person", None)))
        buf = io.StringIO()
        n = write_track_rows(buf, rows)
        if n:
            self._fh.write(buf.getvalue())
            self._fh.flush()
            self.rows_written += n
        return n

    def close(self) -> None:
        self._fh.close()


class EventsWriter:
    """Appends events to a JSON-lines file, one flush per event (see :func:`common.runfiles.event_line`)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fh = _open_append(self.path, header=None)
        self.events_written = 0

    def write(self, event: Event | Mapping[str, Any]) -> None:
        """Append one event (an :class:`~common.messages.Event` or its ``to_dict()``) as one line."""
        obj = event.to_dict() if isinstance(event, Event) else dict(event)
        self._fh.write(event_line(obj))
        self._fh.flush()
        self.events_written += 1

    def close(self) -> None:
        self._fh.close()


class RunOutputs:
    """``tracks.csv`` and ``events.jsonl`` in one folder (created if absent).

    The live server appends (a restart carries on the same files); ``fresh``
    starts both files anew, as a replay of a whole recording must.
    """

    def __init__(self, out_dir: str | Path, *, fresh: bool = False) -> None:
        self.out_dir = Path(out_dir)
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            if fresh:
                for name in (TRACKS_FILE, EVENTS_FILE):
                    (self.out_dir / name).unlink(missing_ok=True)
        except OSError as exc:
            raise ValueError(f"output folder {self.out_dir}: cannot prepare it: {exc.strerror or exc}") from None
        self.tracks = TracksWriter(self.out_dir / TRACKS_FILE)
        try:
            self.events = EventsWriter(self.out_dir / EVENTS_FILE)
        except ValueError:
            self.tracks.close()
            raise

    def write_frame(self, frame: int, stamp_ns: int, tracks: Iterable[TrackRow]) -> int:
        return self.tracks.write_frame(frame, stamp_ns, tracks)

    def write_event(self, event: Event | Mapping[str, Any]) -> None:
        self.events.write(event)

    def close(self) -> None:
        self.tracks.close()
        self.events.close()

    def __enter__(self) -> "RunOutputs":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- helpers


def _open_append(path: Path, *, header: str | None):
    """Open ``path`` for appending after its last complete line; write ``header`` into a new file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("a+b") as raw:
            raw.seek(0, io.SEEK_END)
            size = raw.tell()
            if size:
                _trim_partial_line(raw, size)
                if header is not None:
                    raw.seek(0)
                    first = raw.readline().decode("utf-8", errors="replace").strip()
                    if first and first != header:
                        raise ValueError(f"tracks file {path}: header is {first!r}, expected {header!r}; "
                                         "refusing to append to another kind of file")
        fh = path.open("a", encoding="utf-8", newline="\n")
    except OSError as exc:
        raise ValueError(f"output file {path}: cannot open for appending: {exc.strerror or exc}") from None
    if header is not None and fh.tell() == 0:
        fh.write(header + "\n")
        fh.flush()
    return fh


def _trim_partial_line(raw, size: int) -> None:
    """Cut whatever follows the last newline (a line a killed writer left half written)."""
    raw.seek(size - 1)
    if raw.read(1) == b"\n":
        return
    pos, chunk = size, 4096
    while pos > 0:
        start = max(0, pos - chunk)
        raw.seek(start)
        data = raw.read(pos - start)
        idx = data.rfind(b"\n")
        if idx >= 0:
            raw.truncate(start + idx + 1)
            return
        pos = start
    raw.truncate(0)


def mask_overlay(
    frame_bgr: np.ndarray,
    mask: np.ndarray,
    out_png: str | Path,
    *,
    colour_bgr: tuple[int, int, int] = (0, 0, 255),
    alpha: float = 0.45,
) -> Path:
    """Tint a camera frame where its foreground mask is set and outline the blobs; write a PNG.

    ``frame_bgr`` (H, W, 3) uint8 BGR, or (H, W) uint8 grey; ``mask`` (h, w)
    bool or uint8, foreground > 0 (shadows marked 127, as OpenCV's MOG2 does,
    are tinted grey instead); a mask of another size, e.g. a downscaled one,
    is resized to the frame. The PNG has the frame's size.
    """
    import cv2

    frame = np.asarray(frame_bgr)
    if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
        raise ValueError(f"frame_bgr must be (H, W, 3) or (H, W) uint8, got {frame.shape} {frame.dtype}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must lie in 0..1, got {alpha}")
    if frame.ndim == 2:
        frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    m = np.asarray(mask)
    if m.ndim != 2 or m.size == 0:
        raise ValueError(f"mask must be a non-empty (h, w) array, got shape {m.shape}")
    m = m.astype(np.uint8) * 255 if m.dtype == bool else m.astype(np.uint8)
    h, w = frame.shape[:2]
    if m.shape != (h, w):
        m = cv2.resize(m, (w, h), interpolation=cv2.INTER_NEAREST)
    shadow = m == 127
    fg = (m > 0) & ~shadow
    out = frame.copy()
    for sel, colour in ((fg, colour_bgr), (shadow, (160, 160, 160))):
        if sel.any():
            tint = np.empty_like(frame)
            tint[:] = colour
            blend = cv2.addWeighted(frame, 1.0 - alpha, tint, alpha, 0.0)
            out[sel] = blend[sel]
    contours, _ = cv2.findContours(fg.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, colour_bgr, 1, lineType=cv2.LINE_AA)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out_png), out):
        raise OSError(f"mask overlay {out_png}: OpenCV could not write the PNG")
    return out_png
