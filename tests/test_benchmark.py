"""``voxelwatch bench``: the pipeline and looks sections on a tiny room (what they report, not how fast)."""

from __future__ import annotations

import pytest

from evaluation.benchmark import PIPELINE_ROWS, PipelineRow, _pipeline_table, bench_pipeline


def test_pipeline_section_tracks_the_people_it_places():
    row = PipelineRow(cameras=4, width=160, height=120, room_m=(4.0, 3.0), people=2)
    rows = bench_pipeline(True, rows=[row])

    assert len(rows) == 1
    r = rows[0]
    assert (r["cameras"], r["width"], r["height"], r["room_m"], r["people"]) == (4, 160, 120, [4.0, 3.0], 2)
    # the site file's default carving settings
    assert (r["voxel_sizes_m"], r["min_cameras"], r["min_ratio"], r["mask_scale"]) == ([0.4, 0.2, 0.1, 0.05], 2, 0.75, 1.0)
    assert r["frames"] == 30 and set(r["ms"]) == {"decode", "step", "total", "total_median"}
    assert r["fps"] > 0 and r["target_fps"] is None and r["met"] is None
    assert r["tracks_at_end"] == 2
    assert r["tracks_mean"] == 2.0
    assert "4  160x120" in _pipeline_table(rows)


def test_pipeline_rows_hold_the_speed_targets():
    targets = {(r.cameras, r.width, r.height, r.room_m, r.people): r.target_fps for r in PIPELINE_ROWS if r.target_fps}
    assert targets == {(5, 640, 480, (8.0, 6.0), 4): 60.0, (7, 960, 540, (12.0, 36.0), 20): 20.0}
    assert sorted(r.people for r in PIPELINE_ROWS if (r.cameras, r.room_m) == (5, (8.0, 6.0))) == [1, 4, 8]


def test_looks_section_measures_the_descriptor_budget_and_the_answer_time():
    from evaluation.benchmark import LOOK_BUDGET_B, _looks_table, bench_looks
    from fusion_server.identity import IdentityParams

    r = bench_looks(True, cameras=4, width=160, height=120, room_m=(4.0, 3.0), people=(2,), describe_people=3)

    assert r["rate_hz"] == IdentityParams().rate_hz
    (row,) = r["budget"]
    assert (row["cameras"], row["width"], row["height"], row["people"]) == (4, 160, 120, 2)
    # every person answered about rate_hz times a second in every camera, ~150 bytes each
    assert abs(row["answers_per_person_s_camera"] - r["rate_hz"]) < 0.5
    assert 100 < row["B_per_descriptor"] < 200
    assert row["B_per_person_s_camera"] == pytest.approx(row["answers_per_person_s_camera"] * row["B_per_descriptor"])
    assert row["met"] is True and row["budget_B"] == LOOK_BUDGET_B
    d = r["describe"]
    assert (d["people"], d["width"], d["height"]) == (3, 160, 120)
    assert 0 < d["ms"] < d["worker_total_ms"] and d["ms_per_person"] == pytest.approx(d["ms"] / 3)
    assert "B/person/s/camera" in _looks_table(r) and "for 3 people at 160x120" in _looks_table(r)
