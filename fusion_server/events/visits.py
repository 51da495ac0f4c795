"""Dwelling at hot spots and visits (``dwell_start``, ``dwell_end``, ``visit``).

``dwell_start`` / ``dwell_end``
    :class:`fusion_server.hotspots.DwellDetector` per track (the seed paper's
    variance-of-position test over ``dwell_window_s`` [10 s], still below
    ``dwell_still_std_m`` [0.15 m], moved above ``dwell_move_std_m``
    [0.30 m]), with the hot spot's name, label and kind. A track that leaves
    or vanishes ends its dwell (reason ``lost``).
``visit``
    More than ``residents`` people present for at least ``visit_min_s``
    [10 s] (dips shorter than ``visit_gap_s`` [30 s] forgiven) and, with
    ``visit_gathering`` [on] and hot spots configured, at least two of them
    dwelling at the same hot spot; once per episode of extra people.
    Details: the hot spot where they gather (with gathering off: where they
    spent the most person-time), ``people``, and ``reason``, a time of day
    label from the local time: "for breakfast", "for lunch", "for tea", "for
    dinner" inside the ``meals`` windows, else "in the morning" / "in the
    afternoon" / "in the evening" / "at night".
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Iterable, Sequence

import numpy as np
from pydantic import Field, field_validator, model_validator

from common.settings import Settings, group_of
from fusion_server.events._common import NUMBER, ns, rekey
from fusion_server.events.local_time import DEFAULT_MEALS, time_of_day_label
from fusion_server.events.records import Emitter
from fusion_server.events.track import TrackSnapshot
from fusion_server.hotspots import DwellChange, DwellDetector, Hotspot, hotspot_index


class VisitParams(Settings):
    """Settings of :class:`VisitDetector`, each described in the module text.

    meals: ``(label, first local hour, end local hour)`` of each meal window,
        ``0 <= first < end <= 24``.
    """

    dwell_window_s: float = Field(10.0, gt=0.0, **NUMBER)
    dwell_still_std_m: float = Field(0.15, gt=0.0, **NUMBER)
    dwell_move_std_m: float = Field(0.30, **NUMBER)
    visit_min_s: float = Field(10.0, gt=0.0, **NUMBER)
    visit_gap_s: float = Field(30.0, ge=0.0, **NUMBER)
    visit_gathering: bool = True
    meals: tuple[tuple[str, float, float], ...] = DEFAULT_MEALS

    @field_validator("meals")
    @classmethod
    def _meal_hours(cls, meals: tuple) -> tuple:
        for label, start, end in meals:
            if not 0 <= start < end <= 24:
                raise ValueError(f"({label!r}, {start:g}, {end:g}) is not (label, start hour, end hour) "
                                 "with 0 <= start < end <= 24")
        return meals

    @model_validator(mode="after")
    def _stillness_bounds(self) -> "VisitParams":
        if self.dwell_move_std_m < self.dwell_still_std_m:
            raise ValueError(f"dwell_move_std_m ({self.dwell_move_std_m}) must be at least "
                             f"dwell_still_std_m ({self.dwell_still_std_m})")
        return self


class VisitDetector:
    """Dwells per track and visits over all present tracks.

    hotspots: the site's hot spots (first match wins where they overlap).
    residents: people who live here; more present is a visit.
    """

    def __init__(
        self, params: VisitParams = VisitParams(), *, hotspots: Iterable[Hotspot] = (), residents: int = 1
    ) -> None:
        group_of(params, VisitParams)
        if isinstance(residents, bool) or not isinstance(residents, int) or residents < 0:
            raise ValueError(f"residents must be an int >= 0, got {residents!r}")
        self.params = params
        self.hotspots = tuple(hotspots)
        self.residents = residents
        self._min_ns = ns(params.visit_min_s)
        self._gap_ns = ns(params.visit_gap_s)
        self._dwell: dict[int, DwellDetector] = {}
        self._visit = _VisitState(len(self.hotspots))
        self._new_dwell()  # checks the hot spots now rather than on a first track's frame

    def update(self, frame: TrackSnapshot, emit: Emitter) -> None:
        """Follow one track's dwelling through one frame; emits ``dwell_start`` and ``dwell_end``."""
        dwell = self._dwell.get(frame.track)
        if dwell is None:
            dwell = self._dwell[frame.track] = self._new_dwell()
        for ch in dwell.update(frame.stamp_ns, frame.x, frame.y):
            emit(ch.kind, frame.track, ch.x, ch.y, **_dwell_details(ch))

    def lost(self, track: int, emit: Emitter) -> None:
        """The track left or vanished: end its dwell, if any (reason ``lost``)."""
        dwell = self._dwell.get(track)
        if dwell is not None:
            for ch in dwell.lost(emit.stamp_ns):
                emit(ch.kind, track, ch.x, ch.y, **_dwell_details(ch))

    def rename(self, renames: Mapping[int, int]) -> None:
        """Tracks change ids ({old: new}, at once); their state goes with them."""
        self._dwell = rekey(self._dwell, renames)

    def forget(self, track: int) -> None:
        """The track is gone."""
        self._dwell.pop(track, None)

    def step(
        self, stamp_ns: int, dt_ns: int, present: Sequence[tuple[int, tuple[float, float]]], hour: float,
        emit: Emitter,
    ) -> None:
        """The frame's visit test, after every track's update.

        present: ``(track, (x, y))`` of each present track, by track id.
        dt_ns: time since the previous frame. hour: local time of day, hours.
        """
        p, vs = self.params, self._visit
        n = len(present)
        if n > self.residents:
            if vs.since_ns is None:
                vs.reset(stamp_ns)
            vs.last_over_ns = stamp_ns
            vs.max_people = max(vs.max_people, n)
            if self.hotspots and dt_ns > 0:
                idx = hotspot_index(self.hotspots, np.array([xy for _, xy in present]))
                for k in idx[idx >= 0]:
                    vs.person_ns[k] += dt_ns
        elif vs.since_ns is not None and stamp_ns - vs.last_over_ns > self._gap_ns:
            vs.since_ns = None
        if vs.since_ns is None or vs.emitted or n <= self.residents or stamp_ns - vs.since_ns < self._min_ns:
            return
        spot = None
        if p.visit_gathering and self.hotspots:
            dwelling = [d.current.name for d in (self._dwell.get(tid) for tid, _ in present)
                        if d is not None and d.current is not None]
            counts = {h.name: dwelling.count(h.name) for h in self.hotspots}
            best = max(counts.values(), default=0)
            if best < 2:
                return  # extra people, but not (yet) together somewhere
            spot = next(h for h in self.hotspots if counts[h.name] == best)
        elif self.hotspots and vs.person_ns.max() > 0:
            spot = self.hotspots[int(np.argmax(vs.person_ns))]
        vs.emitted = True
        minutes = int(round(hour * 60)) % 1440
        if spot is not None:
            cx, cy = (float(v) for v in spot.centroid_m)
        else:
            cx = float(np.mean([xy[0] for _, xy in present]))
            cy = float(np.mean([xy[1] for _, xy in present]))
        emit(
            "visit", -1, cx, cy,
            people=vs.max_people,
            residents=self.residents,
            since_ns=vs.since_ns,
            duration_s=round((stamp_ns - vs.since_ns) * 1e-9, 3),
            reason=time_of_day_label(hour, p.meals),
            local_time=f"{minutes // 60:02d}:{minutes % 60:02d}",
            hotspot=spot.name if spot is not None else None,
            hotspot_label=spot.label if spot is not None else None,
            hotspot_kind=spot.kind if spot is not None else None,
        )

    def _new_dwell(self) -> DwellDetector:
        p = self.params
        return DwellDetector(hotspots=self.hotspots, window_s=p.dwell_window_s, still_std_m=p.dwell_still_std_m,
                             move_std_m=p.dwell_move_std_m)


def _dwell_details(ch: DwellChange) -> dict[str, Any]:
    d = dict(hotspot=ch.hotspot.name, label=ch.hotspot.label, hotspot_kind=ch.hotspot.kind, start_ns=ch.start_ns)
    if ch.kind == "dwell_end":
        d.update(duration_s=round(ch.duration_s, 3), reason=ch.reason)
    return d


class _VisitState:
    def __init__(self, n_hotspots: int) -> None:
        self.n = n_hotspots
        self.since_ns: int | None = None
        self.last_over_ns = 0
        self.max_people = 0
        self.emitted = False
        self.person_ns = np.zeros(n_hotspots, dtype=np.int64)

    def reset(self, stamp_ns: int) -> None:
        self.since_ns = stamp_ns
        self.last_over_ns = stamp_ns
        self.max_people = 0
        self.emitted = False
        self.person_ns = np.zeros(self.n, dtype=np.int64)
