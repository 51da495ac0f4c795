"""Who is where, as the notifier tells it: places on the plan, per-person state, alarm texts.

Pure logic, fed with messages and the time (``now_ns``): :class:`PeopleState`
turns the stream of :class:`~common.messages.TrackFrame` into the few state
changes worth publishing (a person's posture, place, presence or name
changed; they moved half a metre, at most once a second; or a minute went by
without news; absent once missing from the tracks for two seconds), :class:`CameraStates` does the same for the cameras of
:class:`~common.messages.Status`, and :func:`describe` makes the one-line
texts of an alarm (the e-mail subject and body).
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from common.messages import Event, Status, TrackFrame

MOVE_M = 0.5
"""A person who moved this far since the last state published is published again."""
MOVE_EVERY_S = 1.0
"""... but not more often than this (positions change every frame)."""
HEARTBEAT_S = 60.0
"""A present person's state is published at least this often (``last_seen`` stays fresh)."""
ABSENT_AFTER_S = 2.0
"""A person missing from the tracks this long (fusion host time) is ``absent``: a track missing
from a frame or two does not flip the state."""


@dataclass(frozen=True)
class Zone:
    """A named floor polygon (a hot spot or a door), world frame, metres."""

    name: str
    polygon_m: tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class PersonState:
    """One person as published: track id, enrolled name (None for anyone else), posture
    (``absent`` once gone), floor position in metres, the place they are in ("" for none)
    and when they were last seen (ns since the epoch, fusion host clock)."""

    id: int
    name: str | None
    posture: str
    x: float
    y: float
    place: str
    last_seen_ns: int

    @property
    def label(self) -> str:
        return self.name or f"person {self.id}"

    def to_dict(self, utc_offset_hours: float = 0.0) -> dict:
        return {"id": self.id, "person": self.name, "posture": self.posture, "x": round(self.x, 2),
                "y": round(self.y, 2), "place": self.place, "last_seen_ns": self.last_seen_ns,
                "last_seen": local_time(self.last_seen_ns, utc_offset_hours).isoformat(timespec="seconds")}


def zones_of(site) -> list[Zone]:
    """The hot spots, then the doors, of a site, as :class:`Zone`."""
    return [Zone(z.name, tuple((float(x), float(y)) for x, y in z.polygon_m)) for z in [*site.hotspots, *site.doors]]


def place_at(x: float, y: float, zones: Sequence[Zone]) -> str:
    """The name of the first zone containing ``(x, y)`` (metres, world frame), "" when none does."""
    for zone in zones:
        if _inside(x, y, zone.polygon_m):
            return zone.name
    return ""


class PeopleState:
    """Per-person state from track frames; :meth:`update` returns what changed enough to publish.

    zones: the places to name. forget_s: a person without an enrolled name who has
    been gone this long is dropped (:meth:`update` lists them in ``forgotten``), so
    that visitors do not pile up; enrolled residents are kept.
    """

    def __init__(self, zones: Sequence[Zone] = (), *, forget_s: float = 600.0) -> None:
        self.zones = list(zones)
        self.forget_s = float(forget_s)
        self.people: dict[int, PersonState] = {}
        self._published: dict[int, tuple[PersonState, int]] = {}  # last state sent and when (host ns)
        self.forgotten: list[int] = []

    def update(self, frame: TrackFrame, now_ns: int) -> list[PersonState]:
        """The states to publish after ``frame`` (arrived at host time ``now_ns``)."""
        out: list[PersonState] = []
        seen = set()
        for t in frame.tracks:
            seen.add(t.id)
            old = self.people.get(t.id)
            name = t.person if t.person is not None else (old.name if old is not None else None)
            state = PersonState(t.id, name, t.posture, float(t.x), float(t.y), place_at(t.x, t.y, self.zones),
                                frame.stamp_ns)
            self.people[t.id] = state
            if self._worth(state, now_ns):
                out.append(self._sent(state, now_ns))
        self.forgotten = []
        for pid, state in list(self.people.items()):
            if pid in seen:
                continue
            missing_s = (frame.stamp_ns - state.last_seen_ns) * 1e-9
            if state.posture != "absent":
                if missing_s < ABSENT_AFTER_S:
                    continue
                gone = replace(state, posture="absent")
                self.people[pid] = gone
                out.append(self._sent(gone, now_ns))
            elif state.name is None and missing_s > self.forget_s:
                del self.people[pid]
                self._published.pop(pid, None)
                self.forgotten.append(pid)
        return out

    def name_of(self, track: int) -> str | None:
        state = self.people.get(track)
        return state.name if state is not None else None

    def _worth(self, state: PersonState, now_ns: int) -> bool:
        last = self._published.get(state.id)
        if last is None:
            return True
        prev, at_ns = last
        if (prev.posture, prev.place, prev.name) != (state.posture, state.place, state.name):
            return True
        since_s = (now_ns - at_ns) * 1e-9
        moved = math.hypot(state.x - prev.x, state.y - prev.y) >= MOVE_M
        return (moved and since_s >= MOVE_EVERY_S) or since_s >= HEARTBEAT_S

    def _sent(self, state: PersonState, now_ns: int) -> PersonState:
        self._published[state.id] = (state, now_ns)
        return state


class CameraStates:
    """Each camera's state (``ok``, ``degraded``, ``lost`` ...) from status reports;
    :meth:`update` returns ``{camera: state}`` for the ones that changed."""

    def __init__(self) -> None:
        self.states: dict[str, str] = {}

    def update(self, status: Status) -> dict[str, str]:
        changed = {c.cam: c.state for c in status.cameras if self.states.get(c.cam) != c.state}
        self.states.update(changed)
        return changed


def local_time(stamp_ns: int, utc_offset_hours: float) -> _dt.datetime:
    """A stamp (ns since the epoch) as the site's local time (an aware datetime)."""
    zone = _dt.timezone(_dt.timedelta(hours=utc_offset_hours))
    return _dt.datetime.fromtimestamp(stamp_ns / 1e9, tz=zone)


def describe(event: Event, *, site: str, person: str = "", place: str = "",
             utc_offset_hours: float = 0.0) -> tuple[str, str]:
    """``(subject, body)`` of an alarm for people: what, who, where, when and the event id.

    Subject: ``voxelwatch <site>: fall (Ada, sofa) 14:03``; the body is plain text.
    """
    when = local_time(event.stamp_ns, utc_offset_hours)
    who = person or (f"person {event.track}" if event.track >= 0 else "")
    camera = str(event.details.get("camera", "")) if event.track < 0 else ""
    about = ", ".join(p for p in (who, place, camera) if p)
    subject = f"voxelwatch {site}: {event.kind}{f' ({about})' if about else ''} {when:%H:%M}"
    hours = f"UTC{utc_offset_hours:+g}" if utc_offset_hours else "UTC"
    lines = [f"What:  {event.kind.replace('_', ' ')}"]
    if who:
        lines.append(f"Who:   {who} (track {event.track})")
    if event.track >= 0:
        lines.append(f"Where: {place + ', ' if place else ''}x {event.x:.1f} m, y {event.y:.1f} m")
    if camera:
        lines.append(f"Camera: {camera}")
    lines.append(f"When:  {when:%Y-%m-%d %H:%M:%S} ({hours}, site time)")
    lines.append(f"Site:  {site}")
    details = ", ".join(f"{k}={v}" for k, v in event.details.items() if k != "camera")
    if details:
        lines.append(f"Details: {details}")
    lines.append(f"Event id: {event.id}")
    lines.append("")
    lines.append("Sent by voxelwatch notify. The same alarm may arrive twice after a restart: "
                 "the event id is the same.")
    return subject, "\n".join(lines) + "\n"


def _inside(x: float, y: float, polygon: Sequence[tuple[float, float]]) -> bool:
    """Even-odd ray casting; points on an edge may fall either way."""
    inside = False
    n = len(polygon)
    for i in range(n):
        (x0, y0), (x1, y1) = polygon[i], polygon[(i + 1) % n]
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside
