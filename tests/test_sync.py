"""Frame-set synchronisation against hand-worked stamps.

Most cases run at fps = 10: one frame period is 100 ms, so the default
tolerance is 50 ms and the default wait one period, 100 ms.
"""

from __future__ import annotations

import numpy as np
import pytest

from fusion_server.sync import COUNTER_NAMES, FrameSynchroniser

MS = 1_000_000


def make(**kw) -> FrameSynchroniser:
    kw.setdefault("camera_ids", ("a", "b", "c"))
    kw.setdefault("fps", 10.0)
    return FrameSynchroniser(**kw)


def test_defaults_follow_the_frame_rate():
    s = FrameSynchroniser(camera_ids=["a"], fps=15.0)
    assert s.tolerance_ns == 33_333_333  # half of 66.67 ms
    assert s.max_wait_ns == 66_666_667
    assert s.counters == {"a": dict.fromkeys(COUNTER_NAMES, 0)}


def test_complete_set_is_released_at_once():
    s = make()
    assert s.push("a", 1, 0, "A") == []
    assert s.push("b", 7, 10 * MS, "B") == []
    (fs,) = s.push("c", 3, -5 * MS, "C")
    assert fs.stamp_ns == 0  # the stamp of the frame that opened the set
    assert fs.payloads == {"a": "A", "b": "B", "c": "C"}
    assert fs.stamps_ns == {"a": 0, "b": 10 * MS, "c": -5 * MS}
    assert fs.seqs == {"a": 1, "b": 7, "c": 3}
    assert fs.complete and fs.missing == () and fs.cameras == ("a", "b", "c")
    assert s.pending == 0 and s.last_released_ns == 0
    assert all(s.counters[c]["released"] == 1 for c in "abc")


def test_silent_camera_does_not_hold_the_others_back():
    s = make()
    assert s.push("a", 1, 0, "a0") == []
    assert s.push("b", 1, 10 * MS, "b0") == []
    # 100 ms after the set's reference: not yet *beyond* the 100 ms wait.
    assert s.push("a", 2, 100 * MS, "a1") == []
    # 105 ms: the set at 0 leaves without c.
    (fs,) = s.push("b", 2, 105 * MS, "b1")
    assert fs.stamp_ns == 0 and fs.payloads == {"a": "a0", "b": "b0"}
    assert fs.missing == ("c",) and not fs.complete
    assert s.sets_partial == 1 and s.pending == 2
    # The set at 100 ms (a1, b1) leaves once a stamp beyond 200 ms arrives.
    (fs,) = s.push("a", 3, 201 * MS, "a2")
    assert fs.stamp_ns == 100 * MS and fs.payloads == {"a": "a1", "b": "b1"}


def test_complete_set_releases_older_partial_sets_first():
    s = make()
    assert s.push("a", 1, 0, "a0") == []
    assert s.push("a", 2, 100 * MS, "a1") == []  # exactly the wait: the set at 0 stays
    assert s.push("b", 2, 100 * MS, "b1") == []
    out = s.push("c", 2, 98 * MS, "c1")
    assert [fs.stamp_ns for fs in out] == [0, 100 * MS]
    assert out[0].payloads == {"a": "a0"} and out[0].missing == ("b", "c")
    assert out[1].complete


def test_duplicates_are_dropped_and_counted():
    s = make()
    s.push("a", 1, 0, "first")
    assert s.push("a", 1, 0, "again") == []  # same seq and stamp
    assert s.push("a", 2, 0, "same stamp") == []
    assert s.push("a", 1, 30 * MS, "same seq") == []
    assert s.counters["a"]["duplicate"] == 3 and s.counters["a"]["received"] == 4
    s.push("b", 1, 0, "b")
    (fs,) = s.push("c", 1, 0, "c")
    assert fs.payloads["a"] == "first"
    # A duplicate of a frame that already left is still a duplicate.
    assert s.push("a", 1, 0, "late copy") == []
    assert s.counters["a"]["duplicate"] == 4


def test_a_restarted_camera_numbering_from_zero_again_is_not_a_duplicate():
    s = make(camera_ids=("a",))
    for i in range(5):
        s.push("a", i, i * 100 * MS, None)
    out = [fs for i in range(5) for fs in s.push("a", i, (10 + i) * 100 * MS, None)]
    assert s.counters["a"]["duplicate"] == 0 and len(out) == 5


def test_frames_of_released_sets_are_out_of_order():
    s = make(camera_ids=("a", "b"))
    s.push("a", 1, 0, None)
    s.push("b", 1, 0, None)  # released, reference 0
    assert s.push("b", 9, 40 * MS, None) == []  # within the released set's window
    assert s.push("a", 0, -200 * MS, None) == []  # older than the released set
    assert s.counters["b"]["out_of_order"] == 1 and s.counters["a"]["out_of_order"] == 1
    # 51 ms is past the released window (0 + 50 ms): it opens a new set.
    assert s.push("b", 10, 51 * MS, None) == []
    assert s.pending == 1


def test_stale_frame_is_dropped():
    s = make(camera_ids=("a", "b"))
    assert s.push("a", 1, 1000 * MS, None) == []
    # Nothing released yet, but the newest stamp is 1 s ahead: beyond the 100 ms wait.
    assert s.push("b", 1, 0, None) == []
    assert s.counters["b"]["stale"] == 1 and s.pending == 1
    # 900 ms is exactly the wait behind the newest stamp: still accepted.
    assert s.push("b", 2, 900 * MS, None) == []
    assert s.pending == 2


def test_second_frame_of_a_camera_in_one_window_is_superseded():
    s = make(camera_ids=("a", "b"))
    s.push("a", 1, 0, "a-near")
    assert s.push("a", 2, 30 * MS, "a-far") == []  # farther from the reference: dropped
    assert s.counters["a"]["superseded"] == 1
    (fs,) = s.push("b", 1, 5 * MS, "b")
    assert fs.payloads == {"a": "a-near", "b": "b"}
    s = make()
    s.push("a", 3, 200 * MS, "x")
    s.push("b", 2, 240 * MS, "b-far")
    assert s.push("b", 3, 190 * MS, "b-near") == []  # nearer than the held frame: replaces it
    (fs,) = s.flush()
    assert fs.payloads == {"a": "x", "b": "b-near"} and s.counters["b"]["superseded"] == 1


def test_buffers_are_bounded():
    s = make(camera_ids=("a", "b"), max_buffer=2, max_wait_ns=10_000 * MS)
    for n in range(3):
        assert s.push("a", n, n * 100 * MS, n) == []
    assert s.counters["a"]["dropped_overflow"] == 1 and s.pending == 2
    out = s.push("b", 0, 200 * MS, "b")
    assert [(fs.stamp_ns, fs.payloads) for fs in out] == [(100 * MS, {"a": 1}), (200 * MS, {"a": 2, "b": "b"})]
    for n in range(100):
        s.push("a", 10 + n, (300 + 100 * n) * MS, n)
    assert s.pending == 2 and s.counters["a"]["dropped_overflow"] == 99


def test_phases_spread_over_the_period_still_make_complete_sets():
    s = make()
    assert s.push("a", 0, 0, "a0") == []  # the lattice anchor: references 0, 100, 200 ms ...
    assert s.push("b", 0, 40 * MS, "b0") == []  # nearest reference 0
    assert s.push("c", 0, 80 * MS, "c0") == []  # nearest reference 100
    assert s.push("a", 1, 100 * MS, "a1") == []
    out = s.push("b", 1, 140 * MS, "b1")
    assert [(fs.stamp_ns, fs.payloads) for fs in out] == [
        (0, {"a": "a0", "b": "b0"}),
        (100 * MS, {"a": "a1", "b": "b1", "c": "c0"}),
    ]
    assert s.push("c", 1, 180 * MS, "c1") == [] and s.push("a", 2, 200 * MS, "a2") == []
    (fs,) = s.push("b", 2, 240 * MS, "b2")
    assert fs.stamp_ns == 200 * MS and fs.complete
    assert s.reference_ns(1234 * MS) == 1200 * MS


def test_frame_between_references_is_unmatched_with_a_narrow_tolerance():
    s = make(tolerance_ns=20 * MS)
    s.push("a", 0, 0, None)
    assert s.push("b", 0, 30 * MS, None) == []
    assert s.push("c", 0, -50 * MS, None) == []
    assert s.counters["b"]["unmatched"] == 1 and s.counters["c"]["unmatched"] == 1 and s.pending == 1


def test_unknown_camera_and_flush():
    s = make()
    assert s.push("zz", 1, 0, None) == [] and s.unknown == 1
    s.push("a", 1, 0, "a")
    s.push("b", 1, 500 * MS, "b")  # releases the set at 0
    (fs,) = s.flush()
    assert fs.stamp_ns == 500 * MS and fs.missing == ("a", "c")
    assert s.flush() == []


@pytest.mark.parametrize("kw, name", [
    ({"camera_ids": []}, "camera_ids"),
    ({"camera_ids": ["a", "a"]}, "camera_ids"),
    ({"fps": 0}, "fps"),
    ({"tolerance_ns": -1}, "tolerance_ns"),
    ({"max_wait_ns": 1.5}, "max_wait_ns"),
    ({"max_buffer": 0}, "max_buffer"),
])
def test_bad_configuration_names_the_argument(kw, name):
    with pytest.raises(ValueError, match=name):
        make(**kw)


def test_jittered_free_running_cameras():
    """Four cameras at 15 fps with fixed phase offsets and 3 ms jitter, shuffled delivery
    within 20 ms, 5 % lost frames, 3 % duplicated, one camera silent for a second."""
    rng = np.random.default_rng(7)
    period = 1e9 / 15
    cams = ("c1", "c2", "c3", "c4")
    frames = []
    for ci, cam in enumerate(cams):
        phase = ci * period / 5
        for n in range(150):
            if cam == "c4" and 40 <= n < 55:
                continue  # silent
            if rng.random() < 0.05:
                continue  # lost
            stamp = int(phase + n * period + rng.normal(0, 3e6))
            arrival = stamp + rng.uniform(0, 20e6)
            frames.append((arrival, cam, n, stamp))
            if rng.random() < 0.03:
                frames.append((arrival + 1e6, cam, n, stamp))
    frames.sort()
    s = FrameSynchroniser(camera_ids=cams, fps=15.0)
    sets = []
    for _, cam, n, stamp in frames:
        sets.extend(s.push(cam, n, stamp, (cam, n)))
    sets.extend(s.flush())
    refs = [fs.stamp_ns for fs in sets]
    assert refs == sorted(refs) and len(set(refs)) == len(refs)
    seen = set()
    for fs in sets:
        for cam, (pc, n) in fs.payloads.items():
            assert pc == cam and (cam, n) not in seen
            seen.add((cam, n))
            assert abs(fs.stamps_ns[cam] - fs.stamp_ns) <= s.tolerance_ns
    # About one set per frame period, mostly complete; c4's silence gives partial sets.
    assert 145 <= len(sets) <= 155
    assert sum(fs.complete for fs in sets) >= 100
    assert any(fs.missing == ("c4",) for fs in sets)
    for cam in cams:
        c = s.counters[cam]
        dropped = sum(c[k] for k in ("duplicate", "out_of_order", "stale", "unmatched", "superseded", "dropped_overflow"))
        assert c["received"] == c["released"] + dropped
