"""Sitting down and standing up (``sit_down``, ``stand_up``) of one person at a time.

The reported posture moves from standing to sitting / from sitting (or, per
``stand_up_from``, lying) to standing; ``bending`` in between (which includes
kneeling) is ignored. The body's top must have moved with it
(:func:`height_change_m`): down by at least ``min_change_frac`` [0.07] of the
standing height to sit, up as much to stand (an adult's seated top is 0.2-0.3
of it lower, a child's on an adult's chair about 0.12); a posture that flips
while the body keeps its height is the reading changing its mind, not the
person, and the posture held before stands (postures given as bare names
carry no height and skip this test). Between sitting and standing the top
moves at most ``max_change_frac`` [0.65] of the standing height (sitting on
the floor is about half of it): a track whose top jumped more took over
another blob (a fragment growing into a whole body), and its new posture is
taken without an event. So is a change from a posture held less than
``hold_s`` [2 s] (a track's first readings of a body still being carved, a
blob that changes under it): someone sits down after standing, and stands up
after sitting, for longer than that. A sitting reading that rests on a body
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
        self._tracks: dict[int, _SitStandTrack] = {}

    def update(self, frame: TrackSnapshot, emit: Emitter) -> None:
        """Follow one track through one frame; emits ``sit_down`` and ``stand_up``."""
        posture, reading = frame.posture, frame.reading
        if posture not in ("standing", "sitting", "lying") or not frame.confirmed:
            return
        st = self._tracks.setdefault(frame.track, _SitStandTrack())
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
        sit_down = prev == "standing" and posture == "sitting"
        stand_up = posture == "standing" and prev in self.params.stand_up_from
        extra = {}
        if reading is not None and (sit_down or stand_up):
            rise = height_change_m([(s[0], s[1]) for s in frame.tops], reading.since_ns, reading.stamp_ns,
                                   before_s=CHANGE_BEFORE_S,
                                   before_quantile=0.75 if sit_down else 0.25)
            need = self.params.min_change_frac * reading.standing_height_m
            if rise is None or (rise > -need if sit_down else rise < need):
                return  # the body kept its height: not a change of posture
            if "sitting" in (prev, posture) and abs(rise) > self.params.max_change_frac * reading.standing_height_m:
                prev = None  # more than a seat explains: the track's blob changed, not the person
            extra = dict(posture_since_ns=reading.since_ns, confidence=round(reading.confidence, 3),
                         height_change_m=round(rise, 3))
        held_ns = frame.stamp_ns - st.stable_since_ns
        st.stable_posture, st.stable_since_ns = posture, frame.stamp_ns
        if prev is None or held_ns < self._hold_ns:
            return
        if sit_down:
            emit("sit_down", frame.track, frame.x, frame.y, from_posture=prev, to_posture=posture, **extra)
        elif stand_up:
            emit("stand_up", frame.track, frame.x, frame.y, from_posture=prev, to_posture=posture, **extra)

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


@dataclass
class _SitStandTrack:
    stable_posture: str | None = None
    stable_since_ns: int = 0
    sitting_since_ns: int | None = None
    sitting_plausible: bool = True
