"""Inactivity (``inactivity``): someone keeping still for a long time.

A person who is present, not lying on the floor (that is ``long_lie``) and
not inside a hot spot whose kind is in ``rest_kinds`` [bed], has kept the
same posture and stayed within ``std_m`` [0.15 m] (position variance over
``window_s`` [30 s]) for ``inactivity_s`` [1800 s]. Once per still period;
moving or changing posture re-arms it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Iterable

from pydantic import Field

from common.settings import Settings, default_of, group_of
from common.site import EventSettings
from fusion_server.events._common import NUMBER, ns, rekey
from fusion_server.events.records import Emitter
from fusion_server.events.track import TrackSnapshot
from fusion_server.hotspots import Hotspot, PositionWindow, hotspot_at


class InactivityParams(Settings):
    """Settings of :class:`InactivityDetector`, each described in the module text
    (seconds, metres; ``rest_kinds``: hot spot kinds where keeping still is rest)."""

    # positive, not the site file's 30 s floor: that floor is the default window below which
    # stillness cannot be judged; here the window is a parameter too
    inactivity_s: float = Field(default_of(EventSettings, "inactivity_s"), gt=0.0, **NUMBER)
    window_s: float = Field(30.0, gt=0.0, **NUMBER)
    std_m: float = Field(0.15, gt=0.0, **NUMBER)
    rest_kinds: frozenset[str] = frozenset({"bed"})


class InactivityDetector:
    """``inactivity`` per track.

    hotspots: the site's hot spots; those of ``params.rest_kinds`` are for resting.
    """

    def __init__(self, params: InactivityParams = InactivityParams(), *, hotspots: Iterable[Hotspot] = ()) -> None:
        group_of(params, InactivityParams)
        self.params = params
        self.hotspots = tuple(hotspots)
        self._inactivity_ns = ns(params.inactivity_s)
        self._var_m2 = params.std_m ** 2
        self._tracks: dict[int, _InactivityTrack] = {}

    def update(self, frame: TrackSnapshot, emit: Emitter, *, on_floor: bool) -> None:
        """Follow one track through one frame; emits ``inactivity``.

        on_floor: the person lies on the floor now (see :meth:`FallDetector.on_floor
        <fusion_server.events.falls.FallDetector.on_floor>`).
        """
        st = self._tracks.get(frame.track)
        if st is None:
            st = self._tracks[frame.track] = _InactivityTrack(PositionWindow(window_s=self.params.window_s))
        stamp_ns, x, y = frame.stamp_ns, frame.x, frame.y
        if frame.posture != st.posture:
            st.posture, st.posture_changed_ns = frame.posture, stamp_ns
        st.still.add(stamp_ns, x, y)
        still = st.still.full and st.still.variance_m2() <= self._var_m2
        if not still or on_floor:
            st.still_since_ns, st.emitted = None, False
            return
        if st.still_since_ns is None:
            settled = st.still.settled_since_ns(math.sqrt(self._var_m2))
            st.still_since_ns = max(settled, st.posture_changed_ns)
        elif st.posture_changed_ns > st.still_since_ns:
            # Standing up or sitting down in place is activity: start the clock again.
            st.still_since_ns, st.emitted = st.posture_changed_ns, False
        if st.emitted or stamp_ns - st.still_since_ns < self._inactivity_ns:
            return
        spot = hotspot_at(self.hotspots, x, y)
        if spot is not None and spot.kind in self.params.rest_kinds:
            return
        st.emitted = True
        emit(
            "inactivity", frame.track, x, y,
            still_since_ns=st.still_since_ns,
            duration_s=round((stamp_ns - st.still_since_ns) * 1e-9, 3),
            posture=frame.posture or "unknown",
            hotspot=spot.name if spot is not None else None,
        )

    def rename(self, renames: Mapping[int, int]) -> None:
        """Tracks change ids ({old: new}, at once); their state goes with them."""
        self._tracks = rekey(self._tracks, renames)

    def forget(self, track: int) -> None:
        """The track is gone."""
        self._tracks.pop(track, None)


@dataclass
class _InactivityTrack:
    still: PositionWindow
    posture: str | None = None
    posture_changed_ns: int = 0
    still_since_ns: int | None = None
    emitted: bool = False
