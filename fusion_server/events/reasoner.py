"""The event reasoner: one frame of tracks and postures in, that frame's events out.

:class:`EventReasoner` keeps what its detectors share -- which tracks are
people and present, each track's recent tops and upright time, the frame
clock and local time -- and hands each present track to the detectors in a
fixed order: sit/stand, falls, dwelling, inactivity; then the visit test over
everyone present. Entries and exits are decided as tracks become present
and leave.

Only established tracks take part: confirmed by the tracker for
``establish_s`` [0.8 s] in a row with a body of at least ``min_volume_m3``
[0.04 m^3] (a person carves 0.1-0.4 m^3; tracker ghosts -- a blob split off a
person for a second, a small blob at a wall -- do not qualify). An
established track that loses confirmation mid-room (occlusion) keeps its
state until it vanishes; one that leaves through a door or the edge takes
part again once established there again. Tracks followed beyond the
monitored volume's open sides (``outside``) keep a history (tops, upright
time, confirmation) but are present only once inside: someone who stood
just outside and fell in fell from their height.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from pydantic import Field
from typing import Any, Iterable, Mapping, Sequence

from common.messages import Event
from common.settings import Settings, group_of
from fusion_server.events._common import NUMBER, ns, rekey
from fusion_server.events.entries import EntryDetector, EntryParams
from fusion_server.events.falls import FallDetector, FallParams
from fusion_server.events.inactivity import InactivityDetector, InactivityParams
from fusion_server.events.local_time import local_hour
from fusion_server.events.records import Emitter
from fusion_server.events.sit_stand import SitStandDetector, SitStandParams
from fusion_server.events.track import TopSample, TrackLike, TrackSnapshot
from fusion_server.events.visits import VisitDetector, VisitParams
from fusion_server.hotspots import Hotspot
from fusion_server.posture import PostureReading, company_of


class PresenceParams(Settings):
    """When a track counts as a person: confirmed for ``establish_s`` seconds in a
    row with a body of at least ``min_volume_m3`` (unknown volumes pass)."""

    establish_s: float = Field(0.8, ge=0.0, **NUMBER)
    min_volume_m3: float = Field(0.04, ge=0.0, **NUMBER)


class EventReasoner:
    """Events from tracks and postures, frame by frame.

    hotspots: hot spots for dwelling, visits, seats and rest.
    doors: door zones (Hotspot objects; kind is not used).
    bounds_xy_m: ``(x_min, y_min, x_max, y_max)`` of the monitored floor,
        metres, for entering and leaving at the edge; None: doors only.
    residents: people who live here; more present is a visit.
    utc_offset_h: local time = UTC + this (the stamps are Unix-epoch ns).
    presence, falls, sit_stand, entries, visits, inactivity: the parameter
        groups of the presence test and of each detector; the detectors are
        the attributes of the same names (``reasoner.falls.params`` ...).
    """

    def __init__(
        self,
        *,
        hotspots: Iterable[Hotspot] = (),
        doors: Iterable[Hotspot] = (),
        bounds_xy_m: Sequence[float] | None = None,
        residents: int = 1,
        utc_offset_h: float = 0.0,
        presence: PresenceParams = PresenceParams(),
        falls: FallParams = FallParams(),
        sit_stand: SitStandParams = SitStandParams(),
        entries: EntryParams = EntryParams(),
        visits: VisitParams = VisitParams(),
        inactivity: InactivityParams = InactivityParams(),
    ) -> None:
        self.hotspots = tuple(hotspots)
        for h in self.hotspots:
            if not isinstance(h, Hotspot):
                raise ValueError(f"hotspots must hold Hotspot instances, got {type(h).__name__}")
        names = [h.name for h in self.hotspots]
        if len(set(names)) != len(names):
            raise ValueError(f"hotspots names must be unique, got {names}")
        if isinstance(utc_offset_h, bool) or not (isinstance(utc_offset_h, (int, float)) and -14 <= utc_offset_h <= 14):
            raise ValueError(f"utc_offset_h must lie in [-14, 14], got {utc_offset_h!r}")
        groups = dict(presence=(presence, PresenceParams), falls=(falls, FallParams),
                      sit_stand=(sit_stand, SitStandParams), entries=(entries, EntryParams),
                      visits=(visits, VisitParams), inactivity=(inactivity, InactivityParams))
        for name, (group, cls) in groups.items():
            group_of(group, cls, name=name)
        self.utc_offset_h = float(utc_offset_h)
        self.presence = presence
        self.entries = EntryDetector(entries, doors=doors, bounds_xy_m=bounds_xy_m)
        self.sit_stand = SitStandDetector(sit_stand, hotspots=self.hotspots)
        self.falls = FallDetector(falls)
        self.visits = VisitDetector(visits, hotspots=self.hotspots, residents=residents)
        self.inactivity = InactivityDetector(inactivity, hotspots=self.hotspots)
        self._establish_ns = ns(presence.establish_s)
        # The tops serve the fall test and the posture-change test.
        self._tops_ns = ns(max(falls.tops_s, sit_stand.tops_s))
        self._tracks: dict[int, _Track] = {}
        self._restoring: dict[int, Mapping[str, Any] | None] = {}  # track -> state, taken on its next frame
        self._last_stamp_ns: int | None = None
        self._first_stamp_ns: int | None = None
        self.rejected_frames = 0
        self.rejected_tracks = 0

    def step(
        self,
        stamp_ns: int,
        frame: int,
        tracks: Iterable[TrackLike],
        postures: Mapping[int, PostureReading | str] | None = None,
        *,
        hour: float | None = None,
        outside: Iterable[int] = (),
    ) -> list[Event]:
        """Events decided by one frame.

        stamp_ns: frame time (Unix-epoch ns for time-of-day labels).
        frame: fused frame number. tracks: this frame's estimates.
        postures: per track id, a :class:`PostureReading` (or a posture name).
        hour: local time of day in hours, overriding ``stamp_ns`` and
            ``utc_offset_h`` for visit labels.
        outside: ids of tracks followed beyond the monitored volume's sides: their
            history counts (tops, upright time, how long the tracker confirmed them),
            but they are present only once inside (an exit when they leave).

        Frames whose stamp goes backwards and tracks with non-finite
        positions (or a repeated id) are dropped and counted
        (:attr:`rejected_frames`, :attr:`rejected_tracks`), never raised.
        """
        stamp_ns, frame = int(stamp_ns), int(frame)
        if stamp_ns < 0 or (self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns):
            self.rejected_frames += 1
            return []
        dt_ns = 0 if self._last_stamp_ns is None else stamp_ns - self._last_stamp_ns
        if self._first_stamp_ns is None:
            self._first_stamp_ns = stamp_ns
        self._last_stamp_ns = stamp_ns
        postures = postures or {}
        current: dict[int, TrackLike] = {}
        for tr in tracks:
            try:
                tid = int(tr.id)
                ok = math.isfinite(float(tr.x)) and math.isfinite(float(tr.y)) and tid not in current
            except (TypeError, ValueError, AttributeError):
                ok = False
            if not ok:
                self.rejected_tracks += 1
                continue
            current[tid] = tr
        out: list[Event] = []
        emit = Emitter(out, stamp_ns, frame)
        for tid in sorted(t for t in self._tracks if t not in current):
            self._vanished(tid, self._tracks.pop(tid), emit)
        beyond = {int(t) for t in outside}
        ids = sorted(current)
        company = dict(zip(ids, company_of([current[t] for t in ids]).tolist()))
        for tid in ids:
            self._track_step(tid, current[tid], postures.get(tid), stamp_ns, emit, inside=tid not in beyond,
                             company_m=company[tid])
        present = [(tid, tr.last_xy) for tid, tr in sorted(self._tracks.items()) if tr.present]
        h = local_hour(stamp_ns, self.utc_offset_h) if hour is None else float(hour) % 24.0
        self.visits.step(stamp_ns, dt_ns, present, h, emit)
        return out

    def rename(self, renames: Mapping[int, int]) -> None:
        """Tracks change ids (``{old: new}``, applied at once, so a swap is two renames):
        what the reasoner and its detectors keep of each goes with it."""
        self._tracks = rekey(self._tracks, renames)
        for detector in self._per_track:
            detector.rename(renames)

    def state_of(self, tid: int) -> dict[str, Any] | None:
        """What a restarted server needs of the track (:meth:`restore`): its fall state and the
        time it was upright; None when it is not low."""
        fall = self.falls.state_of(tid)
        tr = self._tracks.get(tid)
        if fall is None or tr is None:
            return None
        return {**fall, "upright_ns": tr.upright_ns}

    def restore(self, tid: int, state: Mapping[str, Any] | None) -> None:
        """The track is a person a server watched before its restart: already arrived (no entry
        again), and with ``state`` (:meth:`state_of`), their fall and long lie go on, from the
        track's next frame."""
        self._restoring[int(tid)] = state

    # ------------------------------------------------------------------ per track

    def _track_step(self, tid: int, est: TrackLike, reading: Any, stamp_ns: int, emit: Emitter, *,
                    inside: bool = True, company_m: float = math.inf) -> None:
        x, y = float(est.x), float(est.y)
        tr = self._tracks.get(tid)
        if tr is None:
            tr = self._tracks[tid] = _Track(first_xy=(x, y), first_ns=stamp_ns)
        if tid in self._restoring:
            restored = self._restoring.pop(tid)
            tr.confirmed_once = True
            if restored is not None:
                tr.upright_ns = max(tr.upright_ns, int(restored.get("upright_ns", 0)))
                self.falls.restore(tid, restored, stamp_ns)
        if not isinstance(reading, PostureReading):
            posture, reading = (reading if isinstance(reading, str) else None), None
        else:
            posture = reading.posture
        if posture in ("standing", "sitting") and tr.last_ns >= tr.first_ns:
            tr.upright_ns += stamp_ns - tr.last_ns
        tr.last_xy, tr.last_ns = (x, y), stamp_ns
        confirmed = bool(getattr(est, "confirmed", True))
        if not confirmed:
            tr.confirmed_since_ns = None
        elif tr.confirmed_since_ns is None:
            tr.confirmed_since_ns = stamp_ns
        if not tr.present:
            if (confirmed and inside and stamp_ns - tr.confirmed_since_ns >= self._establish_ns
                    and self._big_enough(est, reading)):
                self._arrived(tid, tr, x, y, emit)
        elif not confirmed or not inside:
            self._departed(tid, tr, emit, vanished=not inside)
            if not inside:  # out of the volume: back in, they start afresh (their history stays)
                self._forget(tid)
        if confirmed and inside:
            tr.present_xy, tr.present_ns = (x, y), stamp_ns
        if not inside and not tr.confirmed_once:
            tr.first_xy, tr.first_ns = (x, y), stamp_ns  # first seen, as far as entering goes: where they come in from
        if reading is not None:
            top_m, height_m = reading.raw.top_m, reading.standing_height_m
            body_top_m, centre_m = reading.raw.body_top_m, reading.raw.body_centre_m
        else:
            top_m, centre_m, height_m = float(getattr(est, "z_top_m", float("nan"))), None, None
            body_top_m = top_m
        if math.isfinite(top_m):
            # from the track's first frame: someone who falls while the track is still being
            # established (at start-up, or found late in a crowd) fell from the height seen before
            tr.tops.append((stamp_ns, top_m, centre_m, posture, body_top_m))
            while tr.tops and tr.tops[0][0] < stamp_ns - self._tops_ns:
                tr.tops.popleft()
        if not tr.present and (tr.exited or not tr.confirmed_once):
            return  # not (yet) a person, or gone through a door: nothing to reason about
        seen = TrackSnapshot(tid, stamp_ns, x, y, posture, reading, top_m, centre_m, height_m, tr.tops, tr.upright_ns,
                             confirmed, company_m)
        self.sit_stand.update(seen, emit)
        self.falls.update(seen, emit)
        self.visits.update(seen, emit)
        self.inactivity.update(seen, emit, on_floor=self.falls.on_floor(tid))

    def _big_enough(self, est: TrackLike, reading: PostureReading | None) -> bool:
        """Whether the body is large enough to be a person (unknown volumes pass)."""
        vol = reading.raw.volume_m3 if reading is not None else getattr(est, "volume_m3", None)
        try:
            vol = float(vol)
        except (TypeError, ValueError):
            return True
        return not (vol > 0) or vol >= self.presence.min_volume_m3

    def _arrived(self, tid: int, tr: "_Track", x: float, y: float, emit: Emitter) -> None:
        """The track is established (again): an entry if it came in through a door or the edge."""
        tr.present = True
        if not tr.confirmed_once:
            tr.confirmed_once = True
            self.entries.first_arrival(tid, x, y, first_xy=tr.first_xy, first_ns=tr.first_ns,
                                       start_ns=self._first_stamp_ns, emit=emit)
        elif tr.exited:
            tr.exited = False
            self.entries.return_arrival(tid, x, y, since_ns=tr.confirmed_since_ns, emit=emit)

    def _departed(self, tid: int, tr: "_Track", emit: Emitter, vanished: bool = False) -> None:
        """The track lost its confirmation or vanished: an exit if it was last seen
        in a door zone or at the edge. The tracker keeps reporting a departed
        person unconfirmed for a while before it deletes them; the exit is
        decided at the first of the two."""
        tr.present = False
        place = self.entries.place(*tr.present_xy)
        if place is None and not vanished:
            return  # occluded mid-room: still here
        self.visits.lost(tid, emit)
        if place is not None:
            tr.exited = True
            self.entries.exit(tid, place, tr.present_xy, tr.present_ns, emit)

    def _vanished(self, tid: int, tr: "_Track", emit: Emitter) -> None:
        if tr.present:
            self._departed(tid, tr, emit, vanished=True)
        elif tr.confirmed_once and not tr.exited:
            self.visits.lost(tid, emit)
        self._forget(tid)

    @property
    def _per_track(self) -> tuple:
        """The detectors that keep state per track."""
        return (self.sit_stand, self.falls, self.visits, self.inactivity)

    def _forget(self, tid: int) -> None:
        """Every detector drops what it keeps of track ``tid``."""
        for detector in self._per_track:
            detector.forget(tid)


@dataclass
class _Track:
    """What the reasoner keeps of one track: its presence and the history the detectors share."""

    first_xy: tuple[float, float]
    first_ns: int
    confirmed_since_ns: int | None = None
    confirmed_once: bool = False  # established at least once: a person
    present: bool = False
    exited: bool = False  # left through a door or the edge
    present_xy: tuple[float, float] = (0.0, 0.0)  # last confirmed position
    present_ns: int = 0
    last_xy: tuple[float, float] = (0.0, 0.0)
    last_ns: int = 0
    tops: deque[TopSample] = field(default_factory=deque)
    upright_ns: int = 0  # time this track read standing or sitting, from its first frame
