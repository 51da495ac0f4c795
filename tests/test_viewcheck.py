"""The worker's own view check: the live picture registered against a reference of the empty room.

Oracles: the lattice shift of a translation and of a scale worked out by hand; for a camera turned
about its centre, the angle it turned (the shift over the focal length, as the fusion server reads it:
the picture's middle moves by f tan(angle), the corners of a wide lens by more).
Pictures: rendered rooms of the randomised worlds (tuning seeds) and the lab recording's frames.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from camera_worker.viewcheck import (
    GRID, ViewCheck, ViewCheckParams, lattice_shift, load_reference, save_reference,
)
from synth.degrade import CameraMove
from synth.source import SyntheticCamera
from synth.world import random_world


def test_lattice_shift_of_a_translation_and_a_scale_by_hand():
    move = np.array([[1.0, 0.0, 3.0], [0.0, 1.0, 4.0]])
    assert lattice_shift(move, (100, 100)) == pytest.approx(5.0)
    # a 2 % scale about the corner moves each lattice point (10, 30, 50, 70, 90 on both axes) by
    # 0.02 of its distance to it: mean x^2 = mean y^2 = 3300, so the RMS is 0.02 * sqrt(6600)
    scale = np.array([[1.02, 0.0, 0.0], [0.0, 1.02, 0.0]])
    assert GRID == 5
    assert lattice_shift(scale, (100, 100)) == pytest.approx(0.02 * math.sqrt(6600.0))
    assert lattice_shift(np.eye(2, 3), (120, 160)) == 0.0


@pytest.fixture(scope="module")
def world():
    return random_world(3, duration_s=30.0)


def _camera(world, cam_id: str, move: CameraMove | None = None) -> SyntheticCamera:
    return SyntheticCamera(world.scenario, cam_id, world.seed, camera=world.cameras[cam_id], moved=move)


def test_an_untouched_camera_reads_still_through_people_and_light(world):
    src = _camera(world, "cam1")
    check = ViewCheck(reference=src.background_frame(0))
    seen = []
    for i in range(0, world.scenario.n_frames, 45):
        frame, people = src.frame(i)
        seen.append(check.measure(frame, people).shift_px)
        dimmer = cv2.convertScaleAbs(frame, alpha=0.55, beta=10)  # lights down: another gain and offset
        seen.append(check.measure(dimmer, people).shift_px)
    assert max(seen) < 0.6, seen
    assert math.degrees(max(seen) / world.cameras["cam1"].K[0, 0]) < 0.1


@pytest.mark.parametrize("cam_id,move", [
    ("cam1", CameraMove(first=0, rotation_deg=2.0, axis=(0.6, 0.8, 0.0))),
    ("cam2", CameraMove(first=0, rotation_deg=2.0, axis=(1.0, 0.0, 0.0))),
], ids=["turned-obliquely", "tilted"])
def test_a_turned_camera_reads_the_angle_it_turned(world, cam_id, move):
    before = world.cameras[cam_id]
    src = _camera(world, cam_id, move)
    check = ViewCheck(reference=_camera(world, cam_id).background_frame(0))
    frame, people = src.frame(90)
    reg = check.measure(frame, people)
    assert math.degrees(reg.shift_px / before.K[0, 0]) == pytest.approx(2.0, rel=0.15)
    assert reg.agreeing >= 0.6 * reg.tiles


def test_a_ceiling_fisheye_is_judged_on_its_image_circle_only():
    """A fisheye's black corners stay put when it turns; left in, their edge would hold the fit at rest."""
    world = random_world(5, duration_s=20.0)
    cam = world.cameras["cam4"]
    assert cam.model == "fisheye"
    move = CameraMove(first=0, rotation_deg=2.0, axis=(0.6, 0.8, 0.0))
    check = ViewCheck(reference=_camera(world, "cam4").background_frame(0))
    still = check.measure(*_camera(world, "cam4").frame(60)).shift_px
    turned = check.measure(*_camera(world, "cam4", move).frame(60)).shift_px
    f_tan = cam.K[0, 0] * math.tan(math.radians(2.0))  # r = f theta: the image centre moves f * 2 degrees
    assert still < 0.2 * f_tan and turned > 0.7 * f_tan, (still, turned, f_tan)


def test_measures_once_a_second_and_a_dark_room_keeps_the_last_reading(world):
    src = _camera(world, "cam1")
    check = ViewCheck(reference=src.background_frame(0))
    frame, people = src.frame(30)
    s = int(1e9)
    assert check.observe(frame, people, 10 * s) is not None and check.measured == 1
    assert check.observe(frame, people, 10 * s + s // 2) == check.shift_px and check.measured == 1  # not due
    last = check.shift_px
    dark = np.full_like(frame, 3)   # lights out: no tile shows anything to line up
    assert check.observe(dark, None, 11 * s) == last and check.skipped == 1 and check.measured == 1
    flooded = np.full_like(people, 255)   # the model seeing a changed view: measured past the mask
    assert check.measure(frame, flooded).shift_px < 0.6
    assert ViewCheck().observe(frame, people, 0) is None  # no reference: nothing to say


def test_reference_pictures_are_kept_and_a_broken_one_is_named(tmp_path, world):
    picture = _camera(world, "cam1").background_frame(0)
    path = tmp_path / "views" / "cam1.png"
    assert load_reference(path) is None
    save_reference(path, picture)
    assert np.array_equal(load_reference(path), picture)
    assert not list(path.parent.glob("*.tmp.png"))
    path.write_text("not a picture")
    with pytest.raises(ValueError, match=r"cam1\.png: not an 8-bit picture"):
        load_reference(path)


def test_bad_settings_and_pictures_are_refused():
    with pytest.raises(ValueError, match="width_px"):
        ViewCheckParams(width_px=8)
    with pytest.raises(ValueError, match="min_fit"):
        ViewCheckParams(min_fit=1.5)
    with pytest.raises(ValueError, match="min_tiles"):
        ViewCheckParams(min_tiles=2)
    with pytest.raises(ValueError, match="uint8"):
        ViewCheck(reference=np.zeros((10, 10), np.uint16))
    with pytest.raises(ValueError, match="no reference"):
        ViewCheck().measure(np.zeros((10, 10), np.uint8), None)


# --- the lab recording ----------------------------------------------------------------------------


def _first(path, index: int = 0) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    try:
        for _ in range(index + 1):
            ok, frame = cap.read()
            assert ok, path
        return frame
    finally:
        cap.release()


@pytest.mark.parametrize("cam_id", ["cam1", "cam2", "cam3", "cam4"])
def test_lab_cameras_read_still_and_a_turn_warped_into_their_frames(lab4cam, tmp_path, cam_id):
    """Real frames against the reference a worker takes (its background model after the empty
    room's clip) read still, with the seated person in view unmasked too (as once the model has
    absorbed them); the same frames warped as a 2 degree pan of the shipped lens would move them
    read that turn."""
    from camera_worker.segmentation import ForegroundSegmenter
    from common.site import load_site
    from test_lab_recording import write_lab_site

    cam = load_site(write_lab_site(lab4cam, tmp_path, mask_scale=1.0)).load_cameras()[cam_id]
    segmenter = ForegroundSegmenter(window_frames=100)
    cap = cv2.VideoCapture(str(lab4cam / cam_id / "background.avi"))
    while (got := cap.read())[0]:
        segmenter.learn(got[1])
    cap.release()
    check = ViewCheck(reference=segmenter.background_image())
    frame = _first(lab4cam / cam_id / "video.avi", 40)
    for mask in (segmenter.apply(frame)[0], None):
        still = check.measure(frame, mask)
        # well under the alarm's 0.3 degree: cam2 reads 0.14-0.16 throughout (its view differs that much
        # between the two clips), the others under 0.06
        assert still is not None and math.degrees(still.shift_px / cam.K[0, 0]) < 0.2, still
    K = cam.K
    pan = cv2.Rodrigues(np.array([0.0, math.radians(2.0), 0.0]))[0]
    H = K @ pan @ np.linalg.inv(K)
    h, w = frame.shape[:2]
    turned = cv2.warpPerspective(frame, H, (w, h), borderMode=cv2.BORDER_REFLECT)
    reg = check.measure(turned, None)
    # the lattice reaches the picture's edges, where a pan of this lens moves pixels further than in its middle
    assert reg is not None and math.degrees(reg.shift_px / K[0, 0]) == pytest.approx(2.2, rel=0.12), reg
