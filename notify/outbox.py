"""The notification outbox: an SQLite file that holds every alarm until each channel has it.

One row per event (``events``: id, kind, stamp, the event's JSON text and the
context it was heard with: the person's name and the place) and one row per
event and channel (``deliveries``). :meth:`Outbox.add` is idempotent on the
event id: the same event heard live and again from the history query is one
event and one delivery per channel. A delivery stays ``pending`` until its
channel confirms it (``delivered``) or refuses it for good (``failed``: a 4xx
answer, an outbox over its bound); a failed attempt is tried again after a
back-off that doubles from ``retry_base_s`` up to ``retry_max_s``.

Every write has committed to disk (WAL, ``synchronous=FULL``) when it returns,
so a notifier killed at any moment delivers, after its restart, everything
that was not confirmed: at least once. A delivery may repeat (confirmed by the
receiver, killed before the row was updated); receivers drop repeats by the
event id every delivery carries.

The outbox is bounded: a channel with ``max_pending`` deliveries waiting gives
up its oldest one (counted, logged) for each new one, and events whose
deliveries are all settled are forgotten after ``keep_s`` (long after a
history query could bring them back). Time comes in as an argument
(``now_ns``, host clock, nanoseconds since the epoch); nothing here reads the
clock. One connection is shared by the notifier's threads behind a lock.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from common.messages import Event, WireError

log = logging.getLogger("voxelwatch.notify")

SCHEMA_VERSION = 1
STATES = ("pending", "delivered", "failed")


@dataclass(frozen=True)
class Pending:
    """One delivery waiting for its channel: the event, the context it was heard with
    (``person``, ``place``: texts, possibly empty) and the attempts made so far."""

    event: Event
    context: Mapping[str, str]
    attempts: int


class Outbox:
    """The outbox file at ``path`` (created when missing; ValueError naming the file when it
    cannot be opened or is not an outbox)."""

    def __init__(self, path: str | Path, *, retry_base_s: float = 1.0, retry_max_s: float = 300.0,
                 max_pending: int = 10_000, keep_s: float = 7 * 86400.0) -> None:
        if not 0 < retry_base_s <= retry_max_s:
            raise ValueError(f"retry_base_s must lie in (0, retry_max_s], got {retry_base_s} and {retry_max_s}")
        if max_pending < 1:
            raise ValueError(f"max_pending must be at least 1, got {max_pending}")
        self.path = Path(path)
        self.retry_base_s = float(retry_base_s)
        self.retry_max_s = float(retry_max_s)
        self.max_pending = int(max_pending)
        self.keep_s = float(keep_s)
        self._lock = threading.Lock()
        self._db = self._open()

    # ------------------------------------------------------------------ writing

    def add(self, event: Event, channels: Sequence[str], now_ns: int,
            context: Mapping[str, str] | None = None) -> list[str]:
        """Keep ``event`` for each of ``channels``; the channels it is new for (none when it
        was added before: the id is the key). Committed when it returns."""
        if not channels:
            return []
        body = event.to_json()
        ctx = json.dumps(dict(context or {}), ensure_ascii=False)
        new: list[str] = []
        with self._lock, self._db:
            self._db.execute("INSERT OR IGNORE INTO events (id, kind, stamp_ns, body, context, added_ns) "
                             "VALUES (?, ?, ?, ?, ?, ?)", (event.id, event.kind, event.stamp_ns, body, ctx, now_ns))
            for channel in channels:
                cur = self._db.execute(
                    "INSERT OR IGNORE INTO deliveries (event_id, channel, state, attempts, next_ns, error, done_ns) "
                    "VALUES (?, ?, 'pending', 0, ?, '', 0)", (event.id, channel, now_ns))
                if cur.rowcount:
                    new.append(channel)
                    self._bound(channel, now_ns)
        return new

    def delivered(self, event_id: str, channel: str, now_ns: int) -> None:
        """The channel has the event (also for one already given up or delivered: a late
        acknowledgement)."""
        with self._lock, self._db:
            self._db.execute("UPDATE deliveries SET state = 'delivered', error = '', done_ns = ? "
                             "WHERE event_id = ? AND channel = ?", (now_ns, event_id, channel))

    def retry(self, event_id: str, channel: str, now_ns: int, error: str, *,
              after_s: float | None = None) -> float:
        """An attempt failed for a passing reason: count it and try again after the back-off
        (or ``after_s``, a receiver's Retry-After, within ``retry_max_s``). Returns the wait, s."""
        with self._lock, self._db:
            row = self._db.execute("SELECT attempts, state FROM deliveries WHERE event_id = ? AND channel = ?",
                                   (event_id, channel)).fetchone()
            if row is None or row[1] != "pending":
                return 0.0
            attempts = row[0] + 1
            wait = self.backoff_s(attempts) if after_s is None else min(max(after_s, 0.0), self.retry_max_s)
            self._db.execute("UPDATE deliveries SET attempts = ?, next_ns = ?, error = ? "
                             "WHERE event_id = ? AND channel = ?",
                             (attempts, now_ns + int(wait * 1e9), error[:500], event_id, channel))
        return wait

    def give_up(self, event_id: str, channel: str, now_ns: int, error: str) -> None:
        """The channel refused the event for good (it will not be tried again)."""
        with self._lock, self._db:
            self._db.execute("UPDATE deliveries SET state = 'failed', attempts = attempts + 1, error = ?, done_ns = ? "
                             "WHERE event_id = ? AND channel = ? AND state = 'pending'",
                             (error[:500], now_ns, event_id, channel))

    def hurry(self, channel: str, now_ns: int) -> int:
        """Make every pending delivery of ``channel`` due now (its broker is back); how many."""
        with self._lock, self._db:
            return self._db.execute("UPDATE deliveries SET next_ns = ? WHERE channel = ? AND state = 'pending' "
                                    "AND next_ns > ?", (now_ns, channel, now_ns)).rowcount

    def prune(self, now_ns: int) -> int:
        """Forget events older than ``keep_s`` whose deliveries are all settled; how many."""
        cutoff = now_ns - int(self.keep_s * 1e9)
        with self._lock, self._db:
            old = [r[0] for r in self._db.execute(
                "SELECT id FROM events WHERE added_ns < ? AND NOT EXISTS (SELECT 1 FROM deliveries d "
                "WHERE d.event_id = events.id AND d.state = 'pending')", (cutoff,))]
            for event_id in old:
                self._db.execute("DELETE FROM deliveries WHERE event_id = ?", (event_id,))
                self._db.execute("DELETE FROM events WHERE id = ?", (event_id,))
        return len(old)

    # ------------------------------------------------------------------ reading

    def backoff_s(self, attempts: int) -> float:
        """The wait after the ``attempts``-th failed attempt: base, 2 base, 4 base ... up to the maximum."""
        return min(self.retry_max_s, self.retry_base_s * 2.0 ** min(max(attempts - 1, 0), 60))

    def due(self, channel: str, now_ns: int, limit: int = 20) -> list[Pending]:
        """Pending deliveries of ``channel`` due at ``now_ns``, oldest event first."""
        with self._lock:
            rows = self._db.execute(
                "SELECT e.body, e.context, d.attempts FROM deliveries d JOIN events e ON e.id = d.event_id "
                "WHERE d.channel = ? AND d.state = 'pending' AND d.next_ns <= ? "
                "ORDER BY e.stamp_ns, e.id LIMIT ?", (channel, now_ns, limit)).fetchall()
        out = []
        for body, context, attempts in rows:
            try:
                out.append(Pending(Event.from_json(body), json.loads(context or "{}"), attempts))
            except (WireError, ValueError) as exc:  # written by this module: only a damaged file
                log.warning("outbox %s: a stored event cannot be read (%s); skipped", self.path, exc)
        return out

    def next_due_ns(self, channel: str) -> int | None:
        """When the next pending delivery of ``channel`` is due (None: nothing pending)."""
        with self._lock:
            row = self._db.execute("SELECT MIN(next_ns) FROM deliveries WHERE channel = ? AND state = 'pending'",
                                   (channel,)).fetchone()
        return None if row[0] is None else int(row[0])

    def counts(self, channels: Sequence[str] | None = None) -> dict[str, dict[str, int]]:
        """``{channel: {"pending": n, "delivered": n, "failed": n}}`` (every listed channel, also
        those with nothing yet)."""
        out = {c: dict.fromkeys(STATES, 0) for c in (channels or [])}
        with self._lock:
            for channel, state, n in self._db.execute(
                    "SELECT channel, state, COUNT(*) FROM deliveries GROUP BY channel, state"):
                if channels is None or channel in out:
                    out.setdefault(channel, dict.fromkeys(STATES, 0))[state] = n
        return out

    def state(self, event_id: str, channel: str) -> tuple[str, int, str] | None:
        """``(state, attempts, last error)`` of one delivery, None when there is none."""
        with self._lock:
            row = self._db.execute("SELECT state, attempts, error FROM deliveries WHERE event_id = ? AND channel = ?",
                                   (event_id, channel)).fetchone()
        return None if row is None else (row[0], int(row[1]), row[2])

    def newest_stamp_ns(self) -> int | None:
        """The stamp of the newest event kept (None: an empty outbox)."""
        with self._lock:
            row = self._db.execute("SELECT MAX(stamp_ns) FROM events").fetchone()
        return None if row[0] is None else int(row[0])

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> "Outbox":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------ helpers

    def _bound(self, channel: str, now_ns: int) -> None:
        """Give up the oldest pending deliveries of ``channel`` beyond ``max_pending`` (lock held)."""
        n = self._db.execute("SELECT COUNT(*) FROM deliveries WHERE channel = ? AND state = 'pending'",
                             (channel,)).fetchone()[0]
        if n <= self.max_pending:
            return
        oldest = [r[0] for r in self._db.execute(
            "SELECT d.event_id FROM deliveries d JOIN events e ON e.id = d.event_id WHERE d.channel = ? "
            "AND d.state = 'pending' ORDER BY e.stamp_ns, e.id LIMIT ?", (channel, n - self.max_pending))]
        for event_id in oldest:
            self._db.execute("UPDATE deliveries SET state = 'failed', error = 'outbox full', done_ns = ? "
                             "WHERE event_id = ? AND channel = ?", (now_ns, event_id, channel))
        log.warning("outbox %s: %s has %d deliveries waiting (bound %d): gave up the oldest %d",
                    self.path, channel, n, self.max_pending, len(oldest))

    def _open(self) -> sqlite3.Connection:
        where = f"[notify] outbox {self.path}"
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            db = sqlite3.connect(str(self.path), timeout=5.0, check_same_thread=False, isolation_level=None)
        except (OSError, sqlite3.Error) as exc:
            raise ValueError(f"{where}: cannot open: {exc}") from None
        try:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            db.isolation_level = ""  # "with db:" commits each write as one transaction
            with db:
                db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
                db.execute("CREATE TABLE IF NOT EXISTS events (id TEXT PRIMARY KEY, kind TEXT NOT NULL, "
                           "stamp_ns INTEGER NOT NULL, body TEXT NOT NULL, context TEXT NOT NULL, "
                           "added_ns INTEGER NOT NULL)")
                db.execute("CREATE TABLE IF NOT EXISTS deliveries (event_id TEXT NOT NULL, channel TEXT NOT NULL, "
                           "state TEXT NOT NULL, attempts INTEGER NOT NULL, next_ns INTEGER NOT NULL, "
                           "error TEXT NOT NULL, done_ns INTEGER NOT NULL, PRIMARY KEY (event_id, channel))")
                db.execute("CREATE INDEX IF NOT EXISTS deliveries_due ON deliveries (channel, state, next_ns)")
                db.execute("INSERT OR IGNORE INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
            version = db.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()[0]
        except sqlite3.Error as exc:
            db.close()
            raise ValueError(f"{where}: not a usable outbox ({exc})") from None
        if version != str(SCHEMA_VERSION):
            db.close()
            raise ValueError(f"{where}: outbox schema {version}, this build reads {SCHEMA_VERSION}")
        return db
