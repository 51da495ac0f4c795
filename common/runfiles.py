"""The run files: ``tracks.csv`` and ``events.jsonl``.

The fusion server writes them, the ground truth of a synthetic scenario
comes in them, and the evaluation reads both; this module is where their
names and layouts are defined.

* **tracks CSV** (:data:`TRACKS_FILE`), header :data:`TRACK_HEADER`
  (``frame,stamp_ns,id,x,y,z_top,posture,person``): one row per person per
  frame; ``x``, ``y`` on the floor and ``z_top`` the top of the head, metres,
  world frame, four decimals; ``posture`` one of
  :data:`common.postures.POSTURES`; ``person`` the name of the enrolled
  resident the track is, empty for anyone else. Frames without rows have
  nobody in them. A track id is any non-empty text (``7``, ``alice``).
  Readers find columns by the header: ``person`` is optional
  (:data:`REQUIRED_TRACK_COLUMNS`), as files written before it lack it.
* **events JSON lines** (:data:`EVENTS_FILE`): one compact JSON object per
  line (:func:`event_line`: UTF-8, no spaces, non-finite numbers as
  ``null``), a :class:`common.messages.Event` with the fields
  :data:`EVENT_FIELDS`; ``id`` is optional for readers.
* **meta** (:data:`META_FILE`): a JSON object about a recording (``fps``,
  ``n_frames`` and whatever its writer adds).
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from common.plain import plain_value

TRACKS_FILE = "tracks.csv"
EVENTS_FILE = "events.jsonl"
META_FILE = "meta.json"
START_FILE = "start_ns"
"""The shared start of workers replaying in step (:mod:`common.sharedstart`)."""

TRACK_COLUMNS: tuple[str, ...] = ("frame", "stamp_ns", "id", "x", "y", "z_top", "posture", "person")
"""The columns of a tracks file, in the order they are written."""
REQUIRED_TRACK_COLUMNS: tuple[str, ...] = TRACK_COLUMNS[:7]
"""The columns a reader needs (``person`` came later and may be absent)."""
TRACK_HEADER = ",".join(TRACK_COLUMNS)
"""The first line of a tracks file (without its newline)."""

EVENT_FIELDS: tuple[str, ...] = ("id", "kind", "track", "frame", "stamp_ns", "x", "y", "details")
"""The fields of an event line, in the order ``common.messages.Event.to_dict`` puts them (a reader
takes ``id`` as optional)."""


def write_track_rows(fh: IO[str], rows: Iterable[Sequence[Any]]) -> int:
    """Write ``(frame, stamp_ns, id, x, y, z_top, posture[, person])`` rows to the open text
    file ``fh`` as tracks-file lines (no header); returns the number of rows.

    ``x``, ``y``, ``z_top`` metres, written with four decimals; ``id`` as its text;
    ``person`` empty when absent or None.
    """
    writer = csv.writer(fh, lineterminator="\n")
    n = 0
    for frame, stamp_ns, track_id, x, y, z_top, posture, *rest in rows:
        person = rest[0] if rest and rest[0] is not None else ""
        writer.writerow([int(frame), int(stamp_ns), track_id, f"{x:.4f}", f"{y:.4f}", f"{z_top:.4f}", posture, person])
        n += 1
    return n


def write_tracks_file(path: str | Path, rows: Iterable[Sequence[Any]]) -> Path:
    """Write a whole tracks file anew: the header, then ``rows`` in the order given
    (see :func:`write_track_rows`); creates the folder; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as fh:
        fh.write(TRACK_HEADER + "\n")
        write_track_rows(fh, rows)
    return path


def event_line(obj: Mapping[str, Any]) -> str:
    """One event object as its line of an events file, newline included.

    Numpy values are made plain and non-finite numbers ``null``
    (:func:`common.plain.plain_value`); keys keep their order.
    """
    return json.dumps(plain_value(obj), ensure_ascii=False, allow_nan=False, separators=(",", ":")) + "\n"


def write_events_file(path: str | Path, events: Iterable[Mapping[str, Any]]) -> Path:
    """Write a whole events file anew, one :func:`event_line` per event object; creates the folder;
    returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", encoding="utf-8", newline="\n") as fh:
        for obj in events:
            fh.write(event_line(obj))
    return path
