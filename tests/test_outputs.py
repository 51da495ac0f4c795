"""Track and event output files: read back by the evaluation readers, safe against kills, appended on restart."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from evaluation.io import read_events, read_tracks
from common.messages import Event
from fusion_server.outputs import EVENTS_FILE, TRACKS_FILE, RunOutputs, TracksWriter
from fusion_server.pipeline import TrackOutput


def _track(tid: int, x: float, y: float, z: float = 1.7, posture: str = "standing") -> TrackOutput:
    return TrackOutput(id=tid, x=x, y=y, z_top=z, volume_m3=0.1, posture=posture, reliability=0.9,
                       vx=0.0, vy=0.0, still=False)


def _event(stamp_ns: int, kind: str = "fall", track: int = 1, **details) -> Event:
    return Event(id=f"{stamp_ns}-{kind}-{track}", kind=kind, track=track, stamp_ns=stamp_ns, frame=stamp_ns // 10,
                       x=1.25, y=2.5, details=details)


def test_round_trip_through_the_evaluation_readers(tmp_path: Path) -> None:
    with RunOutputs(tmp_path / "run") as out:
        assert out.write_frame(0, 1000, [_track(1, 1.0, 2.0), _track(2, 3.123456, 0.5, 1.2, "sitting")]) == 2
        assert out.write_frame(1, 2000, []) == 0
        assert out.write_frame(2, 3000, [_track(1, 1.1, 2.0, 0.4, "lying")]) == 1
        out.write_event(_event(3000, zone="sofa", duration_s=np.float64(12.5), n=np.int64(3)))
        out.write_event(_event(4000, "camera_lost", -1, camera="c1"))
    table = read_tracks(tmp_path / "run" / TRACKS_FILE)
    assert table.frame.tolist() == [0, 0, 2]
    assert table.track_id.tolist() == ["1", "2", "1"]
    assert table.x.tolist() == pytest.approx([1.0, 3.1235, 1.1])
    assert table.posture.tolist() == ["standing", "sitting", "lying"]
    events = read_events(tmp_path / "run" / EVENTS_FILE)
    assert [(e.kind, e.track, e.stamp_ns) for e in events] == [("fall", 1, 3000), ("camera_lost", -1, 4000)]
    assert events[0].details == {"zone": "sofa", "duration_s": 12.5, "n": 3}
    lines = (tmp_path / "run" / EVENTS_FILE).read_text().splitlines()
    assert Event.from_dict(json.loads(lines[0])) == _event(3000, zone="sofa", duration_s=12.5, n=3)


def test_restart_appends_after_the_last_complete_line(tmp_path: Path) -> None:
    with RunOutputs(tmp_path) as out:
        out.write_frame(0, 10, [_track(1, 1.0, 1.0)])
        out.write_event(_event(10))
    # a writer killed in mid-line leaves half a row behind
    with (tmp_path / TRACKS_FILE).open("a") as fh:
        fh.write("1,20,1,1.0")
    with (tmp_path / EVENTS_FILE).open("a") as fh:
        fh.write('{"id":"20-fall-1","ki')
    with RunOutputs(tmp_path) as out:
        out.write_frame(2, 30, [_track(1, 2.0, 2.0)])
        out.write_event(_event(30))
    text = (tmp_path / TRACKS_FILE).read_text()
    assert text.count("frame,stamp_ns") == 1
    assert read_tracks(tmp_path / TRACKS_FILE).frame.tolist() == [0, 2]
    assert [e.stamp_ns for e in read_events(tmp_path / EVENTS_FILE)] == [10, 30]


def test_a_foreign_csv_is_refused_with_its_name(tmp_path: Path) -> None:
    path = tmp_path / TRACKS_FILE
    path.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(ValueError, match=r"tracks\.csv.*header"):
        TracksWriter(path)
    assert path.read_text() == "a,b,c\n1,2,3\n"


def test_non_finite_tracks_are_left_out(tmp_path: Path) -> None:
    with RunOutputs(tmp_path) as out:
        assert out.write_frame(0, 1, [_track(1, math.nan, 1.0), _track(2, 1.0, 1.0)]) == 1
    assert read_tracks(tmp_path / TRACKS_FILE).track_id.tolist() == ["2"]


def test_a_killed_writer_loses_nothing_it_wrote(tmp_path: Path) -> None:
    script = textwrap.dedent(f"""
        import sys, time
        from fusion_server.outputs import RunOutputs
        from common.messages import Event
        from fusion_server.pipeline import TrackOutput
        out = RunOutputs({str(tmp_path)!r})
        for f in range(50):
            out.write_frame(f, f * 100, [TrackOutput(id=1, x=1.0, y=float(f), z_top=1.7, volume_m3=0.1,
                            posture="standing", reliability=1.0, vx=0.0, vy=0.0, still=False)])
            if f % 10 == 0:
                out.write_event(Event(id=str(f), kind="enter", track=1, stamp_ns=f * 100, frame=f,
                                            x=1.0, y=0.0, details={{}}))
        print("written", flush=True)
        time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "written"
    finally:
        proc.kill()
        proc.wait(timeout=10)
    assert read_tracks(tmp_path / TRACKS_FILE).frame.tolist() == list(range(50))
    assert [e.frame for e in read_events(tmp_path / EVENTS_FILE)] == [0, 10, 20, 30, 40]


def test_a_fresh_run_starts_both_files_anew(tmp_path):
    """Replaying twice into one folder must not double the rows (the server appends; a replay does not)."""
    from fusion_server.outputs import RunOutputs

    row = type("Row", (), {"id": 1, "x": 1.0, "y": 2.0, "z_top": 1.7, "posture": "standing"})()
    for _ in range(2):
        with RunOutputs(tmp_path, fresh=True) as out:
            out.write_frame(0, 0, [row])
            out.write_event({"id": "e1", "kind": "enter", "track": 1, "stamp_ns": 0, "frame": 0, "x": 1.0, "y": 2.0, "details": {}})
    assert (tmp_path / "tracks.csv").read_text().splitlines()[1:] == ["0,0,1,1.0000,2.0000,1.7000,standing,"]
    assert len((tmp_path / "events.jsonl").read_text().splitlines()) == 1
