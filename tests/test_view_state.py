"""The live view's core (:mod:`view.state`) and its access check, without zenoh or a browser."""

from __future__ import annotations

import pytest

from common.messages import CameraStatus, Event, Status, TrackFrame, TrackState, event_id
from view.server import Access, Client, clean_name
from view.state import GAP_NS, MAX_ALARMS, MAX_RECENT_EVENTS, LiveState

S = 1_000_000_000


def frame(i: int, stamp_s: float, *people) -> TrackFrame:
    return TrackFrame(frame=i, stamp_ns=int(stamp_s * S), cameras=["cam1"], tracks=[
        TrackState(id=tid, x=x, y=y, z_top=1.7, volume_m3=0.07, posture=posture, reliability=0.9, vx=0.0, vy=0.0,
                   still=False, person=name) for tid, x, y, posture, name in people])


def event(kind: str, stamp_s: float, track: int = 1, **details) -> Event:
    stamp = int(stamp_s * S)
    return Event(id=event_id(stamp, kind, track), kind=kind, track=track, stamp_ns=stamp, frame=0, x=1.0, y=2.0,
                 details=details)


def test_trails_keep_trail_s_of_positions_by_the_frames_own_stamps_and_forget_who_left():
    st = LiveState(alarm_kinds=["fall"], trail_s=2.0)
    for i in range(50):  # 5 s at 10 frames/s
        st.on_tracks(frame(i, i / 10, (1, i * 0.1, 0.0, "standing", "Ada")))
    trail = st.trail_lists()["1"]
    assert [p[0] for p in trail] == [int(i / 10 * S) for i in range(29, 50)]  # stamps 2.9 .. 4.9 s: 2 s back
    out = st.on_tracks(frame(50, 5.0))  # gone from view: the path stays until it is older than 2 s
    assert out["tracks"] == [] and [p[0] for p in st.trail_lists()["1"]] == [int(i / 10 * S) for i in range(30, 50)]
    st.on_tracks(frame(80, 8.0))
    assert st.trail_lists() == {}  # nobody seen for more than 2 s
    snap = st.snapshot()
    assert snap["frame"]["frame"] == 80 and snap["trails"] == {}


def test_a_frame_names_each_person_by_their_enrolled_name_or_track_id():
    st = LiveState(alarm_kinds=["fall"], trail_s=10.0)
    out = st.on_tracks(frame(0, 0.0, (1, 1.0, 2.0, "sitting", "Ada"), (7, 3.0, 4.0, "standing", None)))
    assert [(t["id"], t["label"], t["posture"], t["x"], t["y"]) for t in out["tracks"]] == [
        (1, "Ada", "sitting", 1.0, 2.0), (7, "#7", "standing", 3.0, 4.0)]


def test_an_alarm_waits_until_its_acknowledgement_and_each_event_counts_once():
    st = LiveState(alarm_kinds=["fall", "long_lie"], trail_s=10.0)
    fall = event("fall", 10.0)
    out = st.on_event(fall)
    assert [a["id"] for a in out["alarms"]] == [fall.id] and out["event"]["kind"] == "fall"
    assert st.on_event(fall) is None  # the same event again (history and live): once
    assert st.on_event(event("sit_down", 11.0))["alarms"] is None  # not an alarm kind: nothing changes
    ack = Event(id=f"{fall.id}-ack", kind="alarm_ack", track=1, stamp_ns=12 * S, frame=0, x=1.0, y=2.0,
                details={"event": fall.id, "alarm": "fall", "by": "Night nurse"})
    assert st.on_event(ack)["alarms"] == []
    # an acknowledgement heard before its alarm (history order): the alarm never shows
    late = event("long_lie", 40.0)
    st.on_event(Event(id=f"{late.id}-ack", kind="alarm_ack", track=1, stamp_ns=41 * S, frame=0, x=1.0, y=2.0,
                      details={"event": late.id, "alarm": "long_lie", "by": "view"}))
    assert st.on_event(late)["alarms"] is None and st.alarm_list() == []


def test_alarms_and_recent_events_stay_bounded():
    st = LiveState(alarm_kinds=["fall"], trail_s=10.0)
    for i in range(3 * MAX_ALARMS):
        st.on_event(event("fall", i, track=i))
    alarms = st.alarm_list()
    assert len(alarms) == MAX_ALARMS and alarms[-1]["track"] == 3 * MAX_ALARMS - 1  # the newest kept
    for i in range(3 * MAX_RECENT_EVENTS):
        st.on_event(event("sit_down", 1000 + i, track=i))
    assert len(st.snapshot()["recent"]) == MAX_RECENT_EVENTS


def test_the_timeline_has_posture_runs_dwells_and_marks_per_person():
    st = LiveState(alarm_kinds=["fall"], trail_s=10.0)
    for i in range(30):  # standing 0..1.4 s, sitting 1.5..2.9 s
        st.on_tracks(frame(i, i / 10, (1, 1.0, 1.0, "standing" if i < 15 else "sitting", None)))
    st.on_tracks(frame(100, 2.9 + GAP_NS / S + 1.0, (1, 1.0, 1.0, "sitting", None)))  # after a gap: a new run
    st.on_event(event("dwell_start", 2.0, hotspot="sofa", start_ns=int(1.6 * S)))
    st.on_event(event("dwell_end", 2.8, hotspot="sofa", start_ns=int(1.6 * S)))
    st.on_event(event("fall", 2.9))
    visit = Event(id="v", kind="visit", track=-1, stamp_ns=3 * S, frame=0, x=1.0, y=1.0, details={"people": 2})
    st.on_event(visit)
    tl = st.timeline()
    (p,) = tl["people"]
    assert p["label"] == "#1"
    gap_start = int((2.9 + GAP_NS / S + 1.0) * S)
    assert p["runs"] == [[0, int(1.5 * S), "standing"], [int(1.5 * S), int(2.9 * S), "sitting"],
                         [gap_start, gap_start, "sitting"]]
    assert p["dwells"] == [[int(1.6 * S), int(2.8 * S), "sofa"]]
    assert p["marks"] == [[int(2.9 * S), "fall"]]
    assert [v["id"] for v in tl["visits"]] == ["v"]


def test_status_keeps_every_cameras_fields_including_a_consistency_figure():
    st = LiveState(alarm_kinds=[], trail_s=1.0)
    cams = [CameraStatus(cam="cam1", state="ok", received=10, dropped=1, late=2, undecodable=0, rate_hz=15.0,
                         latency_ms=30.0, last_seen_ns=5, clock_offset_ms=1.0, consistency=0.93),
            CameraStatus(cam="cam2", state="stopped", received=0, dropped=0, late=0, undecodable=0, rate_hz=0.0,
                         latency_ms=0.0, last_seen_ns=0, clock_offset_ms=0.0)]
    out = st.on_status(Status(stamp_ns=9, cameras=cams, frame_sets=3, frame_sets_dropped=0))
    assert [(c["cam"], c["state"], c["consistency"]) for c in out["cameras"]] == [("cam1", "ok", 0.93),
                                                                                  ("cam2", "stopped", None)]


def test_a_slow_page_gets_only_the_newest_frame_and_a_bounded_event_queue():
    c = Client()
    for i in range(1000):
        c.frame = f"frame {i}"
        c.push_event(f"event {i}")
    due = c.pending()
    kinds = [k for k, _ in due]
    assert kinds.count("tracks") == 1 and ("tracks", "frame 999") in due
    assert kinds.count("event") == c.events.maxlen and ("event", "event 999") in due
    assert ("resync", '{"dropped": ' + str(1000 - c.events.maxlen) + "}") in due  # the page reloads its list
    assert c.pending() == []


def test_the_session_cookie_carries_the_name_and_is_bound_to_the_token():
    access = Access("correct horse battery")
    cookie = access.cookie_for("Night nurse")
    assert access.name_of(cookie) == "Night nurse"
    assert Access("another token here").name_of(cookie) is None  # a new token logs everyone out
    body, _, sig = cookie.rpartition(".")
    forged = Access("x" * 12).cookie_for("Mallory").split(".")[0] + "." + sig
    assert access.name_of(forged) is None and access.name_of("") is None and access.name_of("garbage") is None
    assert access.token_ok("correct horse battery") and not access.token_ok("correct horse batterx")
    assert not access.token_ok(None) and not access.token_ok("")
    with pytest.raises(ValueError):
        Access("")


def test_names_typed_at_login_lose_the_selector_separators():
    assert clean_name("Night nurse") == "Night nurse"
    assert clean_name("a;b=c&d?e#f/g*h$i") == "abcdefghi"
    assert clean_name("  ") == "view" and clean_name(None) == "view"
    assert len(clean_name("x" * 500)) == 64
