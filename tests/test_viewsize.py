"""The smallest foreground blob a camera keeps follows how small a person can look in its view.

Geometry worked by hand: a pinhole camera (f = 500 px, 640x480) at height
0.5 m looks along +x at a volume 5.3 m long and 0.3 m wide, starting 2 m in
front of it. The floor points sampled every 0.25 m put the farthest 0.3 x 0.3
x 1.0 m body's centre at x = 5.15 m, its near face 7 m from the camera; seen
straight on, its outline is that face, 500 * 0.3 / 7 by 500 * 1.0 / 7 pixels
(the far face projects inside it), 1530.6 px^2, and a quarter of it is 383.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from camera_worker.segmentation import ForegroundSegmenter
from camera_worker.viewsize import DEFAULT_MIN_AREA_PX, FLOOR_PX, min_area_for_site, min_area_for_view
from common.camera import Camera, look_at
from common.site import Volume, load_site

VOLUME = Volume(min_m=(0.0, -0.15, 0.0), max_m=(5.3, 0.15, 2.5))


def _camera(x_m: float, *, size=(640, 480), f=500.0, look=1.0) -> Camera:
    R, t = look_at((x_m, 0.0, 0.5), (x_m + look, 0.0, 0.5))
    return Camera.pinhole("cam", size[0], size[1], fx=f, R=R, t=t)


def test_a_far_view_keeps_a_quarter_of_the_smallest_outline_worked_by_hand():
    assert min_area_for_view(_camera(-2.0), VOLUME) == round(0.25 * 500 * 0.3 * 500 * 1.0 / 7.0**2) == 383


def test_the_bound_is_the_same_part_of_the_view_at_any_resolution():
    # twice the pixels each way and twice the focal length: the same view, the same 640x480 figure
    assert min_area_for_view(_camera(-2.0, size=(1280, 960), f=1000.0), VOLUME) == 383


def test_a_close_view_keeps_the_default_and_a_very_far_one_stops_at_the_noise_floor():
    # 5.5 m to the far face: a quarter outline of 620 px is above the default, which stays
    assert min_area_for_view(_camera(-0.5), VOLUME) == DEFAULT_MIN_AREA_PX
    # 25 m: 0.25 * 500 * 0.3 * 500 / 25^2 = 30, below the floor
    assert min_area_for_view(_camera(-20.0), VOLUME) == FLOOR_PX


def test_a_camera_that_sees_none_of_the_floor_keeps_the_default():
    assert min_area_for_view(_camera(8.0), VOLUME) == DEFAULT_MIN_AREA_PX   # looks away from the room


def test_a_person_at_the_far_end_is_kept_with_the_views_bound_and_was_dropped_at_400():
    """A 1.5 m person drawn at the far end of a long view (a filled outline of a 0.35 x 1.5 m figure
    21 m off, 500 * 0.35 / 21 by 500 * 1.5 / 21 pixels, 333 px drawn) is dropped by the fixed 400 and kept by the
    view's own bound (the floor, 50: the smallest body's quarter outline there is 21 px)."""
    cam = _camera(-16.0)
    bound = min_area_for_view(cam, Volume(min_m=(0.0, -1.0, 0.0), max_m=(5.3, 1.0, 2.5)))
    empty = np.full((480, 640, 3), 90, np.uint8)
    frame = empty.copy()
    corners = np.array([[5.0, dy, z] for dy in (-0.175, 0.175) for z in (0.0, 1.5)])
    uv, ok = cam.project(corners)
    assert ok.all()
    cv2.fillConvexPoly(frame, cv2.convexHull(uv.astype(np.int32)), (200, 40, 40))
    drawn = int(np.count_nonzero(frame[..., 0] == 200))
    assert bound == FLOOR_PX < drawn < DEFAULT_MIN_AREA_PX
    kept = {}
    for px in (DEFAULT_MIN_AREA_PX, bound):
        seg = ForegroundSegmenter(min_area_px=px)
        for _ in range(30):
            seg.learn(empty)
        mask, _ = seg.apply(frame, learn=False)
        kept[px] = int(np.count_nonzero(mask))
    assert kept[DEFAULT_MIN_AREA_PX] == 0
    assert kept[bound] >= 0.8 * drawn


def test_a_site_without_a_readable_calibration_keeps_the_default_and_says_which_file(tmp_path, caplog):
    (tmp_path / "site.toml").write_text(
        'name = "flat"\n[[cameras]]\nid = "hall"\ncalibration = "calib/hall.toml"\nresolution = [640, 480]\n')
    site = load_site(tmp_path / "site.toml")
    with caplog.at_level(logging.WARNING, logger="camera_worker.viewsize"):
        assert min_area_for_site(site, "hall") == DEFAULT_MIN_AREA_PX
    assert str(tmp_path / "calib" / "hall.toml") in caplog.text


def test_the_worker_takes_its_views_bound_from_the_site_unless_told(tmp_path):
    from camera_worker.cli import _configure, build_parser
    from common.calibration import save_voxelwatch

    (tmp_path / "calib").mkdir()
    save_voxelwatch(_camera(-2.0), tmp_path / "calib" / "cam.toml")
    (tmp_path / "site.toml").write_text(
        'name = "hall"\n[volume]\nmin_m = [0.0, -0.15, 0.0]\nmax_m = [5.3, 0.15, 2.5]\n'
        '[[cameras]]\nid = "cam"\ncalibration = "calib/cam.toml"\nformat = "voxelwatch"\nresolution = [640, 480]\n')
    base = ["--site", str(tmp_path / "site.toml"), "--camera", "cam", "--source", "synthetic", "--no-view-check"]
    settings, _, _ = _configure(build_parser().parse_args(base))
    assert settings.segmenter["min_area_px"] == 383
    settings, _, _ = _configure(build_parser().parse_args([*base, "--min-area-px", "120"]))
    assert settings.segmenter["min_area_px"] == 120


def test_a_small_blob_is_kept_apart_from_larger_ones_and_dropped_beside_one():
    """Worked by hand: a 40 x 25 px body (1,000 px) and two 10 x 10 px blobs (100 px each), one 5 px
    right of the body (within its own height, 10 px, and half the body's: a hand or a shadow's
    blotch of someone near) and one 60 px away (someone far). With 50 as the smallest and 400 as
    the size that must stand apart, the near piece goes and the far one stays; with no apart size
    both stay."""
    from camera_worker.segmentation import remove_small_components

    mask = np.zeros((120, 200), np.uint8)
    mask[10:50, 10:35] = 255      # the body: x 10-34, y 10-49
    mask[20:30, 40:50] = 255      # 5 px to its right
    mask[20:30, 95:105] = 255     # 60 px to its right
    out, kept = remove_small_components(mask, 50, 400)
    assert kept == 2 and not out[20:30, 40:50].any() and out[20:30, 95:105].all() and out[10:50, 10:35].all()
    out, kept = remove_small_components(mask, 50)
    assert kept == 3 and np.array_equal(out, mask)
    # feet seen below a tabletop: 12 px under the body, beyond their own 10 px height but within half
    # the body's 40 px: a piece of the body, dropped; 25 px under, past both, they stay
    for gap, stays in ((12, False), (25, True)):
        low = mask.copy()
        low[20:30, 40:50] = 0
        low[50 + gap:60 + gap, 15:25] = 255
        out, kept = remove_small_components(low, 50, 400)
        assert out[50 + gap:60 + gap, 15:25].all() == stays and kept == 2 + stays
    out, kept = remove_small_components(mask, 101, 400)   # below the smallest: gone wherever it is
    assert kept == 1
