"""Writing a scenario to a folder: site, calibrations, videos, masks and truth that read back."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from evaluation.io import read_truth_events, read_truth_meta, read_truth_tracks
from common.site import load_site
from synth.house import measure_render, write_scenario
from synth.source import SyntheticCamera


def _read_all(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    return frames


def test_write_scenario_lays_out_a_replayable_folder(tmp_path):
    out = write_scenario("demo", tmp_path / "house", frames=75, cameras=["cam2", "cam5"], masks=True)
    assert out.n_frames == 75
    site = load_site(out.site)
    assert site.camera_ids == ["cam2", "cam5"]
    assert site.resolve(site.camera("cam2").source) == out.videos["cam2"]
    assert site.resolve(site.camera("cam5").background) == out.backgrounds["cam5"]
    cams = site.load_cameras()
    assert cams["cam5"].model == "fisheye"
    for cid in ("cam2", "cam5"):
        video = _read_all(out.videos[cid])
        assert len(video) == 75 and video[0].shape == (480, 640, 3)
        assert len(_read_all(out.backgrounds[cid])) == 45
        masks = sorted(out.masks[cid].glob("*.png"))
        assert len(masks) == 75
        src = SyntheticCamera("demo", cid, 0)
        bgr, mask = src.frame(70)
        assert np.array_equal(cv2.imread(str(masks[70]), cv2.IMREAD_GRAYSCALE), mask)
        # Motion-JPEG is lossy but close: the error stays at the noise level.
        assert np.abs(video[70].astype(int) - bgr).mean() < 4.0
    meta = read_truth_meta(out.out_dir)
    assert meta.n_frames == 75 and meta.fps == 15.0
    tracks = read_truth_tracks(out.out_dir)
    assert tracks.frame.max() < 75 and len(tracks) > 0
    assert [e.kind for e in read_truth_events(out.out_dir)] == ["enter"]


@pytest.mark.slow
def test_lossless_videos_from_parallel_workers_equal_the_frame_source(tmp_path):
    out = write_scenario("two_pass", tmp_path / "h", frames=4, cameras=["cam1", "cam3"], codec="FFV1", workers=2)
    for cid in ("cam1", "cam3"):
        video = _read_all(out.videos[cid])
        src = SyntheticCamera("two_pass", cid, 0)
        assert len(video) == 4
        for i in range(4):
            assert np.array_equal(video[i], src.frame(i)[0])
        assert np.array_equal(_read_all(out.backgrounds[cid])[3], src.background_frame(3))


def test_truth_only_and_bad_arguments(tmp_path):
    out = write_scenario("walk", tmp_path / "t", video=False)
    assert out.videos == {} and not (out.out_dir / "cam1").exists()
    assert load_site(out.site).camera("cam1").source == ""
    assert read_truth_meta(out.out_dir).n_frames == 450
    with pytest.raises(ValueError, match="codec"):
        write_scenario("walk", tmp_path / "x", codec="H264")
    with pytest.raises(ValueError, match="cameras"):
        write_scenario("walk", tmp_path / "x", cameras=["cam7"])
    with pytest.raises(ValueError, match="frames"):
        write_scenario("walk", tmp_path / "x", frames=10_000)
    with pytest.raises(ValueError, match="scenarios are"):
        write_scenario("nope", tmp_path / "x")


def test_measure_render_reports_a_rate():
    rate = measure_render("walk", cameras=["cam4"], frames=3)
    assert np.isfinite(rate) and rate > 0
