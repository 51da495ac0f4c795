"""Falls and long lies (``fall``, ``long_lie``) of one person at a time.

``fall``
    A fast drop followed by lying on the floor. Whether a body is *low* is
    read from the body's top and centre
    (:attr:`~fusion_server.posture.PostureFeatures.body_top_m`,
    ``body_centre_m``): the top less the thin tent of hull the cameras' cones
    leave over a body lying on the floor (a metre high over a body of 0.3 m,
    it would keep the body from reading low; its volume would lift the
    centre). The drop is read from the top itself, which comes down with the
    body (the body's top, cut where the layers narrow, can jump). The top must
    drop by at least ``min_drop_m`` [0.5 m] at an average of at least
    ``min_speed_mps`` [0.8 m/s] within ``window_s`` [2 s], ending *low* (the
    body's top at most ``low_top_frac`` [0.55] and its centre at most
    ``low_centre_frac`` [0.25] of the person's standing height), and the
    person must then stay low for ``confirm_s`` [1 s] while reading
    ``lying`` (or being very low: the body's top <= ``flat_top_frac`` [0.45]
    of the standing height). Emitted on the confirming frame; ``details`` carry
    ``fall_stamp_ns``, the moment the top of the body passed halfway between
    its height before the drop and its height on the floor, and
    ``drop_start_ns``, when it began to come down. The drop must be one a
    body can make (:func:`drop_is_physical`): the top never comes down
    faster than it would after falling freely through its whole height at
    ``max_accel_mps2`` [1.5 g], give or take ``height_tol_m`` [0.15 m]; a top
    that jumps down between two frames is a blob changing under the track (a
    body cut by holes in the masks, a track taking over a fragment), not a
    fall. And only someone who was upright falls: the track must have read
    standing or sitting for ``upright_s`` [0.5 s] in all since its first
    frame (a person walks or sits before they fall; hull volume by a wall
    that reads lying from its first frame has no such history). The top is
    followed from the track's first frame, so that someone who falls while
    their track is still being established (at start-up, or found late in a
    crowd) falls from the height seen before, and is reported once the track
    is established. Sitting down, kneeling, bending and squatting never end
    low enough; lying down slowly is not fast enough (it may become a
    ``long_lie``).
``long_lie``
    Lying on the floor (low, as above, and reading ``lying`` or very low)
    continuously for ``long_lie_s`` [30 s] since the fall (or since lying
    down, when no fall was seen). Lying on a bed or sofa is not low, so it
    never counts.

A track that leaves its body on the floor still raises the fall: when a track
that got low after a drop (and was confirmed there) reads its top back at
``left_top_frac`` [0.8] of the standing height within ``left_within_s``
[0.8 s] of getting low, at least ``left_moved_m`` [0.4 m] from where it got
low, it has jumped to someone standing beside the body (a helper, a passer-by):
nobody gets up from the floor in under a second. The fall is raised where the
body got low, ``confirm_s`` after it got low as for a track that stays, by that
track, its ``details`` marked ``left_behind``. The rules for the drop (fast,
physical, from someone upright, not made while coasting) are the same.

One fall is one alarm: a fall within ``repeat_radius_m`` [1 m] and
``repeat_s`` [120 s] of one already raised (of where it was raised, or of
where the track that raised it has lain on the floor since: a track raises
where it got low, often off the body) is not raised again (the same body
on the floor taken up by another track: the first track lost it under a
neighbour, or a crowd's blobs regrouped over it; a carer is already on the
way); nor is one whose body reached the floor within ``same_fall_s`` [1 s] of
one already raised and within ``same_fall_radius_m`` [2 m] of it (one body
coming down under two tracks, each placed off it by its neighbours; two
people falling side by side in the same second are one call for help).

Only a track the tracker confirms this frame raises a fall (an unconfirmed
track coasts on its particles, or follows fragments the explanation did not
take for a person: its top is no body's): a fall found while the track is
unconfirmed is raised on its first confirmed frame on the floor. But a drop
the track made while coasting, unconfirmed from before the drop began until
its top passed halfway down, having been confirmed before, is no fall: the top
of a coasting track is the top of whatever voxels are in its box (the hull
over a body lying there for a while, shrinking as its neighbours move off), not
of a body coming down. A track found while someone falls (confirmed for the
first time after the drop) still raises it.

In company the drop may be read from the body's top instead: while another
confirmed track is within ``company_m`` [0.8 m] (their hulls join at that
distance), the top is as much the neighbour's as the body's: a body coming down
beside someone standing keeps the top of the one standing, then the top drops
in one frame to the body on the floor as the blobs part (no body comes down
like that). When the top itself shows no fall there, the drop is looked for in
the body's top, under the same rules (fast, from upright, physical).

Low and on-the-floor spells forgive gaps up to ``low_gap_s`` [0.5 s], but not a
return to the height the body came down from (the top the drop was read from, over the
last three frames, back within ``height_tol_m`` of where the drop began): a body on the
floor does not stand up for a few frames and lie down again, a top that
flickers between a body's height and half of it is a carve changing under the
track.

A track without a posture reading is taken to stand ``standing_height_m``
[1.70 m] tall.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from pydantic import Field

from common.settings import Settings, declared, group_of
from common.site import EventSettings
from fusion_server.events._common import NUMBER, median, ns, rekey
from fusion_server.events.records import Emitter
from fusion_server.events.track import TopSample, TrackSnapshot


class FallParams(Settings):
    """Thresholds of :class:`FallDetector`, each described in the module text
    (seconds, metres, m/s, m/s², fractions of the standing height)."""

    window_s: float = Field(2.0, gt=0.0, **NUMBER)
    min_drop_m: float = Field(0.5, gt=0.0, **NUMBER)
    min_speed_mps: float = Field(0.8, gt=0.0, **NUMBER)
    max_accel_mps2: float = Field(1.5 * 9.81, gt=0.0, **NUMBER)
    height_tol_m: float = Field(0.15, ge=0.0, **NUMBER)
    confirm_s: float = Field(1.0, ge=0.0, **NUMBER)
    upright_s: float = Field(0.5, ge=0.0, **NUMBER)
    low_top_frac: float = Field(0.55, gt=0.0, lt=1.0, **NUMBER)
    low_centre_frac: float = Field(0.25, gt=0.0, lt=1.0, **NUMBER)
    flat_top_frac: float = Field(0.45, gt=0.0, lt=1.0, **NUMBER)
    low_gap_s: float = Field(0.5, ge=0.0, **NUMBER)
    company_m: float = Field(0.8, ge=0.0, **NUMBER)
    repeat_radius_m: float = Field(1.0, ge=0.0, **NUMBER)
    repeat_s: float = Field(120.0, ge=0.0, **NUMBER)
    same_fall_s: float = Field(1.0, ge=0.0, **NUMBER)
    same_fall_radius_m: float = Field(2.0, ge=0.0, **NUMBER)
    left_within_s: float = Field(0.8, ge=0.0, **NUMBER)
    left_top_frac: float = Field(0.8, gt=0.0, le=1.0, **NUMBER)
    left_moved_m: float = Field(0.4, ge=0.0, **NUMBER)
    long_lie_s: float = declared(EventSettings, "long_lie_s")   # the site file's [events] declares it
    standing_height_m: float = Field(1.70, gt=0.0, **NUMBER)

    @property
    def tops_s(self) -> float:
        """How far back the detector reads a track's tops, seconds: a drop may start a
        window before the body gets low, and be looked for a window after."""
        return 2 * self.window_s + self.confirm_s + 0.5


class FallDetector:
    """``fall`` and ``long_lie`` per track, from the track's tops and posture."""

    def __init__(self, params: FallParams = FallParams()) -> None:
        group_of(params, FallParams)
        self.params = params
        self._window_ns = ns(params.window_s)
        self._confirm_ns = ns(params.confirm_s)
        self._upright_ns = ns(params.upright_s)
        self._low_gap_ns = ns(params.low_gap_s)
        self._long_lie_ns = ns(params.long_lie_s)
        self._repeat_ns = ns(params.repeat_s)
        self._same_fall_ns = ns(params.same_fall_s)
        self._tracks: dict[int, _FallTrack] = {}
        self._raised: list[_Raised] = []
        # falls whose track left the body on the floor, raised at their time: (due_ns, (x, y), drop, track)
        self._left: list[tuple[int, tuple[float, float], dict[str, Any], int]] = []
        self._left_within_ns = ns(params.left_within_s)
        self._tops_ns = ns(params.tops_s)

    def update(self, frame: TrackSnapshot, emit: Emitter) -> None:
        """Follow one track through one frame; emits ``fall`` and ``long_lie``."""
        if not math.isfinite(frame.top_m):
            return
        p = self.params
        fs = self._tracks.setdefault(frame.track, _FallTrack())
        stamp_ns = frame.stamp_ns
        fs.follow_confirmation(frame.confirmed, stamp_ns, stamp_ns - self._tops_ns)
        height_m = frame.standing_height_m if frame.standing_height_m is not None else p.standing_height_m
        tops = frame.tops
        # A median over the last three frames keeps one bad carve from toggling "low".
        recent = [tops[-k] for k in range(1, min(3, len(tops)) + 1)]
        top_med = median([s[4] for s in recent])
        cen = [s[2] for s in recent if s[2] is not None]
        centre_med = median(cen) if cen else None
        low = top_med <= p.low_top_frac * height_m and (
            centre_med is None or centre_med <= p.low_centre_frac * height_m
        )
        on_floor = low and (frame.posture == "lying" or top_med <= p.flat_top_frac * height_m)
        self._raise_left(stamp_ns, emit)
        if on_floor and fs.fall_emitted:
            self._body_lies(frame.track, frame.x, frame.y)
        if not low and self._left_behind(fs, frame, top_med, height_m):
            fs.fall_emitted = True
            self._left.append((fs.low_since_ns + self._confirm_ns, fs.low_xy, fs.drop, frame.track))
        if low:
            if fs.low_since_ns is None:
                fs.low_xy = (frame.x, frame.y)
                fs.low_confirmed = False
                fs.low_since_ns = stamp_ns
                fs.drop = None
                fs.fall_emitted = False
                fs.long_lie_emitted = False
                fs.floor_since_ns = None
            fs.last_low_ns = stamp_ns
            fs.low_confirmed |= frame.confirmed
        elif fs.low_since_ns is not None and (
            stamp_ns - fs.last_low_ns > self._low_gap_ns
            or (fs.drop is not None
                and median([s[fs.drop_series] for s in recent]) >= fs.drop["top_before_m"] - p.height_tol_m)
        ):
            fs.low_since_ns = None   # up again, or back at the height it came down from: no gap forgiven
            fs.floor_since_ns = None
        if fs.low_since_ns is None:
            return
        if fs.drop is None and stamp_ns - fs.low_since_ns <= self._window_ns:
            fs.drop, fs.drop_series = self._find_drop(tops, fs.low_since_ns, height_m), 1
            if fs.drop is None and frame.company_m <= p.company_m:
                fs.drop, fs.drop_series = self._find_drop(tops, fs.low_since_ns, height_m, series=4), 4
        if on_floor:
            if fs.floor_since_ns is None:
                fs.floor_since_ns = stamp_ns
            fs.last_floor_ns = stamp_ns
        elif fs.floor_since_ns is not None and stamp_ns - fs.last_floor_ns > self._low_gap_ns:
            fs.floor_since_ns = None
        tid, x, y = frame.track, frame.x, frame.y
        if (
            not fs.fall_emitted
            and fs.drop is not None
            and on_floor
            and stamp_ns - fs.low_since_ns >= self._confirm_ns
            and frame.upright_ns >= self._upright_ns
            and frame.confirmed
        ):
            fs.fall_emitted = True   # decided for this spell on the floor, raised or not
            if not fs.coasting_through(fs.drop["drop_start_ns"], fs.drop["fall_stamp_ns"]) and not self._raised_before(
                    stamp_ns, x, y, fs.drop["fall_stamp_ns"]):
                self._raised.append(_Raised(stamp_ns, tid, fs.drop["fall_stamp_ns"], [(x, y)]))
                emit("fall", tid, x, y, **fs.drop, confirm_s=round((stamp_ns - fs.low_since_ns) * 1e-9, 3))
        if fs.floor_since_ns is not None and not fs.long_lie_emitted:
            since = fs.floor_since_ns
            if fs.drop is not None:
                since = min(since, fs.drop["fall_stamp_ns"])
            if stamp_ns - since >= self._long_lie_ns:
                fs.long_lie_emitted = True
                emit(
                    "long_lie", tid, x, y,
                    lying_since_ns=since,
                    duration_s=round((stamp_ns - since) * 1e-9, 3),
                    after_fall=fs.drop is not None,
                    fall_stamp_ns=fs.drop["fall_stamp_ns"] if fs.drop is not None else None,
                )

    def _left_behind(self, fs: "_FallTrack", frame: TrackSnapshot, top_med: float, height_m: float) -> bool:
        """Whether the track, back up after a fall it has not raised, left its body on the floor:
        its top came back to ``left_top_frac`` of the standing height within ``left_within_s`` of
        getting low, ``left_moved_m`` from where it got low (see the module text)."""
        p = self.params
        return (
            fs.low_since_ns is not None and fs.drop is not None and not fs.fall_emitted
            and frame.confirmed and fs.low_confirmed and frame.upright_ns >= self._upright_ns
            and frame.stamp_ns - fs.low_since_ns <= self._left_within_ns
            and top_med >= p.left_top_frac * height_m
            and math.hypot(frame.x - fs.low_xy[0], frame.y - fs.low_xy[1]) >= p.left_moved_m
            and not fs.coasting_through(fs.drop["drop_start_ns"], fs.drop["fall_stamp_ns"])
        )

    def _raise_left(self, stamp_ns: int, emit: Emitter) -> None:
        """Raise the falls left behind that are due (``confirm_s`` after their body got low)."""
        due = [e for e in self._left if e[0] <= stamp_ns]
        if not due:
            return
        self._left = [e for e in self._left if e[0] > stamp_ns]
        for due_ns, (x, y), drop, tid in due:
            if not self._raised_before(stamp_ns, x, y, drop["fall_stamp_ns"]):
                self._raised.append(_Raised(stamp_ns, tid, drop["fall_stamp_ns"], [(x, y)]))
                low_since_ns = due_ns - self._confirm_ns
                emit("fall", tid, x, y, **drop, confirm_s=round((stamp_ns - low_since_ns) * 1e-9, 3), left_behind=True)

    def _raised_before(self, stamp_ns: int, x: float, y: float, fall_stamp_ns: int) -> bool:
        """Whether this fall at (x, y), its body on the floor at ``fall_stamp_ns``, was raised
        already: a fall raised in the last ``repeat_s`` within ``repeat_radius_m`` of where it was
        raised or of where its track has lain on the floor since, or one whose body came down
        within ``same_fall_s`` of it and within ``same_fall_radius_m``."""
        p = self.params
        self._raised = [r for r in self._raised if stamp_ns - r.stamp_ns <= self._repeat_ns]
        for r in self._raised:
            d = min(math.hypot(rx - x, ry - y) for rx, ry in r.places)
            if d <= p.repeat_radius_m or (
                d <= p.same_fall_radius_m and abs(r.fall_stamp_ns - fall_stamp_ns) <= self._same_fall_ns
            ):
                return True
        return False

    def _body_lies(self, track: int, x: float, y: float) -> None:
        """The track that raised a fall lies on the floor at (x, y): where its body is, for
        the repeats (a track raises where it got low, often off the body it follows; the
        body's own place is where the next track to find it will be)."""
        for r in self._raised:
            if r.track == track and min(math.hypot(rx - x, ry - y) for rx, ry in r.places) >= _PLACE_STEP_M:
                r.places.append((x, y))
                del r.places[1:-_MAX_PLACES]

    def on_floor(self, track: int) -> bool:
        """Whether the track is lying on the floor now (a long lie's business, not inactivity's)."""
        fs = self._tracks.get(track)
        return fs is not None and fs.floor_since_ns is not None

    def low(self, track: int, top_m: float | None = None, height_m: float | None = None) -> bool:
        """Whether the track is low: coming down or on the floor as of its last frame, or, given
        this frame's ``top_m``, that top at most ``low_top_frac`` of its standing height
        (``height_m``; the default standing height when unknown)."""
        fs = self._tracks.get(track)
        if fs is not None and (fs.low_since_ns is not None or fs.floor_since_ns is not None):
            return True
        if top_m is None:
            return False
        return top_m <= self.params.low_top_frac * (height_m or self.params.standing_height_m)

    def rename(self, renames: Mapping[int, int]) -> None:
        """Tracks change ids ({old: new}, at once); their state goes with them."""
        self._tracks = rekey(self._tracks, renames)
        for r in self._raised:
            r.track = renames.get(r.track, r.track)

    def state_of(self, track: int) -> dict[str, Any] | None:
        """What a restarted server needs to go on with the track's fall and long lie (None
        when it is not low): since when it is low and on the floor, its drop, what was raised."""
        fs = self._tracks.get(track)
        if fs is None or fs.low_since_ns is None:
            return None
        return {"low_since_ns": fs.low_since_ns, "floor_since_ns": fs.floor_since_ns, "drop": fs.drop,
                "drop_series": fs.drop_series, "fall_emitted": fs.fall_emitted, "long_lie_emitted": fs.long_lie_emitted}

    def restore(self, track: int, state: Mapping[str, Any], stamp_ns: int) -> None:
        """Go on with a track as :meth:`state_of` described it before a restart, at ``stamp_ns``
        (the track is low now, or the state lapses after ``low_gap_s`` as usual)."""
        fs = self._tracks.setdefault(track, _FallTrack())
        fs.low_since_ns = int(state["low_since_ns"])
        fs.last_low_ns = int(stamp_ns)
        floor = state.get("floor_since_ns")
        fs.floor_since_ns = None if floor is None else int(floor)
        fs.last_floor_ns = int(stamp_ns)
        fs.drop = dict(state["drop"]) if state.get("drop") else None
        fs.drop_series = 4 if state.get("drop_series") == 4 else 1
        fs.fall_emitted = bool(state.get("fall_emitted", False))
        fs.long_lie_emitted = bool(state.get("long_lie_emitted", False))

    def forget(self, track: int) -> None:
        """The track is gone."""
        self._tracks.pop(track, None)

    def _find_drop(self, tops: Sequence[TopSample], low_since_ns: int, height_m: float,
                   series: int = 1) -> dict[str, Any] | None:
        """The fall's drop in the ``window_s`` before ``low_since_ns``, read from the tops
        (``series`` 1) or the body's tops (4), None when there is none."""
        p = self.params
        start = low_since_ns - self._window_ns
        samples = [s for s in tops if s[0] >= start]
        if len(samples) < 2:
            return None
        t0 = samples[0][0]
        t = np.array([(s[0] - t0) * 1e-9 for s in samples])
        z = np.array([s[series] for s in samples])
        pair = detect_fast_drop(t, z, window_s=p.window_s, min_drop_m=p.min_drop_m, min_speed_mps=p.min_speed_mps)
        if pair is None:
            return None
        i, j = pair
        if z[i] < p.flat_top_frac * height_m:
            return None  # started on the floor already: not a fall from standing or sitting
        if not drop_is_physical(t, z, i, j, max_accel_mps2=p.max_accel_mps2, tol_m=p.height_tol_m):
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


_PLACE_STEP_M = 0.2   # a raised fall's body noted again once its track lies this far from every place noted
_MAX_PLACES = 16      # the place it was raised and the latest of the places its body lay since


@dataclass
class _Raised:
    """A fall raised: when, by which track, when its body reached the floor, and the places of
    its body (where it was raised, then where its track lay on the floor)."""

    stamp_ns: int
    track: int
    fall_stamp_ns: int
    places: list[tuple[float, float]]


@dataclass
class _FallTrack:
    low_xy: tuple[float, float] = (0.0, 0.0)   # where the track got low
    low_confirmed: bool = False                 # the tracker confirmed it at some frame since
    low_since_ns: int | None = None
    last_low_ns: int = 0
    floor_since_ns: int | None = None
    last_floor_ns: int = 0
    drop: dict[str, Any] | None = None
    drop_series: int = 1                        # where the drop was read: the tops (1) or the body's tops (4)
    fall_emitted: bool = False
    long_lie_emitted: bool = False
    ever_confirmed: bool = False
    coast_since_ns: int | None = None   # start of the spell the track has been unconfirmed since, once confirmed
    coasts: list[tuple[int, int]] = field(default_factory=list)   # earlier such spells (start_ns, end_ns)

    def follow_confirmation(self, confirmed: bool, stamp_ns: int, keep_since_ns: int) -> None:
        """Note whether the tracker confirms the track this frame; spells ended before
        ``keep_since_ns`` are forgotten."""
        if confirmed:
            if self.coast_since_ns is not None:
                self.coasts.append((self.coast_since_ns, stamp_ns))
                self.coast_since_ns = None
            self.ever_confirmed = True
        elif self.ever_confirmed and self.coast_since_ns is None:
            self.coast_since_ns = stamp_ns
        self.coasts = [c for c in self.coasts if c[1] >= keep_since_ns]

    def coasting_through(self, start_ns: int, end_ns: int) -> bool:
        """Whether the track, confirmed before, was unconfirmed from ``start_ns`` to ``end_ns``."""
        spells = self.coasts + ([(self.coast_since_ns, end_ns)] if self.coast_since_ns is not None else [])
        return any(s <= start_ns and e >= end_ns for s, e in spells)
