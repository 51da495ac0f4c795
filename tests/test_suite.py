"""The scenario suite, reduced: two short scenarios replayed and scored.

``voxelwatch eval --suite`` as a user runs it (a real process, which calls
:func:`evaluation.suite.run_suite`) with two camera counts: per count, one
table row per scenario and a total row from summed counts, and the same
figures written as JSON.

slow: the suite with an enrolled resident (``tests/test_enrolment.py`` names
the resident on the same house in the default run).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from evaluation.suite import cameras_for

VOXELWATCH = Path(sys.executable).with_name("voxelwatch")
SCENARIOS = ("walk", "two_pass")
FRAMES = 20


def table_rows(text: str) -> dict[str, list[str]]:
    """First cell -> cells of every table row in ``text`` (header and rules left out)."""
    rows = {}
    for line in text.splitlines():
        cells = line.split()
        if cells and cells[0] in (*SCENARIOS, "total"):
            rows[cells[0]] = cells
    return rows


def check_report(report: dict, counts: tuple[int, ...]) -> None:
    """The JSON report: per camera count, the cameras, every scenario's scores and the totals."""
    assert sorted(report) == sorted(f"{c}cam" for c in counts)
    for count in counts:
        part = report[f"{count}cam"]
        assert len(part["cameras"]) == count
        assert sorted(part["scenarios"]) == sorted(SCENARIOS)
        gt = 0
        for name in SCENARIOS:
            scores = part["scenarios"][name]
            assert scores["frames"]["count"] == FRAMES
            assert 0.0 <= scores["tracking"]["mota"] <= 1.0
            gt += scores["tracking"]["gt"]
        # walk: one person, two_pass: two people, every frame
        assert gt == 3 * FRAMES
        assert part["total"]["tracking"]["gt"] == gt


@pytest.mark.slow  # a long scenario replay; the default run keeps the others
def test_eval_suite_command_prints_a_row_per_scenario_and_writes_json(tmp_path):
    """Two camera counts: a table for each, one row per scenario and a total row."""
    if not VOXELWATCH.is_file():
        pytest.skip(f"the voxelwatch command is not installed beside {sys.executable}")
    out, report = tmp_path / "suite", tmp_path / "suite.json"
    done = subprocess.run(
        [str(VOXELWATCH), "eval", "--suite", "--scenarios", ",".join(SCENARIOS), "--frames", str(FRAMES),
         "--cameras", "5,3", "--out", str(out), "--json", str(report)],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert done.returncode == 0, done.stderr
    five, three = done.stdout.split("3 cameras (cam1, cam2, cam3)")
    assert "5 cameras (cam1, cam2, cam3, cam4, cam5)" in five
    for table in (five, three):
        rows = table_rows(table)
        assert sorted(rows) == sorted((*SCENARIOS, "total")), done.stdout
        for name in SCENARIOS:
            assert rows[name][1] == str(FRAMES)  # the frames column
        assert rows["total"][1] == str(2 * FRAMES)
    data = json.loads(report.read_text())
    check_report(data, (5, 3))
    # People walking in the first second and a half are found with five cameras.
    assert data["5cam"]["total"]["tracking"]["mota"] >= 0.8
    # The runs and the truth they were scored against stay in the working folder.
    for name in SCENARIOS:
        for count in (5, 3):
            assert (out / f"run-{count}cam" / name / "tracks.csv").is_file()
        assert (out / "truth" / name / "tracks.csv").is_file()


def test_cameras_for_keeps_opposite_corners_last():
    cams = ["cam1", "cam2", "cam3", "cam4", "cam5"]
    assert cameras_for(5, cams) == cams
    assert cameras_for(4, cams) == ["cam1", "cam2", "cam3", "cam4"]
    assert cameras_for(2, cams) == ["cam1", "cam3"]
    with pytest.raises(ValueError, match="camera count"):
        cameras_for(6, cams)


@pytest.mark.slow
def test_the_suite_scores_an_enrolled_resident(tmp_path):
    """With an enrolment (here a model of colours nobody in the house wears), the site of the
    suite enrols it and every scenario scores who carries the name."""
    from common.appearance import AppearanceModel
    from evaluation.suite import run_suite

    model = AppearanceModel()
    model.hist[:, 0] = 1.0
    model.frames[:] = 50
    model.height_m = 1.0
    enrolment = tmp_path / "nobody.json"
    enrolment.write_text(json.dumps({"name": "Nobody", **model.to_dict()}))
    import io

    report, stream = tmp_path / "suite.json", io.StringIO()
    run_suite(out_dir=tmp_path / "suite", scenarios=["two_pass"], max_frames=FRAMES, json_path=report,
              enrolled=enrolment, enrolled_person=2, stream=stream)
    table = stream.getvalue()
    assert "false res" in table and "res named" in table
    data = json.loads(report.read_text())["5cam"]
    res = data["scenarios"]["two_pass"]["resident"]
    assert (res["person"], res["name"]) == ("2", "Nobody")
    assert res["false_named"] == 0 and res["named_rows"] == 0 and res["resident_named"] == 0
    assert res["resident_matched"] > 0 and res["named_ratio"] == 0.0
    assert data["total"]["resident"]["resident_matched"] == res["resident_matched"]
    site = (tmp_path / "suite" / "site" / "site.toml").read_text()
    assert "[[enrolled]]" in site and str(enrolment.resolve()) in site


def test_a_bad_enrolment_stops_the_suite_before_any_replay(tmp_path):
    from evaluation.suite import run_suite

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"name": "Ada", "bands": ["head"]}))
    with pytest.raises(ValueError, match="bad.json: bands must be"):
        run_suite(out_dir=tmp_path / "suite", scenarios=["walk"], enrolled=bad)
    with pytest.raises(ValueError, match="no name"):
        bad.write_text("{}")
        run_suite(out_dir=tmp_path / "suite", scenarios=["walk"], enrolled=bad)
    assert not (tmp_path / "suite" / "run-5cam").exists()
