"""Ground truth: postures agree with geometry and events, files follow the documented formats."""

from __future__ import annotations

import json

import numpy as np
import pytest

from evaluation.io import read_truth_events, read_truth_meta, read_truth_tracks
from common.runfiles import TRACK_HEADER
from synth.scenarios import get_scenario, list_scenarios
from synth.truth import DWELL_WINDOW_S, derive_truth, visit_reason, write_truth


@pytest.fixture(scope="module")
def truths():
    return {name: derive_truth(get_scenario(name, 0)) for name in list_scenarios()}


def _posture(truth, person, frame):
    rows = truth.rows_at(frame)
    rows = rows[truth.person[rows] == person]
    return truth.posture[rows[0]] if rows.size else None


@pytest.mark.parametrize("name, direction", [("fall_forward", "forward"), ("fall_backward", "backward"),
                                             ("fall_sideways", "right")])
def test_falls_end_lying_low(truths, name, direction):
    tr = truths[name]
    (fall,) = tr.events_of("fall")
    assert fall.details["direction"] == direction
    assert _posture(tr, fall.track, fall.frame) == "lying"
    assert _posture(tr, fall.track, fall.frame - 1) == "standing"
    after = (tr.person == fall.track) & (tr.frame >= fall.frame)
    assert np.all(tr.posture[after] == "lying")
    assert tr.z_top[after].max() < 0.65
    before = (tr.person == fall.track) & (tr.frame < fall.frame - 15)
    assert tr.z_top[before].min() > 1.45


def test_postures_match_heights_in_every_scenario(truths):
    for name, tr in truths.items():
        # Frames within 1.5 s of a posture change are in between postures; the rest are held postures.
        steady = np.ones(len(tr.frame), dtype=bool)
        for pid in np.unique(tr.person):
            rows = np.nonzero(tr.person == pid)[0]
            change = tr.frame[rows][1:][tr.posture[rows][1:] != tr.posture[rows][:-1]]
            for f in change:
                steady[rows[np.abs(tr.frame[rows] - f) <= 22]] = False
        # The limits are an adult's; a child (never above 1.45 m) stands at their own height.
        child = np.zeros(len(tr.frame), dtype=bool)
        for pid in np.unique(tr.person):
            rows = tr.person == pid
            if tr.z_top[rows].max() < 1.45:
                child |= rows
                stand = rows & steady & (tr.posture == "standing")
                assert np.all(tr.z_top[stand] >= 0.95 * tr.z_top[rows].max()), (name, pid)
        limits = (("lying", 0.0, 0.7), ("sitting", 1.0, 1.6), ("standing", 1.45, 2.0), ("bending", 0.9, 1.8))
        for post, lo, hi in limits:
            m = (tr.posture == post) & steady & ~child
            if m.any():
                assert lo <= tr.z_top[m].min() and tr.z_top[m].max() <= hi, (name, post)
        # Held (non-transition) postures separate cleanly by height.
        sit = np.median(tr.z_top[tr.posture == "sitting"]) if (tr.posture == "sitting").any() else None
        stand = np.median(tr.z_top[tr.posture == "standing"]) if (tr.posture == "standing").any() else None
        if sit is not None and stand is not None:
            assert stand - sit > 0.25, name


def test_events_agree_with_postures_and_presence(truths):
    switches = {"sit_down": ("standing", "sitting"), "stand_up": (None, "standing"), "fall": ("standing", "lying")}
    for name, tr in truths.items():
        for ev in tr.events:
            assert tr.stamp_ns[0] <= ev.stamp_ns if len(tr.frame) else True
            if ev.kind in switches:
                before, after = switches[ev.kind]
                assert _posture(tr, ev.track, ev.frame) == after, (name, ev)
                prev = _posture(tr, ev.track, ev.frame - 1)
                assert prev != after and (before is None or prev == before), (name, ev, prev)
            if ev.kind == "enter":
                assert _posture(tr, ev.track, ev.frame) is not None and _posture(tr, ev.track, ev.frame - 1) is None
                assert ev.x < 1.0, name
            if ev.kind == "exit":
                assert _posture(tr, ev.track, ev.frame) is None and _posture(tr, ev.track, ev.frame - 1) is not None
            if ev.kind == "dwell_start":
                since = ev.details["since_frame"]
                assert ev.frame - since == round(DWELL_WINDOW_S * 15)
        starts = {(e.track, e.details["hotspot"], e.frame) for e in tr.events_of("dwell_start")}
        for end in tr.events_of("dwell_end"):
            assert any(t == end.track and h == end.details["hotspot"] and f < end.frame for t, h, f in starts)


def test_scenario_events_cover_the_library(truths):
    kinds = {e.kind for tr in truths.values() for e in tr.events}
    assert {"fall", "sit_down", "stand_up", "enter", "exit", "dwell_start", "dwell_end", "visit", "long_lie"} <= kinds
    tr = truths["enter_exit"]
    assert [e.kind for e in tr.events if e.kind in ("enter", "exit")] == ["enter", "exit"]
    assert not any(e.kind in ("fall",) for e in truths["bend_kneel"].events)
    assert "bending" in set(truths["bend_kneel"].posture)
    dwelt = {e.details["hotspot"] for e in truths["hotspot_dwell"].events_of("dwell_start")}
    assert dwelt == {"kitchen", "TV", "sofa", "dinner table"}


def test_dinner_visit_is_for_dinner(truths):
    (visit,) = truths["dinner_visit"].events_of("visit")
    assert visit.details["hotspot"] == "dinner table"
    assert visit.details["reason"] == "for dinner"
    assert visit.track == 2
    assert visit_reason("table", 12.5) == "for lunch" and visit_reason("sofa", 16.0) == "for tea"


def test_tracks_only_inside_the_volume_and_stamped(truths):
    sc = get_scenario("enter_exit")
    tr = truths["enter_exit"]
    assert np.all((tr.x >= 0) & (tr.x <= 8) & (tr.y >= 0) & (tr.y <= 6))
    assert np.all(tr.stamp_ns == sc.start_ns + np.round(tr.frame * 1e9 / sc.fps).astype(np.int64))
    assert tr.frame.min() > 0 and tr.frame.max() < sc.n_frames - 1


def test_truth_files_follow_the_documented_format(tmp_path):
    sc = get_scenario("dinner_visit")
    paths = write_truth(sc, tmp_path / "truth", n_frames=2000)
    lines = paths["tracks"].read_text().splitlines()
    assert lines[0] == TRACK_HEADER
    table = read_truth_tracks(tmp_path)
    events = read_truth_events(tmp_path)
    meta = read_truth_meta(tmp_path)
    assert meta.fps == 15.0 and meta.n_frames == 2000
    assert table.frame.max() < 2000 and set(table.posture) <= {"standing", "sitting", "lying", "bending"}
    raw = [json.loads(s) for s in paths["events"].read_text().splitlines()]
    assert all(list(r) == ["id", "kind", "track", "frame", "stamp_ns", "x", "y", "details"] for r in raw)
    assert all(r["id"] == f"{r['stamp_ns']}-{r['kind']}-{r['track']}" for r in raw)
    assert len(events) == len(raw) and all(e.frame < 2000 for e in events)
    assert {e.kind for e in events} >= {"enter", "sit_down", "dwell_start"}
