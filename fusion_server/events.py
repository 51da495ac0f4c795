"""From tracked people and their postures to the events a carer acts on.

:class:`EventReasoner` takes one fused frame at a time -- its stamp, number,
the tracker's estimates and the posture readings -- and returns the
:class:`EventRecord` s that frame decides. Same inputs, same events, same ids.

Kinds and their meaning (thresholds are keyword arguments, defaults in
brackets):

``fall``
    A fast drop followed by lying on the floor. The body's top height must
    drop by at least ``fall_min_drop_m`` [0.5 m] at an average of at least
    ``fall_min_speed_mps`` [0.8 m/s] within ``fall_window_s`` [2 s], ending
    *low* (top at most ``low_top_frac`` [0.55] and mass centre at most
    ``low_centre_frac`` [0.25] of the person's standing height), and the
    person must then stay low for ``fall_confirm_s`` [1 s] while reading
    ``lying`` (or being very low: top <= ``flat_top_frac`` [0.45] of the
    standing height). Emitted on the confirming frame; ``details`` carry
    ``fall_stamp_ns``, the moment the top of the body passed halfway between
    its height before the drop and its height on the floor, and
    ``drop_start_ns``, when it began to come down. The drop must
    be one a body can make (:func:`drop_is_physical`): the top never comes
    down faster than it would after falling freely through its whole height
    at ``fall_max_accel_mps2`` [1.5 g], give or take ``fall_height_tol_m``
    [0.15 m]; a top that jumps down between two frames is a blob changing
    under the track (a body cut by holes in the masks, a track taking over
    a fragment), not a fall. And only someone who was upright falls: the
    track must have read standing or sitting for ``fall_history_s`` [0.5 s]
    in all since its first frame (a person walks or sits before they fall;
    hull volume by a wall that reads lying from its first frame has no such
    history). The top is followed from the track's first frame, so that
    someone who falls while their track is still being established (at
    start-up, or found late in a crowd) falls from the height seen before,
    and is reported once the track is established. Sitting down,
    kneeling, bending and squatting never end low enough; lying down slowly
    is not fast enough (it may become a ``long_lie``).
``long_lie``
    Lying on the floor (low, as above, and reading ``lying`` or very low)
    continuously for ``long_lie_s`` [30 s] since the fall (or since lying
    down, when no fall was seen). Lying on a bed or sofa is not low, so it
    never counts.
``sit_down`` / ``stand_up``
    The reported posture moves from standing to sitting / from sitting (or,
    per ``stand_up_from``, lying) to standing; ``bending`` in between (which
    includes kneeling) is ignored. The body's top must have moved with it
    (:func:`height_change_m`): down by at least ``sit_min_change_frac`` [0.07]
    of the standing height to sit, up as much to stand (an adult's seated top
    is 0.2-0.3 of it lower, a child's on an adult's chair about 0.12); a
    posture that flips while the body keeps its height is the reading
    changing its mind, not the person, and the posture held before stands
    (postures given as bare names carry no height and skip this test).
    Between sitting and standing the top moves at most
    ``sit_max_change_frac`` [0.65] of the standing height (sitting on the
    floor is about half of it): a track whose top jumped more took over
    another blob (a fragment growing into a whole body), and its new
    posture is taken without an event. So is a change from a posture held
    less than ``posture_hold_s`` [2 s] (a track's first readings of a body
    still being carved, a blob that changes under it): someone sits down
    after standing, and stands up after sitting, for longer than that. A
    sitting reading that rests on a body floating at seat height (lower legs
    not carved: the ``sitting_raised`` posture state) counts only inside a
    hot spot whose kind is in ``seat_kinds`` [sofa, table, chair, armchair,
    bench, bed], when the site has any: someone kneeling behind a sofa looks
    the same.
``enter`` / ``exit``
    A track first seen inside a door zone (or, when ``bounds_xy_m`` is
    given, within ``edge_margin_m`` [0.4 m] of the monitored area's border)
    enters when it is established (below); people already there during the
    first ``startup_s`` [1 s] do not enter. A present track whose last
    confirmed position is in such a place exits when the tracker stops
    confirming it or stops reporting it, whichever comes first (the
    tracker coasts a departed person unconfirmed for a couple of seconds
    before deleting them). A track that has exited and is established again
    in a door zone or at the edge enters again. Tracks that appear, lose confirmation (occlusion) or
    vanish mid-room are neither.
``dwell_start`` / ``dwell_end``
    :class:`fusion_server.hotspots.DwellDetector` per track (the seed
    paper's variance-of-position test), with the hot spot's name, label and
    kind.
``visit``
    More than ``residents`` people present for at least ``visit_min_s``
    [10 s] (dips shorter than ``visit_gap_s`` [30 s] forgiven) and, with
    ``visit_gathering`` [on] and hot spots configured, at least two of them
    dwelling at the same hot spot; once per episode of extra people. Details:
    the hot spot where they gather (with gathering off: where they spent the
    most person-time), ``people``, and ``reason``, a time of day label from
    the local time (``utc_offset_h``): "for breakfast", "for lunch", "for
    tea", "for dinner" inside the meal windows, else "in the morning" / "in
    the afternoon" / "in the evening" / "at night".
``inactivity``
    A person who is present, not lying on the floor (that is ``long_lie``)
    and not inside a hot spot whose kind is in ``rest_kinds`` [bed], has
    kept the same posture and stayed within ``inactivity_std_m`` [0.15 m]
    (position variance over ``inactivity_window_s`` [30 s]) for
    ``inactivity_s`` [1800 s]. Once per still period; moving or changing
    posture re-arms it.

Only established tracks take part: confirmed by the tracker for
``establish_s`` [0.8 s] in a row with a body of at least ``min_volume_m3``
[0.04 m^3] (a person carves 0.1-0.4 m^3; tracker ghosts -- a blob split off
a person for a second, a small blob at a wall -- do not qualify). An
established track that loses confirmation mid-room (occlusion) keeps its
state until it vanishes.

Pure logic: no clock, no I/O. Frames whose stamp goes backwards and tracks
with non-finite positions are dropped and counted, never raised.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Protocol, Sequence

import numpy as np

from common import messages
from fusion_server.hotspots import DwellDetector, Hotspot, PositionWindow, hotspot_at, hotspot_index
from fusion_server.posture import PostureReading

EVENT_KINDS: tuple[str, ...] = messages.PERSON_EVENT_KINDS
"""Kinds :class:`EventReasoner` emits (a subset of the wire's event kinds)."""

DEFAULT_MEALS: tuple[tuple[str, float, float], ...] = (
    ("for breakfast", 6.0, 10.0),
    ("for lunch", 11.5, 14.0),
    ("for tea", 15.0, 17.5),
    ("for dinner", 17.5, 21.5),
)
"""(label, first local hour, end local hour) of each meal window."""


class TrackLike(Protocol):
    """What the reasoner reads of a track estimate (any object with these attributes)."""

    id: int
    x: float
    y: float
    z_top_m: float
    confirmed: bool


@dataclass(frozen=True)
class EventRecord:
    """One event. Field names match the wire ``Event`` message.

    id: ``f"{stamp_ns}-{kind}-{track}"``, unique and deterministic.
    kind: one of :data:`EVENT_KINDS`.
    track: track id, -1 when the event concerns no single track (visits).
    stamp_ns: the frame that decided the event. frame: its number.
    x, y: world floor position, metres.
    details: flat map of str -> str | int | float | bool | None.
    """

    id: str
    kind: str
    track: int
    stamp_ns: int
    frame: int
    x: float
    y: float
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (a copy)."""
        return {
            "id": self.id,
            "kind": self.kind,
            "track": self.track,
            "stamp_ns": self.stamp_ns,
            "frame": self.frame,
            "x": self.x,
            "y": self.y,
            "details": dict(self.details),
        }

    @classmethod
    def from_dict(cls, obj: Mapping[str, Any]) -> "EventRecord":
        """Inverse of :meth:`to_dict`; ValueError naming the bad field."""
        if not isinstance(obj, Mapping):
            raise ValueError(f"event must be a mapping, got {type(obj).__name__}")
        out: dict[str, Any] = {}
        for name, typ in (("id", str), ("kind", str), ("track", int), ("stamp_ns", int), ("frame", int)):
            if name not in obj:
                raise ValueError(f"event field {name!r} is missing")
            val = obj[name]
            if isinstance(val, bool) or not isinstance(val, typ):
                raise ValueError(f"event field {name!r} must be {typ.__name__}, got {type(val).__name__}")
            out[name] = val
        if not out["id"]:
            raise ValueError("event field 'id' must not be empty")
        for name in ("x", "y"):
            val = obj.get(name, 0.0)
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
                raise ValueError(f"event field {name!r} must be a finite number, got {val!r}")
            out[name] = float(val)
        details = obj.get("details") or {}
        if not isinstance(details, Mapping):
            raise ValueError(f"event field 'details' must be a mapping, got {type(details).__name__}")
        out["details"] = dict(details)
        return cls(**out)


def event_id(stamp_ns: int, kind: str, track: int) -> str:
    """The deterministic event id ``f"{stamp_ns}-{kind}-{track}"``."""
    return f"{int(stamp_ns)}-{kind}-{int(track)}"


def local_hour(stamp_ns: int, utc_offset_h: float = 0.0) -> float:
    """Local time of day in hours [0, 24) of a Unix-epoch ``stamp_ns``."""
    seconds = stamp_ns / 1e9 + utc_offset_h * 3600.0
    return (seconds % 86400.0) / 3600.0


def time_of_day_label(hour: float, meals: Sequence[tuple[str, float, float]] = DEFAULT_MEALS) -> str:
    """Meal label for a local hour, or a part of the day outside the meal windows."""
    h = float(hour) % 24.0
    for label, start, end in meals:
        if start <= h < end:
            return label
    if 5.0 <= h < 12.0:
        return "in the morning"
    if 12.0 <= h < 17.0:
        return "in the afternoon"
    if 17.0 <= h < 22.0:
        return "in the evening"
    return "at night"


def detect_fast_drop(
    t_s: np.ndarray, z_m: np.ndarray, *, window_s: float, min_drop_m: float, min_speed_mps: float
) -> tuple[int, int] | None:
    """The largest fast drop in a height series, as sample indices ``(i, j)``.

    t_s: (N,) float64 increasing times, seconds; z_m: (N,) heights, metres.
    A pair ``i < j`` qualifies when ``0 < t[j] - t[i] <= window_s``,
    ``z[i] - z[j] >= min_drop_m`` and the average speed
    ``(z[i] - z[j]) / (t[j] - t[i]) >= min_speed_mps``. The largest drop
    wins; ties go to the earliest ``j``, then the latest ``i``.
    """
    t = np.asarray(t_s, dtype=np.float64)
    z = np.asarray(z_m, dtype=np.float64)
    if t.shape != z.shape or t.ndim != 1:
        raise ValueError(f"t_s and z_m must be (N,) arrays of equal length, got {t.shape} and {z.shape}")
    if len(t) < 2:
        return None
    drop = z[:, None] - z[None, :]
    dt = t[None, :] - t[:, None]
    ok = (dt > 0) & (dt <= window_s) & (drop >= min_drop_m) & (drop >= min_speed_mps * dt)
    if not ok.any():
        return None
    best = np.where(ok, drop, -np.inf).max()
    ii, jj = np.nonzero(ok & (drop >= best - 1e-12))
    order = np.lexsort((-ii, jj))
    return int(ii[order[0]]), int(jj[order[0]])


def drop_is_physical(
    t_s: np.ndarray, z_m: np.ndarray, i: int, j: int, *, max_accel_mps2: float, tol_m: float
) -> bool:
    """Whether the drop of ``z`` from sample ``i`` to ``j`` is one a falling body can make.

    A top that falls from rest through its whole height ``z[i]`` at ``max_accel_mps2`` reaches
    ``v = sqrt(2 * max_accel_mps2 * z[i])``; between no two samples in ``[i, j]`` may it have come
    down faster than that, give or take ``tol_m`` of measured height. The tip of a rigid body
    toppling over its feet accelerates down at up to 1.5 g; a top that comes down faster was not
    one body falling. t_s, z_m: (N,) seconds and metres, as for :func:`detect_fast_drop`.
    """
    t = np.asarray(t_s, dtype=np.float64)[i : j + 1]
    z = np.asarray(z_m, dtype=np.float64)[i : j + 1]
    v_max = math.sqrt(2.0 * max_accel_mps2 * max(float(z[0]), 0.0))
    drop = z[:, None] - z[None, :]
    dt = t[None, :] - t[:, None]
    return bool(np.all((dt <= 0) | (drop <= v_max * dt + tol_m)))


# Where a posture change looks for the top held before it: from 4 s to 0.3 s
# before the filter switched (the switch lags the movement by about a second).
_CHANGE_BEFORE_S = (4.0, 0.3)


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
    lo_ns, hi_ns = change_ns - _ns(before_s[0]), change_ns - _ns(before_s[1])
    before = [z for t, z in samples if lo_ns <= t <= hi_ns and math.isfinite(z)]
    after = [z for t, z in samples if change_ns <= t <= now_ns and math.isfinite(z)]
    if not before or not after:
        return None
    return _median(after) - float(np.quantile(before, before_quantile))


def crossing_time(t_s: np.ndarray, z_m: np.ndarray, i: int, j: int, level_m: float) -> float:
    """First time after sample ``i`` (up to ``j``) at which ``z`` falls to ``level_m``,
    linearly interpolated between samples; seconds."""
    t = np.asarray(t_s, dtype=np.float64)
    z = np.asarray(z_m, dtype=np.float64)
    for k in range(i + 1, j + 1):
        if z[k] <= level_m:
            z0, z1 = z[k - 1], z[k]
            f = 1.0 if z0 == z1 else (z0 - level_m) / (z0 - z1)
            return float(t[k - 1] + min(max(f, 0.0), 1.0) * (t[k] - t[k - 1]))
    return float(t[j])


class EventReasoner:
    """Events from tracks and postures, frame by frame. See the module docstring
    for each kind; every threshold is a keyword argument.

    hotspots: hot spots for dwelling, visits and ``rest_kinds``.
    doors: door zones (Hotspot objects; kind is not used).
    bounds_xy_m: ``(x_min, y_min, x_max, y_max)`` of the monitored floor,
        for entering and leaving at the edge; None: doors only.
    residents: people who live here; more present is a visit.
    utc_offset_h: local time = UTC + this (the stamps are Unix-epoch ns).
    standing_height_m: used when a track has no posture reading with a
        learnt standing height.
    """

    def __init__(
        self,
        *,
        hotspots: Iterable[Hotspot] = (),
        doors: Iterable[Hotspot] = (),
        bounds_xy_m: Sequence[float] | None = None,
        edge_margin_m: float = 0.4,
        residents: int = 1,
        utc_offset_h: float = 0.0,
        meals: Sequence[tuple[str, float, float]] = DEFAULT_MEALS,
        rest_kinds: Iterable[str] = ("bed",),
        seat_kinds: Iterable[str] = ("sofa", "table", "chair", "armchair", "bench", "bed"),
        standing_height_m: float = 1.70,
        fall_window_s: float = 2.0,
        fall_min_drop_m: float = 0.5,
        fall_min_speed_mps: float = 0.8,
        fall_max_accel_mps2: float = 1.5 * 9.81,
        fall_height_tol_m: float = 0.15,
        fall_confirm_s: float = 1.0,
        fall_history_s: float = 0.5,
        low_top_frac: float = 0.55,
        low_centre_frac: float = 0.25,
        flat_top_frac: float = 0.45,
        low_gap_s: float = 0.5,
        long_lie_s: float = 30.0,
        stand_up_from: Iterable[str] = ("sitting", "lying"),
        sit_min_change_frac: float = 0.07,
        sit_max_change_frac: float = 0.65,
        posture_hold_s: float = 2.0,
        dwell_window_s: float = 10.0,
        dwell_still_std_m: float = 0.15,
        dwell_move_std_m: float = 0.30,
        visit_min_s: float = 10.0,
        visit_gap_s: float = 30.0,
        visit_gathering: bool = True,
        startup_s: float = 1.0,
        establish_s: float = 0.8,
        min_volume_m3: float = 0.04,
        inactivity_s: float = 1800.0,
        inactivity_window_s: float = 30.0,
        inactivity_std_m: float = 0.15,
    ) -> None:
        self.hotspots = tuple(hotspots)
        self.doors = tuple(doors)
        for name, items in (("hotspots", self.hotspots), ("doors", self.doors)):
            for h in items:
                if not isinstance(h, Hotspot):
                    raise ValueError(f"{name} must hold Hotspot instances, got {type(h).__name__}")
        names = [h.name for h in self.hotspots]
        if len(set(names)) != len(names):
            raise ValueError(f"hotspots names must be unique, got {names}")
        if bounds_xy_m is not None:
            b = tuple(float(v) for v in bounds_xy_m)
            if len(b) != 4 or not all(math.isfinite(v) for v in b) or not (b[0] < b[2] and b[1] < b[3]):
                raise ValueError(f"bounds_xy_m must be (x_min, y_min, x_max, y_max) with min < max, got {bounds_xy_m}")
            bounds_xy_m = b
        self.bounds_xy_m = bounds_xy_m
        positive = dict(
            standing_height_m=standing_height_m,
            fall_window_s=fall_window_s,
            fall_min_drop_m=fall_min_drop_m,
            fall_min_speed_mps=fall_min_speed_mps,
            fall_max_accel_mps2=fall_max_accel_mps2,
            long_lie_s=long_lie_s,
            dwell_window_s=dwell_window_s,
            visit_min_s=visit_min_s,
            inactivity_s=inactivity_s,
            inactivity_window_s=inactivity_window_s,
            inactivity_std_m=inactivity_std_m,
        )
        for name, val in positive.items():
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be a positive number, got {val!r}")
        non_negative = dict(edge_margin_m=edge_margin_m, fall_confirm_s=fall_confirm_s, low_gap_s=low_gap_s,
                            visit_gap_s=visit_gap_s, startup_s=startup_s, establish_s=establish_s,
                            min_volume_m3=min_volume_m3, fall_height_tol_m=fall_height_tol_m,
                            fall_history_s=fall_history_s, sit_min_change_frac=sit_min_change_frac,
                            posture_hold_s=posture_hold_s)
        for name, val in non_negative.items():
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {val!r}")
        for name, val in (("low_top_frac", low_top_frac), ("low_centre_frac", low_centre_frac),
                          ("flat_top_frac", flat_top_frac)):
            if not 0 < val < 1:
                raise ValueError(f"{name} must lie in (0, 1), got {val!r}")
        if isinstance(residents, bool) or not isinstance(residents, int) or residents < 0:
            raise ValueError(f"residents must be an int >= 0, got {residents!r}")
        if not (isinstance(utc_offset_h, (int, float)) and -14 <= utc_offset_h <= 14):
            raise ValueError(f"utc_offset_h must lie in [-14, 14], got {utc_offset_h!r}")
        for m in meals:
            if len(m) != 3 or not isinstance(m[0], str) or not 0 <= m[1] < m[2] <= 24:
                raise ValueError(f"meals entries must be (label, start_hour, end_hour) with 0 <= start < end <= 24, got {m!r}")
        self.stand_up_from = frozenset(stand_up_from)
        self.sit_min_change_frac = float(sit_min_change_frac)
        if not (isinstance(sit_max_change_frac, (int, float)) and sit_min_change_frac < sit_max_change_frac < math.inf):
            raise ValueError(f"sit_max_change_frac must be a number above sit_min_change_frac, got {sit_max_change_frac!r}")
        self.sit_max_change_frac = float(sit_max_change_frac)
        self.posture_hold_ns = _ns(posture_hold_s)
        if not self.stand_up_from <= {"sitting", "lying", "bending"}:
            raise ValueError(f"stand_up_from may hold 'sitting', 'lying', 'bending', got {sorted(self.stand_up_from)}")
        # Validate the dwell settings once, up front.
        DwellDetector(hotspots=self.hotspots, window_s=dwell_window_s, still_std_m=dwell_still_std_m,
                      move_std_m=dwell_move_std_m)
        self._dwell_kwargs = dict(window_s=dwell_window_s, still_std_m=dwell_still_std_m, move_std_m=dwell_move_std_m)
        self.edge_margin_m = float(edge_margin_m)
        self.residents = residents
        self.utc_offset_h = float(utc_offset_h)
        self.meals = tuple(meals)
        self.rest_kinds = frozenset(rest_kinds)
        self.seat_kinds = frozenset(seat_kinds)
        self._seat_spots = tuple(h for h in self.hotspots if h.kind in self.seat_kinds)
        self.standing_height_m = float(standing_height_m)
        self.fall_window_s = float(fall_window_s)
        self.fall_min_drop_m = float(fall_min_drop_m)
        self.fall_min_speed_mps = float(fall_min_speed_mps)
        self.fall_max_accel_mps2 = float(fall_max_accel_mps2)
        self.fall_height_tol_m = float(fall_height_tol_m)
        self.fall_confirm_ns = _ns(fall_confirm_s)
        self.fall_history_ns = _ns(fall_history_s)
        self.low_top_frac = float(low_top_frac)
        self.low_centre_frac = float(low_centre_frac)
        self.flat_top_frac = float(flat_top_frac)
        self.low_gap_ns = _ns(low_gap_s)
        self.long_lie_ns = _ns(long_lie_s)
        self.visit_min_ns = _ns(visit_min_s)
        self.visit_gap_ns = _ns(visit_gap_s)
        self.visit_gathering = bool(visit_gathering)
        self.startup_ns = _ns(startup_s)
        self.establish_ns = _ns(establish_s)
        self.min_volume_m3 = float(min_volume_m3)
        self.inactivity_ns = _ns(inactivity_s)
        self.inactivity_window_s = float(inactivity_window_s)
        self.inactivity_var_m2 = float(inactivity_std_m) ** 2
        # The top history serves the fall test and the posture-change test.
        self._buffer_ns = _ns(max(2 * fall_window_s + fall_confirm_s + 0.5, _CHANGE_BEFORE_S[0] + 2.5))
        self._tracks: dict[int, _TrackState] = {}
        self._last_stamp_ns: int | None = None
        self._first_stamp_ns: int | None = None
        self._visit = _VisitState(len(self.hotspots))
        self.rejected_frames = 0
        self.rejected_tracks = 0

    # ------------------------------------------------------------------ public

    def step(
        self,
        stamp_ns: int,
        frame: int,
        tracks: Iterable[TrackLike],
        postures: Mapping[int, PostureReading | str] | None = None,
        *,
        hour: float | None = None,
    ) -> list[EventRecord]:
        """Events decided by one frame.

        stamp_ns: frame time (Unix-epoch ns for time-of-day labels).
        frame: fused frame number. tracks: this frame's estimates.
        postures: per track id, a :class:`PostureReading` (or a posture name).
        hour: local time of day in hours, overriding ``stamp_ns`` and
            ``utc_offset_h`` for visit labels.
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
        out: list[EventRecord] = []
        emit = _Emitter(out, stamp_ns, frame)
        for tid in sorted(t for t in self._tracks if t not in current):
            self._vanished(tid, self._tracks.pop(tid), emit)
        for tid in sorted(current):
            self._track_step(tid, current[tid], postures.get(tid), stamp_ns, emit)
        self._visit_step(stamp_ns, dt_ns, emit, hour)
        return out

    # ------------------------------------------------------------------ per track

    def _track_step(self, tid: int, tr: TrackLike, reading: Any, stamp_ns: int, emit: "_Emitter") -> None:
        x, y = float(tr.x), float(tr.y)
        st = self._tracks.get(tid)
        if st is None:
            st = self._tracks[tid] = _TrackState(
                first_xy=(x, y),
                first_ns=stamp_ns,
                dwell=DwellDetector(hotspots=self.hotspots, **self._dwell_kwargs),
                still=PositionWindow(window_s=self.inactivity_window_s),
            )
        upright = (reading.posture if isinstance(reading, PostureReading) else reading) in ("standing", "sitting")
        if upright and st.last_ns >= st.first_ns:
            st.upright_ns += stamp_ns - st.last_ns
        st.last_xy, st.last_ns = (x, y), stamp_ns
        confirmed = bool(getattr(tr, "confirmed", True))
        if not confirmed:
            st.confirmed_since_ns = None
        elif st.confirmed_since_ns is None:
            st.confirmed_since_ns = stamp_ns
        if not st.present:
            if confirmed and stamp_ns - st.confirmed_since_ns >= self.establish_ns and self._big_enough(tr, reading):
                self._arrived(tid, st, x, y, emit)
        elif not confirmed:
            self._departed(tid, st, emit)
        if confirmed:
            st.present_xy, st.present_ns = (x, y), stamp_ns
        posture, top_m, centre_m, height_m = self._observe(tr, reading)
        if math.isfinite(top_m):
            # from the track's first frame: someone who falls while the track is still being
            # established (at start-up, or found late in a crowd) fell from the height seen before
            fs = st.fall
            fs.samples.append((stamp_ns, top_m, centre_m, posture))
            while fs.samples and fs.samples[0][0] < stamp_ns - self._buffer_ns:
                fs.samples.popleft()
        if not st.present and (st.exited or not st.confirmed_once):
            return  # not (yet) a person, or gone through a door: nothing to reason about
        if posture != st.posture:
            st.posture, st.posture_changed_ns = posture, stamp_ns
        self._posture_events(tid, st, stamp_ns, posture, reading, x, y, emit)
        self._fall_events(tid, st, stamp_ns, posture, top_m, centre_m, height_m, x, y, emit)
        for ch in st.dwell.update(stamp_ns, x, y):
            emit(ch.kind, tid, ch.x, ch.y, **_dwell_details(ch))
        self._inactivity(tid, st, stamp_ns, posture, x, y, emit)

    def _observe(self, tr: TrackLike, reading: Any) -> tuple[str | None, float, float | None, float]:
        """Posture, top and centre heights (m above the floor) and standing height."""
        if isinstance(reading, PostureReading):
            return reading.posture, reading.raw.top_m, reading.raw.centre_m, reading.standing_height_m
        posture = reading if isinstance(reading, str) else None
        top = float(getattr(tr, "z_top_m", float("nan")))
        return posture, top, None, self.standing_height_m

    def _posture_events(self, tid, st, stamp_ns, posture, reading, x, y, emit) -> None:
        if posture not in ("standing", "sitting", "lying"):
            return
        if posture == "sitting":
            # Judge each sitting episode once, when it starts: the state drifts as the person rises.
            since = reading.since_ns if isinstance(reading, PostureReading) else None
            if since is None or since != st.sitting_since_ns:
                st.sitting_since_ns = since
                st.sitting_plausible = self._seat_plausible(reading, x, y)
            if not st.sitting_plausible:
                return
        prev = st.stable_posture
        if prev == posture:
            return
        sit_down = prev == "standing" and posture == "sitting"
        stand_up = posture == "standing" and prev in self.stand_up_from
        extra = {}
        if isinstance(reading, PostureReading) and (sit_down or stand_up):
            rise = height_change_m([(s[0], s[1]) for s in st.fall.samples], reading.since_ns, reading.stamp_ns,
                                   before_s=_CHANGE_BEFORE_S,
                                   before_quantile=0.75 if sit_down else 0.25)
            need = self.sit_min_change_frac * reading.standing_height_m
            if rise is None or (rise > -need if sit_down else rise < need):
                return  # the body kept its height: not a change of posture
            if "sitting" in (prev, posture) and abs(rise) > self.sit_max_change_frac * reading.standing_height_m:
                prev = None  # more than a seat explains: the track's blob changed, not the person
            extra = dict(posture_since_ns=reading.since_ns, confidence=round(reading.confidence, 3),
                         height_change_m=round(rise, 3))
        held_ns = stamp_ns - st.stable_since_ns
        st.stable_posture, st.stable_since_ns = posture, stamp_ns
        if prev is None or held_ns < self.posture_hold_ns:
            return
        if sit_down:
            emit("sit_down", tid, x, y, from_posture=prev, to_posture=posture, **extra)
        elif stand_up:
            emit("stand_up", tid, x, y, from_posture=prev, to_posture=posture, **extra)

    def _seat_plausible(self, reading: Any, x: float, y: float) -> bool:
        """Whether a sitting reading is believable here. A body floating at seat
        height (lower legs not carved) also looks like someone kneeling or
        bending behind furniture; where the site marks its seats with hot spots
        of ``seat_kinds``, it counts as sitting only inside one of them."""
        if not self._seat_spots or not isinstance(reading, PostureReading) or reading.state != "sitting_raised":
            return True
        return hotspot_at(self._seat_spots, x, y) is not None

    def _fall_events(self, tid, st, stamp_ns, posture, top_m, centre_m, height_m, x, y, emit) -> None:
        if not math.isfinite(top_m):
            return
        fs = st.fall
        # A median over the last three frames keeps one bad carve from toggling "low".
        recent = [fs.samples[-k] for k in range(1, min(3, len(fs.samples)) + 1)]
        top_med = _median([s[1] for s in recent])
        cen = [s[2] for s in recent if s[2] is not None]
        centre_med = _median(cen) if cen else None
        low = top_med <= self.low_top_frac * height_m and (
            centre_med is None or centre_med <= self.low_centre_frac * height_m
        )
        on_floor = low and (posture == "lying" or top_med <= self.flat_top_frac * height_m)
        if low:
            if fs.low_since_ns is None:
                fs.low_since_ns = stamp_ns
                fs.drop = None
                fs.fall_emitted = False
                fs.long_lie_emitted = False
                fs.floor_since_ns = None
            fs.last_low_ns = stamp_ns
        elif fs.low_since_ns is not None and stamp_ns - fs.last_low_ns > self.low_gap_ns:
            fs.low_since_ns = None
            fs.floor_since_ns = None
        if fs.low_since_ns is None:
            return
        if fs.drop is None and stamp_ns - fs.low_since_ns <= _ns(self.fall_window_s):
            fs.drop = self._find_drop(fs, height_m)
        if on_floor:
            if fs.floor_since_ns is None:
                fs.floor_since_ns = stamp_ns
            fs.last_floor_ns = stamp_ns
        elif fs.floor_since_ns is not None and stamp_ns - fs.last_floor_ns > self.low_gap_ns:
            fs.floor_since_ns = None
        if (
            not fs.fall_emitted
            and fs.drop is not None
            and on_floor
            and stamp_ns - fs.low_since_ns >= self.fall_confirm_ns
            and st.upright_ns >= self.fall_history_ns
        ):
            fs.fall_emitted = True
            emit("fall", tid, x, y, **fs.drop, confirm_s=round((stamp_ns - fs.low_since_ns) * 1e-9, 3))
        if fs.floor_since_ns is not None and not fs.long_lie_emitted:
            since = fs.floor_since_ns
            if fs.drop is not None:
                since = min(since, fs.drop["fall_stamp_ns"])
            if stamp_ns - since >= self.long_lie_ns:
                fs.long_lie_emitted = True
                emit(
                    "long_lie", tid, x, y,
                    lying_since_ns=since,
                    duration_s=round((stamp_ns - since) * 1e-9, 3),
                    after_fall=fs.drop is not None,
                    fall_stamp_ns=fs.drop["fall_stamp_ns"] if fs.drop is not None else None,
                )

    def _find_drop(self, fs: "_FallState", height_m: float) -> dict[str, Any] | None:
        start = fs.low_since_ns - _ns(self.fall_window_s)
        samples = [s for s in fs.samples if s[0] >= start]
        if len(samples) < 2:
            return None
        t0 = samples[0][0]
        t = np.array([(s[0] - t0) * 1e-9 for s in samples])
        z = np.array([s[1] for s in samples])
        pair = detect_fast_drop(t, z, window_s=self.fall_window_s, min_drop_m=self.fall_min_drop_m,
                                min_speed_mps=self.fall_min_speed_mps)
        if pair is None:
            return None
        i, j = pair
        if z[i] < self.flat_top_frac * height_m:
            return None  # started on the floor already: not a fall from standing or sitting
        if not drop_is_physical(t, z, i, j, max_accel_mps2=self.fall_max_accel_mps2, tol_m=self.fall_height_tol_m):
            return None
        t_fall = crossing_time(t, z, i, j, 0.5 * (z[i] + z[j]))
        return dict(
            fall_stamp_ns=t0 + int(round(t_fall * 1e9)),
            drop_start_ns=int(samples[i][0]),
            from_posture=samples[i][3] or "unknown",
            top_before_m=round(float(z[i]), 3),
            top_after_m=round(float(z[j]), 3),
            drop_m=round(float(z[i] - z[j]), 3),
            drop_speed_mps=round(float((z[i] - z[j]) / (t[j] - t[i])), 3),
        )

    def _inactivity(self, tid, st, stamp_ns, posture, x, y, emit) -> None:
        st.still.add(stamp_ns, x, y)
        on_floor = st.fall.floor_since_ns is not None
        still = st.still.full and st.still.variance_m2() <= self.inactivity_var_m2
        if not still or on_floor:
            st.still_since_ns, st.inactivity_emitted = None, False
            return
        if st.still_since_ns is None:
            settled = st.still.settled_since_ns(math.sqrt(self.inactivity_var_m2))
            st.still_since_ns = max(settled, st.posture_changed_ns)
        elif st.posture_changed_ns > st.still_since_ns:
            # Standing up or sitting down in place is activity: start the clock again.
            st.still_since_ns, st.inactivity_emitted = st.posture_changed_ns, False
        if st.inactivity_emitted or stamp_ns - st.still_since_ns < self.inactivity_ns:
            return
        spot = hotspot_at(self.hotspots, x, y)
        if spot is not None and spot.kind in self.rest_kinds:
            return
        st.inactivity_emitted = True
        emit(
            "inactivity", tid, x, y,
            still_since_ns=st.still_since_ns,
            duration_s=round((stamp_ns - st.still_since_ns) * 1e-9, 3),
            posture=posture or "unknown",
            hotspot=spot.name if spot is not None else None,
        )

    def _arrived(self, tid: int, st: "_TrackState", x: float, y: float, emit: "_Emitter") -> None:
        """The track is confirmed (again): an entry if it came in through a door or the edge."""
        st.present = True
        if not st.confirmed_once:
            st.confirmed_once = True
            place = self._entry_place(*st.first_xy)
            # People already in the room when monitoring starts did not enter.
            if place is not None and st.first_ns - self._first_stamp_ns > self.startup_ns:
                emit("enter", tid, x, y, door=place, first_seen_ns=st.first_ns)
        elif st.exited:
            st.exited = False
            place = self._entry_place(x, y)
            if place is not None:  # came back in; confirmed again mid-room, they never left
                emit("enter", tid, x, y, door=place, first_seen_ns=st.confirmed_since_ns)

    def _big_enough(self, tr: TrackLike, reading: Any) -> bool:
        """Whether the body is large enough to be a person (unknown volumes pass)."""
        vol = reading.raw.volume_m3 if isinstance(reading, PostureReading) else getattr(tr, "volume_m3", None)
        try:
            vol = float(vol)
        except (TypeError, ValueError):
            return True
        return not (vol > 0) or vol >= self.min_volume_m3

    def _departed(self, tid: int, st: "_TrackState", emit: "_Emitter", vanished: bool = False) -> None:
        """The track lost its confirmation or vanished: an exit if it was last seen
        in a door zone or at the edge. The tracker keeps reporting a departed
        person unconfirmed for a while before it deletes them; the exit is
        decided at the first of the two."""
        st.present = False
        place = self._entry_place(*st.present_xy)
        if place is None and not vanished:
            return  # occluded mid-room: still here
        for ch in st.dwell.lost(emit.stamp_ns):
            emit(ch.kind, tid, ch.x, ch.y, **_dwell_details(ch))
        if place is not None:
            st.exited, st.exit_place = True, place
            emit("exit", tid, st.present_xy[0], st.present_xy[1], door=place, last_seen_ns=st.present_ns)

    def _vanished(self, tid: int, st: "_TrackState", emit: "_Emitter") -> None:
        if st.present:
            self._departed(tid, st, emit, vanished=True)
        elif st.confirmed_once and not st.exited:
            for ch in st.dwell.lost(emit.stamp_ns):
                emit(ch.kind, tid, ch.x, ch.y, **_dwell_details(ch))

    def _entry_place(self, x: float, y: float) -> str | None:
        """Name of the door zone containing the point, ``"edge"`` near the border, else None."""
        door = hotspot_at(self.doors, x, y)
        if door is not None:
            return door.name
        if self.bounds_xy_m is not None:
            x0, y0, x1, y1 = self.bounds_xy_m
            if min(x - x0, y - y0, x1 - x, y1 - y) <= self.edge_margin_m:
                return "edge"
        return None

    # ------------------------------------------------------------------ visits

    def _visit_step(self, stamp_ns: int, dt_ns: int, emit: "_Emitter", hour: float | None) -> None:
        vs = self._visit
        present = [(tid, st) for tid, st in sorted(self._tracks.items()) if st.present]
        n = len(present)
        if n > self.residents:
            if vs.since_ns is None:
                vs.reset(stamp_ns)
            vs.last_over_ns = stamp_ns
            vs.max_people = max(vs.max_people, n)
            if self.hotspots and dt_ns > 0:
                idx = hotspot_index(self.hotspots, np.array([st.last_xy for _, st in present]))
                for k in idx[idx >= 0]:
                    vs.person_ns[k] += dt_ns
        elif vs.since_ns is not None and stamp_ns - vs.last_over_ns > self.visit_gap_ns:
            vs.since_ns = None
        if vs.since_ns is None or vs.emitted or n <= self.residents or stamp_ns - vs.since_ns < self.visit_min_ns:
            return
        spot = None
        if self.visit_gathering and self.hotspots:
            dwelling = [st.dwell.current.name for _, st in present if st.dwell.current is not None]
            counts = {h.name: dwelling.count(h.name) for h in self.hotspots}
            best = max(counts.values(), default=0)
            if best < 2:
                return  # extra people, but not (yet) together somewhere
            spot = next(h for h in self.hotspots if counts[h.name] == best)
        elif self.hotspots and vs.person_ns.max() > 0:
            spot = self.hotspots[int(np.argmax(vs.person_ns))]
        vs.emitted = True
        h = local_hour(stamp_ns, self.utc_offset_h) if hour is None else float(hour) % 24.0
        minutes = int(round(h * 60)) % 1440
        if spot is not None:
            cx, cy = (float(v) for v in spot.centroid_m)
        else:
            cx = float(np.mean([st.last_xy[0] for _, st in present]))
            cy = float(np.mean([st.last_xy[1] for _, st in present]))
        emit(
            "visit", -1, cx, cy,
            people=vs.max_people,
            residents=self.residents,
            since_ns=vs.since_ns,
            duration_s=round((stamp_ns - vs.since_ns) * 1e-9, 3),
            reason=time_of_day_label(h, self.meals),
            local_time=f"{minutes // 60:02d}:{minutes % 60:02d}",
            hotspot=spot.name if spot is not None else None,
            hotspot_label=spot.label if spot is not None else None,
            hotspot_kind=spot.kind if spot is not None else None,
        )


# --------------------------------------------------------------------------- helpers


def _median(values: list[float]) -> float:
    v = sorted(values)
    n = len(v)
    return float(v[n // 2]) if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def _ns(seconds: float) -> int:
    return int(round(float(seconds) * 1e9))


def _dwell_details(ch) -> dict[str, Any]:
    d = dict(hotspot=ch.hotspot.name, label=ch.hotspot.label, hotspot_kind=ch.hotspot.kind, start_ns=ch.start_ns)
    if ch.kind == "dwell_end":
        d.update(duration_s=round(ch.duration_s, 3), reason=ch.reason)
    return d


@dataclass
class _FallState:
    samples: deque = field(default_factory=deque)  # (stamp_ns, top_m, centre_m | None, posture | None)
    low_since_ns: int | None = None
    last_low_ns: int = 0
    floor_since_ns: int | None = None
    last_floor_ns: int = 0
    drop: dict[str, Any] | None = None
    fall_emitted: bool = False
    long_lie_emitted: bool = False


@dataclass
class _TrackState:
    first_xy: tuple[float, float]
    first_ns: int
    dwell: DwellDetector
    still: PositionWindow
    confirmed_once: bool = False
    present: bool = False
    exited: bool = False
    exit_place: str = ""
    confirmed_since_ns: int | None = None
    present_xy: tuple[float, float] = (0.0, 0.0)
    present_ns: int = 0
    last_xy: tuple[float, float] = (0.0, 0.0)
    last_ns: int = 0
    posture: str | None = None
    stable_posture: str | None = None
    stable_since_ns: int = 0
    fall: _FallState = field(default_factory=_FallState)
    posture_changed_ns: int = 0
    sitting_since_ns: int | None = None
    sitting_plausible: bool = True
    still_since_ns: int | None = None
    inactivity_emitted: bool = False
    upright_ns: int = 0  # time this track read standing or sitting, from its first frame


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


class _Emitter:
    """Builds records for one frame, in call order."""

    def __init__(self, out: list[EventRecord], stamp_ns: int, frame: int) -> None:
        self.out, self.stamp_ns, self.frame = out, stamp_ns, frame

    def __call__(self, kind: str, track: int, x: float, y: float, **details: Any) -> None:
        clean = {k: _plain(v) for k, v in details.items()}
        self.out.append(
            EventRecord(
                id=event_id(self.stamp_ns, kind, track),
                kind=kind,
                track=int(track),
                stamp_ns=self.stamp_ns,
                frame=self.frame,
                x=float(x),
                y=float(y),
                details=clean,
            )
        )


def _plain(v: Any) -> Any:
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    return str(v)
