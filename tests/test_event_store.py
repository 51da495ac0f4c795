"""Event store: round trip, durability across reopen, filters, idempotence,
threads, and the history selector parser."""

from __future__ import annotations

import sqlite3
import threading

import pytest
import zenoh

from fusion_server.event_store import (
    DEFAULT_LIMIT,
    EventStore,
    HistoryFilter,
    parse_history_selector,
    parse_time_ns,
)
from common.messages import Event, event_id

NS = 1_000_000_000
T0 = 1_714_521_600 * NS  # 2024-05-01T00:00:00Z


def ev(stamp_ns: int, kind: str = "fall", track: int = 1, **details) -> Event:
    return Event(id=event_id(stamp_ns, kind, track), kind=kind, track=track, stamp_ns=stamp_ns,
                 frame=stamp_ns // (NS // 15), x=1.25, y=-0.5,
                 details=details or {"fall_stamp_ns": stamp_ns - NS, "from_posture": "standing", "drop_m": 1.234,
                                     "after_fall": True, "hotspot": None})


@pytest.fixture
def db_path(tmp_path):
    return tmp_path / "history" / "events.sqlite"


def test_round_trip_and_reopen(db_path):
    events = [ev(T0 + i * NS, kind) for i, kind in enumerate(["enter", "sit_down", "fall", "long_lie"])]
    with EventStore(db_path) as store:
        assert all(store.add(e) for e in events)
        assert store.query() == events
    with EventStore(db_path) as store:  # a restarted server keeps its history
        assert store.query() == events
        assert store.count() == 4
    mode = sqlite3.connect(db_path).execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"


def test_add_is_committed_before_it_returns(db_path):
    store = EventStore(db_path)
    try:
        store.add(ev(T0))
        # another connection (another process, or the store after a crash) sees it at once
        other = sqlite3.connect(db_path)
        assert other.execute("SELECT id FROM events").fetchall() == [(event_id(T0, "fall", 1),)]
        other.close()
    finally:
        store.close()


def test_add_is_idempotent_on_id(db_path):
    with EventStore(db_path) as store:
        first = ev(T0)
        assert store.add(first) is True
        assert store.add(first) is False
        changed = first.model_copy(update={"x": 9.0, "y": 9.0, "details": {"x": 1}})
        assert store.add(changed) is False
        assert store.query() == [first]  # the first write wins
        assert store.add_many([first, ev(T0 + NS), ev(T0 + NS)]) == 1
        assert store.count() == 2


def test_filters(db_path):
    with EventStore(db_path) as store:
        store.add_many(ev(T0 + i * NS, kind) for i, kind in enumerate(["enter", "fall", "sit_down", "fall", "exit"]))
        stamps = lambda rs: [(r.stamp_ns - T0) // NS for r in rs]  # noqa: E731
        assert stamps(store.query(since_ns=T0 + NS, until_ns=T0 + 3 * NS)) == [1, 2]  # half-open
        assert stamps(store.query(kinds=["fall"])) == [1, 3]
        assert stamps(store.query(kinds="exit")) == [4]
        assert stamps(store.query(kinds=["fall", "enter"], since_ns=T0 + NS)) == [1, 3]
        assert store.query(kinds=[]) == []
        assert stamps(store.query(limit=2)) == [0, 1]
        assert stamps(store.query(limit=2, newest_first=True)) == [4, 3]
        assert stamps(store.query_filter(parse_history_selector("kind=fall,exit;limit=2"))) == [1, 3]
        with pytest.raises(ValueError, match="limit"):
            store.query(limit=0)
        with pytest.raises(ValueError, match="since_ns"):
            store.query(since_ns="yesterday")


def test_same_stamp_keeps_insertion_order(db_path):
    with EventStore(db_path) as store:
        same = [ev(T0, "exit", 2), ev(T0, "enter", 7), ev(T0, "dwell_end", 1)]
        store.add_many(same)
        assert store.query() == same


def test_usable_from_other_threads(db_path):
    store = EventStore(db_path)  # created on this thread
    errors = []

    def writer(w):
        try:
            for i in range(50):
                store.add(ev(T0 + i * NS, "fall", w))
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(w,)) for w in range(4)]
    for t in threads:
        t.start()
    got = []
    reader = threading.Thread(target=lambda: got.append(len(store.query(limit=1000))))
    reader.start()
    for t in threads + [reader]:
        t.join()
    assert errors == []
    assert store.count() == 200
    store.close()
    store.close()  # twice is harmless
    with pytest.raises(ValueError, match="closed"):
        store.add(ev(T0))


def test_bad_events_and_bad_files(tmp_path):
    with EventStore(":memory:") as store:
        with pytest.raises(ValueError, match="'stamp_ns'"):
            store.add({"id": "a", "kind": "fall", "track": 1, "stamp_ns": "now", "frame": 1, "x": 0.0, "y": 0.0})
        with pytest.raises(ValueError, match="details"):
            store.add(ev(T0, details_obj=object()))
        with pytest.raises(ValueError, match="'stamp_ns'"):
            store.add({**ev(T0).to_dict(), "stamp_ns": -5})
        assert store.count() == 0
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not a database, just text " * 100)
    with pytest.raises(ValueError, match=str(junk)):
        EventStore(junk)


# --------------------------------------------------------------------------- selector


def test_selector_from_text_mapping_and_zenoh_parameters():
    want = HistoryFilter(since_ns=T0, until_ns=T0 + 19 * 3600 * NS, kinds=("fall", "sit_down"), format="msgpack")
    text = f"since={T0};until=2024-05-01T19:00:00Z;kind=fall,sit_down;format=msgpack"
    assert parse_history_selector(text) == want
    assert parse_history_selector("voxelwatch/home/history/events?" + text) == want
    assert parse_history_selector(zenoh.Parameters(text)) == want
    assert parse_history_selector({"since": T0, "until": "2024-05-01T21:00+02:00", "kind": ["fall", "sit_down"],
                                   "format": "msgpack"}) == want
    assert parse_history_selector("") == HistoryFilter()
    assert parse_history_selector(None).limit == DEFAULT_LIMIT
    assert parse_history_selector("kind=fall|exit;_time=[now(-1h)..];limit=5") == HistoryFilter(kinds=("fall", "exit"),
                                                                                            limit=5)


def test_iso_times():
    assert parse_time_ns("2024-05-01T00:00:00Z") == T0
    assert parse_time_ns("2024-05-01") == T0
    assert parse_time_ns("2024-05-01T02:00:00", utc_offset_h=2.0) == T0
    assert parse_time_ns("2024-05-01T00:00:00.000001+00:00") == T0 + 1000
    assert parse_time_ns(str(T0)) == T0
    assert parse_history_selector("since=2024-05-01T19:00", utc_offset_h=2.0).since_ns == T0 + 17 * 3600 * NS


@pytest.mark.parametrize(
    "text, message",
    [
        ("sinse=5", "unknown parameter"),
        ("since=yesterday", "since"),
        ("until=2024-13-45", "until"),
        ("since=10;until=5", "before until"),
        ("since=5;until=5", "before until"),
        ("kind=fall,flying", "flying"),
        ("kind=", "kind is empty"),
        ("format=xml", "format"),
        ("limit=0", "limit"),
        ("limit=many", "limit"),
        ("since=1;since=2", "twice"),
        ("since", "no value"),
        ("=5", "no name"),
        ("since=1969-01-01T00:00:00Z", "before 1970"),
    ],
)
def test_bad_selectors_raise_clear_errors(text, message):
    with pytest.raises(ValueError, match=message):
        parse_history_selector(text)


# --------------------------------------------------------------------------- write failures


class _Locker:
    """Another process's connection holding the database's write lock (a real SQLite lock)."""

    def __init__(self, path) -> None:
        self.db = sqlite3.connect(str(path), timeout=0.1, isolation_level=None)
        self.db.execute("BEGIN EXCLUSIVE")

    def release(self) -> None:
        self.db.execute("COMMIT")
        self.db.close()


def test_an_event_the_database_cannot_write_goes_to_the_fallback_and_is_merged_at_the_next_write(db_path):
    from fusion_server.event_store import EventNotStored

    store = EventStore(db_path, timeout_s=0.1)
    first, locked, later = ev(T0), ev(T0 + NS, "long_lie"), ev(T0 + 2 * NS, "enter")
    assert store.add(first)
    lock = _Locker(db_path)
    with pytest.raises(EventNotStored, match="locked") as refused:
        store.add(locked)
    assert refused.value.kept and store.pending == 1
    lines = store.fallback_path.read_text().splitlines()
    assert [Event.from_json(line) for line in lines] == [locked]
    lock.release()
    assert store.add(later)  # the next write merges the waiting event first
    assert store.pending == 0 and not store.fallback_path.exists()
    assert store.query() == [first, locked, later]
    store.close()


def test_events_waiting_in_the_fallback_are_merged_when_the_store_opens(db_path):
    from fusion_server.event_store import EventNotStored

    store = EventStore(db_path, timeout_s=0.1)
    lock = _Locker(db_path)
    waiting = [ev(T0 + i * NS) for i in range(3)]
    for e in waiting:
        with pytest.raises(EventNotStored):
            store.add(e)
    store.close()  # the server stops before the lock goes
    with store.fallback_path.open("a") as f:
        f.write("{not an event\n")
    lock.release()
    with EventStore(db_path) as again:
        assert again.pending == 0 and again.query() == waiting and again.merged == 3
        assert not again.fallback_path.exists()
