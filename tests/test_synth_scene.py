"""The synthetic house's room, cameras and site file."""

from __future__ import annotations

import numpy as np
import pytest

from common.site import load_site
from synth.scene import CAMERA_IDS, default_cameras, default_room, default_site, floor_coverage


def _inside_box_xy(xy, box, margin=0.0) -> bool:
    return (box.min_m[0] - margin <= xy[0] <= box.max_m[0] + margin
            and box.min_m[1] - margin <= xy[1] <= box.max_m[1] + margin)


def test_room_layout_is_consistent():
    room = default_room()
    assert room.size_m == (8.0, 6.0, 2.5)
    for box in room.boxes:
        assert all(0.0 <= lo < hi <= lim for lo, hi, lim in zip(box.min_m, box.max_m, room.size_m)), box.name
    kinds = {b.kind for b in room.boxes}
    assert {"sofa", "table", "chair", "kitchen", "tv"} <= kinds
    assert {"sofa", "dinner table", "kitchen", "TV"} == {h.name for h in room.hotspots}
    floor_boxes = [b for b in room.boxes if b.min_m[2] < 1.0]
    # Standing spots and approach points are clear of furniture by a body's half-depth.
    for name, xy in room.waypoints.items():
        assert not any(_inside_box_xy(xy, b, 0.12) for b in floor_boxes), name
    for seat in room.seats:
        assert not any(_inside_box_xy(seat.approach_xy_m, b, 0.1) for b in floor_boxes), seat.name
        hs = room.hotspot(seat.hotspot)
        xs, ys = zip(*hs.polygon_m)
        assert min(xs) <= seat.xy_m[0] <= max(xs) and min(ys) <= seat.xy_m[1] <= max(ys), seat.name
    door = room.door("front door")
    assert door.outside_xy_m[0] < 0 < door.inside_xy_m[0]
    assert door.y_range_m[0] <= door.outside_xy_m[1] <= door.y_range_m[1]


def test_unknown_names_are_clear_errors():
    room = default_room()
    with pytest.raises(ValueError, match="seats are"):
        room.seat("throne")
    with pytest.raises(ValueError, match="hot spots are"):
        room.hotspot("garden")
    with pytest.raises(ValueError, match="waypoints are"):
        room.point("attic")


def test_cameras_match_the_seed_setup_and_cover_the_room():
    cams = default_cameras()
    assert tuple(cams) == CAMERA_IDS
    for cid in CAMERA_IDS[:4]:
        cam = cams[cid]
        assert cam.model == "pinhole" and (cam.width, cam.height) == (640, 480)
        assert cam.center[2] == pytest.approx(2.4)
        assert np.any(cam.dist != 0)
        # Looking at the room centre: its projection is near the image centre.
        uv, valid = cam.project(np.array([[4.0, 3.0, 0.8]]))
        assert valid[0] and abs(uv[0, 0] - 320) < 5 and abs(uv[0, 1] - 240) < 5
    fish = cams["cam5"]
    assert fish.model == "fisheye" and fish.forward[2] < -0.999
    # Every floor point at chest height is seen by at least three cameras, most by all five.
    cover = floor_coverage(cams, z_m=1.0, step_m=0.5)
    assert cover.min() >= 3
    assert np.mean(cover == 5) > 0.7


def test_scaled_cameras_for_fast_tests():
    small = default_cameras(scale=0.5)
    assert (small["cam1"].width, small["cam1"].height) == (320, 240)
    full = default_cameras()
    p = np.array([[2.0, 3.0, 1.0]])
    uv_s, _ = small["cam3"].project(p)
    uv_f, _ = full["cam3"].project(p)
    np.testing.assert_allclose((uv_s + 0.5) * 2 - 0.5, uv_f, atol=1e-6)


def test_default_site_round_trips(tmp_path):
    site = default_site(tmp_path, sources={"cam1": "cam1/video.avi"})
    again = load_site(tmp_path / "site.toml")
    assert again.name == "synthetic-house"
    assert again.camera_ids == list(CAMERA_IDS)
    assert [h.name for h in again.hotspots] == ["sofa", "dinner table", "kitchen", "TV"]
    assert again.doors[0].name == "front door"
    assert again.camera("cam1").source == "cam1/video.avi"
    loaded = site.load_cameras()
    for cid, cam in default_cameras().items():
        got = loaded[cid]
        assert got.model == cam.model
        np.testing.assert_allclose(got.K, cam.K)
        np.testing.assert_allclose(got.dist, cam.dist)
        np.testing.assert_allclose(got.R, cam.R, atol=1e-12)
        np.testing.assert_allclose(got.t, cam.t, atol=1e-12)
