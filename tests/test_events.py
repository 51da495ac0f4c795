"""Events from hand-built track sequences whose height profiles come from the
synthetic articulated bodies of tests/test_posture.py."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import pytest

from fusion_server.events import (
    EVENT_KINDS,
    EntryParams,
    EventReasoner,
    FallParams,
    InactivityParams,
    PresenceParams,
    SitStandParams,
    VisitParams,
    crossing_time,
    detect_fast_drop,
    drop_is_physical,
    height_change_m,
    local_hour,
    time_of_day_label,
)
from fusion_server.hotspots import Hotspot
from fusion_server.posture import PostureBank, PostureEstimator
from test_posture import NZ, VOXEL_M, blend, body_profile

FPS = 15
NS = 1_000_000_000
FRAME_NS = NS // FPS
# 2024-05-01 00:00:00 UTC: stamps are Unix-epoch nanoseconds
DAY0_NS = 1_714_521_600 * NS


@dataclass
class Est:
    """The attributes of the tracker's TrackEstimate that reasoning reads."""

    id: int
    x: float
    y: float
    height_profile: np.ndarray
    confirmed: bool = True
    z_top_m: float = 0.0
    volume_m3: float = 0.0
    reliability: float = 1.0
    age_frames: int = 1
    vx: float = 0.0
    vy: float = 0.0
    still: bool = False

    def __post_init__(self):
        nz = np.flatnonzero(self.height_profile)
        self.z_top_m = float((nz[-1] + 1) * VOXEL_M) if len(nz) else 0.0


@lru_cache(maxsize=None)
def _profile(pose: str, **kw) -> np.ndarray:
    return body_profile(pose, **kw)


STAND = _profile("standing")
SIT = _profile("sitting")
LIE = _profile("standing", tilt_deg=90)


@dataclass
class Person:
    """One person's timeline: per frame (x, y, profile, confirmed) or None when absent."""

    tid: int
    frames: list = field(default_factory=list)

    def absent(self, seconds: float):
        self.frames += [None] * int(round(seconds * FPS))
        return self

    def hold(self, seconds: float, profile=STAND, xy=None, confirmed=True):
        xy = xy or self._xy()
        self.frames += [(xy[0], xy[1], profile, confirmed)] * int(round(seconds * FPS))
        return self

    def move(self, seconds: float, profiles, xy_to=None, path=lambda f: f):
        """``profiles(f)`` gives the profile a fraction f in (0, 1] through the movement; the floor
        position is ``path(f)`` of the way to ``xy_to``."""
        n = int(round(seconds * FPS))
        x0, y0 = self._xy()
        x1, y1 = xy_to or (x0, y0)
        for i in range(n):
            f = (i + 1) / n
            g = path(f)
            self.frames.append((x0 + g * (x1 - x0), y0 + g * (y1 - y0), profiles(f), True))
        return self

    def walk(self, xy_to, speed_mps: float = 1.0, profile=STAND):
        x0, y0 = self._xy()
        d = math.hypot(xy_to[0] - x0, xy_to[1] - y0)
        return self.move(max(d / speed_mps, 1.0 / FPS), lambda f: profile, xy_to)

    def _xy(self):
        for fr in reversed(self.frames):
            if fr is not None:
                return fr[0], fr[1]
        raise ValueError("place the person first with hold(..., xy=...)")


def run(people, reasoner: EventReasoner, *, t0_ns: int = 0, bank: PostureBank | None = None, monitored=None):
    """``monitored``: (x0, y0, x1, y1) of the monitored floor; tracks beyond it are passed as outside."""
    bank = bank or PostureBank(voxel_m=VOXEL_M)
    n = max(len(p.frames) for p in people)
    events = []
    for k in range(n):
        stamp = t0_ns + k * FRAME_NS
        tracks = []
        for p in people:
            fr = p.frames[k] if k < len(p.frames) else None
            if fr is not None:
                tracks.append(Est(p.tid, fr[0], fr[1], fr[2], confirmed=fr[3]))
        readings = bank.update(stamp, tracks)
        outside = [] if monitored is None else [
            t.id for t in tracks if not (monitored[0] <= t.x <= monitored[2] and monitored[1] <= t.y <= monitored[3])]
        events += reasoner.step(stamp, k, tracks, readings, outside=outside)
    return events


def kinds(events, kind=None):
    return [e.kind for e in events] if kind is None else [e for e in events if e.kind == kind]


def t_s(stamp_ns: int, t0_ns: int = 0) -> float:
    return (stamp_ns - t0_ns) / NS


# --------------------------------------------------------------------------- pure helpers


def test_time_of_day_labels_and_local_hour():
    assert local_hour(DAY0_NS + 17 * 3600 * NS, 2.0) == pytest.approx(19.0)
    assert local_hour(DAY0_NS + 23 * 3600 * NS, 2.0) == pytest.approx(1.0)
    assert local_hour(DAY0_NS + 1 * 3600 * NS, -3.5) == pytest.approx(21.5)
    assert time_of_day_label(19.0) == "for dinner"
    assert time_of_day_label(8.0) == "for breakfast"
    assert time_of_day_label(12.5) == "for lunch"
    assert time_of_day_label(16.0) == "for tea"
    assert time_of_day_label(10.5) == "in the morning"
    assert time_of_day_label(14.5) == "in the afternoon"
    assert time_of_day_label(21.75) == "in the evening"
    assert time_of_day_label(3.0) == "at night"


def test_detect_fast_drop_hand_worked():
    t = np.arange(10) * 0.1
    z = np.array([1.7, 1.7, 1.7, 1.4, 1.0, 0.6, 0.4, 0.4, 0.4, 0.4])
    i, j = detect_fast_drop(t, z, window_s=2.0, min_drop_m=0.5, min_speed_mps=0.8)
    assert z[i] - z[j] == pytest.approx(1.3)
    assert (i, j) == (2, 6)  # latest start of the largest drop, earliest end
    # the same drop over 2.4 s: no 2 s stretch of it reaches 0.8 m/s
    assert detect_fast_drop(t * 6, z, window_s=2.0, min_drop_m=0.5, min_speed_mps=0.8) is None
    # a 0.3 m drop is too small
    assert detect_fast_drop(t, np.clip(z, 1.4, None), window_s=2.0, min_drop_m=0.5, min_speed_mps=0.8) is None
    # halfway (1.05 m) is crossed between samples 3 (1.4) and 4 (1.0): 7/8 of the way
    assert crossing_time(t, z, i, j, 1.05) == pytest.approx(0.3 + 0.0875)


def test_event_round_trip_through_a_dict():
    from common.messages import EVENT_KINDS as WIRE_KINDS
    from common.messages import Event, event_id

    rec = Event(id=event_id(5, "fall", 3), kind="fall", track=3, stamp_ns=5, frame=1, x=1.5, y=2.0,
                details={"fall_stamp_ns": 4, "from_posture": "standing"})
    assert rec.id == "5-fall-3"
    assert Event.from_dict(rec.to_dict()) == rec
    assert set(EVENT_KINDS) <= set(WIRE_KINDS)
    with pytest.raises(ValueError, match="'track'"):
        Event.from_dict({**rec.to_dict(), "track": "3"})
    with pytest.raises(ValueError, match="'x'"):
        Event.from_dict({**rec.to_dict(), "x": float("nan")})
    with pytest.raises(ValueError, match="'kind'"):
        Event.from_dict({k: v for k, v in rec.to_dict().items() if k != "kind"})
    with pytest.raises(ValueError, match="'details"):
        Event.from_dict({**rec.to_dict(), "details": {"path": [1, 2]}})


# --------------------------------------------------------------------------- falls


def _toppling(f: float) -> float:
    """How far along the floor a toppling body's centre has gone, a fraction f through the fall
    (the sine of the tilt of :func:`_fall_profiles`)."""
    return math.sin(0.5 * math.pi * f * f)


def _fall_profiles(start="standing", lift=0.0):
    def prof(f):
        # accelerating tilt about the feet, the body straightening out on the way down
        angles = blend(start, "standing", min(1.0, 2 * f)) if start != "standing" else start
        return body_profile(angles, tilt_deg=90 * f * f, lift_m=lift)

    return prof


def test_fall_from_standing_is_one_fall_with_the_right_time_then_a_long_lie():
    fall_start_s, fall_s = 3.0, 0.8
    # toppling, the body's floor centre moves from the feet to about half its height away
    p = Person(1).hold(fall_start_s, STAND, xy=(3.0, 3.0))
    p.move(fall_s, _fall_profiles(), (3.8, 3.0), _toppling).hold(65.0, LIE)
    reasoner = EventReasoner(falls=FallParams(long_lie_s=60.0), sit_stand=SitStandParams(stand_up_from=("sitting",)))
    events = run([p], reasoner)
    falls = kinds(events, "fall")
    assert len(falls) == 1
    fall = falls[0]
    fall_at = t_s(fall.details["fall_stamp_ns"])
    landed = fall_start_s + fall_s
    # the moment of the fall lies inside the movement ...
    assert fall_start_s < fall_at < landed
    # ... and the event is out within 1.5 s of landing: the 1 s confirmation plus at most 0.5 s
    assert 0 < t_s(fall.stamp_ns) - landed <= 1.5
    assert fall.details["from_posture"] == "standing"
    assert fall.details["drop_m"] > 1.0 and fall.details["drop_speed_mps"] >= 0.8
    assert (fall.x, fall.y) == (3.8, 3.0) and fall.track == 1
    lies = kinds(events, "long_lie")
    assert len(lies) == 1 and lies[0].details["after_fall"] is True
    assert t_s(lies[0].stamp_ns) - fall_at == pytest.approx(60.0, abs=2 / FPS)
    assert set(kinds(events)) == {"fall", "long_lie"}


def test_getting_up_after_a_fall_is_a_stand_up_and_default_long_lie_is_30_s():
    p = Person(8).hold(2.0, STAND, xy=(3.0, 3.0)).move(0.8, _fall_profiles(), (3.0, 3.7), _toppling).hold(35.0, LIE)
    p.move(2.0, lambda f: body_profile("kneeling", tilt_deg=90 * (1 - f)))  # up onto the knees
    p.move(2.0, lambda f: body_profile(blend("kneeling", "standing", f))).hold(3.0, STAND)
    events = run([p], EventReasoner())
    assert kinds(events) == ["fall", "long_lie", "stand_up"]
    fall, lie, up = events
    assert t_s(lie.stamp_ns) - t_s(fall.details["fall_stamp_ns"]) == pytest.approx(30.0, abs=2 / FPS)
    assert up.details["from_posture"] in ("lying", "sitting")  # rising through the knees may read sitting
    assert 2.8 + 35.0 + 2.0 < t_s(up.stamp_ns) < 2.8 + 35.0 + 4.0 + 1.5


def test_a_track_jumping_from_a_body_on_the_floor_to_someone_standing_is_no_stand_up():
    """A person has lain on the floor for 10 s; the track then jumps (one frame) to someone standing
    0.6 m away: the top rises 1.35 m at once, faster than anyone gets up (over 0.8 m within 0.4 s).
    No stand_up, though the track now reads standing. Getting up where it lay, onto the knees in 2 s
    and up from them in 2 s more, is one."""
    def lying_then(rise):
        p = Person(3).hold(10.0, LIE, xy=(3.0, 3.0))
        rise(p)
        p.hold(4.0, STAND)
        return kinds(run([p], EventReasoner()))

    assert lying_then(lambda p: p.hold(1 / FPS, STAND, xy=(3.6, 3.0))) == []
    def get_up(p):
        p.move(2.0, lambda f: body_profile("kneeling", tilt_deg=90 * (1 - f)))
        p.move(2.0, lambda f: body_profile(blend("kneeling", "standing", f)))

    assert lying_then(get_up) == ["stand_up"]


def test_a_drop_faster_than_a_falling_body_is_not_physical():
    g = 9.81
    t = np.arange(10) / 15.0
    # a top of 1.7 m falling freely at 1.5 g reaches sqrt(2 * 1.5 g * 1.7) = 7.07 m/s: 0.47 m a frame
    v = math.sqrt(2 * 1.5 * g * 1.7)
    assert v / 15 == pytest.approx(0.471, abs=1e-3)
    toppling = np.array([1.7, 1.7, 1.65, 1.5, 1.25, 0.9, 0.5, 0.3, 0.3, 0.3])  # at most 0.4 m a frame
    assert drop_is_physical(t, toppling, 1, 7, max_accel_mps2=1.5 * g, tol_m=0.15)
    # the top jumps from 1.85 to 0.2 m between two frames: a track taking over a fragment, 1.65 m
    # where at most 0.47 + 0.15 m can go
    jump = np.array([1.85] * 5 + [0.2] * 5)
    i, j = detect_fast_drop(t, jump, window_s=2.0, min_drop_m=0.5, min_speed_mps=0.8)
    assert not drop_is_physical(t, jump, i, j, max_accel_mps2=1.5 * g, tol_m=0.15)
    assert not drop_is_physical(t, jump, 0, 9, max_accel_mps2=1.5 * g, tol_m=0.15)  # however long the pair
    # 0.6 m in one frame passes only with more tolerance than the 0.15 m of measured height
    step = np.array([1.7, 1.7, 1.1, 1.1])
    assert not drop_is_physical(t[:4], step, 0, 3, max_accel_mps2=1.5 * g, tol_m=0.1)
    assert drop_is_physical(t[:4], step, 0, 3, max_accel_mps2=1.5 * g, tol_m=0.15)


def test_a_top_jumping_to_the_floor_raises_no_fall():
    """A standing person whose track takes over a fragment of their legs for a few frames (holes in
    the masks cut the body): the top falls 1.2 m between two frames, then the legs stay low."""
    p = Person(3).hold(3.0, STAND, xy=(2.0, 2.0)).hold(5.0, LIE, xy=(2.7, 2.0))
    assert kinds(run([p], EventReasoner()), "fall") == []
    # without the bound on speed the same frames read as a fall
    assert len(kinds(run([p], EventReasoner(falls=FallParams(max_accel_mps2=1e6))), "fall")) == 1


def test_only_someone_who_was_upright_falls():
    """Hull volume that reads bending or lying from its first frame and drops to the floor has no
    person's history: no fall; the same frames after standing are a fall."""

    def frames(first: str, top: float):
        out = [(first, top)] * 30
        out += [("lying", top - (top - 0.3) * (k + 1) / 6) for k in range(6)]
        return out + [("lying", 0.3)] * 25

    def column(top_m: float) -> np.ndarray:  # a profile whose top is top_m (the reasoner reads the top)
        prof = np.zeros(NZ, np.int32)
        prof[: int(round(top_m / VOXEL_M))] = 10
        return prof

    def falls(seq, **kw):
        r, out = EventReasoner(**kw), []
        for k, (post, top) in enumerate(seq):  # the body moves 0.7 m along the floor as it comes down
            x = 1.0 + 0.7 * min(1.0, max(0, k - 29) / 6)
            out += r.step(k * FRAME_NS, k, [Est(1, x, 1.0, column(top))], {1: post})
        return kinds(out, "fall")

    assert falls(frames("bending", 1.2)) == []
    assert len(falls(frames("bending", 1.2), falls=FallParams(upright_s=0.0))) == 1  # the drop itself is a fall's
    assert len(falls(frames("standing", 1.7))) == 1


def test_a_fall_before_the_track_is_established_is_a_fall():
    """Someone who falls within their track's first second (at start-up, or found late): the drop
    happened before the track was established, and counts once it is."""
    p = Person(1).hold(0.6, STAND, xy=(2.0, 2.0)).move(0.8, _fall_profiles(), (2.7, 2.0), _toppling)
    p.hold(4.0, LIE)
    falls = kinds(run([p], EventReasoner(presence=PresenceParams(establish_s=1.5))), "fall")
    assert len(falls) == 1
    assert 0.6 < t_s(falls[0].details["fall_stamp_ns"]) < 1.4


def test_fall_from_a_chair_is_a_fall():
    p = Person(4).hold(3.0, SIT, xy=(2.0, 2.0)).move(0.7, _fall_profiles("sitting"), (2.5, 2.3), _toppling)
    p.hold(5.0, LIE)
    events = run([p], EventReasoner())
    falls = kinds(events, "fall")
    assert len(falls) == 1 and falls[0].details["from_posture"] == "sitting"
    assert 3.0 < t_s(falls[0].details["fall_stamp_ns"]) < 3.7


def test_sit_down_and_stand_up_without_fall():
    p = Person(2).hold(3.0, STAND, xy=(1.0, 1.0))
    p.move(1.0, lambda f: body_profile(blend("standing", "sitting", f))).hold(6.0, SIT)
    p.move(1.0, lambda f: body_profile(blend("sitting", "standing", f))).hold(3.0, STAND)
    events = run([p], EventReasoner())
    assert kinds(events) == ["sit_down", "stand_up"]
    sit, stand = events
    assert 4.0 <= t_s(sit.stamp_ns) <= 4.0 + 1.5  # movement ends at 4 s
    # movement ends at 11 s; the body is mostly up, and reads standing, up to half a second before
    assert 11.0 - 0.5 <= t_s(stand.stamp_ns) <= 11.0 + 1.5
    assert sit.details["from_posture"] == "standing" and sit.details["to_posture"] == "sitting"
    assert stand.details["from_posture"] == "sitting"


def test_a_posture_flip_at_constant_height_is_no_sit_or_stand():
    # Seated, the carve turns for 4 s into the shape of someone standing whose
    # top is the seated top (legs carved whole under the seat): the reading
    # flips to standing and back, the body's top never moves.
    top_sit = (np.nonzero(SIT)[0].max() + 1) * VOXEL_M
    upright_at_seat_top = body_profile("standing", height_m=top_sit)
    p = Person(2).hold(3.0, STAND, xy=(1.0, 1.0))
    p.move(1.0, lambda f: body_profile(blend("standing", "sitting", f))).hold(4.0, SIT)
    p.hold(4.0, upright_at_seat_top).hold(3.0, SIT)
    events = run([p], EventReasoner())
    assert kinds(events) == ["sit_down"]
    assert events[0].details["height_change_m"] == pytest.approx(-0.45, abs=0.051)
    # without the height test the flips are a stand_up and a second sit_down
    loose = run([p], EventReasoner(sit_stand=SitStandParams(min_change_frac=0.0, max_change_frac=5.0)))
    assert kinds(loose) == ["sit_down", "stand_up", "sit_down"]


@pytest.mark.xfail(strict=True, reason="known defect: the first posture, read against an adult's height before the "
                   "child's own is learnt, is kept, and the sit_down reads as no change of posture")
def test_a_child_read_seated_at_first_sits_down_and_stands_up():
    """A child of 1.25 m stands still for 5 s: read at first against an adult's height, their top is a
    seated adult's, then standing once their height is learnt, at the same height (no stand_up).
    They sit down on a chair and stand up again: both should be told. The detector keeps the first
    (seated) posture, since the standing one came at a constant height, and the sit_down reads as
    no change (tuning world 190). Adopting any posture read 2 s at a constant height found it
    there but raised false stand_ups where the new posture was the misread one (a 1.0 m child read
    seated, worlds 199 and 210)."""
    h = 1.25
    p = Person(1).hold(5.0, body_profile("standing", height_m=h), xy=(2.0, 2.0))
    p.move(1.0, lambda f: body_profile(blend("standing", "sitting", f), height_m=h)).hold(6.0, body_profile("sitting", height_m=h))
    p.move(1.0, lambda f: body_profile(blend("sitting", "standing", f), height_m=h)).hold(4.0, body_profile("standing", height_m=h))
    events = run([p], EventReasoner())
    assert kinds(events) == ["sit_down", "stand_up"]
    assert 6.0 <= t_s(events[0].stamp_ns) <= 6.0 + 1.5 and 13.0 <= t_s(events[1].stamp_ns) <= 13.0 + 1.5
    # as said: the standing child reads seated for its first two seconds, then standing
    estimator = PostureEstimator(voxel_m=VOXEL_M)
    read = [estimator.update(k * FRAME_NS, body_profile("standing", height_m=h)).posture for k in range(75)]
    assert read[0] == read[29] == "sitting" and read[-1] == "standing"


def test_height_change_reads_the_posture_held_before_the_switch():
    s = 1_000_000_000
    # top 1.7 m until 3 s, coming down to 1.2 m by 4 s, the filter switching at 4.5 s
    samples = [(k * s // 10, 1.7 if k <= 30 else max(1.2, 1.7 - 0.05 * (k - 30))) for k in range(0, 61)]
    # 0.3-4.2 s before the switch: 28 samples at 1.7 m and 12 coming down; since it, all at 1.2 m
    assert height_change_m(samples, 45 * s // 10, 6 * s, before_s=(4.2, 0.3)) == pytest.approx(-0.5)
    assert height_change_m(samples, 45 * s // 10, 6 * s, before_s=(4.2, 0.3), before_quantile=0.75) == pytest.approx(-0.5)
    # 0.3-1.5 s before: 1.7, 1.65 ... 1.25, 1.2 x3 (13 samples): median 1.4, upper quartile 1.55
    assert height_change_m(samples, 45 * s // 10, 6 * s, before_s=(1.5, 0.3)) == pytest.approx(-0.2)
    assert height_change_m(samples, 45 * s // 10, 6 * s, before_s=(1.5, 0.3), before_quantile=0.75) == pytest.approx(-0.35)
    assert height_change_m(samples, 1 * s // 10, 6 * s, before_s=(4.0, 0.3)) is None  # nothing before
    assert height_change_m(samples, 7 * s, 8 * s, before_s=(4.0, 0.3)) is None  # nothing since


def _hidden_below(profile: np.ndarray, height_m: float) -> np.ndarray:
    """The profile with the layers below ``height_m`` lost (furniture hides them from some cameras)."""
    out = profile.copy()
    out[: int(round(height_m / VOXEL_M))] = 0
    return out


def test_body_floating_at_seat_height_sits_only_on_seats():
    # kneeling behind the sofa's back and sitting on the sofa with the shins hidden carve alike
    kneel_hidden = _hidden_below(_profile("kneeling"), 0.5)
    sit_hidden = _hidden_below(SIT, 0.45)
    behind = Person(1).hold(3.0, STAND, xy=(5.5, 3.0)).hold(6.0, kneel_hidden).hold(3.0, STAND)
    on_sofa = Person(2).hold(3.0, STAND, xy=(5.0, 0.5)).hold(6.0, sit_hidden).hold(3.0, STAND)
    events = run([behind, on_sofa], EventReasoner(hotspots=[SOFA, TABLE]))
    assert [(e.kind, e.track) for e in events if e.kind in ("sit_down", "stand_up")] == [("sit_down", 2), ("stand_up", 2)]
    # a site without seat hot spots believes every sitting reading
    events = run([behind], EventReasoner())
    assert kinds(events) == ["sit_down", "stand_up"]


@pytest.mark.parametrize("pose", ["kneeling", "bending", "squatting"])
def test_fast_kneel_bend_or_squat_is_never_a_fall(pose):
    p = Person(3).hold(2.0, STAND, xy=(2.0, 2.0))
    p.move(0.5, lambda f: body_profile(blend("standing", pose, f))).hold(8.0, _profile(pose))
    p.move(0.8, lambda f: body_profile(blend(pose, "standing", f))).hold(2.0, STAND)
    events = run([p], EventReasoner(falls=FallParams(long_lie_s=5.0)))
    assert not kinds(events, "fall") and not kinds(events, "long_lie")
    assert set(kinds(events)) <= {"sit_down", "stand_up"}


def test_slow_lying_down_is_no_fall_but_becomes_a_long_lie():
    p = Person(5).hold(2.0, STAND, xy=(4.0, 1.0))
    p.move(2.0, lambda f: body_profile(blend("standing", "kneeling", f)))
    # from kneeling, tipping over to lying in 5 s: the top falls at 0.44 m/s at most
    p.move(5.0, lambda f: body_profile(blend("kneeling", "standing", f), tilt_deg=90 * f)).hold(25.0, LIE)
    events = run([p], EventReasoner(falls=FallParams(long_lie_s=20.0)))
    assert not kinds(events, "fall")
    lies = kinds(events, "long_lie")
    assert len(lies) == 1 and lies[0].details["after_fall"] is False
    assert lies[0].details["fall_stamp_ns"] is None


def test_flopping_onto_a_bed_is_neither_fall_nor_long_lie():
    bed = Hotspot("bed", [[3, 0], [5, 0], [5, 2], [3, 2]], kind="bed")
    p = Person(6).hold(2.0, STAND, xy=(4.0, 1.0))
    p.move(0.6, lambda f: body_profile("standing", tilt_deg=90 * f, lift_m=0.45 * f))
    p.hold(30.0, _profile("standing", tilt_deg=90, lift_m=0.45))
    events = run([p], EventReasoner(hotspots=[bed], falls=FallParams(long_lie_s=10.0),
                                   inactivity=InactivityParams(inactivity_s=15.0, window_s=5.0)))
    assert not kinds(events, "fall") and not kinds(events, "long_lie")
    assert not kinds(events, "inactivity")  # still in bed is rest


def test_getting_up_before_confirmation_is_no_fall():
    p = Person(7).hold(2.0, STAND, xy=(2.0, 2.0)).move(0.6, _fall_profiles())
    p.hold(0.5, LIE).move(1.0, lambda f: body_profile("standing", tilt_deg=90 * (1 - f))).hold(3.0, STAND)
    events = run([p], EventReasoner(falls=FallParams(confirm_s=1.0)))
    assert not kinds(events, "fall")


# --------------------------------------------------------------------------- doors


DOOR = Hotspot("front door", [[0.0, 2.0], [0.5, 2.0], [0.5, 3.0], [0.0, 3.0]])


def test_enter_and_exit_through_a_door_and_at_the_edge():
    a = Person(1).absent(2.0).hold(0.4, xy=(0.2, 2.5), confirmed=False).walk((3.0, 2.5)).hold(2.0)
    a.walk((0.25, 2.5)).hold(0.2).absent(1.0)
    b = Person(2).absent(1.0).hold(1.0, xy=(3.0, 1.0)).absent(3.0)  # appears and vanishes mid-room
    c = Person(3).absent(3.0).hold(0.3, xy=(5.8, 4.0), confirmed=False).walk((4.0, 3.0)).hold(1.0)
    d = Person(4).absent(1.5).hold(0.3, xy=(0.3, 2.8), confirmed=False).absent(1.0)  # never confirmed: noise
    e = Person(5).hold(3.0, xy=(0.3, 2.2))  # at the door when monitoring starts: not an entry
    events = run([a, b, c, d, e], EventReasoner(doors=[DOOR], bounds_xy_m=(0.0, 0.0, 6.0, 5.0),
                                               entries=EntryParams(edge_margin_m=0.4)))
    got = [(e.kind, e.track, e.details.get("door")) for e in events]
    assert got == [("exit", 5, "front door"), ("enter", 1, "front door"), ("enter", 3, "edge"),
                   ("exit", 1, "front door")]
    enter_a = events[1]
    # established: confirmed (at 2.4 s) for establish_s (0.8 s)
    assert t_s(enter_a.stamp_ns) == pytest.approx(2.4 + 0.8, abs=1.5 / FPS)
    assert t_s(enter_a.details["first_seen_ns"]) == pytest.approx(2.0, abs=1.5 / FPS)
    exit_a = events[-1]
    assert exit_a.details["last_seen_ns"] == exit_a.stamp_ns - FRAME_NS
    assert (exit_a.x, exit_a.y) == pytest.approx((0.25, 2.5))


def test_people_followed_beyond_an_open_side_enter_when_inside_and_leave_when_outside():
    """The monitored floor is 6 x 5 m of a larger one. One person stands beyond its side x = 6 for
    3 s, walks in, stays 2 s and walks out again; another stays beyond the side throughout."""
    a = Person(1).hold(3.0, xy=(6.4, 2.5)).walk((5.0, 2.5)).hold(2.0).walk((6.5, 2.5)).hold(1.0)
    b = Person(2).hold(9.0, xy=(6.3, 1.0))
    events = run([a, b], EventReasoner(bounds_xy_m=(0.0, 0.0, 6.0, 5.0)), monitored=(0.0, 0.0, 6.0, 5.0))
    assert [(e.kind, e.track, e.details.get("door")) for e in events] == [("enter", 1, "edge"), ("exit", 1, "edge")]
    enter, leave = events
    # confirmed by the tracker for seconds: present on their first frame inside, first seen (as far
    # as entering goes) on their last frame beyond the side
    assert 5.9 < enter.x <= 6.0 and t_s(enter.stamp_ns) == pytest.approx(3.0 + 0.4, abs=1.5 / FPS)
    assert enter.details["first_seen_ns"] == enter.stamp_ns - FRAME_NS
    assert leave.x == pytest.approx(6.0, abs=0.1)


def test_someone_who_stood_beyond_an_open_side_and_fell_in_fell_from_their_height():
    p = Person(1).hold(3.0, STAND, xy=(6.3, 3.0))
    p.move(0.8, _fall_profiles(), (5.5, 3.0), _toppling).hold(3.0, LIE)
    events = run([p], EventReasoner(bounds_xy_m=(0.0, 0.0, 6.0, 5.0)), monitored=(0.0, 0.0, 6.0, 5.0))
    (fall,) = kinds(events, "fall")
    assert fall.details["from_posture"] == "standing" and fall.x < 6.0
    assert 0 < t_s(fall.stamp_ns) - 3.8 <= 1.5


def test_exit_when_the_tracker_stops_confirming_a_person_at_the_door():
    # the tracker keeps a departed person unconfirmed for a while before deleting them
    a = Person(1).absent(2.0).hold(0.3, xy=(0.2, 2.5), confirmed=False).walk((3.0, 2.5)).walk((0.2, 2.5))
    a.hold(2.0, confirmed=False).absent(1.0)
    # occluded mid-room: unconfirmed for a while, then confirmed again: neither exit nor entry
    b = Person(2).hold(3.0, xy=(3.0, 1.0)).hold(1.5, confirmed=False).hold(2.0)
    # goes out and comes straight back in through the same door
    c = Person(3).absent(2.0).hold(0.3, xy=(0.2, 2.2), confirmed=False).walk((2.0, 2.2)).walk((0.2, 2.2))
    c.hold(1.0, confirmed=False).hold(1.0).walk((2.0, 2.2))
    events = run([a, b, c], EventReasoner(doors=[DOOR]))
    got = [(e.kind, e.track) for e in events]
    assert got == [("enter", 1), ("enter", 3), ("exit", 3), ("enter", 3), ("exit", 1)]
    exit_a = events[-1]
    # decided on the first unconfirmed frame, long before the tracker would delete the track
    assert exit_a.stamp_ns - exit_a.details["last_seen_ns"] == FRAME_NS
    assert t_s(exit_a.details["last_seen_ns"]) == pytest.approx(2.3 + 2 * 2.8, abs=0.2)  # two 2.8 m walks


# --------------------------------------------------------------------------- hot spots, visits, inactivity


SOFA = Hotspot("sofa", [[4.0, 0.0], [6.0, 0.0], [6.0, 1.0], [4.0, 1.0]], label="the sofa", kind="sofa")
TABLE = Hotspot("dinner table", [[1.0, 3.0], [3.0, 3.0], [3.0, 4.5], [1.0, 4.5]], kind="table")


def test_dwell_start_and_end_at_a_named_hotspot():
    p = Person(1).hold(1.0, xy=(2.0, 2.0)).walk((5.0, 0.5)).hold(30.0, SIT).walk((5.0, 2.5))
    events = run([p], EventReasoner(hotspots=[TABLE, SOFA], visits=VisitParams(dwell_window_s=10.0)))
    dwell = [e for e in events if e.kind.startswith("dwell")]
    assert [e.kind for e in dwell] == ["dwell_start", "dwell_end"]
    assert {e.details["hotspot"] for e in dwell} == {"sofa"}
    assert dwell[0].details["label"] == "the sofa" and dwell[0].details["hotspot_kind"] == "sofa"
    arrive = 1.0 + math.hypot(3.0, 1.5)
    assert t_s(dwell[0].details["start_ns"]) == pytest.approx(arrive, abs=0.5)
    assert t_s(dwell[1].stamp_ns) - (arrive + 30.0) < 1.2
    assert dwell[1].details["duration_s"] == pytest.approx(30.0, abs=3.0)


def _table_guests(n, seconds, arrive_s=0.0):
    seats = [(1.5, 3.5), (2.5, 3.5), (1.5, 4.0), (2.5, 4.0)]
    return [Person(10 + k).absent(arrive_s).hold(seconds, SIT, xy=seats[k]) for k in range(n)]


def test_visit_for_dinner_at_the_dinner_table():
    t0 = DAY0_NS + 17 * 3600 * NS  # 17:00 UTC = 19:00 local at UTC+2
    people = _table_guests(3, 80.0)
    events = run(people, EventReasoner(hotspots=[SOFA, TABLE], residents=1, utc_offset_h=2.0,
                                 visits=VisitParams(visit_min_s=60.0)), t0_ns=t0)
    visits = kinds(events, "visit")
    assert len(visits) == 1
    v = visits[0]
    assert v.track == -1 and v.id == f"{v.stamp_ns}-visit--1"
    assert v.details["reason"] == "for dinner"
    assert v.details["local_time"] == "19:01"
    assert v.details["hotspot"] == "dinner table" and v.details["people"] == 3
    assert t_s(v.stamp_ns, t0) == pytest.approx(60.0 + 0.8, abs=0.15)  # counted once established
    assert (v.x, v.y) == pytest.approx((2.0, 3.75))


def test_no_visit_when_only_residents_are_home_and_hour_override():
    people = _table_guests(2, 80.0)
    assert not kinds(run(people, EventReasoner(residents=2, visits=VisitParams(visit_min_s=60.0))), "visit")

    class Morning(EventReasoner):
        def step(self, *a, **kw):
            return super().step(*a, hour=8.25, **kw)

    v = kinds(run(people, Morning(hotspots=[TABLE], residents=1, visits=VisitParams(visit_min_s=60.0))), "visit")
    assert len(v) == 1 and v[0].details["reason"] == "for breakfast" and v[0].details["local_time"] == "08:15"


def test_visit_needs_people_gathered_at_one_hotspot():
    apart = [Person(1).hold(40.0, SIT, xy=(1.5, 3.5)), Person(2).hold(40.0, SIT, xy=(5.0, 0.5))]
    cfg = dict(hotspots=[SOFA, TABLE], residents=1)
    visits = VisitParams(visit_min_s=5.0, dwell_window_s=5.0)
    assert not kinds(run(apart, EventReasoner(**cfg, visits=visits)), "visit")
    # without the gathering rule, extra people for visit_min_s are enough; the hot spot is where they spent most time
    v = kinds(run(apart, EventReasoner(**cfg, visits=visits.model_copy(update={"visit_gathering": False}))), "visit")
    assert len(v) == 1 and t_s(v[0].stamp_ns) == pytest.approx(5.0 + 0.8, abs=0.15)
    # gathered: at the moment the second of them has dwelt a window at the table
    together = _table_guests(2, 40.0) + [Person(3).hold(40.0, xy=(5.0, 0.5))]
    v = kinds(run(together, EventReasoner(**cfg, visits=visits)), "visit")
    assert len(v) == 1 and v[0].details["hotspot"] == "dinner table" and v[0].details["people"] == 3
    assert t_s(v[0].stamp_ns) == pytest.approx(5.0 + 0.8, abs=0.5)


def test_inactivity_while_seated_still_but_not_in_bed():
    chair = Hotspot("armchair", [[0, 0], [1, 0], [1, 1], [0, 1]], kind="chair")
    p = Person(1).hold(2.0, xy=(0.5, 0.5)).hold(80.0, SIT)
    r = EventReasoner(hotspots=[chair], inactivity=InactivityParams(inactivity_s=60.0, window_s=10.0),
                      visits=VisitParams(dwell_window_s=10.0))
    events = run([p], r)
    ina = kinds(events, "inactivity")
    assert len(ina) == 1
    assert ina[0].details["posture"] == "sitting" and ina[0].details["hotspot"] == "armchair"
    # the clock starts when the seated posture starts (about 2 s + the posture delay)
    assert t_s(ina[0].stamp_ns) == pytest.approx(62.5, abs=1.0)


# --------------------------------------------------------------------------- robustness


def test_same_inputs_same_events_and_unique_ids():
    def scene():
        p = Person(1).absent(1.5).hold(0.5, xy=(0.2, 2.5)).walk((5.0, 0.5)).hold(15.0, SIT)
        p.move(1.0, lambda f: body_profile(blend("sitting", "standing", f))).hold(2.0)
        p.move(0.8, _fall_profiles(), (5.0, 1.3), _toppling).hold(3.0, LIE)
        return [p] + _table_guests(2, 25.0)

    cfg = dict(hotspots=[SOFA, TABLE], doors=[DOOR], residents=1,
               visits=VisitParams(visit_min_s=20.0, dwell_window_s=5.0))
    a = run(scene(), EventReasoner(**cfg))
    b = run(scene(), EventReasoner(**cfg))
    assert a == b and len(a) >= 6
    assert len({e.id for e in a}) == len(a)
    assert all(e.id == f"{e.stamp_ns}-{e.kind}-{e.track}" for e in a)
    assert {"enter", "dwell_start", "visit", "stand_up", "fall"} <= set(kinds(a))


def test_ghost_tracks_take_part_in_nothing():
    # a blob split off a person at the door for half a second, and a small blob at the wall for a minute
    split = Person(2).absent(2.0).hold(0.5, xy=(0.2, 2.6)).absent(1.0)
    small = [Est(3, 5.9, 4.0, np.where(np.arange(NZ) < 4, 20, 0).astype(np.int32))]  # 0.01 m^3
    r = EventReasoner(doors=[DOOR], bounds_xy_m=(0.0, 0.0, 6.0, 5.0), residents=0,
                      visits=VisitParams(visit_min_s=1.0, visit_gathering=False))
    events = run([split], r)
    bank = PostureBank(voxel_m=VOXEL_M)
    for k in range(60 * FPS):
        s = (10 * FPS + k) * FRAME_NS
        events += r.step(s, k, small, bank.update(s, small))
    assert events == []


def test_bad_frames_and_tracks_are_counted_and_dropped():
    r = EventReasoner()
    assert r.step(10 * NS, 0, [Est(1, 1.0, 1.0, STAND)]) == []
    assert r.step(5 * NS, 1, [Est(1, 1.0, 1.0, STAND)]) == []  # back in time
    assert r.rejected_frames == 1
    r.step(11 * NS, 2, [Est(2, float("nan"), 1.0, STAND), Est(3, 1.0, 1.0, STAND), Est(3, 2.0, 1.0, STAND)])
    assert r.rejected_tracks == 2


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(residents=-1), "residents"),
        (dict(bounds_xy_m=(0, 0, -1, 5)), "bounds_xy_m"),
        (dict(utc_offset_h=20), "utc_offset_h"),
        (dict(hotspots=[SOFA, SOFA]), "unique"),
        (dict(hotspots=[[0, 0]]), "hotspots"),
        (dict(doors=[[0, 0]]), "doors"),
        (dict(falls=dict(long_lie_s=60.0)), "falls"),
        (dict(presence=None), "presence"),
    ],
)
def test_reasoner_validation(kwargs, name):
    # the thresholds are checked by their parameter groups: tests/test_event_detectors.py
    with pytest.raises(ValueError, match=name):
        EventReasoner(**kwargs)


def test_posture_names_may_replace_readings():
    r = EventReasoner()
    out = []
    for k, post in enumerate(["standing"] * 45 + ["sitting"] * 5):
        out += r.step(k * FRAME_NS, k, [Est(1, 1.0, 1.0, STAND)], {1: post})
    assert kinds(out) == ["sit_down"]


def test_a_posture_held_briefly_gives_no_event():
    # Standing for 1 s (under posture_hold_s = 2 s) after the track's first
    # reading, then sitting: the first readings of a body still being carved.
    r = EventReasoner()
    out = []
    for k, post in enumerate(["standing"] * 15 + ["sitting"] * 45 + ["standing"] * 5):
        out += r.step(k * FRAME_NS, k, [Est(1, 1.0, 1.0, STAND)], {1: post})
    assert kinds(out) == ["stand_up"]  # sat 3 s: standing up from it counts
    assert NZ * VOXEL_M == pytest.approx(2.5)


# --------------------------------------------------------------------------- synthetic house against its ground truth


def _synth_profile(body, voxel_m: float = VOXEL_M) -> np.ndarray:
    """(NZ,) voxels per layer of a synthetic-house body, voxelised at voxel centres."""
    lo, hi = body.aabb()
    xs = np.arange(np.floor(lo[0] / voxel_m), np.ceil(hi[0] / voxel_m)) * voxel_m + voxel_m / 2
    ys = np.arange(np.floor(lo[1] / voxel_m), np.ceil(hi[1] / voxel_m)) * voxel_m + voxel_m / 2
    zs = np.arange(0, min(np.ceil(hi[2] / voxel_m), NZ)) * voxel_m + voxel_m / 2
    grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1)
    inside = body.contains(grid.reshape(-1, 3)).reshape(grid.shape[:3])
    prof = np.zeros(NZ, np.int32)
    prof[: inside.shape[2]] = inside.sum(axis=(0, 1))
    return prof


def _run_synthetic(name: str, seed: int = 0):
    """Events of the reasoning layer on a synthetic-house scenario and its truth events.

    Stands in for carving and tracking with their documented behaviour: a
    person inside the monitored volume is a track at their pelvis with the
    voxelised body as height profile, confirmed from its 3rd frame; a person
    who leaves stays reported at the last position for 35 frames, unconfirmed
    from the 8th (the tracker's defaults)."""
    from synth.body import pose_body
    from synth.scenarios import get_scenario
    from synth.truth import derive_truth

    sc = get_scenario(name, seed)
    room = sc.room
    reasoner = EventReasoner(
        hotspots=[Hotspot(h.name, h.polygon_m, kind=h.kind) for h in room.hotspots],
        doors=[Hotspot(d.name, d.polygon_m) for d in room.doors],
        residents=sc.spec.residents,
    )
    bank = PostureBank(voxel_m=VOXEL_M)
    seen: dict[int, int] = {}
    gone: dict[int, int] = {}
    last: dict[int, Est] = {}
    profiles: dict[tuple, np.ndarray] = {}
    events = []
    for f in range(sc.n_frames):
        tracks = []
        for person, st in zip(sc.people, sc.states):
            pid = person.person_id
            if st["present"][f] and room.inside_volume(st["xy"][f: f + 1])[0]:
                seen[pid], gone[pid] = seen.get(pid, 0) + 1, 0
                pose = (pid, st["q"][f].tobytes())   # a person holding still is voxelised once
                if pose not in profiles:
                    profiles[pose] = _synth_profile(pose_body(person.shape, st["q"][f], pid))
                prof = profiles[pose]
                last[pid] = Est(pid, float(st["xy"][f, 0]), float(st["xy"][f, 1]), prof, confirmed=seen[pid] >= 3)
                tracks.append(last[pid])
            elif pid in seen:
                gone[pid] += 1
                if gone[pid] <= 35:
                    tracks.append(Est(pid, last[pid].x, last[pid].y, last[pid].height_profile, confirmed=gone[pid] < 8))
                else:
                    del seen[pid]
        stamp = sc.stamp_ns(f)
        events += reasoner.step(stamp, f, tracks, bank.update(stamp, tracks))
    return events, derive_truth(sc).events


@pytest.mark.parametrize(
    "name",
    ["demo"] + [pytest.param(n, marks=pytest.mark.slow) for n in
                ("fall_backward", "fall_sideways", "bend_kneel", "behind_sofa", "enter_exit", "sit_stand",
                 "dinner_visit")],
)
def test_synthetic_scenario_events_match_truth(name):
    from evaluation.events import score_events

    run_events, truth_events = _run_synthetic(name)
    scores = score_events(truth_events, run_events)  # the project's protocol: same kind within 30 frames
    assert truth_events or name == "behind_sofa", name  # behind_sofa: bending and kneeling, nothing to report
    assert scores.unmatched_truth == [] and scores.unmatched_run == [], (scores.unmatched_truth, scores.unmatched_run)
    # falls are confirmed within 1.5 s of the body reaching the floor (the truth's fall frame)
    assert all(0 < d <= 1.5 for d in scores.delays_s("fall"))
