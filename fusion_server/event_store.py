"""The event history: an SQLite file the fusion server writes before it publishes.

:class:`EventStore` keeps every :class:`~common.messages.Event`
in one table keyed by the event id. ``add`` is idempotent (a second event
with the same id is ignored and reported as not added) and has committed
to disk when it returns, so an event that was published is always in the
history, also after a crash or restart. The database runs in WAL mode with
``synchronous=FULL``; one connection is shared by all threads behind a lock
(the zenoh queryable answers on its own thread).

When a write fails (the disk is full, the file is locked by another
process, the database is damaged), ``add`` appends the event to the
store's fallback file, ``<store>.pending.jsonl`` (one JSON event per line,
flushed to disk), and raises :class:`EventNotStored` saying whether the
event was kept there. The fallback is merged back into the database at the
next successful write and when the store is opened; ``pending`` says how
many events wait in it.

:func:`parse_history_selector` turns the parameters of a
``<p>/history/events`` query into a :class:`HistoryFilter`:

* ``since``, ``until``: integer nanoseconds since the Unix epoch, or an
  ISO-8601 time (``2024-05-01T19:00:00Z``, ``2024-05-01T19:00+02:00``,
  ``2024-05-01``); times without a zone are site-local (``utc_offset_h``).
  The range is half-open: ``since <= stamp_ns < until``.
* ``kind``: one kind or a comma (or ``|``) separated list.
* ``format``: ``json`` (default) or ``msgpack``: how the replies are encoded.
* ``limit``: at most this many events (default 1000, at most 100000),
  oldest first.

Parameters whose name starts with ``_`` are zenoh's own and are ignored.
Times beyond the year 2262 (the largest 64-bit nanosecond stamp) are refused
like any other bad value; error texts quote at most a few dozen characters of
what was asked, however long the query.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import sqlite3
import threading
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, Iterable, Mapping

from common.messages import Event

log = logging.getLogger("voxelwatch.fusion")

SCHEMA_VERSION = 1
PENDING_SUFFIX = ".pending.jsonl"
"""Appended to the store's file name to name its fallback file."""
DEFAULT_LIMIT = 1000
MAX_LIMIT = 100_000
FORMATS = ("json", "msgpack")
SELECTOR_PARAMETERS = ("since", "until", "kind", "format", "limit")
MAX_STAMP_NS = 2**63 - 1
"""The largest stamp the store (a 64-bit integer column) can hold or compare."""

_SCHEMA = """
CREATE TABLE IF NOT EXISTS events (
    id       TEXT PRIMARY KEY,
    kind     TEXT NOT NULL,
    track    INTEGER NOT NULL,
    stamp_ns INTEGER NOT NULL,
    frame    INTEGER NOT NULL,
    x        REAL NOT NULL,
    y        REAL NOT NULL,
    details  TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS events_by_stamp ON events (stamp_ns);
CREATE INDEX IF NOT EXISTS events_by_kind ON events (kind, stamp_ns);
CREATE TABLE IF NOT EXISTS snapshot (
    id       INTEGER PRIMARY KEY CHECK (id = 1),
    stamp_ns INTEGER NOT NULL,
    body     TEXT NOT NULL
);
"""


class EventNotStored(ValueError):
    """An event the database could not write; ``kept``: it went to the fallback file instead."""

    def __init__(self, message: str, *, kept: bool) -> None:
        super().__init__(message)
        self.kept = kept


class EventStore:
    """Durable, thread-safe event history in an SQLite file.

    path: the database file (created with its folder if absent), or
        ``":memory:"`` for a throw-away store (no fallback file).
    timeout_s: how long to wait for another process's write lock.
    fallback_path: where events go when the database cannot take them
        (default: ``path`` + ``.pending.jsonl``).
    """

    def __init__(self, path: str | Path, *, timeout_s: float = 5.0, fallback_path: str | Path | None = None) -> None:
        self.path = str(path) if str(path) == ":memory:" else str(Path(path).expanduser())
        if fallback_path is not None:
            self.fallback_path: Path | None = Path(fallback_path).expanduser()
        else:
            self.fallback_path = None if self.path == ":memory:" else Path(self.path + PENDING_SUFFIX)
        self.pending = 0
        self.merged = 0
        if self.path != ":memory:":
            try:
                Path(self.path).resolve().parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise ValueError(f"event store {self.path}: cannot create its folder: {exc}") from None
        self._lock = threading.Lock()
        try:
            self._db: sqlite3.Connection | None = sqlite3.connect(
                self.path, timeout=timeout_s, check_same_thread=False
            )
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version > SCHEMA_VERSION:
                raise ValueError(
                    f"event store {self.path}: schema version {version} is newer than this build's {SCHEMA_VERSION}"
                )
            self._db.executescript(_SCHEMA)
            self._db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
            self._db.commit()
        except sqlite3.Error as exc:
            raise ValueError(f"event store {self.path}: cannot open: {exc}") from None
        with self._lock:
            self.pending = self._count_pending()
            if self.pending:
                self._merge_pending()

    # ------------------------------------------------------------------ writing

    def add(self, event: Event | Mapping[str, Any]) -> bool:
        """Store one event and commit. True if it was new, False if its id was
        already stored (the stored one is kept). ValueError for a malformed event;
        :class:`EventNotStored` when the database cannot write it (the event is then
        in the fallback file if that could be written). A successful write first
        merges what waits in the fallback file."""
        row = _row(event)
        with self._lock:
            db = self._open()
            if self.pending:
                self._merge_pending()
            try:
                cur = db.execute("INSERT OR IGNORE INTO events VALUES (?, ?, ?, ?, ?, ?, ?, ?)", row)
                db.commit()
            except sqlite3.Error as exc:
                _rollback(db)
                kept = self._keep_pending(event, row)
                where = f"kept in {self.fallback_path} until it can be merged" if kept else "and not kept anywhere"
                raise EventNotStored(f"event store {self.path}: cannot write event {row[0]!r} ({exc}); {where}",
                                     kept=kept) from None
            return cur.rowcount == 1

    def merge_pending(self) -> int:
        """Move the events of the fallback file into the database now; how many were new."""
        with self._lock:
            self._open()
            return self._merge_pending()

    def add_many(self, events: Iterable[Event | Mapping[str, Any]]) -> int:
        """Store several events in one transaction; returns how many were new."""
        rows = [_row(e) for e in events]
        with self._lock:
            db = self._open()
            try:
                before = db.total_changes
                db.executemany("INSERT OR IGNORE INTO events VALUES (?, ?, ?, ?, ?, ?, ?, ?)", rows)
                db.commit()
                return db.total_changes - before
            except sqlite3.Error as exc:
                db.rollback()
                raise ValueError(f"event store {self.path}: cannot write events: {exc}") from None

    # ------------------------------------------------------------------ reading

    def query(
        self,
        since_ns: int | None = None,
        until_ns: int | None = None,
        kinds: Iterable[str] | None = None,
        limit: int = DEFAULT_LIMIT,
        *,
        newest_first: bool = False,
    ) -> list[Event]:
        """Events with ``since_ns <= stamp_ns < until_ns`` (either bound optional)
        and a kind in ``kinds`` (None: all), oldest first (or newest first),
        at most ``limit``; ties in time keep the order they were added in."""
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_LIMIT:
            raise ValueError(f"limit must be an int in 1..{MAX_LIMIT}, got {limit!r}")
        where, args = [], []
        if since_ns is not None:
            where.append("stamp_ns >= ?")
            args.append(_int(since_ns, "since_ns"))
        if until_ns is not None:
            where.append("stamp_ns < ?")
            args.append(_int(until_ns, "until_ns"))
        if kinds is not None:
            kinds = [kinds] if isinstance(kinds, str) else list(kinds)
            if not kinds:
                return []
            where.append(f"kind IN ({', '.join('?' * len(kinds))})")
            args.extend(str(k) for k in kinds)
        order = "DESC" if newest_first else "ASC"
        sql = "SELECT id, kind, track, stamp_ns, frame, x, y, details FROM events"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += f" ORDER BY stamp_ns {order}, rowid {order} LIMIT ?"
        args.append(limit)
        with self._lock:
            try:
                rows = self._open().execute(sql, args).fetchall()
            except sqlite3.Error as exc:
                raise ValueError(f"event store {self.path}: cannot read: {exc}") from None
        return [
            Event(id=r[0], kind=r[1], track=r[2], stamp_ns=r[3], frame=r[4], x=r[5], y=r[6],
                  details=json.loads(r[7]))
            for r in rows
        ]

    def get(self, event_id: str) -> Event | None:
        """The stored event with id ``event_id``, or None."""
        with self._lock:
            try:
                row = self._open().execute(
                    "SELECT id, kind, track, stamp_ns, frame, x, y, details FROM events WHERE id = ?",
                    (str(event_id),)).fetchone()
            except sqlite3.Error as exc:
                raise ValueError(f"event store {self.path}: cannot read: {exc}") from None
        if row is None:
            return None
        return Event(id=row[0], kind=row[1], track=row[2], stamp_ns=row[3], frame=row[4], x=row[5], y=row[6],
                     details=json.loads(row[7]))

    def query_filter(self, flt: "HistoryFilter") -> list[Event]:
        """:meth:`query` with a :class:`HistoryFilter` from :func:`parse_history_selector`."""
        return self.query(flt.since_ns, flt.until_ns, flt.kinds, flt.limit)

    # ------------------------------------------------------------------ the fallback file

    def _keep_pending(self, event: Event | Mapping[str, Any], row: tuple) -> bool:
        """Append one event to the fallback file (flushed to disk); False if that fails too."""
        if self.fallback_path is None:
            return False
        rec = event if isinstance(event, Event) else Event.from_dict(dict(event))
        try:
            self.fallback_path.parent.mkdir(parents=True, exist_ok=True)
            with self.fallback_path.open("a", encoding="utf-8") as f:
                f.write(rec.to_json() + "\n")
                f.flush()
                os.fsync(f.fileno())
        except (OSError, ValueError) as exc:
            log.error("event store %s: cannot keep event %s in %s either: %s", self.path, row[0],
                      self.fallback_path, exc)
            return False
        self.pending += 1
        return True

    def _count_pending(self) -> int:
        if self.fallback_path is None or not self.fallback_path.is_file():
            return 0
        try:
            with self.fallback_path.open("rb") as f:
                return sum(1 for line in f if line.strip())
        except OSError:
            return 0

    def _merge_pending(self) -> int:
        """(Lock held.) Write the fallback file's events in one transaction, then remove it.
        Lines that do not parse are logged and left out; on a write error nothing changes."""
        path = self.fallback_path
        if path is None or not path.is_file():
            self.pending = 0
            return 0
        try:
            lines = [line for line in path.read_text(encoding="utf-8", errors="replace").splitlines() if line.strip()]
        except OSError as exc:
            log.warning("event store %s: cannot read %s: %s", self.path, path, exc)
            return 0
        rows = []
        for n, line in enumerate(lines, 1):
            try:
                rows.append(_row(Event.from_json(line)))
            except ValueError as exc:
                log.warning("event store %s: %s line %d is not an event, left out: %s", self.path, path, n,
                            str(exc)[:200])
        db = self._open()
        try:
            before = db.total_changes
            db.executemany("INSERT OR IGNORE INTO events VALUES (?, ?, ?, ?, ?, ?, ?, ?)", rows)
            db.commit()
            added = db.total_changes - before
        except sqlite3.Error as exc:
            _rollback(db)
            self.pending = len(lines)
            log.debug("event store %s: %d pending events not merged yet: %s", self.path, len(lines), exc)
            return 0
        try:
            path.unlink()
        except OSError as exc:  # merged; a second merge only finds them stored already
            log.warning("event store %s: merged %s but cannot remove it: %s", self.path, path, exc)
        self.pending = 0
        self.merged += added
        log.info("event store %s: %d events from %s merged into the store", self.path, added, path)
        return added

    def save_snapshot(self, stamp_ns: int, body: str) -> None:
        """Keep ``body`` (the server's :class:`~fusion_server.snapshot.Snapshot` as text) in place
        of the last one; ValueError when the database cannot write it."""
        with self._lock:
            db = self._open()
            try:
                db.execute("INSERT OR REPLACE INTO snapshot VALUES (1, ?, ?)", (int(stamp_ns), str(body)))
                db.commit()
            except sqlite3.Error as exc:
                _rollback(db)
                raise ValueError(f"event store {self.path}: cannot write the snapshot: {exc}") from None

    def load_snapshot(self) -> tuple[int, str] | None:
        """The last snapshot kept, ``(stamp_ns, body)``, or None."""
        with self._lock:
            try:
                row = self._open().execute("SELECT stamp_ns, body FROM snapshot WHERE id = 1").fetchone()
            except sqlite3.Error as exc:
                raise ValueError(f"event store {self.path}: cannot read the snapshot: {exc}") from None
        return None if row is None else (int(row[0]), str(row[1]))

    def count(self) -> int:
        with self._lock:
            return int(self._open().execute("SELECT COUNT(*) FROM events").fetchone()[0])

    # ------------------------------------------------------------------ lifetime

    def close(self) -> None:
        """Close the database; closing twice is harmless."""
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None

    def __enter__(self) -> "EventStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _open(self) -> sqlite3.Connection:
        if self._db is None:
            raise ValueError(f"event store {self.path} is closed")
        return self._db


@dataclass(frozen=True)
class HistoryFilter:
    """What a history query asks for (see :func:`parse_history_selector`)."""

    since_ns: int | None = None
    until_ns: int | None = None
    kinds: tuple[str, ...] | None = None
    format: str = "json"
    limit: int = DEFAULT_LIMIT


def parse_history_selector(
    parameters: str | Mapping[str, Any] | Any,
    *,
    utc_offset_h: float = 0.0,
    known_kinds: Iterable[str] | None = None,
) -> HistoryFilter:
    """Parse the parameters of a history query.

    parameters: the selector's parameter text (``since=...;kind=fall``, a
        leading ``key?`` is skipped), a mapping, or any object whose ``str()``
        is such text (``zenoh.Parameters``).
    utc_offset_h: zone of ISO times written without one.
    known_kinds: accepted event kinds (default: the wire's event kinds).

    Raises ValueError naming the parameter and the problem.
    """
    if known_kinds is None:
        from common.messages import EVENT_KINDS  # the wire's list is the reference

        known_kinds = EVENT_KINDS
    known = frozenset(known_kinds)
    items = _selector_items(parameters)
    unknown = sorted(k for k in items if k not in SELECTOR_PARAMETERS)
    if unknown:
        raise ValueError(
            f"history selector: unknown parameter(s) {_quote_list(unknown)} "
            f"(known: {', '.join(SELECTOR_PARAMETERS)})"
        )
    since = _time_param(items, "since", utc_offset_h)
    until = _time_param(items, "until", utc_offset_h)
    if since is not None and until is not None and since >= until:
        raise ValueError(f"history selector: since ({since}) must be before until ({until})")
    kinds = None
    if "kind" in items:
        raw = items["kind"]
        parts = list(raw) if isinstance(raw, (list, tuple)) else re.split(r"[,|]", str(raw))
        kinds = tuple(dict.fromkeys(str(p).strip() for p in parts if str(p).strip()))
        if not kinds:
            raise ValueError("history selector: kind is empty")
        bad = [k for k in kinds if k not in known]
        if bad:
            raise ValueError(f"history selector: unknown kind(s) {_quote_list(bad)} (known: {', '.join(sorted(known))})")
    fmt = str(items.get("format", "json")).strip().lower()
    if fmt not in FORMATS:
        raise ValueError(f"history selector: format {_quote(items['format'])} is not one of {', '.join(FORMATS)}")
    limit = DEFAULT_LIMIT
    if "limit" in items:
        raw = str(items["limit"]).strip()
        if not raw.isdigit() or not 1 <= int(raw) <= MAX_LIMIT:
            raise ValueError(f"history selector: limit {_quote(items['limit'])} must be an integer in 1..{MAX_LIMIT}")
        limit = int(raw)
    return HistoryFilter(since_ns=since, until_ns=until, kinds=kinds, format=fmt, limit=limit)


def parse_time_ns(text: str | int, *, utc_offset_h: float = 0.0) -> int:
    """Nanoseconds since the Unix epoch from an integer (ns) or ISO-8601 text.

    Times without a zone are taken at ``utc_offset_h``. ValueError otherwise.
    """
    if isinstance(text, bool):
        raise ValueError(f"not a time: {text!r}")
    if isinstance(text, int):
        if text < 0:
            raise ValueError(f"time {_quote(text)} is negative")
        if text > MAX_STAMP_NS:
            raise ValueError(f"time {_quote(text)} is beyond the largest stamp ({MAX_STAMP_NS} ns)")
        return text
    s = str(text).strip()
    if re.fullmatch(r"[0-9]+", s):
        return parse_time_ns(int(s)) if len(s) <= 30 else parse_time_ns(MAX_STAMP_NS + 1)
    try:
        dt = datetime.fromisoformat(s)
    except ValueError:
        raise ValueError(f"{_quote(s)} is neither integer nanoseconds nor an ISO-8601 time") from None
    if dt.tzinfo is None:
        if not (isinstance(utc_offset_h, (int, float)) and math.isfinite(utc_offset_h)):
            raise ValueError(f"utc_offset_h must be a finite number, got {utc_offset_h!r}")
        dt = dt.replace(tzinfo=timezone(timedelta(hours=utc_offset_h)))
    micros = (dt - datetime(1970, 1, 1, tzinfo=timezone.utc)) // timedelta(microseconds=1)
    if micros < 0:
        raise ValueError(f"time {_quote(s)} is before 1970")
    if micros * 1000 > MAX_STAMP_NS:
        raise ValueError(f"time {_quote(s)} is beyond the largest stamp (the year 2262)")
    return micros * 1000


# --------------------------------------------------------------------------- helpers


def _row(event: Event | Mapping[str, Any]) -> tuple:
    rec = event if isinstance(event, Event) else Event.from_dict(dict(event))
    try:
        details = json.dumps(rec.details, sort_keys=True, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"event {rec.id!r}: details are not plain JSON values: {exc}") from None
    return (rec.id, rec.kind, rec.track, rec.stamp_ns, rec.frame, rec.x, rec.y, details)


def _quote(value: Any, limit: int = 40) -> str:
    """``repr(value)``, cut to about ``limit`` characters: an error never echoes a huge query."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def _quote_list(values: list, most: int = 5) -> str:
    shown = ", ".join(_quote(v) for v in values[:most])
    return shown if len(values) <= most else f"{shown} and {len(values) - most} more"


def _rollback(db: sqlite3.Connection) -> None:
    try:
        db.rollback()
    except sqlite3.Error:
        pass


def _int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an int (nanoseconds), got {value!r}")
    return value


def _selector_items(parameters: Any) -> dict[str, Any]:
    if isinstance(parameters, Mapping):
        items = {str(k).strip(): v for k, v in parameters.items()}
    else:
        text = "" if parameters is None else str(parameters)
        if "?" in text:
            text = text.split("?", 1)[1]
        items = {}
        for part in re.split(r"[;&]", text):
            part = part.strip()
            if not part:
                continue
            key, sep, value = part.partition("=")
            key = key.strip()
            if not key:
                raise ValueError(f"history selector: parameter {_quote(part)} has no name")
            if not sep:
                raise ValueError(f"history selector: parameter {_quote(key)} has no value (write name=value)")
            if key in items:
                raise ValueError(f"history selector: parameter {_quote(key)} is given twice")
            items[key] = value.strip()
    return {k: v for k, v in items.items() if not k.startswith("_")}


def _time_param(items: Mapping[str, Any], name: str, utc_offset_h: float) -> int | None:
    if name not in items:
        return None
    try:
        return parse_time_ns(items[name], utc_offset_h=utc_offset_h)
    except ValueError as exc:
        raise ValueError(f"history selector: {name}: {exc}") from None
