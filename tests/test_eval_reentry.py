"""Identity across re-entries against a hand-worked case: kept, changed, never matched, too late."""

from __future__ import annotations

import json

import pytest

from evaluation import io
from evaluation.io import Event, TrackTable
from evaluation.reentry import reentry_identity
from evaluation.report import evaluate, format_table, suite_totals
from evaluation.tracking import clear_mot

FPS = 2.0  # the windows: 1 s before = 2 frames, 3 s after = 6 frames
NS = 500_000_000


def hand_case() -> tuple[list[tuple], list[tuple], list[Event]]:
    """Five people 5 m apart on the x axis, each in frames 0-4, exiting at frame 5 and back later.

    person 1 at x 0: run track 6 in frames 0-2, 7 in 3-4 (the last second before: 7); back at
    frame 10 with 8 in 10-11, 7 in 12-15, 8 in 16-19 (the first 3 s after: 7 four times to 8 twice)
    -> same id, though 6 and 8 win over the whole stay;
    person 2 at x 5: 20 before, back at 8 as 21 -> a new id;
    person 3 at x 10: 30 before, back at 8 and never matched -> not the same;
    person 4 at x 15: matched nowhere, back at 8 -> not the same;
    person 5 at x 20: back 1201 frames (600.5 s) later -> not a re-entry.
    """
    truth, run = [], []
    stay = {1: range(10, 20), 2: range(8, 20), 3: range(8, 20), 4: range(8, 20), 5: range(1206, 1208)}
    for pid in range(1, 6):
        for f in [*range(0, 5), *stay[pid]]:
            truth.append((f, f * NS, str(pid), 5.0 * (pid - 1), 0.0, 1.7, "standing"))
    tracks = {1: {**dict.fromkeys(range(0, 3), "6"), **dict.fromkeys(range(3, 5), "7"),
                  **dict.fromkeys([10, 11, 16, 17, 18, 19], "8"), **dict.fromkeys(range(12, 16), "7")},
              2: {**dict.fromkeys(range(0, 5), "20"), **dict.fromkeys(range(8, 20), "21")},
              3: dict.fromkeys(range(0, 5), "30"),
              5: {**dict.fromkeys(range(0, 5), "50"), **dict.fromkeys(range(1206, 1208), "50")}}
    for pid, by_frame in tracks.items():
        for f, tid in by_frame.items():
            run.append((f, f * NS, tid, 5.0 * (pid - 1) + 0.1, 0.0, 1.7, "standing"))
    events = []
    for pid in range(1, 6):
        back = stay[pid][0]
        events += [Event.from_dict(dict(kind="exit", frame=5, stamp_ns=5 * NS, track=pid, x=0.0, y=0.0)),
                   Event.from_dict(dict(kind="enter", frame=back, stamp_ns=back * NS, track=pid, x=0.0, y=0.0))]
    # a person arriving late enters without having left: no re-entry
    events.append(Event.from_dict(dict(kind="enter", frame=3, stamp_ns=3 * NS, track=9, x=0.0, y=0.0)))
    return truth, run, events


def test_reentries_keep_change_or_lose_their_id_as_worked_out_by_hand() -> None:
    truth_rows, run_rows, events = hand_case()
    truth, run = TrackTable.from_rows(truth_rows), TrackTable.from_rows(run_rows)
    result = reentry_identity(truth, run, clear_mot(truth, run).pairs, events, FPS)
    got = [(r.person, r.exit_frame, r.enter_frame, r.before, r.after, r.same_id) for r in result.reentries]
    assert got == [("1", 5, 10, "7", "7", True), ("2", 5, 8, "20", "21", False), ("3", 5, 8, "30", None, False),
                   ("4", 5, 8, None, None, False)]
    assert result.summary() == {"reentries": 4, "same_id": 1, "rate": 0.25, "within_s": 600.0, "before_s": 1.0,
                                "after_s": 3.0}
    # with whole stays as windows person 1 would have changed id (6 before, 8 after)
    wide = reentry_identity(truth, run, clear_mot(truth, run).pairs, events, FPS, before_s=10.0, after_s=10.0)
    assert [r.same_id for r in wide.reentries] == [False] * 4
    with pytest.raises(ValueError, match="fps"):
        reentry_identity(truth, run, clear_mot(truth, run).pairs, events, 0.0)


def test_evaluate_reports_the_reentries_and_the_suite_sums_them(tmp_path) -> None:
    truth_rows, run_rows, events = hand_case()
    tdir, run_dir = tmp_path / "truth", tmp_path / "run"
    io.write_tracks(tdir / "tracks.csv", truth_rows)
    io.write_events(tdir / "events.jsonl", events)
    (tdir / "meta.json").write_text(json.dumps({"fps": FPS, "n_frames": 1208}))
    io.write_tracks(run_dir / "tracks.csv", run_rows)
    io.write_events(run_dir / "events.jsonl", [])
    r = evaluate(tmp_path, run_dir)
    assert (r["identity"]["reentries"], r["identity"]["same_id"], r["identity"]["rate"]) == (4, 1, 0.25)
    assert "re-entries 4  same id 1  rate 25.0%" in format_table(r)
    total = suite_totals([r, r, {**r, "identity": None}])
    assert (total["identity"]["reentries"], total["identity"]["same_id"], total["identity"]["rate"]) == (8, 2, 0.25)
