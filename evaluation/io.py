"""Reading, writing and validating the track and event files.

The formats are the run files of :mod:`common.runfiles` (a tracks CSV and
events JSON lines), used both for ground truth and for a run's output.
Postures are checked against :data:`POSTURES`; events are
:class:`~common.messages.Event`, the system's one event type, and kinds
outside :data:`SCORED_KINDS` (``camera_lost`` and the like) are read and kept
but not scored.

Ground truth sits in ``TRUTH/truth/`` or directly in ``TRUTH/``, optionally
with ``meta.json`` holding ``fps`` and ``n_frames``. Every problem raises
:class:`EvalFormatError` naming the file, the line and the field.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common import messages, runfiles
from common.messages import Event
from common.postures import POSTURES
from common.runfiles import EVENTS_FILE, META_FILE, REQUIRED_TRACK_COLUMNS, TRACKS_FILE

SCORED_KINDS: tuple[str, ...] = messages.PERSON_EVENT_KINDS


class EvalFormatError(ValueError):
    """A track, event or meta file that cannot be used; the message names file, line and field."""


@dataclass(frozen=True)
class TrackTable:
    """All rows of one tracks file, as parallel arrays sorted by (frame, id).

    ``frame`` (N,) int64; ``stamp_ns`` (N,) int64; ``track_id`` (N,) str;
    ``x``, ``y``, ``z_top`` (N,) float64, world frame, metres; ``posture`` (N,) str;
    ``person`` (N,) str, the enrolled resident's name, empty for anyone else (None
    given: all empty).
    """

    frame: np.ndarray
    stamp_ns: np.ndarray
    track_id: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z_top: np.ndarray
    posture: np.ndarray
    person: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.person is None:
            object.__setattr__(self, "person", np.full(self.frame.shape[0], "", dtype="<U1"))

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    @property
    def xy_m(self) -> np.ndarray:
        """(N, 2) float64 floor positions, world frame, metres."""
        return np.column_stack([self.x, self.y]) if len(self) else np.zeros((0, 2))

    def fps_from_stamps(self) -> float | None:
        """Frames per second from the first and last frame's earliest stamps; None when unusable."""
        if len(self) < 2:
            return None
        f0, f1 = int(self.frame.min()), int(self.frame.max())
        if f1 == f0:
            return None
        s0 = int(self.stamp_ns[self.frame == f0].min())
        s1 = int(self.stamp_ns[self.frame == f1].min())
        return None if s1 <= s0 else (f1 - f0) / ((s1 - s0) / 1e9)

    @classmethod
    def from_rows(cls, rows: Iterable[Sequence[Any]]) -> "TrackTable":
        """Build from ``(frame, stamp_ns, id, x, y, z_top, posture[, person])`` tuples; sorts by
        (frame, id)."""
        rows = [tuple(r) if len(r) > 7 else (*r, "") for r in rows]
        if not rows:
            return cls.empty()
        cols = list(zip(*rows))
        table = cls(
            frame=np.asarray(cols[0], dtype=np.int64),
            stamp_ns=np.asarray(cols[1], dtype=np.int64),
            track_id=np.asarray([str(v) for v in cols[2]], dtype=str),
            x=np.asarray(cols[3], dtype=np.float64),
            y=np.asarray(cols[4], dtype=np.float64),
            z_top=np.asarray(cols[5], dtype=np.float64),
            posture=np.asarray([str(v) for v in cols[6]], dtype=str),
            person=np.asarray(["" if v is None else str(v) for v in cols[7]], dtype=str),
        )
        return table.sorted()

    @classmethod
    def empty(cls) -> "TrackTable":
        f = np.zeros(0, dtype=np.int64)
        z = np.zeros(0, dtype=np.float64)
        s = np.zeros(0, dtype=str)
        return cls(frame=f, stamp_ns=f.copy(), track_id=s, x=z, y=z.copy(), z_top=z.copy(), posture=s.copy())

    def sort_order(self) -> np.ndarray:
        """(N,) int64 row order that sorts the table by (frame, id)."""
        return np.lexsort((self.track_id, self.frame)).astype(np.int64)

    def take(self, rows: np.ndarray) -> "TrackTable":
        """The table made of ``rows`` (an index array or boolean mask), in that order."""
        return TrackTable(**{name: getattr(self, name)[rows] for name in _FIELDS})

    def sorted(self) -> "TrackTable":
        return self.take(self.sort_order())

    def rows(self) -> Iterable[tuple[int, int, str, float, float, float, str]]:
        """``(frame, stamp_ns, id, x, y, z_top, posture)`` per row (see :meth:`named_rows`)."""
        for i in range(len(self)):
            yield (
                int(self.frame[i]),
                int(self.stamp_ns[i]),
                str(self.track_id[i]),
                float(self.x[i]),
                float(self.y[i]),
                float(self.z_top[i]),
                str(self.posture[i]),
            )


    def named_rows(self) -> Iterable[tuple[int, int, str, float, float, float, str, str]]:
        """:meth:`rows` with each row's ``person`` at the end."""
        for row, person in zip(self.rows(), self.person):
            yield (*row, str(person))


_FIELDS = ("frame", "stamp_ns", "track_id", "x", "y", "z_top", "posture", "person")


@dataclass(frozen=True)
class Meta:
    """What ``meta.json`` says about a recording; None where it says nothing."""

    fps: float | None = None
    n_frames: int | None = None


# ---------------------------------------------------------------- tracks


def read_tracks(path: str | Path) -> TrackTable:
    """Read and validate a tracks CSV; raise :class:`EvalFormatError` on any problem."""
    path = Path(path)
    text = _read_text(path)
    reader = csv.reader(text.splitlines())
    try:
        header = next(reader)
    except StopIteration:
        raise EvalFormatError(f"tracks file {path}: empty, expected the header {','.join(REQUIRED_TRACK_COLUMNS)}") from None
    header = [h.strip() for h in header]
    missing = [c for c in REQUIRED_TRACK_COLUMNS if c not in header]
    if missing:
        raise EvalFormatError(
            f"tracks file {path}, line 1: header lacks {missing}; expected {','.join(REQUIRED_TRACK_COLUMNS)}"
            f" (and optionally person), got {','.join(header)}"
        )
    dupes = sorted({h for h in header if header.count(h) > 1})
    if dupes:
        raise EvalFormatError(f"tracks file {path}, line 1: repeated columns {dupes}")
    col = {name: header.index(name) for name in REQUIRED_TRACK_COLUMNS}
    person_col = header.index("person") if "person" in header else None
    rows: list[tuple] = []
    seen: dict[tuple[int, str], int] = {}
    for line_no, cells in enumerate(reader, start=2):
        if not cells or all(not c.strip() for c in cells):
            continue
        if len(cells) != len(header):
            raise EvalFormatError(f"tracks file {path}, line {line_no}: {len(cells)} fields, the header has {len(header)}")
        where = f"tracks file {path}, line {line_no}"
        frame = _int_cell(cells[col["frame"]], where, "frame", minimum=0)
        stamp_ns = _int_cell(cells[col["stamp_ns"]], where, "stamp_ns")
        track_id = cells[col["id"]].strip()
        if not track_id:
            raise EvalFormatError(f"{where}, field id: empty")
        x = _float_cell(cells[col["x"]], where, "x")
        y = _float_cell(cells[col["y"]], where, "y")
        z_top = _float_cell(cells[col["z_top"]], where, "z_top")
        posture = cells[col["posture"]].strip()
        if posture not in POSTURES:
            raise EvalFormatError(f"{where}, field posture: {posture!r} is not one of {list(POSTURES)}")
        key = (frame, track_id)
        if key in seen:
            raise EvalFormatError(f"{where}, field id: track {track_id} appears twice in frame {frame} (first on line {seen[key]})")
        seen[key] = line_no
        person = cells[person_col].strip() if person_col is not None else ""
        rows.append((frame, stamp_ns, track_id, x, y, z_top, posture, person))
    return TrackTable.from_rows(rows)


def write_tracks(path: str | Path, tracks: TrackTable | Iterable[Sequence[Any]]) -> Path:
    """Write a tracks CSV (header first, rows sorted by frame then id); returns the path."""
    table = tracks if isinstance(tracks, TrackTable) else TrackTable.from_rows(tracks)
    return runfiles.write_tracks_file(path, table.named_rows())


# ---------------------------------------------------------------- events


def read_events(path: str | Path) -> list[Event]:
    """Read and validate an events JSON-lines file (blank lines are skipped); sorted by frame."""
    path = Path(path)
    text = _read_text(path)
    events: list[Event] = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        where = f"events file {path}, line {line_no}"
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            raise EvalFormatError(f"{where}: not valid JSON: {exc.msg} at column {exc.colno}") from None
        events.append(event_from_json(obj, where))
    events.sort(key=lambda e: (e.frame, e.stamp_ns))
    return events


def event_from_json(obj: Any, where: str = "event") -> Event:
    """Validate one decoded event object; ``where`` prefixes every error message.

    The object is an :class:`~common.messages.Event` as its ``to_dict`` writes
    it, with ``id`` optional, ``track`` an integer (or its text; null or -1 for
    none) and ``x``/``y`` null for no place.
    """
    if not isinstance(obj, dict):
        raise EvalFormatError(f"{where}: expected a JSON object, got {type(obj).__name__}")
    for name in ("kind", "frame", "stamp_ns"):
        if name not in obj:
            raise EvalFormatError(f"{where}, field {name}: required field is missing")
    fields = dict(obj)
    fields["frame"] = _json_int(obj["frame"], where, "frame", minimum=0)
    fields["stamp_ns"] = _json_int(obj["stamp_ns"], where, "stamp_ns")
    track = obj.get("track")
    if isinstance(track, str):
        try:
            fields["track"] = int(track)
        except ValueError:
            raise EvalFormatError(f"{where}, field track: expected an integer track id or null, got {track!r}") from None
    x = _json_coord(obj.get("x"), where, "x")
    y = _json_coord(obj.get("y"), where, "y")
    if (x is None) != (y is None):
        raise EvalFormatError(f"{where}, fields x/y: give both or neither")
    details = obj.get("details")
    if details is not None and not isinstance(details, dict):
        raise EvalFormatError(f"{where}, field details: expected an object, got {type(details).__name__}")
    try:
        return Event.from_dict(fields)
    except messages.WireError as exc:
        text = str(exc).removeprefix("Event: ").replace("field '", "field ").replace("':", ":")
        raise EvalFormatError(f"{where}, {text}") from None


def write_events(path: str | Path, events: Iterable[Event]) -> Path:
    """Write events as JSON lines, one object per line; returns the path."""
    return runfiles.write_events_file(path, (ev.to_dict() for ev in events))


# ---------------------------------------------------------------- meta and folders


def read_meta(path: str | Path) -> Meta:
    """Read ``meta.json``: ``fps`` (> 0) and ``n_frames`` (>= 0), both optional; other keys are ignored."""
    path = Path(path)
    where = f"meta file {path}"
    try:
        obj = json.loads(_read_text(path))
    except json.JSONDecodeError as exc:
        raise EvalFormatError(f"{where}, line {exc.lineno}: not valid JSON: {exc.msg}") from None
    if not isinstance(obj, dict):
        raise EvalFormatError(f"{where}: expected a JSON object")
    fps = obj.get("fps")
    if fps is not None:
        if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
            raise EvalFormatError(f"{where}, field fps: expected a positive number, got {fps!r}")
        fps = float(fps)
    n_frames = obj.get("n_frames")
    if n_frames is not None:
        n_frames = _json_int(n_frames, where, "n_frames", minimum=0)
    return Meta(fps=fps, n_frames=n_frames)


def truth_file(truth_dir: str | Path, name: str) -> Path | None:
    """``TRUTH/truth/<name>`` if present, else ``TRUTH/<name>`` if present, else None."""
    truth_dir = Path(truth_dir)
    for candidate in (truth_dir / "truth" / name, truth_dir / name):
        if candidate.is_file():
            return candidate
    return None


def read_truth_tracks(truth_dir: str | Path) -> TrackTable:
    path = truth_file(truth_dir, TRACKS_FILE)
    if path is None:
        raise EvalFormatError(f"truth folder {truth_dir}: no {TRACKS_FILE} in {Path(truth_dir) / 'truth'} or {truth_dir}")
    return read_tracks(path)


def read_truth_events(truth_dir: str | Path) -> list[Event] | None:
    """The truth events, or None when the truth folder has no events file."""
    path = truth_file(truth_dir, EVENTS_FILE)
    return None if path is None else read_events(path)


def read_truth_meta(truth_dir: str | Path) -> Meta:
    path = truth_file(truth_dir, META_FILE)
    return Meta() if path is None else read_meta(path)


def read_run_tracks(run_dir: str | Path) -> TrackTable:
    path = Path(run_dir) / TRACKS_FILE
    if not path.is_file():
        raise EvalFormatError(f"run folder {run_dir}: no {TRACKS_FILE}")
    return read_tracks(path)


def read_run_events(run_dir: str | Path, *, required: bool = True) -> list[Event]:
    """The run's events; a missing file is an error when ``required``, else no events."""
    path = Path(run_dir) / EVENTS_FILE
    if not path.is_file():
        if required:
            raise EvalFormatError(f"run folder {run_dir}: no {EVENTS_FILE} (the truth has events to score)")
        return []
    return read_events(path)


# ---------------------------------------------------------------- helpers


def _read_text(path: Path) -> str:
    kind = {".csv": "tracks file", ".jsonl": "events file", ".json": "meta file"}.get(path.suffix, "file")
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise EvalFormatError(f"{kind} {path}: not found") from None
    except IsADirectoryError:
        raise EvalFormatError(f"{kind} {path}: is a folder, expected a file") from None
    except UnicodeDecodeError:
        raise EvalFormatError(f"{kind} {path}: not UTF-8 text") from None
    except OSError as exc:
        raise EvalFormatError(f"{kind} {path}: cannot read: {exc.strerror or exc}") from None


def _int_cell(text: str, where: str, name: str, *, minimum: int | None = None) -> int:
    text = text.strip()
    try:
        value = int(text)
    except ValueError:
        raise EvalFormatError(f"{where}, field {name}: expected an integer, got {text!r}") from None
    if minimum is not None and value < minimum:
        raise EvalFormatError(f"{where}, field {name}: must be >= {minimum}, got {value}")
    return value


def _float_cell(text: str, where: str, name: str) -> float:
    text = text.strip()
    try:
        value = float(text)
    except ValueError:
        raise EvalFormatError(f"{where}, field {name}: expected a number in metres, got {text!r}") from None
    if not math.isfinite(value):
        raise EvalFormatError(f"{where}, field {name}: must be finite, got {text!r}")
    return value


def _json_int(value: Any, where: str, name: str, *, minimum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (isinstance(value, float) and not value.is_integer()):
        raise EvalFormatError(f"{where}, field {name}: expected an integer, got {value!r}")
    value = int(value)
    if minimum is not None and value < minimum:
        raise EvalFormatError(f"{where}, field {name}: must be >= {minimum}, got {value}")
    return value


def _json_coord(value: Any, where: str, name: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise EvalFormatError(f"{where}, field {name}: expected a finite number in metres or null, got {value!r}")
    return float(value)
