"""``voxelwatch replay`` as a user runs it: a real process over recorded inputs.

The inputs come from ``voxelwatch synth`` (the synthetic house rendered to
per-camera videos, with the empty room before and the true silhouettes):
per-camera videos, the same frames as image folders, and recorded mask
folders. Each replay must write ``tracks.csv`` and ``events.jsonl`` that
follow the one person of the scenario; a missing input gives one clear
message and a non-zero exit.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from evaluation import read_events, read_tracks
from synth import derive_truth, get_scenario

VOXELWATCH = Path(sys.executable).with_name("voxelwatch")
SCENARIO = "walk"
FRAMES = 24
"""Frame sets rendered and replayed (1.6 s of someone walking through the room's middle)."""
CONFIRMED_BY = 5
"""Frames a new track needs before it is reported (the tracker confirms on the third match)."""
POSITION_TOLERANCE_M = {"videos": 0.2, "images": 0.2, "masks": 0.15}
"""Largest floor distance between the replayed track and the true person."""


def voxelwatch(*args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess:
    if not VOXELWATCH.is_file():
        pytest.skip(f"the voxelwatch command is not installed beside {sys.executable}")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [str(VOXELWATCH), *args], capture_output=True, text=True, timeout=timeout_s, env=env, check=False
    )


@pytest.fixture(scope="module")
def house(tmp_path_factory) -> Path:
    """``voxelwatch synth --frames N --masks``: site, calibrations, videos, masks, truth."""
    out = tmp_path_factory.mktemp("house")
    done = voxelwatch("synth", "--scenario", SCENARIO, "--frames", str(FRAMES), "--masks", "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert f"{FRAMES} frames of 5 cameras" in done.stdout
    return out


@pytest.fixture(scope="module")
def cache(lut_cache) -> Path:
    return lut_cache


@pytest.fixture(scope="module")
def inputs(house, tmp_path_factory) -> dict[str, Path]:
    """Three replay input folders from the same rendering.

    videos: ``<cam>/video.avi`` and ``<cam>/background.avi``;
    images: ``<cam>/000000.png ...`` (the video's frames) beside ``<cam>/background.avi``;
    masks: ``<cam>/masks/000000.png ...`` only.
    """
    root = tmp_path_factory.mktemp("inputs")
    folders = {kind: root / kind for kind in ("videos", "images", "masks")}
    for cam_dir in sorted(p for p in house.iterdir() if (p / "video.avi").is_file()):
        cam = cam_dir.name
        for kind in ("videos", "images"):
            (folders[kind] / cam).mkdir(parents=True)
            shutil.copy(cam_dir / "background.avi", folders[kind] / cam / "background.avi")
        shutil.copy(cam_dir / "video.avi", folders["videos"] / cam / "video.avi")
        shutil.copytree(cam_dir / "masks", folders["masks"] / cam / "masks")
        cap = cv2.VideoCapture(str(cam_dir / "video.avi"))
        n = 0
        while True:
            ok, image = cap.read()
            if not ok:
                break
            cv2.imwrite(str(folders["images"] / cam / f"{n:06d}.png"), image)
            n += 1
        cap.release()
        assert n == FRAMES, f"{cam_dir / 'video.avi'}: {n} frames"
    return folders


def check_run(run: Path, tolerance_m: float) -> None:
    """One track follows the true person from frame CONFIRMED_BY on; no event."""
    assert (run / "tracks.csv").is_file() and (run / "events.jsonl").is_file()
    tracks = read_tracks(run / "tracks.csv")
    truth = derive_truth(get_scenario(SCENARIO, 0))
    assert read_events(run / "events.jsonl") == []
    assert set(tracks.frame.tolist()) <= set(range(FRAMES))
    for frame in range(CONFIRMED_BY, FRAMES):
        rows = np.flatnonzero(tracks.frame == frame)
        assert len(rows) == 1, f"frame {frame}: {len(rows)} tracks"
        t = truth.rows_at(frame)
        error = np.hypot(tracks.x[rows[0]] - truth.x[t[0]], tracks.y[rows[0]] - truth.y[t[0]])
        assert error <= tolerance_m, f"frame {frame}: {error:.2f} m from the person"
    assert len(set(tracks.track_id.tolist())) == 1


@pytest.mark.parametrize("kind", [pytest.param("videos", marks=pytest.mark.slow),
                                  pytest.param("images", marks=pytest.mark.slow), "masks"])
def test_replay_from_recorded_inputs(kind, house, inputs, cache, tmp_path):
    run = tmp_path / "run"
    done = voxelwatch(
        "replay", "--site", str(house / "site.toml"), "--input", str(inputs[kind]), "--out", str(run),
        "--cache-dir", str(cache), "--quiet",
    )
    assert done.returncode == 0, done.stderr
    assert f"replay: {FRAMES} frame sets of 5 cameras" in done.stdout
    check_run(run, POSITION_TOLERANCE_M[kind])


def test_replay_a_camera_subset_from_videos(house, inputs, cache, tmp_path):
    """``--cameras`` replays only the cameras named (the others' folders are not needed)."""
    subset = tmp_path / "input"
    for cam in ("cam1", "cam3", "cam5"):
        shutil.copytree(inputs["videos"] / cam, subset / cam)
    run = tmp_path / "run"
    done = voxelwatch(
        "replay", "--site", str(house / "site.toml"), "--input", str(subset), "--out", str(run),
        "--cameras", "cam1,cam3,cam5", "--frames", "12", "--cache-dir", str(cache), "--quiet",
    )
    assert done.returncode == 0, done.stderr
    assert "replay: 12 frame sets of 3 cameras" in done.stdout
    tracks = read_tracks(run / "tracks.csv")
    assert set(range(CONFIRMED_BY, 12)) <= set(tracks.frame.tolist()) <= set(range(12))
    assert len(set(tracks.track_id.tolist())) == 1


@pytest.mark.parametrize("missing", ["input folder", pytest.param("camera folder", marks=pytest.mark.slow)])
def test_missing_input_is_one_clear_message(missing, house, inputs, cache, tmp_path):
    if missing == "input folder":
        source = tmp_path / "nowhere"
    else:
        source = tmp_path / "input"
        for cam in ("cam1", "cam2", "cam4", "cam5"):  # cam3 missing
            shutil.copytree(inputs["masks"] / cam, source / cam)
    done = voxelwatch(
        "replay", "--site", str(house / "site.toml"), "--input", str(source), "--out", str(tmp_path / "run"),
        "--cache-dir", str(cache), "--quiet",
    )
    assert done.returncode != 0
    assert "Traceback" not in done.stderr, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, done.stderr
    assert str(source) in lines[0]
    if missing == "camera folder":
        assert "cam3" in lines[0]


@pytest.mark.slow
def test_replay_of_the_house_with_a_thermal_and_a_depth_camera(tmp_path):
    """The house's site with cam2 a range camera and cam4 a thermal one: replay renders them as
    such, segments them with their own segmenters, passes cam2's foreground range to the pipeline
    and still tracks the person walking through."""
    from common.site import load_site
    from synth import default_site
    from fusion_server.pipeline import FusionPipeline
    from fusion_server.replay import replay

    default_site(tmp_path / "site")
    path = tmp_path / "site" / "site.toml"
    text = path.read_text(encoding="utf-8")
    blocks = text.split("[[cameras]]")
    for cam, modality in (("cam2", "depth"), ("cam4", "thermal")):
        blocks = [b.replace('modality = "colour"', f'modality = "{modality}"') if f'id = "{cam}"' in b else b
                  for b in blocks]
    path.write_text("[[cameras]]".join(blocks), encoding="utf-8")
    site = load_site(path)
    assert site.camera("cam2").modality == "depth" and site.camera("cam4").modality == "thermal"

    class Recording(FusionPipeline):
        def step(self, masks, stamp_ns, frame, looks=None, *, depths=None):
            self.seen.append((masks, depths))
            return super().step(masks, stamp_ns, frame, looks, depths=depths)

    pipeline = Recording.from_site(site, cache_dir=tmp_path / "cache")
    pipeline.seen = []
    summary = replay(site, tmp_path / "run", synthetic=SCENARIO, max_frames=FRAMES, pipeline=pipeline)
    assert summary.frames == FRAMES
    assert all(set(depths) == {"cam2"} for _, depths in pipeline.seen)
    late_masks, late_depths = pipeline.seen[-1]
    assert np.count_nonzero(late_masks["cam4"]) > 100 and np.count_nonzero(late_masks["cam2"]) > 100
    assert np.count_nonzero(late_depths["cam2"]) > 50
    assert np.all(late_masks["cam2"][late_depths["cam2"] > 0] > 0)
    tracks = read_tracks(tmp_path / "run" / "tracks.csv")
    assert len(tracks) > 0


def _panning_room(folder: Path, *, pan_at_s: float, length_s: float, shift_px: int = 8) -> tuple[Path, dict, dict]:
    """The tiny site's three cameras recording a textured empty room (``INPUT/<cam>/video.avi`` and
    ``background.avi``); c2's picture slides ``shift_px`` sideways at ``pan_at_s``, as if panned.
    Returns (site file, cameras, each camera's picture of the room before any pan)."""
    from tinysite import FPS, H, W, write_site

    site_file, cams = write_site(folder)
    rng = np.random.default_rng(7)
    rooms = {c: np.clip(120 + 60 * cv2.resize(rng.normal(0, 1, (H // 8, W // 8 + 5, 3)).astype(np.float32),
                                               (W + 40, H)), 0, 255).astype(np.uint8) for c in cams}
    pan_at, n = int(pan_at_s * FPS), int(length_s * FPS)
    for cam, room in rooms.items():
        sub = folder / "input" / cam
        sub.mkdir(parents=True)
        for name, frames in (("background.avi", 15), ("video.avi", n)):
            writer = cv2.VideoWriter(str(sub / name), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
            for i in range(frames):
                x = 20 + (shift_px if cam == "c2" and name == "video.avi" and i >= pan_at else 0)
                writer.write(np.ascontiguousarray(room[:, x:x + W]))
            writer.release()
    return site_file, cams, {c: np.ascontiguousarray(room[:, 20:20 + W]) for c, room in rooms.items()}


@pytest.mark.slow  # a moved camera is judged in the default run by tests/test_camera_moved.py
def test_a_camera_whose_recorded_view_pans_raises_camera_moved_in_the_replay(tmp_path):
    """Three cameras of the tiny site recording a textured empty room (videos with their empty-room
    clips); c2's picture slides 8 px sideways 2 s in, as if the camera had been panned by about
    5 degrees (its focal length is 95 px). The replay's view checks, run as the workers run them,
    raise one camera_moved for c2, 10 s of capture after the pan, and none for the others."""
    import json
    import math

    from common.site import load_site
    from fusion_server.replay import replay

    site_file, cams, _ = _panning_room(tmp_path, pan_at_s=2.0, length_s=14.0)
    replay(load_site(site_file), tmp_path / "out", input_dir=tmp_path / "input")
    events = [json.loads(line) for line in (tmp_path / "out" / "events.jsonl").read_text().splitlines()]
    moved = [e for e in events if e["kind"] == "camera_moved"]
    assert [e["details"]["camera"] for e in moved] == ["c2"], events
    assert moved[0]["details"]["evidence"] == "view"
    turned_deg = math.degrees(8 / cams["c2"].K[0, 0])
    assert moved[0]["details"]["view_deg"] == pytest.approx(turned_deg, rel=0.15)
    assert 10.0 <= moved[0]["stamp_ns"] / 1e9 - 2.0 <= 11.5  # measured once a second, held 10 s


def test_site_check_reads_each_clips_view_against_the_cameras_reference_picture(tmp_path, capsys):
    """The site names each camera's reference picture of the room (as its worker keeps it); clips
    taken after c2 was panned by 8 px: site check says how far each view has turned."""
    import math
    import re

    from camera_worker.viewcheck import save_reference
    from voxelwatch.cli import main

    site_file, cams, pictures = _panning_room(tmp_path, pan_at_s=0.0, length_s=3.0)
    text = site_file.read_text()
    for cam, picture in pictures.items():
        save_reference(tmp_path / "views" / f"{cam}.png", picture)
        text = text.replace(f'calibration = "{cam}.toml"\n',
                            f'calibration = "{cam}.toml"\nview_reference = "views/{cam}.png"\n')
    site_file.write_text(text)
    clips = [f"--clip={c}={tmp_path / 'input' / c / 'video.avi'}" for c in cams]
    assert main(["site", "check", str(site_file), *clips]) == 0
    lines = {line.split(":")[0].split()[-1]: line for line in capsys.readouterr().out.splitlines()
             if line.strip().startswith("camera ") and "reference picture" in line}
    read = {c: float(re.search(r"view ([0-9.]+) deg from its reference picture", line).group(1))
            for c, line in lines.items()}
    assert set(read) == set(cams), lines
    assert read["c2"] == pytest.approx(math.degrees(8 / cams["c2"].K[0, 0]), rel=0.15)
    assert read["c1"] < 0.1 and read["c3"] < 0.1
