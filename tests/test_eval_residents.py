"""Scoring the name of an enrolled resident: worked by hand on tiny tables."""

from __future__ import annotations

import pytest

from evaluation import TrackTable, clear_mot, evaluate, format_table, suite_table, suite_totals, write_tracks
from evaluation.residents import resident_scores

NS = 66_666_667


def _tables() -> tuple[TrackTable, TrackTable]:
    """Truth: person 1 (the resident) at (0, 0) and person 2 at (3, 0), frames 0-3.
    Run: track 1 follows person 1, named Ada from frame 1 on (recognised a frame late);
    track 2 follows person 2, wrongly named Ada in frames 2 and 3; track 3, named Ada in
    frame 3, is 3 m from anybody."""
    truth = [(f, f * NS, p, x, 0.0, 1.7, "standing") for f in range(4) for p, x in (("1", 0.0), ("2", 3.0))]
    run = [(f, f * NS, "1", 0.1, 0.0, 1.7, "standing", "Ada" if f >= 1 else "") for f in range(4)]
    run += [(f, f * NS, "2", 3.0, 0.1, 1.7, "standing", "Ada" if f >= 2 else "") for f in range(4)]
    run += [(3, 3 * NS, "3", 6.0, 0.0, 1.7, "standing", "Ada")]
    return TrackTable.from_rows(truth), TrackTable.from_rows(run)


def test_false_resident_frames_and_the_named_share_by_hand():
    truth, run = _tables()
    res = resident_scores(truth, run, clear_mot(truth, run).pairs, person="1", name="Ada")
    assert res == {
        "person": "1", "name": "Ada",
        "named_rows": 6,          # 3 on track 1, 2 on track 2, 1 on track 3
        "false_named": 2,         # track 2 on person 2 in frames 2 and 3
        "named_unmatched": 1,     # track 3
        "resident_matched": 4,    # person 1 matched in every frame
        "resident_named": 3,      # ... named in frames 1-3
        "named_ratio": 0.75,
    }
    # a name nobody carries: nothing named, the resident never named
    other = resident_scores(truth, run, clear_mot(truth, run).pairs, person="1", name="Bob")
    assert (other["named_rows"], other["false_named"], other["named_ratio"]) == (0, 0, 0.0)
    # the resident absent from the truth: no share to give
    absent = resident_scores(truth, run, clear_mot(truth, run).pairs, person="9", name="Ada")
    assert absent["resident_matched"] == 0 and absent["named_ratio"] is None and absent["false_named"] == 5


def test_evaluate_the_suite_totals_and_table_carry_the_resident(tmp_path):
    truth, run = _tables()
    write_tracks(tmp_path / "truth" / "tracks.csv", [r[:7] for r in truth.rows()])  # truth without names
    write_tracks(tmp_path / "run" / "tracks.csv", run)
    (tmp_path / "run" / "events.jsonl").write_text("")
    result = evaluate(tmp_path / "truth", tmp_path / "run", resident=("1", "Ada"))
    assert result["resident"]["false_named"] == 2 and result["resident"]["named_ratio"] == pytest.approx(0.75)
    assert "enrolled resident Ada (truth person 1): named on 75.0% of their 4 matched frames; " \
           "someone else named 2 times" in format_table(result)
    assert "resident" not in evaluate(tmp_path / "truth", tmp_path / "run")
    total = suite_totals([result, result])
    assert (total["resident"]["false_named"], total["resident"]["resident_matched"]) == (4, 8)
    assert total["resident"]["named_ratio"] == pytest.approx(0.75)
    lines = suite_table({"a": result, "b": result}).splitlines()
    assert lines[0].split()[-4:] == ["false", "res", "res", "named"]
    assert lines[-1].split()[-2:] == ["4", "75.0%"]
    assert "false res" not in suite_table({"a": evaluate(tmp_path / "truth", tmp_path / "run")})
