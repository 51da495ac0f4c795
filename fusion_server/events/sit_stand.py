"""Sitting down and standing up (``sit_down``, ``stand_up``) of one person at a time.

The reported posture moves from standing to sitting / from sitting (or, per
``stand_up_from``, lying) to standing; ``bending`` in between (which includes
kneeling) is ignored. The body's top must have moved with it
(:func:`height_change_m`): down by at least ``min_change_frac`` [0.07] of the
standing height to sit, up as much to stand (an adult's seated top is 0.2-0.3
of it lower, a child's on an adult's chair about 0.12); a posture that flips
while the body keeps its height is the reading changing its mind, not the
person, and the posture held before stands (postures given as bare names
carry no height and skip this test). A seated top is also below the
person's standing height by as much (``standing_height_m`` of the reading):
a body that came down to the person's own height and stays there did not sit,
its top before was someone else's (a short person walking beside a tall one,
carved as one body, who stops apart from them). Between sitting and standing the top
moves at most ``max_change_frac`` [0.65] of the standing height from where
it was while the posture before was held (sitting on the floor is about half
of it; someone who gets up from the floor through a seated shape stands up
from sitting, and their top on the floor is not the seat's): a track whose top jumped more took over
another blob (a fragment growing into a whole body), and its new posture is
taken without an event. So is one across which the top moved the wrong
way too fast: up (to stand) or down (to sit) by more than ``max_move_m``
[0.8 m] within ``move_window_s`` [0.4 s], anywhere from 4 s before the
change to now (each top read as the median of it and the two before: one
frame's bad carve is no movement). People sit down and stand up, from a chair or from the floor,
with the head moving under a metre a second; 2 m/s held for 0.4 s is a track
jumping from a body lying on the floor to someone standing beside it, or
from a fragment to a whole body. Likewise up from lying: nobody gets up from
the floor without passing through kneeling, crouching or sitting, and the
reading has left lying ``floor_rise_s`` [0.5 s] or more before it reads
standing; a track read lying on one frame and standing the next took over
someone standing beside the body. So is a change from a posture held less than
``hold_s`` [2 s] (a track's first readings of a body still being carved, a
blob that changes under it): someone sits down after standing, and stands up
after sitting, for longer than that. But a posture held less than that
between two others is a passage: someone who gets up from the floor may read
sitting for a second on the way, and stands up from lying; the change is
judged from the posture held before the passage (left at most ``hold_s``
before it began, and not the passage's own posture: standing, a second of
sitting, standing and sitting again is no sit_down). A sitting reading that rests on a body
floating at seat height (lower legs not carved: the ``sitting_raised``
posture state) counts only inside a hot spot whose kind is in ``seat_kinds``
[sofa, table, chair, armchair, bench, bed], when the site has any: someone
kneeling behind a sofa looks the same. Only frames where the tracker confirms
the track are read: an unconfirmed track coasts on its particles or follows
what the explanation did not take for a person, and its posture is no body's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Iterable, Literal, Sequence

import numpy as np
from pydantic import Field, model_validator

from common.settings import Settings, group_of
from fusion_server.events._common import NUMBER, median, ns, rekey
from fusion_server.events.records import Emitter
from fusion_server.events.track import TrackSnapshot
from fusion_server.hotspots import SEAT_KINDS, Hotspot, hotspot_at
from fusion_server.posture import PostureReading

CHANGE_BEFORE_S = (4.0, 0.3)
"""Where a posture change looks for the top held before it: from 4 s to 0.3 s
before the filter switched (the switch lags the movement by about a second)."""


class SitStandParams(Settings):
    """Settings of :class:`SitStandDetector`, each described in the module text.

    stand_up_from: postures whose change to standing is a ``stand_up``, out
        of ``sitting``, ``lying`` and ``bending``.
    seat_kinds: hot spot kinds where a body floating at seat height sits.
    """

    stand_up_from: frozenset[Literal["sitting", "lying", "bending"]] = frozenset({"sitting", "lying"})
    min_change_frac: float = Field(0.07, ge=0.0, **NUMBER)
    max_change_frac: float = Field(0.65, **NUMBER)
    hold_s: float = Field(2.0, ge=0.0, **NUMBER)
    max_move_m: float = Field(0.8, gt=0.0, **NUMBER)
    move_window_s: float = Field(0.4, gt=0.0, **NUMBER)
    floor_rise_s: float = Field(0.5, ge=0.0, **NUMBER)
    seat_kinds: frozenset[str] = SEAT_KINDS

    @model_validator(mode="after")
    def _change_range(self) -> "SitStandParams":
        if not self.max_change_frac > self.min_change_frac:
            raise ValueError(f"max_change_frac must be above min_change_frac ({self.min_change_frac}), "
                             f"got {self.max_change_frac}")
        return self

    @property
    def tops_s(self) -> float:
        """How far back the detector reads a track's tops, seconds."""
        return CHANGE_BEFORE_S[0] + 2.5


class SitStandDetector:
    """``sit_down`` and ``stand_up`` per track, from its posture readings and tops.

    hotspots: the site's hot spots; those of ``params.seat_kinds`` are its seats.
    """

    def __init__(self, params: SitStandParams = SitStandParams(), *, hotspots: Iterable[Hotspot] = ()) -> None:
        group_of(params, SitStandParams)
        self.params = params
        self._seats = tuple(h for h in hotspots if h.kind in params.seat_kinds)
        self._hold_ns = ns(params.hold_s)
        self._floor_rise_ns = ns(params.floor_rise_s)
        self._tracks: dict[int, _SitStandTrack] = {}

    def update(self, frame: TrackSnapshot, emit: Emitter) -> None:
        """Follow one track through one frame; emits ``sit_down`` and ``stand_up``."""
        posture, reading = frame.posture, frame.reading
        if posture not in ("standing", "sitting", "lying") or not frame.confirmed:
            return
        st = self._tracks.setdefault(frame.track, _SitStandTrack())
        if posture == "lying":
            st.lying_ns = frame.stamp_ns
        if posture == "sitting":
            # Judge each sitting episode once, when it starts: the state drifts as the person rises.
            since = reading.since_ns if reading is not None else None
            if since is None or since != st.sitting_since_ns:
                st.sitting_since_ns = since
                st.sitting_plausible = self._seat_plausible(reading, frame.x, frame.y)
            if not st.sitting_plausible:
                return
        prev = st.stable_posture
        if prev == posture:
            return
        now_ns = frame.stamp_ns
        settled = prev is not None and now_ns - st.stable_since_ns >= self._hold_ns   # ``prev`` held long enough
        if settled:
            origin, origin_since_ns = prev, st.stable_since_ns
        elif (st.origin is not None and prev is not None and prev != st.origin
              and st.stable_since_ns - st.origin_left_ns <= self._hold_ns):
            origin, origin_since_ns = st.origin, st.origin_since_ns   # ``prev`` was a passage from it
        else:
            origin, origin_since_ns = None, st.stable_since_ns   # too short a posture to tell
        frm = prev if origin is None else origin
        sit_down = frm == "standing" and posture == "sitting"
        stand_up = posture == "standing" and frm in self.params.stand_up_from
        extra = {}
        if stand_up and frm == "lying" and st.lying_ns is not None and now_ns - st.lying_ns < self._floor_rise_ns:
            origin = None  # up from the floor in a blink: the track jumped to someone standing
        if reading is not None and (sit_down or stand_up):
            tops = [(s[0], s[1]) for s in frame.tops]
            rise = height_change_m(tops, reading.since_ns, reading.stamp_ns,
                                   before_s=CHANGE_BEFORE_S,
                                   before_quantile=0.75 if sit_down else 0.25)
            need = self.params.min_change_frac * reading.standing_height_m
            if rise is None or (rise > -need if sit_down else rise < need):
                return  # the body kept its height: not a change of posture
            seated_top = median([z for t, z in tops if t >= reading.since_ns and math.isfinite(z)])
            if sit_down and seated_top > reading.standing_height_m - need:
                return  # a body as tall as the person stands sits nowhere: the top before was not theirs
            # the jump is judged against the top held while the posture before was (a person who
            # got up from the floor through a seated shape stood up from sitting, not from lying)
            held = height_change_m([s for s in tops if s[0] >= origin_since_ns],
                                   reading.since_ns, reading.stamp_ns, before_s=CHANGE_BEFORE_S,
                                   before_quantile=0.75 if sit_down else 0.25)
            jump = rise if held is None else held
            if "sitting" in (frm, posture) and abs(jump) > self.params.max_change_frac * reading.standing_height_m:
                origin = None  # more than a seat explains: the track's blob changed, not the person
            move = fastest_move_m(tops, reading.since_ns - ns(CHANGE_BEFORE_S[0]),
                                  ns(self.params.move_window_s))
            if (move[1] if stand_up else -move[0]) > self.params.max_move_m:
                origin = None  # faster than a person sits or stands: the track jumped to another blob
            extra = dict(posture_since_ns=reading.since_ns, confidence=round(reading.confidence, 3),
                         height_change_m=round(rise, 3))
        if settled:
            st.origin, st.origin_since_ns, st.origin_left_ns = prev, st.stable_since_ns, now_ns
        st.stable_posture, st.stable_since_ns = posture, now_ns
        if origin is None or not (sit_down or stand_up):
            return
        st.origin = None   # told: what follows is judged afresh
        kind = "sit_down" if sit_down else "stand_up"
        emit(kind, frame.track, frame.x, frame.y, from_posture=frm, to_posture=posture, **extra)

    def rename(self, renames: Mapping[int, int]) -> None:
        """Tracks change ids ({old: new}, at once); their state goes with them."""
        self._tracks = rekey(self._tracks, renames)

    def forget(self, track: int) -> None:
        """The track is gone."""
        self._tracks.pop(track, None)

    def _seat_plausible(self, reading: PostureReading | None, x: float, y: float) -> bool:
        """Whether a sitting reading is believable here. A body floating at seat
        height (lower legs not carved) also looks like someone kneeling or
        bending behind furniture; where the site marks its seats with hot spots
        of ``seat_kinds``, it counts as sitting only inside one of them."""
        if not self._seats or reading is None or reading.state != "sitting_raised":
            return True
        return hotspot_at(self._seats, x, y) is not None


def height_change_m(
    samples: Sequence[tuple[int, float]], change_ns: int, now_ns: int, *, before_s: tuple[float, float],
    before_quantile: float = 0.5,
) -> float | None:
    """How much a body's top rose (negative: came down) across a posture change:
    the median top since ``change_ns`` minus the ``before_quantile`` of the top
    in ``[change_ns - before_s[0], change_ns - before_s[1]]`` (seconds before
    the change: the filter reports a new posture only after the body has
    started to move, so the window reaches back past the movement, and a
    quantile above the median (for a sit) or below it (for a stand) reads the
    posture held before rather than the movement). samples: ``(stamp_ns,
    top_m)`` pairs, oldest first. None when either window holds no sample (a
    track too young to say)."""
    lo_ns, hi_ns = change_ns - ns(before_s[0]), change_ns - ns(before_s[1])
    before = [z for t, z in samples if lo_ns <= t <= hi_ns and math.isfinite(z)]
    after = [z for t, z in samples if change_ns <= t <= now_ns and math.isfinite(z)]
    if not before or not after:
        return None
    return median(after) - float(np.quantile(before, before_quantile))


def fastest_move_m(samples: Sequence[tuple[int, float]], since_ns: int, window_ns: int) -> tuple[float, float]:
    """The largest fall and the largest rise of a body's top within any ``window_ns``
    from ``since_ns`` on, metres, as ``(most negative change, most positive change)``
    (0.0 each when nothing moved that way), read on the median of each sample and the two
    before it (one frame's bad carve is no movement). samples: ``(stamp_ns, top_m)``
    pairs, oldest first; non-finite tops are left out."""
    pts = [(t, z) for t, z in samples if math.isfinite(z)]
    smooth = [(t, median([z for _, z in pts[max(0, i - 2): i + 1]])) for i, (t, _) in enumerate(pts)]
    smooth = [p for p in smooth if p[0] >= since_ns]
    if len(smooth) < 2:
        return 0.0, 0.0
    t = np.array([p[0] for p in smooth], dtype=np.int64)
    z = np.array([p[1] for p in smooth], dtype=np.float64)
    change = z[None, :] - z[:, None]   # [from, to]
    gap = t[None, :] - t[:, None]
    near = (gap > 0) & (gap <= window_ns)
    if not near.any():
        return 0.0, 0.0
    return float(min(change[near].min(), 0.0)), float(max(change[near].max(), 0.0))


@dataclass
class _SitStandTrack:
    stable_posture: str | None = None
    stable_since_ns: int = 0
    origin: str | None = None     # the last posture held for hold_s, while what followed it is a passage
    origin_since_ns: int = 0
    origin_left_ns: int = 0
    sitting_since_ns: int | None = None
    sitting_plausible: bool = True
    lying_ns: int | None = None    # the last frame read lying
