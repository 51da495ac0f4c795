"""Event scoring, evaluate() end to end, and the console and suite tables."""

from __future__ import annotations

import json

import numpy as np
import pytest

from evaluation import io
from evaluation.events import TrackLinks, score_events
from evaluation.io import Event, TrackTable
from evaluation.report import evaluate, format_table, suite_table, suite_totals, to_json

NS = 66_666_667  # one frame at 15 fps


def ev(kind: str, frame: int, track: int | None = 1, x: float | None = 1.0, y: float | None = 1.0, *, late_s: float = 0.0) -> Event:
    return Event.from_dict(dict(kind=kind, frame=frame, stamp_ns=frame * NS + int(late_s * 1e9), track=track, x=x, y=y))


def test_window_is_thirty_frames_inclusive() -> None:
    truth = [ev("fall", 100), ev("fall", 500)]
    run = [ev("fall", 130), ev("fall", 469)]  # +30 matches, -31 does not
    s = score_events(truth, run)
    k = s.per_kind["fall"]
    assert (k.tp, k.fp, k.fn) == (1, 1, 1)
    assert [p.truth.frame for p in s.pairs] == [100]


def test_matching_is_one_to_one_and_by_kind() -> None:
    # two run falls for one truth fall: one TP, one FP; a sit_down at the same frame is not a fall
    s = score_events([ev("fall", 100)], [ev("fall", 101), ev("fall", 102), ev("sit_down", 100)])
    assert (s.per_kind["fall"].tp, s.per_kind["fall"].fp) == (1, 1)
    assert (s.per_kind["sit_down"].truth, s.per_kind["sit_down"].fp) == (0, 1)
    assert s.per_kind["sit_down"].precision == 0.0 and s.per_kind["sit_down"].recall is None
    assert s.pairs[0].run.frame == 101  # the nearer one


def test_matching_is_optimal_not_greedy() -> None:
    # truth 100 and 130; run 115 (15 from both) and 75 (25 from 100, 55 from 130)
    # greedy nearest-first gives 100-115 and leaves 130 alone; the best one-to-one gives 100-75, 130-115
    s = score_events([ev("sit_down", 100), ev("sit_down", 130)], [ev("sit_down", 115), ev("sit_down", 75)])
    assert s.per_kind["sit_down"].tp == 2
    assert sorted((p.truth.frame, p.run.frame) for p in s.pairs) == [(100, 75), (130, 115)]


def test_position_gate_applies_to_enter_and_exit_only() -> None:
    truth = [ev("enter", 10, x=0.0, y=5.0), ev("exit", 300, x=0.0, y=5.0), ev("fall", 600, x=4.0, y=2.0)]
    run = [
        ev("enter", 12, x=2.0, y=5.0),  # 2 m away: not the same entry
        ev("exit", 305, x=0.8, y=5.0),  # 0.8 m: same exit
        ev("fall", 610, x=7.0, y=2.0),  # 3 m away, but falls carry no gate
    ]
    s = score_events(truth, run)
    assert (s.per_kind["enter"].tp, s.per_kind["exit"].tp, s.per_kind["fall"].tp) == (0, 1, 1)
    # with no gates at all the entry matches too
    assert score_events(truth, run, position_gate_m={}).per_kind["enter"].tp == 1
    # an event without a place sits at (0, 0), as on the wire: the gate applies to it like to any other
    assert score_events([ev("enter", 10, x=None, y=None)], [ev("enter", 11, x=0.3, y=0.0)]).per_kind["enter"].tp == 1
    assert score_events([ev("enter", 10, x=None, y=None)], [ev("enter", 11)]).per_kind["enter"].tp == 0


def test_track_requirement_uses_tracking_links() -> None:
    # truth person 21 was matched to run track 7 in frames 95..105, to track 8 from frame 200
    links = TrackLinks({("21", "7"): range(95, 106), ("21", "8"): range(200, 300)})
    truth = [ev("fall", 100, track=21), ev("fall", 250, track=21)]
    run = [ev("fall", 110, track=7), ev("fall", 255, track=7)]
    assert score_events(truth, run).per_kind["fall"].tp == 2
    strict = score_events(truth, run, track_links=links)
    assert strict.per_kind["fall"].tp == 1 and strict.track_required
    assert strict.pairs[0].truth.frame == 100


def test_track_links_from_matches() -> None:
    from evaluation.tracking import clear_mot

    truth = TrackTable.from_rows([(f, f * NS, "A", 0.0, 0.0, 1.7, "standing") for f in range(5)])
    run = TrackTable.from_rows([(f, f * NS, "7", 0.1, 0.0, 1.7, "standing") for f in range(3)])
    links = TrackLinks.from_matches(truth, run, clear_mot(truth, run).pairs)
    assert links.linked("A", "7", 2, 10) and not links.linked("A", "7", 3, 10) and not links.linked("A", "8", 0, 10)


def test_fall_delays_false_alarms_and_unscored_kinds() -> None:
    truth = [ev("fall", 100), ev("fall", 1000), ev("sit_down", 2000)]
    run = [
        ev("fall", 110, late_s=0.25),  # 10 frames + 0.25 s late: 10/15 + 0.25 s
        ev("fall", 995),  # 5 frames early
        ev("fall", 5000), ev("long_lie", 6000),  # two false alarms
        ev("sit_down", 9000),  # a wrong sit-down is an FP but no alarm
        ev("camera_lost", 50),
    ]
    s = score_events(truth, run)
    delays = s.delays_s("fall")
    assert delays[0] == pytest.approx((10 * NS) / 1e9 + 0.25, abs=1e-9)
    assert delays[1] == pytest.approx(-5 * NS / 1e9, abs=1e-9)
    assert s.false_alarms() == 2
    assert s.unscored_run == 1 and "camera_lost" not in s.per_kind
    summary = s.summary(duration_s=1800.0)  # half an hour: 2 false alarms = 4 per hour
    assert summary["false_alarms_per_hour"] == pytest.approx(4.0)
    assert summary["fall_delay_max_s"] == pytest.approx(delays[0])
    # scored run events: 2 found falls + fall 5000, long_lie, sit_down 9000 = 3 FP; truth sit_down 2000 = 1 FN
    assert (summary["overall"]["tp"], summary["overall"]["fp"], summary["overall"]["fn"]) == (2, 3, 1)
    assert s.summary(duration_s=None)["false_alarms_per_hour"] is None


def test_f1_and_undefined_ratios() -> None:
    s = score_events([ev("fall", 10), ev("fall", 500)], [])
    k = s.per_kind["fall"]
    assert (k.precision, k.recall, k.f1) == (None, 0.0, 0.0)
    assert s.per_kind["visit"].f1 is None  # nothing to find, nothing found
    s = score_events([ev("fall", 10), ev("fall", 500)], [ev("fall", 12), ev("fall", 900), ev("fall", 1500)])
    # tp 1, fp 2, fn 1: P 1/3, R 1/2, F1 2/(2+2+1) = 0.4
    k = s.per_kind["fall"]
    assert k.precision == pytest.approx(1 / 3) and k.recall == pytest.approx(0.5) and k.f1 == pytest.approx(0.4)


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="window_frames"):
        score_events([], [], window_frames=-1)
    with pytest.raises(ValueError, match=r"position_gate_m\['enter'\]"):
        score_events([], [], position_gate_m={"enter": 0})


def test_long_recordings_split_into_small_problems() -> None:
    # 3000 falls spaced 100 frames apart, each detected 5 frames late: all matched, quickly and exactly
    truth = [ev("fall", 100 * k) for k in range(3000)]
    run = [ev("fall", 100 * k + 5) for k in range(3000)]
    s = score_events(truth, run)
    assert s.per_kind["fall"].tp == 3000
    assert all(p.frame_offset == 5 for p in s.pairs)


# ---------------------------------------------------------------- evaluate() end to end


def write_scenario(root, *, falls_truth: list[int], falls_run: list[int], fps: float | None = 15.0, n_frames: int = 900,
                   flat: bool = False) -> tuple:
    """One person 21 standing at (2, 2); the run follows as track 5, 0.1 m off, and says sitting in 20 frames."""
    truth_dir, run_dir = root / "truth_root", root / "run"
    tdir = truth_dir if flat else truth_dir / "truth"
    truth_rows, run_rows = [], []
    for f in range(100, 200):
        truth_rows.append((f, f * NS, "21", 2.0, 2.0, 1.7, "bending" if f < 110 else "standing"))
        run_rows.append((f, f * NS, "5", 2.1, 2.0, 1.7, "sitting" if f >= 180 else "standing"))
    io.write_tracks(tdir / "tracks.csv", truth_rows)
    io.write_tracks(run_dir / "tracks.csv", run_rows)
    io.write_events(tdir / "events.jsonl", [ev("fall", f, track=21) for f in falls_truth])
    io.write_events(run_dir / "events.jsonl", [ev("fall", f, track=5) for f in falls_run])
    if fps is not None:
        (tdir / "meta.json").write_text(json.dumps({"fps": fps, "n_frames": n_frames}))
    return truth_dir, run_dir


@pytest.mark.parametrize("origin_s, shifted", [(0.0, False), (0.4, False), (1_709_650_000.0, True)])
def test_a_run_on_another_clock_is_brought_to_the_truth_clock_for_delays(tmp_path, origin_s, shifted) -> None:
    # a run stamped with the date of its recording; the truth frame f at f / fps (or the other way round)
    truth_dir, run_dir = write_scenario(tmp_path, falls_truth=[150], falls_run=[160])
    off = int(origin_s * 1e9)
    rows = [(f, f * NS + off, "5", 2.1, 2.0, 1.7, "standing") for f in range(100, 200)]
    io.write_tracks(run_dir / "tracks.csv", rows)
    io.write_events(run_dir / "events.jsonl", [ev("fall", 160, track=5).model_copy(update={"stamp_ns": 160 * NS + off})])
    r = evaluate(truth_dir, run_dir)
    # ten frames late, on the truth's clock; a small offset (a live run's clocks) is left alone
    expected = 10 * NS / 1e9 + (0.0 if shifted else origin_s)
    assert r["events"]["fall_delays_s"] == [pytest.approx(expected, abs=1e-6)]
    assert any("clock differs" in n for n in r["notes"]) == shifted


def test_evaluate_end_to_end(tmp_path) -> None:
    truth_dir, run_dir = write_scenario(tmp_path, falls_truth=[150], falls_run=[160, 700])
    r = evaluate(truth_dir, run_dir)
    assert r["frames"] == {"first": 0, "last": 899, "count": 900}
    assert (r["fps"], r["fps_source"], r["duration_s"]) == (15.0, "meta.json", 60.0)
    t = r["tracking"]
    assert (t["gt"], t["matches"], t["mota"], t["idf1"]) == (100, 100, 1.0, 1.0)
    assert t["motp_m"] == pytest.approx(0.1, abs=1e-9)
    assert r["per_frame"]["mtpf"] == 0.0 and r["per_frame"]["frames"] == 900
    fall = r["events"]["per_kind"]["fall"]
    assert (fall["tp"], fall["fp"], fall["fn"]) == (1, 1, 0)
    assert r["events"]["fall_delays_s"] == [pytest.approx(10 * NS / 1e9)]
    # one false fall in 60 s = 60 per hour
    assert r["events"]["false_alarms_per_hour"] == pytest.approx(60.0)
    # posture: 100 pairs; truth bending 10 (run standing), standing 90 of which run says sitting in 20
    # strict: 70 right; lenient (bending = standing): 80 right
    p = r["posture"]
    assert (p["scored"], p["strict_correct"], p["lenient_correct"]) == (100, 70, 80)
    json.loads(to_json(r))  # plain JSON
    text = format_table(r)
    for needle in ("MOTA", "IDF1", "MOTME", "fall", "strict 70.0%", "lenient (bending = standing) 80.0%"):
        assert needle in text


def test_evaluate_frame_rate_from_stamps_and_argument(tmp_path) -> None:
    truth_dir, run_dir = write_scenario(tmp_path, falls_truth=[], falls_run=[], fps=None, flat=True)
    r = evaluate(truth_dir, run_dir)
    assert r["fps_source"] == "truth stamps" and r["fps"] == pytest.approx(15.0, rel=1e-6)
    assert r["frames"] == {"first": 100, "last": 199, "count": 100}
    r = evaluate(truth_dir, run_dir, fps=30.0, n_frames=400)
    assert (r["fps"], r["fps_source"], r["duration_s"]) == (30.0, "argument", 400 / 30.0)


def test_evaluate_without_truth_events_skips_event_scoring(tmp_path) -> None:
    truth_dir, run_dir = write_scenario(tmp_path, falls_truth=[], falls_run=[])
    (truth_dir / "truth" / "events.jsonl").unlink()
    (run_dir / "events.jsonl").unlink()
    r = evaluate(truth_dir, run_dir)
    assert r["events"] is None and any("not scored" in n for n in r["notes"])


def test_evaluate_needs_run_events_when_truth_has_them(tmp_path) -> None:
    truth_dir, run_dir = write_scenario(tmp_path, falls_truth=[150], falls_run=[])
    (run_dir / "events.jsonl").unlink()
    with pytest.raises(io.EvalFormatError, match="events.jsonl"):
        evaluate(truth_dir, run_dir)


def test_evaluate_widens_range_for_rows_beyond_n_frames(tmp_path) -> None:
    truth_dir, run_dir = write_scenario(tmp_path, falls_truth=[], falls_run=[], n_frames=150)
    r = evaluate(truth_dir, run_dir)
    assert r["frames"] == {"first": 0, "last": 199, "count": 200}
    assert any("widened" in n for n in r["notes"])


def test_suite_totals_sum_counts_not_ratios(tmp_path) -> None:
    # scenario a: 3 falls all found (recall 1); scenario b: 1 fall missed (recall 0)
    # total recall = 3/4, not the mean 0.5; precision a 3/3, b undefined -> total 3/3
    a = evaluate(*write_scenario(tmp_path / "a", falls_truth=[120, 400, 800], falls_run=[121, 401, 801]))
    b = evaluate(*write_scenario(tmp_path / "b", falls_truth=[150], falls_run=[]))
    total = suite_totals([a, b])
    fall = total["events"]["per_kind"]["fall"]
    assert (fall["tp"], fall["fn"], fall["recall"], fall["precision"]) == (3, 1, 0.75, 1.0)
    assert total["duration_s"] == 120.0 and total["frames"]["count"] == 1800
    assert total["posture"]["strict_accuracy"] == pytest.approx(140 / 200)
    text = suite_table({"a": a, "b": b})
    lines = text.splitlines()
    assert lines[0].split()[0] == "scenario" and lines[-1].split()[0] == "total"
    assert "75.0%" in lines[-1]  # the pooled fall recall
    assert np.array(total["posture"]["confusion"]).sum() == 200
