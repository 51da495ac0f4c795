"""Track and event files: round trips, folder layouts, and errors that name file, line and field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from evaluation import io
from evaluation.io import EvalFormatError, Event, TrackTable
from evaluation.report import evaluate

HEADER = "frame,stamp_ns,id,x,y,z_top,posture\n"


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def test_tracks_round_trip_sorted(tmp_path) -> None:
    rows = [
        (2, 200, "b", 1.25, 2.5, 1.7, "standing"),
        (1, 100, "a", 0.0, -1.0, 0.4, "lying"),
        (2, 200, "a", 3.0, 4.0, 1.2, "sitting"),
    ]
    path = io.write_tracks(tmp_path / "run" / "tracks.csv", rows)
    assert path.read_text().splitlines()[0] == "frame,stamp_ns,id,x,y,z_top,posture,person"
    t = io.read_tracks(path)
    assert list(t.rows()) == sorted(rows, key=lambda r: (r[0], r[2]))
    assert t.xy_m.shape == (3, 2) and t.frame.dtype == np.int64
    assert t.fps_from_stamps() == pytest.approx(1e9 / 100)


def test_tracks_header_only_and_extra_columns(tmp_path) -> None:
    assert len(io.read_tracks(write(tmp_path / "a.csv", HEADER))) == 0
    # columns in another order plus an extra one are accepted
    t = io.read_tracks(write(tmp_path / "b.csv", "id,posture,frame,stamp_ns,x,y,z_top,reliability\n7,sitting,3,30,1,2,1.1,0.9\n"))
    assert list(t.rows()) == [(3, 30, "7", 1.0, 2.0, 1.1, "sitting")]


def test_tracks_without_a_person_column_read_as_nobody_named(tmp_path) -> None:
    # ground truth and runs written before the person column
    t = io.read_tracks(write(tmp_path / "old.csv", HEADER + "0,0,a,1,1,1.7,standing\n0,0,b,2,1,1.6,sitting\n"))
    assert t.person.tolist() == ["", ""]
    # the column anywhere, found by its header
    t = io.read_tracks(write(tmp_path / "new.csv", "person,frame,stamp_ns,id,x,y,z_top,posture\n"
                                                   "Ada,0,0,1,1,1,1.7,standing\n,0,0,2,2,1,1.6,sitting\n"))
    assert t.person.tolist() == ["Ada", ""] and t.track_id.tolist() == ["1", "2"]


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ("0,0,a,1.0,zz,1.7,standing\n", "line 2, field y: expected a number"),
        ("0,0,a,1.0,2.0,1.7,standing\n1,1,a,nan,2.0,1.7,standing\n", "line 3, field x: must be finite"),
        ("0,0,a,1.0,2.0,1.7,crouching\n", "line 2, field posture: 'crouching' is not one of"),
        ("-1,0,a,1.0,2.0,1.7,standing\n", "line 2, field frame: must be >= 0"),
        ("0.5,0,a,1.0,2.0,1.7,standing\n", "line 2, field frame: expected an integer"),
        ("0,0,,1.0,2.0,1.7,standing\n", "line 2, field id: empty"),
        ("0,0,a,1.0,2.0,1.7\n", "line 2: 6 fields, the header has 7"),
        ("0,0,a,1,2,1.7,standing\n\n0,0,a,1,2,1.7,standing\n", "line 4, field id: track a appears twice in frame 0 (first on line 2)"),
    ],
)
def test_track_errors_name_file_line_and_field(tmp_path, body: str, needle: str) -> None:
    path = write(tmp_path / "tracks.csv", HEADER + body)
    with pytest.raises(EvalFormatError) as err:
        io.read_tracks(path)
    assert str(path) in str(err.value) and needle in str(err.value)


def test_track_header_errors(tmp_path) -> None:
    with pytest.raises(EvalFormatError, match="empty, expected the header"):
        io.read_tracks(write(tmp_path / "e.csv", ""))
    with pytest.raises(EvalFormatError, match=r"line 1: header lacks \['z_top', 'posture'\]"):
        io.read_tracks(write(tmp_path / "h.csv", "frame,stamp_ns,id,x,y\n"))
    with pytest.raises(EvalFormatError, match="not found"):
        io.read_tracks(tmp_path / "missing.csv")
    with pytest.raises(EvalFormatError, match="not UTF-8"):
        (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00")
        io.read_tracks(tmp_path / "bin.csv")


def test_events_round_trip(tmp_path) -> None:
    events = [
        Event(kind="fall", frame=40, stamp_ns=4000, track=3, x=1.5, y=2.0, details={"from": "standing"}, id="e2"),
        Event.from_dict(dict(kind="enter", frame=10, stamp_ns=1000, track=3, x=0.2, y=5.0)),
        Event.from_dict(dict(kind="visit", frame=20, stamp_ns=2000)),
        Event.from_dict(dict(kind="camera_lost", frame=30, stamp_ns=3000, details={"camera": "cam2"})),
    ]
    path = io.write_events(tmp_path / "events.jsonl", events)
    back = io.read_events(path)
    assert [e.frame for e in back] == [10, 20, 30, 40]
    assert back == [events[1], events[2], events[3], events[0]]
    assert back[0].id == "1000-enter-3" and (back[1].track, back[1].x, back[1].y) == (-1, 0.0, 0.0)


def test_events_accept_tracks_as_numbers_or_their_text_and_blank_lines(tmp_path) -> None:
    text = ('\n{"kind": "fall", "track": 7, "frame": 3, "stamp_ns": 300, "x": 1, "y": 2, "details": {}}\n\n'
            '{"kind": "fall", "track": "8", "frame": 4, "stamp_ns": 400, "x": 1, "y": 2}\n')
    first, second = io.read_events(write(tmp_path / "events.jsonl", text))
    assert (first.track, first.x, first.frame, second.track) == (7, 1.0, 3, 8)


@pytest.mark.parametrize(
    ("line", "needle"),
    [
        ('{"kind": "fall", "frame": 3', "line 2: not valid JSON"),
        ('{"frame": 3, "stamp_ns": 1}', "line 2, field kind: required field is missing"),
        ('{"kind": "fall", "frame": -2, "stamp_ns": 1}', "line 2, field frame: must be >= 0"),
        ('{"kind": "fall", "frame": "3", "stamp_ns": 1}', "line 2, field frame: expected an integer"),
        ('{"kind": "fall", "frame": 3, "stamp_ns": 1, "x": 1.0}', "line 2, fields x/y: give both or neither"),
        ('{"kind": "fall", "frame": 3, "stamp_ns": 1, "x": "a", "y": 1}', "line 2, field x: expected a finite number"),
        ('{"kind": "fall", "frame": 3, "stamp_ns": 1, "track": [1]}', "line 2, field track"),
        ('{"kind": "fall", "frame": 3, "stamp_ns": 1, "details": 5}', "line 2, field details: expected an object"),
        ('[1, 2]', "line 2: expected a JSON object"),
    ],
)
def test_event_errors_name_file_line_and_field(tmp_path, line: str, needle: str) -> None:
    good = '{"kind": "enter", "frame": 1, "stamp_ns": 1}'
    path = write(tmp_path / "events.jsonl", good + "\n" + line + "\n")
    with pytest.raises(EvalFormatError) as err:
        io.read_events(path)
    assert str(path) in str(err.value) and needle in str(err.value)


def test_meta(tmp_path) -> None:
    meta = io.read_meta(write(tmp_path / "meta.json", '{"fps": 15, "n_frames": 900, "scenario": "fall"}'))
    assert (meta.fps, meta.n_frames) == (15.0, 900)
    assert io.read_meta(write(tmp_path / "m2.json", "{}")) == io.Meta()
    with pytest.raises(EvalFormatError, match="field fps: expected a positive number"):
        io.read_meta(write(tmp_path / "m3.json", '{"fps": 0}'))
    with pytest.raises(EvalFormatError, match="field n_frames: expected an integer"):
        io.read_meta(write(tmp_path / "m4.json", '{"n_frames": 1.5}'))
    with pytest.raises(EvalFormatError, match="not valid JSON"):
        io.read_meta(write(tmp_path / "m5.json", "{fps"))


def test_truth_folder_layouts(tmp_path) -> None:
    nested, flat = tmp_path / "nested", tmp_path / "flat"
    write(nested / "truth" / "tracks.csv", HEADER + "0,0,a,1,1,1.7,standing\n")
    write(flat / "tracks.csv", HEADER + "0,0,b,1,1,1.7,standing\n")
    assert io.read_truth_tracks(nested).track_id.tolist() == ["a"]
    assert io.read_truth_tracks(flat).track_id.tolist() == ["b"]
    assert io.read_truth_events(flat) is None and io.read_truth_meta(flat) == io.Meta()
    with pytest.raises(EvalFormatError, match="truth folder .*: no tracks.csv"):
        io.read_truth_tracks(tmp_path / "nothing")
    with pytest.raises(EvalFormatError, match="run folder .*: no tracks.csv"):
        evaluate(nested, tmp_path / "no-run")


def test_evaluate_reports_the_bad_line(tmp_path) -> None:
    write(tmp_path / "t" / "tracks.csv", HEADER + "0,0,a,1,1,1.7,standing\n")
    write(tmp_path / "r" / "tracks.csv", HEADER + "0,0,1,1,1,1.7,standing\n1,1,1,1,oops,1.7,standing\n")
    with pytest.raises(EvalFormatError, match=r"r/tracks.csv, line 3, field y"):
        evaluate(tmp_path / "t", tmp_path / "r")


def test_table_constructors() -> None:
    assert len(TrackTable.empty()) == 0 and TrackTable.empty().xy_m.shape == (0, 2)
    t = TrackTable.from_rows([(5, 0, 12, 1, 2, 1.7, "standing")])
    assert t.track_id.tolist() == ["12"] and t.fps_from_stamps() is None
    assert json.loads(Event.from_dict(dict(kind="fall", frame=1, stamp_ns=2)).to_json())["kind"] == "fall"
