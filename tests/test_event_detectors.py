"""Each event detector driven on its own with hand-built frames, and the checks of
the parameter groups. Frames are 0.1 s apart; expectations are worked out by hand
in the comments."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from common.messages import Event
from fusion_server.events import (
    DEFAULT_MEALS,
    Emitter,
    EntryDetector,
    EntryParams,
    FallDetector,
    FallParams,
    InactivityDetector,
    InactivityParams,
    PresenceParams,
    SitStandDetector,
    SitStandParams,
    TrackSnapshot,
    VisitDetector,
    VisitParams,
)
from fusion_server.hotspots import Hotspot
from fusion_server.posture import company_of

TICK_NS = 100_000_000  # 0.1 s
DOOR = Hotspot("front door", [[0.0, 2.0], [0.5, 2.0], [0.5, 3.0], [0.0, 3.0]])
TABLE = Hotspot("dinner table", [[1.0, 3.0], [3.0, 3.0], [3.0, 4.5], [1.0, 4.5]], kind="table")
BED = Hotspot("bed", [[3.0, 0.0], [5.0, 0.0], [5.0, 2.0], [3.0, 2.0]], kind="bed")


def frame(k: int, *, track: int = 1, xy=(1.0, 1.0), posture=None, top_m=float("nan"), tops=(), upright_ns=0,
          confirmed=True, company_m=math.inf):
    """Track ``track`` at tick ``k`` without a posture reading (so no centre and no learnt height)."""
    return TrackSnapshot(track, k * TICK_NS, xy[0], xy[1], posture, None, top_m, None, None, tops, upright_ns,
                         confirmed, company_m)


def emitter(k: int, out: list[Event]) -> Emitter:
    return Emitter(out, k * TICK_NS, k)


# --------------------------------------------------------------------------- parameter groups


def test_parameter_groups_hold_the_documented_defaults():
    def as_dict(group):
        return group.model_dump()

    assert as_dict(PresenceParams()) == dict(establish_s=0.8, min_volume_m3=0.04)
    assert as_dict(FallParams()) == dict(
        window_s=2.0, min_drop_m=0.5, min_speed_mps=0.8, max_accel_mps2=1.5 * 9.81, height_tol_m=0.15,
        confirm_s=1.0, upright_s=0.5, low_top_frac=0.55, low_centre_frac=0.25, flat_top_frac=0.45,
        low_gap_s=0.5, company_m=0.8, repeat_radius_m=1.0, repeat_s=120.0, same_fall_s=1.0, same_fall_radius_m=2.0,
        left_within_s=0.8, left_top_frac=0.8, left_moved_m=0.4, long_lie_s=30.0, standing_height_m=1.70,
    )
    assert as_dict(SitStandParams()) == dict(
        stand_up_from={"sitting", "lying"}, min_change_frac=0.07, max_change_frac=0.65, hold_s=2.0,
        max_move_m=0.8, move_window_s=0.4, floor_rise_s=0.5,
        seat_kinds={"sofa", "table", "chair", "armchair", "bench", "bed"},
    )
    assert as_dict(EntryParams()) == dict(edge_margin_m=0.4, startup_s=1.0)
    assert as_dict(VisitParams()) == dict(
        dwell_window_s=10.0, dwell_still_std_m=0.15, dwell_move_std_m=0.30, visit_min_s=10.0, visit_gap_s=30.0,
        visit_gathering=True, meals=DEFAULT_MEALS,
    )
    assert as_dict(InactivityParams()) == dict(inactivity_s=1800.0, window_s=30.0, std_m=0.15, rest_kinds={"bed"})
    # checked once, then frozen; kinds become sets and numbers floats
    p = SitStandParams(stand_up_from=["sitting"], hold_s=3)
    assert p.stand_up_from == frozenset({"sitting"}) and isinstance(p.hold_s, float)
    with pytest.raises(ValueError, match="frozen"):
        p.hold_s = 1.0


@pytest.mark.parametrize(
    "group, kwargs, pattern",
    [
        (PresenceParams, dict(establish_s=-1), "establish_s.*-1"),
        (PresenceParams, dict(min_volume_m3="0.04"), "min_volume_m3.*'0.04'"),
        (FallParams, dict(window_s=0), "window_s.*0"),
        (FallParams, dict(min_drop_m=0), "min_drop_m.*0"),
        (FallParams, dict(max_accel_mps2=0), "max_accel_mps2.*0"),
        (FallParams, dict(height_tol_m=-0.1), r"height_tol_m.*-0\.1"),
        (FallParams, dict(upright_s=float("inf")), "upright_s.*inf"),
        (FallParams, dict(long_lie_s=float("nan")), "long_lie_s.*nan"),
        (FallParams, dict(low_top_frac=1.5), r"low_top_frac.*1\.5"),
        (FallParams, dict(standing_height_m=True), "standing_height_m.*True"),
        (SitStandParams, dict(min_change_frac=-0.1), r"min_change_frac.*-0\.1"),
        (SitStandParams, dict(max_change_frac=0.05), r"max_change_frac.*0\.05"),
        (SitStandParams, dict(max_change_frac="big"), "max_change_frac.*'big'"),
        (SitStandParams, dict(hold_s=float("nan")), "hold_s.*nan"),
        (SitStandParams, dict(stand_up_from=("flying",)), "stand_up_from.*flying"),
        (SitStandParams, dict(seat_kinds="sofa"), "seat_kinds.*'sofa'"),
        (EntryParams, dict(edge_margin_m=-0.4), r"edge_margin_m.*-0\.4"),
        (EntryParams, dict(startup_s=float("nan")), "startup_s.*nan"),
        (VisitParams, dict(visit_min_s=0), "visit_min_s.*0"),
        (VisitParams, dict(visit_gap_s=-1), "visit_gap_s.*-1"),
        (VisitParams, dict(dwell_window_s=-10), "dwell_window_s.*-10"),
        (VisitParams, dict(dwell_still_std_m=0.5, dwell_move_std_m=0.2), r"dwell_move_std_m \(0\.2\)"),
        (VisitParams, dict(meals=(("for tea", 17, 15),)), "meals.*'for tea', 17, 15"),
        (InactivityParams, dict(inactivity_s=0), "inactivity_s.*0"),
        (InactivityParams, dict(window_s=float("inf")), "window_s.*inf"),
        (InactivityParams, dict(std_m=-0.15), r"std_m.*-0\.15"),
        (InactivityParams, dict(rest_kinds=3), "rest_kinds.*3"),
    ],
)
def test_parameter_groups_name_the_bad_field_and_value(group, kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        group(**kwargs)


@pytest.mark.parametrize("detector", [FallDetector, SitStandDetector, EntryDetector, VisitDetector, InactivityDetector])
def test_detectors_take_only_their_own_group(detector):
    with pytest.raises(ValueError, match="params"):
        detector(PresenceParams())


# --------------------------------------------------------------------------- falls


def _fall_tops():
    """(posture, top) per tick: standing at 1.75 m for 1 s (ticks 0-9), down 0.25 m a tick
    to 0.5 m at tick 14, lying from tick 13, then at 0.25 m from tick 15."""
    tops = [1.75] * 10 + [1.5, 1.25, 1.0, 0.75, 0.5] + [0.25] * 60
    return [("standing" if k < 13 else "lying", z) for k, z in enumerate(tops)]


def _run_falls(detector: FallDetector, upright_ns: int, *, track: int = 1, start: int = 0, xy=(2.0, 1.5),
               confirmed=lambda k: True, out: list[Event] | None = None) -> list[Event]:
    """The fall of :func:`_fall_tops` by ``track`` at ``xy`` (or at ``xy(k)`` on the fall's k-th tick)
    from tick ``start``; ``confirmed(k)`` says whether the tracker confirms the track on the k-th tick."""
    out = [] if out is None else out
    history = []
    for k, (posture, top) in enumerate(_fall_tops()):
        tick = start + k
        history.append((tick * TICK_NS, top, None, posture, top))
        at = xy(k) if callable(xy) else xy
        f = frame(tick, track=track, xy=at, posture=posture, top_m=top, tops=tuple(history), upright_ns=upright_ns,
                  confirmed=confirmed(k))
        detector.update(f, emitter(tick, out))
    return out


def test_fall_detector_hand_worked():
    falls = FallDetector(FallParams(long_lie_s=5.0))
    out = _run_falls(falls, upright_ns=900_000_000)
    # Low: the median of the last three tops at most 0.55 * 1.70 = 0.935 m, first at tick 14
    # (1.0, 0.75, 0.5); lying there, so on the floor from 1.4 s. The largest fast drop in the 2 s
    # before is 1.75 -> 0.5 m, from the latest 1.75 (tick 9) to tick 14: 1.25 m in 0.5 s. Halfway,
    # 1.125 m, is passed halfway between ticks 11 (1.25) and 12 (1.0): 1.15 s. Confirmed 1 s after
    # getting low: tick 24.
    fall, lie = out
    assert (fall.kind, fall.frame, fall.track, fall.x, fall.y) == ("fall", 24, 1, 2.0, 1.5)
    assert fall.details == dict(
        fall_stamp_ns=1_150_000_000, drop_start_ns=900_000_000, from_posture="standing", top_before_m=1.75,
        top_after_m=0.5, drop_m=1.25, drop_speed_mps=2.5, confirm_s=1.0,
    )
    # On the floor since the fall (1.15 s, before the 1.4 s it got low): 5 s later is 6.15 s, tick 62.
    assert (lie.kind, lie.frame) == ("long_lie", 62)
    assert lie.details == dict(lying_since_ns=1_150_000_000, duration_s=5.05, after_fall=True,
                               fall_stamp_ns=1_150_000_000)
    assert falls.on_floor(1) and not falls.on_floor(2)
    assert falls.low(1) and falls.low(1, top_m=1.8)  # on the floor: low whatever this frame's top
    # an unknown track is low by this frame's top alone: at most 0.55 of its height (0.99 m for
    # 1.80 m), or of the default 1.70 m (0.935 m) when its height is unknown
    assert not falls.low(2) and falls.low(2, 0.99, 1.80) and not falls.low(2, 1.0, 1.80)
    assert falls.low(2, 0.93) and not falls.low(2, 0.94)
    falls.forget(1)
    assert not falls.on_floor(1)


def test_a_fall_under_a_tent_of_hull_is_read_by_the_bodys_top():
    """A fall whose hull keeps a tent over the body on the floor: the top comes down only from
    1.75 to 1.2 m, the body's top from 1.5 to 0.55 m then 0.3 m. Read by the body's top, the body
    is low from tick 13 (median of 1.05, 0.8, 0.55 is 0.8 <= 0.935 m) and lying: raised 1 s later,
    tick 23. The drop is the top's: the largest fast one is 1.75 -> 1.2 m (the latest 1.75, tick
    9, to the first 1.2, tick 12: 0.55 m in 0.3 s); halfway, 1.475 m, is passed an eighth of the
    way from tick 10 (1.5) to tick 11 (1.3): 1.0125 s. Read by the hull's top alone (the same
    series as both heights), the body never gets low (1.2 > 0.935 m): nothing is raised."""
    raw = [1.75] * 10 + [1.5, 1.3, 1.2] + [1.2] * 62
    body = [1.5] * 10 + [1.3, 1.05, 0.8, 0.55] + [0.3] * 61

    def run(bodies):
        return _run_series(raw, bodies)

    (fall,) = run(body)
    assert (fall.kind, fall.frame) == ("fall", 23)
    assert fall.details == dict(
        fall_stamp_ns=1_012_500_000, drop_start_ns=900_000_000, from_posture="standing", top_before_m=1.75,
        top_after_m=1.2, drop_m=0.55, drop_speed_mps=1.833, confirm_s=1.0,
    )
    assert run(raw) == []


def _run_series(raw: list[float], body: list[float], company_m: float = math.inf) -> list[Event]:
    """Track 1 at (2.0, 1.5), standing up to tick 12 and lying from tick 13, with these tops and
    body tops one a tick, the nearest other confirmed track ``company_m`` away."""
    out, history = [], []
    detector = FallDetector(FallParams(long_lie_s=60.0))
    for k, (top, body_top) in enumerate(zip(raw, body)):
        posture = "standing" if k < 13 else "lying"
        history.append((k * TICK_NS, top, None, posture, body_top))
        detector.update(frame(k, xy=(2.0, 1.5), posture=posture, top_m=top, tops=tuple(history),
                              upright_ns=900_000_000, company_m=company_m), emitter(k, out))
    return out


def _run_tops(detector: FallDetector, tops: list[float], out: list[Event]) -> list[Event]:
    """Track 1 at (2.0, 1.5) with these tops, one a tick: standing above 0.935 m, lying below."""
    history = []
    for k, top in enumerate(tops):
        posture = "standing" if top > 0.935 else "lying"
        history.append((k * TICK_NS, top, None, posture, top))
        detector.update(frame(k, xy=(2.0, 1.5), posture=posture, top_m=top, tops=tuple(history),
                              upright_ns=900_000_000), emitter(k, out))
    return out


def test_a_top_back_at_the_height_it_came_down_from_ends_the_spell_on_the_floor():
    """The hand-worked fall's tops (down to 0.25 m at tick 15), then from tick 16 the top flickers back
    to 1.75 m for three ticks in every seven: each time the last three tops' median is back within
    0.15 m of the 1.75 m the drop began at (from the second tick up), so the spell on the floor ends
    there although the gap (0.3 s) is under ``low_gap_s``; no spell lasts the 1 s a fall needs. The
    same fall with single-tick flickers (the median never comes back up) is raised as before, at
    tick 24."""
    landed = [1.75] * 10 + [1.5, 1.25, 1.0, 0.75, 0.5, 0.25]
    flicker = landed + ([1.75] * 3 + [0.25] * 4) * 8
    assert _run_tops(FallDetector(FallParams(long_lie_s=60.0)), flicker, []) == []
    pops = landed + ([1.75] + [0.25] * 6) * 8
    (fall,) = _run_tops(FallDetector(FallParams(long_lie_s=60.0)), pops, [])
    assert (fall.kind, fall.frame, fall.details["top_before_m"]) == ("fall", 24, 1.75)


def _run_beside(company_m: float) -> list[Event]:
    """A fall beside someone standing, track 1 at (2.0, 1.5), the nearest other confirmed track
    ``company_m`` away: the body's top comes down 0.25 m a tick from 1.5 m (ticks 0-9) to 0.5 m at
    tick 13 and 0.25 m after, lying from tick 13; the top stays the neighbour's 1.75 m until the blobs
    part at tick 15, then 0.3 m."""
    raw = [1.75] * 15 + [0.3] * 60
    body = [1.5] * 10 + [1.25, 1.0, 0.75, 0.5] + [0.25] * 61
    return _run_series(raw, body, company_m)


def test_in_company_the_drop_is_read_from_the_bodys_top():
    """Read by the body's top the body is low from tick 13 (median of 1.0, 0.75, 0.5 is 0.75 <=
    0.935 m). The top shows no fall: it stays at 1.75 m, then drops 1.45 m in one tick (faster than
    a body falling from 1.75 m at 1.5 g, 0.72 m a tick give or take 0.15 m). Beside someone (0.6 m)
    the drop is read from the body's top: the latest 1.5 m (tick 9) to 0.5 m at tick 13, 1.0 m in
    0.4 s; halfway, 1.0 m, is reached at tick 11: 1.1 s. Raised 1 s after getting low, tick 23.
    Alone (or with the neighbour 0.9 m away) the top is the body's own, and no fall is read."""
    (fall,) = _run_beside(0.6)
    assert (fall.kind, fall.frame) == ("fall", 23)
    assert fall.details == dict(
        fall_stamp_ns=1_100_000_000, drop_start_ns=900_000_000, from_posture="standing", top_before_m=1.5,
        top_after_m=0.5, drop_m=1.0, drop_speed_mps=2.5, confirm_s=1.0,
    )
    assert _run_beside(0.9) == [] and _run_beside(math.inf) == []


def test_company_is_measured_among_confirmed_tracks():
    """Company is the floor distance to the nearest other track the tracker confirms: track 1 at
    (0, 0) has track 2 (3, 4) 5 m away, track 3 (0.6, 0) is unconfirmed and is nobody's company
    (it is in company itself, 0.6 m from track 1), a track without a position neither has nor
    keeps company; alone, a track has none."""
    one, two = SimpleNamespace(id=1, x=0.0, y=0.0, confirmed=True), SimpleNamespace(id=2, x=3.0, y=4.0, confirmed=True)
    three, nowhere = SimpleNamespace(id=3, x=0.6, y=0.0, confirmed=False), SimpleNamespace(id=4, confirmed=True)
    assert company_of([one, two, three, nowhere]).tolist() == pytest.approx([5.0, 5.0, 0.6, math.inf])
    assert company_of([one]).tolist() == [math.inf] and company_of([]).shape == (0,)


def test_one_fall_is_one_alarm_where_one_was_just_raised():
    """The hand-worked fall (raised on its 24th tick) by track 1 at (2.0, 1.5); then the same fall by
    track 2 at (2.8, 1.5), 0.8 m away, from tick 100: not raised (within 1 m and 120 s); by track
    3 at (3.1, 1.5), 1.1 m away, from tick 200: raised; and by track 4 at (2.0, 1.5) from tick 1,400,
    140 s after the first: raised again."""
    falls = FallDetector(FallParams(long_lie_s=60.0))
    out: list[Event] = []
    for track, x, start in ((1, 2.0, 0), (2, 2.8, 100), (3, 3.1, 200), (4, 2.0, 1_400)):
        _run_falls(falls, 900_000_000, track=track, start=start, xy=(x, 1.5), out=out)
    assert [(e.kind, e.track, e.frame) for e in out] == [("fall", 1, 24), ("fall", 3, 224), ("fall", 4, 1_424)]


def test_a_fall_raised_off_its_body_is_not_raised_again_where_the_body_lies():
    """Track 1 raises the hand-worked fall at (2.0, 1.5) on its 24th tick, then lies on the floor at
    (2.6, 1.5) from tick 30 (it got low off the body it follows, and settled on it). Track 2 takes up
    the body at (3.3, 1.5) from tick 100: 1.3 m from where the fall was raised (over 1 m) but 0.7 m
    from where track 1 lay: the same body, not raised again. Had track 1 stayed at (2.0, 1.5), the
    second would be raised (1.3 m off, its body down 10 s after the first's)."""
    def run(settles: bool) -> list[tuple[int, int]]:
        falls = FallDetector(FallParams(long_lie_s=60.0))
        out: list[Event] = []
        _run_falls(falls, 900_000_000, track=1, xy=lambda k: (2.6 if settles and k >= 30 else 2.0, 1.5), out=out)
        _run_falls(falls, 900_000_000, track=2, start=100, xy=(3.3, 1.5), out=out)
        return [(e.track, e.frame) for e in out if e.kind == "fall"]

    assert run(settles=True) == [(1, 24)]
    assert run(settles=False) == [(1, 24), (2, 124)]


def test_one_body_coming_down_under_two_tracks_is_one_alarm():
    """The hand-worked fall by track 1 at (2.0, 1.5) and, two ticks later, by track 2 at (3.6, 1.5),
    1.6 m away (its body reached the floor 0.2 s after track 1's: within 1 s and 2 m): one alarm.
    Track 3's at (4.2, 1.5), 2.2 m away, three ticks after track 1's: raised."""
    falls = FallDetector(FallParams(long_lie_s=60.0))
    out: list[Event] = []
    for track, x, start in ((1, 2.0, 0), (2, 3.6, 2), (3, 4.2, 3)):
        _run_falls(falls, 900_000_000, track=track, start=start, xy=(x, 1.5), out=out)
    out.sort(key=lambda e: e.frame)
    assert [(e.kind, e.track, e.frame) for e in out] == [("fall", 1, 24), ("fall", 3, 27)]


def test_only_a_confirmed_track_raises_a_fall():
    """The hand-worked fall (found on tick 24) by a track the tracker does not confirm on ticks
    20-29: raised on tick 30, its first confirmed tick on the floor, with the same fall moment.
    Never confirmed from tick 20 on: not raised at all."""
    out = _run_falls(FallDetector(FallParams(long_lie_s=60.0)), 900_000_000, confirmed=lambda k: not 20 <= k < 30)
    (fall,) = out
    assert (fall.frame, fall.details["fall_stamp_ns"], fall.details["confirm_s"]) == (30, 1_150_000_000, 1.6)
    assert _run_falls(FallDetector(FallParams(long_lie_s=60.0)), 900_000_000, confirmed=lambda k: k < 20) == []


def test_fall_detector_needs_an_upright_history():
    # upright for 0.4 s, under upright_s (0.5 s): the same drop is no fall
    out = _run_falls(FallDetector(FallParams(long_lie_s=60.0)), upright_ns=400_000_000)
    assert out == []


# --------------------------------------------------------------------------- sit / stand


def test_a_drop_made_while_coasting_is_no_fall():
    """The same drop (ticks 9-14, from 1.75 m) by a track confirmed up to tick 7, then unconfirmed
    (coasting) until tick 19, through the whole drop, confirmed again on the floor from tick 20:
    its top was no body's while it came down, so no fall. A track confirmed for the first time at
    tick 20 (found while the person fell) raises it on tick 24, as when confirmed throughout."""
    coasting = _run_falls(FallDetector(FallParams(long_lie_s=60.0)), 900_000_000, confirmed=lambda k: not 8 <= k < 20)
    assert coasting == []
    (found_late,) = _run_falls(FallDetector(FallParams(long_lie_s=60.0)), 900_000_000, confirmed=lambda k: k >= 20)
    assert (found_late.kind, found_late.frame, found_late.details["fall_stamp_ns"]) == ("fall", 24, 1_150_000_000)
    # Confirmed again before the top passed halfway down (1.15 s; tick 11 is 1.1 s): the drop was
    # not all coasting, raised on tick 24.
    (back,) = _run_falls(FallDetector(FallParams(long_lie_s=60.0)), 900_000_000, confirmed=lambda k: not 8 <= k < 11)
    assert back.frame == 24
    # Coasting through the drop is decided once: lying on after the spell is forgotten (5.5 s) never
    # raises it later.
    assert _run_falls(FallDetector(FallParams(long_lie_s=600.0)), 900_000_000, confirmed=lambda k: not 8 <= k < 12) == []


def _leave_body(*, back_tick: int = 17, to_xy=(2.6, 1.5), confirmed=lambda k: True) -> list[Event]:
    """The fall of :func:`_fall_tops` at (2.0, 1.5), low from tick 14, until the track jumps at
    ``back_tick`` to someone standing at ``to_xy`` (top 1.7 m) and follows them for 4 s."""
    falls = FallDetector(FallParams(long_lie_s=60.0))
    out: list[Event] = []
    history = []
    for k, (posture, top) in enumerate(_fall_tops()[:back_tick] + [("standing", 1.7)] * 40):
        xy = (2.0, 1.5) if k < back_tick else to_xy
        history.append((k * TICK_NS, top, None, posture, top))
        falls.update(frame(k, xy=xy, posture=posture, top_m=top, tops=tuple(history), upright_ns=900_000_000,
                           confirmed=confirmed(k)), emitter(k, out))
    return out


def test_a_track_that_leaves_the_body_on_the_floor_still_raises_its_fall():
    """Low from tick 14 (1.4 s) after the drop of 1.75 -> 0.5 m, the track jumps at tick 17 to
    someone standing 0.6 m away; its top (the median of three frames) reads 1.7 m (over 0.8 x 1.70 =
    1.36 m) at tick 18, 0.4 s after getting low: nobody gets up from the floor that fast, so it left
    the body there. The fall is raised where the body got low, at 2.4 s (tick 24, a second after
    getting low, as for a track that stays), by the track, marked as left behind."""
    (fall,) = _leave_body()
    assert (fall.kind, fall.frame, fall.track, fall.x, fall.y) == ("fall", 24, 1, 2.0, 1.5)
    assert fall.details["fall_stamp_ns"] == 1_150_000_000 and fall.details["left_behind"] is True
    assert fall.details["confirm_s"] == 1.0
    # Back up only after 1.0 s (read at tick 24, past 0.8 s): someone getting up, not a body left behind.
    assert _leave_body(back_tick=23) == []
    # Back up 0.3 m from where it got low (under 0.4 m): the same body rising, not another's.
    assert _leave_body(to_xy=(2.3, 1.5)) == []
    # Never confirmed while low (ticks 14-17): its low frames were no body's.
    assert _leave_body(confirmed=lambda k: not 14 <= k < 18) == []


def _run_postures(detector: SitStandDetector, postures: list[str], confirmed=lambda k: True) -> list[tuple[str, int, str, str]]:
    out: list[Event] = []
    for k, posture in enumerate(postures):
        detector.update(frame(k, posture=posture, confirmed=confirmed(k)), emitter(k, out))
    return [(e.kind, e.frame, e.details["from_posture"], e.details["to_posture"]) for e in out]


def test_sit_stand_detector_hand_worked():
    # Bare posture names carry no height: only the postures and how long each was held count.
    # Standing from 0 s, sitting at 3 s (standing held 3 s >= 2 s), standing at 6 s (sat 3 s).
    seq = ["standing"] * 30 + ["sitting"] * 30 + ["standing"] * 10
    assert _run_postures(SitStandDetector(), seq) == [("sit_down", 30, "standing", "sitting"),
                                                      ("stand_up", 60, "sitting", "standing")]
    # Sat 1 s only (under hold_s): standing again is no event; bending in between is ignored.
    seq = ["standing"] * 30 + ["sitting"] * 10 + ["bending"] * 5 + ["standing"] * 10
    assert _run_postures(SitStandDetector(), seq) == [("sit_down", 30, "standing", "sitting")]
    # Up from lying is a stand_up only when lying is in stand_up_from.
    seq = ["lying"] * 30 + ["bending"] * 6 + ["standing"] * 5
    assert _run_postures(SitStandDetector(), seq) == [("stand_up", 36, "lying", "standing")]
    assert _run_postures(SitStandDetector(SitStandParams(stand_up_from=("sitting",))), seq) == []
    # Lying, then standing the next tick: no one gets up from the floor in 0.1 s (floor_rise_s 0.5 s);
    # through 0.4 s of kneeling (last lying at tick 29, standing at 33), still too fast; through 0.5 s, up.
    assert _run_postures(SitStandDetector(), ["lying"] * 30 + ["standing"] * 5) == []
    assert _run_postures(SitStandDetector(), ["lying"] * 30 + ["bending"] * 3 + ["standing"] * 5) == []
    assert _run_postures(SitStandDetector(), ["lying"] * 30 + ["bending"] * 4 + ["standing"] * 5) == [
        ("stand_up", 34, "lying", "standing")]
    assert _run_postures(SitStandDetector(SitStandParams(floor_rise_s=0.0)), ["lying"] * 30 + ["standing"] * 5) == [
        ("stand_up", 30, "lying", "standing")]


def test_a_short_posture_between_two_others_is_a_passage():
    # Lying 3 s, a second of sitting on the way up, then standing: up from lying, at 4 s (the
    # sitting, held under hold_s, is a passage). Standing 3 s, lying half a second, then sitting:
    # a sit_down from standing at 3.5 s.
    seq = ["lying"] * 30 + ["sitting"] * 10 + ["standing"] * 10
    assert _run_postures(SitStandDetector(), seq) == [("stand_up", 40, "lying", "standing")]
    seq = ["standing"] * 30 + ["lying"] * 5 + ["sitting"] * 30
    assert _run_postures(SitStandDetector(), seq) == [("sit_down", 35, "standing", "sitting")]
    # Told once: sat down at 3 s, then a second up and a second down again is no second event.
    seq = ["standing"] * 30 + ["sitting"] * 10 + ["standing"] * 10 + ["sitting"] * 30
    assert _run_postures(SitStandDetector(), seq) == [("sit_down", 30, "standing", "sitting")]


def _sit_after_walking_beside(top_before_m: float, seated_top_m: float, height_m: float) -> list[str]:
    """Standing 3 s with the top ``top_before_m``, then 1 s at 1.55 m, then the reading turns sitting
    (for 3 s, top ``seated_top_m``) with the learnt standing height ``height_m``: the kinds emitted."""
    from fusion_server.posture import PostureReading

    detector = SitStandDetector()
    tops: list = []
    out: list[Event] = []
    since_ns = 40 * TICK_NS
    for k in range(70):
        sitting = k >= 40
        top = seated_top_m if sitting else (top_before_m if k < 30 else 1.55)
        tops.append((k * TICK_NS, top, None, None, top))
        posture = "sitting" if sitting else "standing"
        reading = PostureReading(posture=posture, since_ns=since_ns if sitting else 0, probabilities=(0.9, 0.1, 0.0, 0.0),
                                 raw=None, smoothed=None, standing_height_m=height_m, stamp_ns=k * TICK_NS, state=posture)
        snap = TrackSnapshot(1, k * TICK_NS, 1.0, 1.0, posture, reading, top, None, height_m, tuple(tops), k * TICK_NS, True)
        detector.update(snap, emitter(k, out))
    return [e.kind for e in out]


def test_a_sit_down_leaves_the_top_below_the_standing_height():
    # A 1.5 m person walked beside a 1.9 m one (their track's top was the other's head), then stood
    # apart at their own 1.55 m top and read sitting: the top came down 0.35 m (over 0.07 x 1.5 m),
    # but a seated top at the person's own standing height is no seat's: no sit_down. Their top
    # coming down to 1.15 m is one (0.35 m under their height); a 1.9 m person whose top came down
    # to 1.55 m sat too. The line is 0.07 x 1.5 = 0.105 m under the height: 1.42 m no, 1.38 m yes.
    for top_before, seated, height, kinds in ((1.9, 1.55, 1.5, []), (1.9, 1.15, 1.5, ["sit_down"]),
                                              (1.9, 1.55, 1.9, ["sit_down"]), (1.9, 1.42, 1.5, []),
                                              (1.9, 1.38, 1.5, ["sit_down"])):
        assert _sit_after_walking_beside(top_before, seated, height) == kinds, (top_before, seated, height)


def test_fastest_move_hand_worked():
    from fusion_server.events.sit_stand import fastest_move_m
    ms = 1_000_000
    # every 0.1 s; a one-frame spike at 0.2 s, then up from 0.6 s. The median of each top and the
    # two before: 0.4 up to 0.6 s, 1.2 at 0.7 s, 1.6 from 0.8 s (the spike is gone).
    z = [0.4, 0.4, 1.6, 0.4, 0.4, 0.4, 1.2, 1.6, 1.6, 1.6]
    tops = [(k * 100 * ms, v) for k, v in enumerate(z)] + [(1000 * ms, float("nan"))]
    assert fastest_move_m(tops, 0, 400 * ms) == (0.0, pytest.approx(1.2))   # 0.4 at 0.5 s -> 1.6 at 0.8 s
    assert fastest_move_m(tops, 0, 100 * ms) == (0.0, pytest.approx(0.8))   # 0.4 -> 1.2, 0.6 -> 0.7 s
    assert fastest_move_m(tops, 750 * ms, 400 * ms) == (0.0, 0.0)           # from 0.8 s on, still
    down = [(k * 100 * ms, 2.0 - v) for k, v in enumerate(z)]
    assert fastest_move_m(down, 0, 400 * ms) == (pytest.approx(-1.2), 0.0)


def test_sit_stand_reads_only_confirmed_frames():
    # Standing 3 s, then sitting; the track unconfirmed from 3 s to 6 s (coasting: its posture is no
    # body's). The sitting is taken on its first confirmed frame, 6 s, as sitting after standing held
    # since 0 s; standing again at 9 s while unconfirmed is not read, so no stand_up.
    seq = ["standing"] * 30 + ["sitting"] * 60 + ["standing"] * 20
    got = _run_postures(SitStandDetector(), seq, confirmed=lambda k: not (30 <= k < 60 or k >= 90))
    assert got == [("sit_down", 60, "standing", "sitting")]


# --------------------------------------------------------------------------- entries


def test_entry_detector_hand_worked():
    entries = EntryDetector(doors=[DOOR], bounds_xy_m=(0.0, 0.0, 6.0, 5.0))
    assert entries.place(0.2, 2.5) == "front door"
    assert entries.place(5.8, 4.0) == "edge"  # 0.2 m from x_max, within 0.4 m
    assert entries.place(0.45, 1.0) is None  # 0.45 m from x_min
    assert entries.place(3.0, 2.5) is None
    assert EntryDetector(doors=[DOOR]).place(5.8, 4.0) is None  # doors only

    out: list[Event] = []
    emit = emitter(30, out)
    # first seen in the door 2 s after monitoring began: an entry; 1 s after (not over startup_s): none
    entries.first_arrival(1, 1.0, 2.5, first_xy=(0.2, 2.5), first_ns=2_000_000_000, start_ns=0, emit=emit)
    entries.first_arrival(2, 1.0, 2.5, first_xy=(0.2, 2.5), first_ns=1_000_000_000, start_ns=0, emit=emit)
    entries.first_arrival(3, 1.0, 2.5, first_xy=(3.0, 2.5), first_ns=2_000_000_000, start_ns=0, emit=emit)
    # back at the edge after leaving: an entry; back mid-room: none
    entries.return_arrival(4, 5.8, 4.0, since_ns=2_500_000_000, emit=emit)
    entries.return_arrival(5, 3.0, 2.5, since_ns=2_500_000_000, emit=emit)
    entries.exit(1, "front door", (0.25, 2.5), 2_900_000_000, emit)
    assert [(e.kind, e.track, e.x, e.y, e.details) for e in out] == [
        ("enter", 1, 1.0, 2.5, dict(door="front door", first_seen_ns=2_000_000_000)),
        ("enter", 4, 5.8, 4.0, dict(door="edge", first_seen_ns=2_500_000_000)),
        ("exit", 1, 0.25, 2.5, dict(door="front door", last_seen_ns=2_900_000_000)),
    ]
    assert all(e.stamp_ns == 3_000_000_000 and e.frame == 30 for e in out)


# --------------------------------------------------------------------------- dwell and visits


def test_visit_detector_hand_worked():
    visits = VisitDetector(VisitParams(dwell_window_s=1.0, visit_min_s=2.0), hotspots=[TABLE], residents=1)
    seats = {1: (1.5, 3.5), 2: (2.5, 3.5)}
    out: list[Event] = []
    for k in range(26):
        emit = emitter(k, out)
        for tid, xy in seats.items():
            visits.update(frame(k, track=tid, xy=xy), emit)
        visits.step(k * TICK_NS, TICK_NS if k else 0, sorted(seats.items()), 19.0, emit)
    # Still at the table: each dwells once the 1 s window is full (tick 10), settled since 0 s.
    # Two people, one resident, since 0 s: 2 s later (tick 20) both dwell at the table: a visit
    # there (its centroid), at 19:00 local time.
    starts = [e for e in out if e.kind == "dwell_start"]
    assert [(e.track, e.frame, e.x, e.y) for e in starts] == [(1, 10, 1.5, 3.5), (2, 10, 2.5, 3.5)]
    assert starts[0].details == dict(hotspot="dinner table", label="dinner table", hotspot_kind="table", start_ns=0)
    (visit,) = [e for e in out if e.kind == "visit"]
    assert (visit.track, visit.frame) == (-1, 20)
    assert (visit.x, visit.y) == pytest.approx((2.0, 3.75))
    assert visit.details == dict(
        people=2, residents=1, since_ns=0, duration_s=2.0, reason="for dinner", local_time="19:00",
        hotspot="dinner table", hotspot_label="dinner table", hotspot_kind="table",
    )
    assert len(out) == 3
    # track 1 leaves at 2.5 s: its dwell ends, lost, 2.5 s after it began
    visits.lost(1, emitter(25, out))
    assert out[-1].kind == "dwell_end" and (out[-1].track, out[-1].x, out[-1].y) == (1, 1.5, 3.5)
    assert out[-1].details == dict(hotspot="dinner table", label="dinner table", hotspot_kind="table", start_ns=0,
                                   duration_s=2.5, reason="lost")
    visits.lost(1, emitter(26, out))  # no dwell left to end
    assert len(out) == 4


# --------------------------------------------------------------------------- inactivity


def test_inactivity_detector_hand_worked():
    params = InactivityParams(inactivity_s=5.0, window_s=2.0)
    ina = InactivityDetector(params, hotspots=[BED])
    out: list[Event] = []
    for k in range(121):
        # seated still at (1, 1) to 6 s, then standing up in place
        posture = "sitting" if k < 60 else "standing"
        ina.update(frame(k, posture=posture), emitter(k, out), on_floor=False)
    # The 2 s window is full at 2 s; still since its first sample (0 s) and the posture since 0 s:
    # 5 s still at 5 s (tick 50). Standing up at 6 s starts the clock again: 11 s (tick 110).
    assert [(e.kind, e.frame, e.details) for e in out] == [
        ("inactivity", 50, dict(still_since_ns=0, duration_s=5.0, posture="sitting", hotspot=None)),
        ("inactivity", 110, dict(still_since_ns=6_000_000_000, duration_s=5.0, posture="standing", hotspot=None)),
    ]
    # lying on the floor (a long lie's business) or still in bed is no inactivity
    for on_floor, xy in ((True, (1.0, 1.0)), (False, (4.0, 1.0))):
        ina, out = InactivityDetector(params, hotspots=[BED]), []
        for k in range(121):
            ina.update(frame(k, xy=xy, posture="lying"), emitter(k, out), on_floor=on_floor)
        assert out == []
