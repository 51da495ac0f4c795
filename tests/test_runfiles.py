"""Run files: the tracks CSV and events JSON lines written byte for byte the same by every writer."""

from __future__ import annotations

import io as text_io
import math

import numpy as np

from common import runfiles
from evaluation import io
from common.messages import Event
from fusion_server.outputs import RunOutputs
from fusion_server.pipeline import TrackOutput


def test_track_rows_by_hand() -> None:
    buf = text_io.StringIO()
    n = runfiles.write_track_rows(buf, [(3, 1_000_000_000, 7, 1.23456, -0.5, np.float64(1.7), "standing"),
                                        (3, 1_000_000_000, "alice", 0.0, 2.0, 0.44444, "lying"),
                                        (4, 1_066_666_667, 1, 1.0, 1.0, 1.6, "sitting", "Ada Lovelace, née Byron"),
                                        (4, 1_066_666_667, 2, 3.0, 1.0, 1.7, "standing", None)])
    assert n == 4
    # person last: empty for anyone not enrolled, quoted when the name holds a comma
    assert buf.getvalue() == ("3,1000000000,7,1.2346,-0.5000,1.7000,standing,\n"
                              "3,1000000000,alice,0.0000,2.0000,0.4444,lying,\n"
                              '4,1066666667,1,1.0000,1.0000,1.6000,sitting,"Ada Lovelace, née Byron"\n'
                              "4,1066666667,2,3.0000,1.0000,1.7000,standing,\n")


def test_tracks_file_has_the_header_first(tmp_path) -> None:
    path = runfiles.write_tracks_file(tmp_path / "a" / runfiles.TRACKS_FILE, [(0, 5, 1, 1.0, 2.0, 1.5, "sitting")])
    assert path.read_text(encoding="utf-8") == "frame,stamp_ns,id,x,y,z_top,posture,person\n0,5,1,1.0000,2.0000,1.5000,sitting,\n"
    assert runfiles.TRACK_HEADER == ",".join(runfiles.TRACK_COLUMNS)
    assert runfiles.TRACK_COLUMNS[-1] == "person" and "person" not in runfiles.REQUIRED_TRACK_COLUMNS


def test_event_line_order_by_hand() -> None:
    obj = Event(id="e1", kind="fall", track=2, frame=10, stamp_ns=99, x=1.5, y=2.25,
                details={"n": 3, "seat": "canapé"}).to_dict()
    assert list(obj) == list(runfiles.EVENT_FIELDS)
    assert runfiles.event_line(obj) == (
        '{"id":"e1","kind":"fall","track":2,"frame":10,"stamp_ns":99,"x":1.5,"y":2.25,'
        '"details":{"n":3,"seat":"canapé"}}\n'
    )
    # numpy values are made plain and non-finite numbers null
    assert runfiles.event_line({"x": np.float32(2.25), "d": {"n": np.int64(3), "v": math.nan}}) == (
        '{"x":2.25,"d":{"n":3,"v":null}}\n'
    )


def test_live_and_evaluation_writers_write_the_same_bytes(tmp_path) -> None:
    with RunOutputs(tmp_path / "live") as out:
        out.write_frame(4, 400, [TrackOutput(id=2, x=1.0, y=2.123456, z_top=1.7, volume_m3=0.1, posture="bending",
                                             reliability=0.9, vx=0.0, vy=0.0, still=False)])
        out.write_event(Event(id="x", kind="fall", track=2, frame=4, stamp_ns=400, x=1.0, y=2.0,
                              details={"direction": "left"}))
    io.write_tracks(tmp_path / "eval" / runfiles.TRACKS_FILE, [(4, 400, "2", 1.0, 2.123456, 1.7, "bending")])
    io.write_events(tmp_path / "eval" / runfiles.EVENTS_FILE,
                    [Event(id="x", kind="fall", track=2, frame=4, stamp_ns=400, x=1.0, y=2.0, details={"direction": "left"})])
    for name in (runfiles.TRACKS_FILE, runfiles.EVENTS_FILE):
        assert (tmp_path / "live" / name).read_bytes() == (tmp_path / "eval" / name).read_bytes()


def test_a_named_track_reaches_the_file_and_the_reader(tmp_path) -> None:
    with RunOutputs(tmp_path / "live") as out:
        out.write_frame(4, 400, [
            TrackOutput(id=1, x=1.0, y=2.0, z_top=1.7, volume_m3=0.1, posture="standing", reliability=0.9,
                        vx=0.0, vy=0.0, still=False, person="Ada"),
            TrackOutput(id=2, x=3.0, y=2.0, z_top=1.6, volume_m3=0.1, posture="sitting", reliability=0.9,
                        vx=0.0, vy=0.0, still=True),
        ])
    path = tmp_path / "live" / runfiles.TRACKS_FILE
    assert path.read_text().splitlines() == ["frame,stamp_ns,id,x,y,z_top,posture,person",
                                             "4,400,1,1.0000,2.0000,1.7000,standing,Ada",
                                             "4,400,2,3.0000,2.0000,1.6000,sitting,"]
    table = io.read_tracks(path)
    assert table.person.tolist() == ["Ada", ""]
    assert list(table.rows())[0] == (4, 400, "1", 1.0, 2.0, 1.7, "standing")  # the old row layout
    back = io.read_tracks(io.write_tracks(tmp_path / "again.csv", table))
    assert back.person.tolist() == ["Ada", ""] and list(back.named_rows())[0][-1] == "Ada"
    assert table.take(np.array([1])).person.tolist() == [""]
