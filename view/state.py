"""What the live view knows: a pure core fed with decoded messages, no zenoh, no clock.

:class:`LiveState` takes every :class:`~common.messages.TrackFrame`,
:class:`~common.messages.Event` and :class:`~common.messages.Status` the
view hears (and the events the history returns when the view starts), and
keeps, all of it bounded:

* the latest track frame and each person's recent path (``trail_s`` of
  positions, by the frames' own stamps);
* the alarms waiting for someone: events of the ``alarm_kinds`` that no
  ``alarm_ack`` event has answered (at most :data:`MAX_ALARMS`);
* the latest status;
* a day timeline per person: runs of one posture (``[start_ns, end_ns,
  posture]``, a new run after a gap of :data:`GAP_NS`), dwells at hot spots
  (``dwell_start`` .. ``dwell_end``) and marks for the person's other events;
  and the visits. At most :data:`MAX_RUNS` runs per person and
  :data:`MAX_PEOPLE` people: the oldest go first.

Each ``on_*`` method returns the JSON-ready dict the browsers are sent
(``None`` when nothing changed for them); :meth:`snapshot` is what a page
that just opened needs. Times are the messages' own ``stamp_ns``.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Iterable, Sequence
from typing import Any

from common.messages import Event, Status, TrackFrame

MAX_ALARMS = 64
MAX_RECENT_EVENTS = 200
MAX_RUNS = 2000
MAX_MARKS = 500
MAX_PEOPLE = 64
MAX_VISITS = 200
GAP_NS = 5_000_000_000
"""A person unseen this long starts a new run on the timeline."""
DAY_NS = 86_400_000_000_000


class LiveState:
    """The view's memory of the home (see the module text). ``alarm_kinds``: event kinds shown as
    an alarm until acknowledged; ``trail_s``: seconds of path kept per person."""

    def __init__(self, *, alarm_kinds: Sequence[str], trail_s: float) -> None:
        if not trail_s >= 0:
            raise ValueError(f"trail_s must be >= 0, got {trail_s!r}")
        self.alarm_kinds = frozenset(alarm_kinds)
        self.trail_ns = int(trail_s * 1e9)
        self.frame: dict[str, Any] | None = None
        self.trails: dict[int, deque] = {}
        self.alarms: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self.acked: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self.recent: deque[dict[str, Any]] = deque(maxlen=MAX_RECENT_EVENTS)
        self.status: dict[str, Any] | None = None
        self.people: OrderedDict[str, _Person] = OrderedDict()
        self.visits: deque[dict[str, Any]] = deque(maxlen=MAX_VISITS)
        self.names: dict[int, str] = {}
        self._seen_events: OrderedDict[str, None] = OrderedDict()

    # ------------------------------------------------------------------ feeding

    def on_tracks(self, msg: TrackFrame) -> dict[str, Any]:
        """A fused frame: the latest positions, each person's trail and timeline. Returns the frame
        as the page gets it: ``{"frame", "stamp_ns", "cameras", "tracks": [{"id", "label", "x", "y",
        "z_top", "posture", "still", "reliability", "person"}]}``."""
        stamp = msg.stamp_ns
        tracks = []
        for t in msg.tracks:
            if t.person:
                self.names[t.id] = t.person
            label = t.person or f"#{t.id}"
            tracks.append({"id": t.id, "label": label, "person": t.person, "x": round(t.x, 3), "y": round(t.y, 3),
                           "z_top": round(t.z_top, 2), "posture": t.posture, "still": t.still,
                           "reliability": round(t.reliability, 2)})
            trail = self.trails.get(t.id)
            if trail is None:
                trail = self.trails[t.id] = deque()
            trail.append((stamp, round(t.x, 3), round(t.y, 3)))
            self._person(t.id).posture(stamp, t.posture)
        horizon = stamp - self.trail_ns
        for tid in list(self.trails):
            trail = self.trails[tid]
            while trail and trail[0][0] < horizon:
                trail.popleft()
            if not trail:
                del self.trails[tid]
        if len(self.names) > 4 * MAX_PEOPLE:
            for tid in list(self.names)[: len(self.names) - 4 * MAX_PEOPLE]:
                del self.names[tid]
        self.frame = {"frame": msg.frame, "stamp_ns": stamp, "cameras": list(msg.cameras), "tracks": tracks}
        return self.frame

    def on_event(self, event: Event) -> dict[str, Any] | None:
        """One event (live or from the history; each id counts once). Returns ``{"event": ...,
        "alarms": [...] or None}``: the event as the page shows it and, when the alarms changed,
        the whole list of those waiting; None for an event already seen."""
        if event.id in self._seen_events:
            return None
        self._seen_events[event.id] = None
        if len(self._seen_events) > 4 * MAX_RECENT_EVENTS:
            self._seen_events.popitem(last=False)
        shown = self.event_dict(event)
        self.recent.append(shown)
        changed = False
        if event.kind in self.alarm_kinds and event.id not in self.acked:
            self.alarms[event.id] = shown
            while len(self.alarms) > MAX_ALARMS:
                self.alarms.popitem(last=False)
            changed = True
        elif event.kind == "alarm_ack":
            target = str(event.details.get("event", ""))
            self.acked[target] = shown
            while len(self.acked) > 4 * MAX_ALARMS:
                self.acked.popitem(last=False)
            changed = self.alarms.pop(target, None) is not None
        self._timeline_event(event, shown)
        return {"event": shown, "alarms": self.alarm_list() if changed else None}

    def on_status(self, msg: Status) -> dict[str, Any]:
        """The fusion server's health report as the page shows it (every camera's fields, and
        ``consistency`` when a camera reports one)."""
        cams = [c.model_dump(mode="json") for c in msg.cameras]
        self.status = {"stamp_ns": msg.stamp_ns, "frame_sets": msg.frame_sets,
                       "frame_sets_dropped": msg.frame_sets_dropped, "events_not_stored": msg.events_not_stored,
                       "events_pending": msg.events_pending, "cameras": cams}
        return self.status

    def seed(self, events: Iterable[Event]) -> None:
        """Events from the history (oldest first): the alarms still waiting, the timeline, the list."""
        for event in sorted(events, key=lambda e: e.stamp_ns):
            self.on_event(event)

    # ------------------------------------------------------------------ reading

    def alarm_list(self) -> list[dict[str, Any]]:
        return list(self.alarms.values())

    def trail_lists(self) -> dict[str, list[list[float]]]:
        """Each track's recent path ``[[stamp_ns, x, y], ...]``, by track id (as text)."""
        return {str(tid): [list(p) for p in trail] for tid, trail in self.trails.items()}

    def snapshot(self) -> dict[str, Any]:
        """Everything a page that has just opened needs."""
        return {"frame": self.frame, "trails": self.trail_lists(), "alarms": self.alarm_list(),
                "recent": list(self.recent), "status": self.status}

    def timeline(self, *, since_ns: int | None = None) -> dict[str, Any]:
        """The day per person: ``{"people": [{"key", "label", "runs": [[start, end, posture]],
        "dwells": [[start, end or None, hotspot]], "marks": [[stamp, kind]]}], "visits": [...],
        "now_ns"}``; with ``since_ns``, only what reaches past it."""
        lo = since_ns if since_ns is not None else -1
        people = []
        for key, p in self.people.items():
            people.append({"key": key, "label": self.names.get(p.track, f"#{p.track}"),
                           "runs": [list(r) for r in p.runs if r[1] >= lo],
                           "dwells": [list(d) for d in p.dwells if d[1] is None or d[1] >= lo],
                           "marks": [list(m) for m in p.marks if m[0] >= lo]})
        now = self.frame["stamp_ns"] if self.frame else None
        return {"people": people, "visits": [v for v in self.visits if v["stamp_ns"] >= lo], "now_ns": now}

    @staticmethod
    def event_dict(event: Event) -> dict[str, Any]:
        """An event as the page shows it: its fields (``Event.to_dict``)."""
        return event.to_dict()

    # ------------------------------------------------------------------ helpers

    def _person(self, track: int) -> "_Person":
        key = str(track)
        p = self.people.get(key)
        if p is None:
            p = self.people[key] = _Person(track)
            while len(self.people) > MAX_PEOPLE:
                self.people.popitem(last=False)
        else:
            self.people.move_to_end(key)
        return p

    def _timeline_event(self, event: Event, shown: dict[str, Any]) -> None:
        if event.kind == "visit":
            self.visits.append(shown)
            return
        if event.track < 0 or event.kind == "alarm_ack":
            return
        p = self._person(event.track)
        if event.kind == "dwell_start":
            p.dwells.append([int(event.details.get("start_ns") or event.stamp_ns), None,
                             str(event.details.get("hotspot") or "")])
        elif event.kind == "dwell_end":
            spot = str(event.details.get("hotspot") or "")
            open_one = next((d for d in reversed(p.dwells) if d[1] is None and d[2] == spot), None)
            if open_one is not None:
                open_one[1] = event.stamp_ns
            else:
                p.dwells.append([int(event.details.get("start_ns") or event.stamp_ns), event.stamp_ns, spot])
        else:
            p.marks.append([event.stamp_ns, event.kind])


class _Person:
    """One track's day: posture runs, dwells and event marks (bounded deques)."""

    def __init__(self, track: int) -> None:
        self.track = track
        self.runs: deque[list] = deque(maxlen=MAX_RUNS)
        self.dwells: deque[list] = deque(maxlen=MAX_RUNS)
        self.marks: deque[list] = deque(maxlen=MAX_MARKS)

    def posture(self, stamp_ns: int, posture: str) -> None:
        last = self.runs[-1] if self.runs else None
        if last is not None and 0 <= stamp_ns - last[1] <= GAP_NS:
            last[1] = stamp_ns  # a run reaches the next one: no hole on the timeline
            if last[2] == posture:
                return
        self.runs.append([stamp_ns, stamp_ns, posture])
