"""The floor board fitted to the image as a whole (calibrate.boardfit), against the board's true corners
on rendered floor views."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from calibrate.board import Board, find_board
from calibrate.boardfit import MAX_MOVE_PX, fit_board, refined_corners
from evaluation.calibration_suite import rough_cameras
from synth.board import BoardRenderer, corners_world
from synth.world import random_world

MAT = Board(9, 6, 0.25)


def _floor_pose(x: float, y: float, yaw: float):
    return (np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]]),
            np.array([x, y, 0.0]))


@pytest.fixture(scope="module")
def grazing_view():
    """Tuning seed 0's cam6 (320x240, a wide lens of 107 px, 2 m up) sees the 250 mm mat on the floor about 4 m
    away: its rows 1.5-4 px apart. The median of five noisy frames, as a still stretch gives it."""
    world = random_world(0)
    cam = world.cameras["cam6"]
    pose = _floor_pose(4.377252893450217, 1.6129622192362363, -0.037530903369848795)
    renderer = BoardRenderer(cam, world.room, seed=0)
    gray = np.median(np.stack([renderer.render(MAT, pose, key=k) for k in range(5)]), axis=0).astype(np.uint8)
    truth, _ = cam.project(corners_world(MAT, pose))
    rough = rough_cameras(world.cameras)["cam6"]
    found = find_board(gray, MAT, camera=cam, thorough=True, rough_pose=(rough.R, rough.t))
    assert found is not None
    return cam, gray, truth, found


def test_a_board_seen_at_a_grazing_angle_is_fitted_closer_to_its_true_corners_than_the_detector_puts_them(
        grazing_view):
    """Measured: the detector's corners (the best flat fit of every way of looking) 0.09 px from the truth on
    average, the fitted board's 0.02 px."""
    cam, gray, truth, found = grazing_view
    fit = fit_board(gray, found, MAT, cam)
    assert fit is not None
    before = np.linalg.norm(found - truth, axis=1).mean()
    after = np.linalg.norm(fit.corners - truth, axis=1).mean()
    print(f"detected {before:.3f} px from the truth, fitted {after:.3f} px; blur {fit.blur_px:.2f} px, "
          f"{fit.pixels} pixels, grey misfit {fit.rms_before:.1f} -> {fit.rms_after:.1f}")
    assert after < 0.06
    assert after < 0.5 * before
    assert fit.rms_after < fit.rms_before
    # the renderer's 2x2 samples per pixel and no optical blur: a pixel's width alone (0.29 px) and the samples'
    assert 0.29 < fit.blur_px < 0.6


def test_uneven_light_and_a_foot_on_the_board_do_not_pull_the_fit(grazing_view):
    """The same view lit from one side (the far left half as bright as the near right) with a dark shoe over two
    squares: the contrast and level follow the light, the shoe's pixels are discounted, and the fitted corners
    stay within 0.08 px of the truth (the detector's, on the same image, as given)."""
    cam, gray, truth, found = grazing_view
    h, w = gray.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    lit = gray * (0.5 + 0.5 * (u / w + v / h) / 2 + 0.25)
    centre = truth[3 * MAT.cols + 4]
    step = np.linalg.norm(truth[3 * MAT.cols + 5] - centre)
    shoe = ((u - centre[0]) / (1.2 * step)) ** 2 + ((v - centre[1]) / (0.8 * step)) ** 2 <= 1.0
    lit[shoe] = 40.0
    img = np.clip(np.rint(lit), 0, 255).astype(np.uint8)
    fit = fit_board(img, found, MAT, cam)
    assert fit is not None
    err = np.linalg.norm(fit.corners - truth, axis=1)
    print(f"fitted {err.mean():.3f} px mean, {err.max():.3f} max; shoe over {shoe.sum()} pixels")
    assert err.mean() < 0.08


def test_a_fit_that_would_move_the_board_far_from_its_detection_is_refused(grazing_view):
    """Corners given a square off along the rows (a detector's grid on the wrong squares) are not pulled back by
    the fit, which could as well settle on the squares it was given (the pattern looks the same a square over, its
    colours swapped): the fit moves them under MAX_MOVE_PX or is refused, and refined_corners keeps them as given
    where it is refused."""
    cam, gray, truth, found = grazing_view
    grid = found.reshape(MAT.rows, MAT.cols, 2)
    shifted = (grid + (grid[:, 1:2] - grid[:, 0:1])).reshape(-1, 2)   # every corner one square further along
    fit = fit_board(gray, shifted, MAT, cam)
    assert fit is None or fit.moved_px <= MAX_MOVE_PX
    kept = refined_corners(gray, shifted, MAT, cam)
    assert np.linalg.norm(kept - truth, axis=1).mean() > 2.0   # not taken for the true board


def test_a_board_too_small_to_fit_is_left_as_found():
    """A 9x6 board of 30 mm squares 5 m away: under four pixels per square; the detected corners come back as
    given."""
    world = random_world(0)
    cam = world.cameras["cam6"]
    board = Board(9, 6, 0.03)
    corners, _ = cam.project(corners_world(board, _floor_pose(4.4, 1.6, 0.0)))
    gray = np.full((cam.height, cam.width), 120, dtype=np.uint8)
    assert fit_board(gray, corners, board, cam) is None
    assert np.array_equal(refined_corners(gray, corners, board, cam), corners)


@pytest.mark.slow
def test_the_fit_takes_a_real_lens_blur():
    """A board rendered sharp and then blurred by a Gaussian of 1.2 px (a lens out of focus), seen by tuning seed 0's
    cam1 (320x240, 232 px) 2 m away: the detector's corners come out 0.53 px from the truth, the fitted board's
    within 0.05 px, its blur well over the sharp renders' 0.4 px (1.8 px measured: where the board's two families of
    edges cross at a slant, the model's blur taken across each family alone stands for the whole Gaussian)."""
    world = random_world(0)
    cam = world.cameras["cam1"]
    pose = _floor_pose(3.5, 2.0, 0.1)
    renderer = BoardRenderer(cam, world.room, seed=0)
    img = renderer.render(MAT, pose, key=0, noise_std=0.0).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 1.2)
    gray = np.clip(np.rint(img + np.random.default_rng(0).normal(0, 1.0, img.shape)), 0, 255).astype(np.uint8)
    truth, _ = cam.project(corners_world(MAT, pose))
    rough = rough_cameras(world.cameras)["cam1"]
    found = find_board(gray, MAT, camera=cam, thorough=True, rough_pose=(rough.R, rough.t))
    assert found is not None
    fit = fit_board(gray, found, MAT, cam)
    assert fit is not None
    before = np.linalg.norm(found - truth, axis=1).mean()
    err = np.linalg.norm(fit.corners - truth, axis=1).mean()
    print(f"blur {fit.blur_px:.2f} px, corners {err:.3f} px; detected {before:.3f} px")
    assert err < 0.05 and err < 0.5 * before
    assert fit.blur_px > 1.0


@pytest.mark.slow
def test_floor_sightings_take_the_fitted_board_on_request_and_keep_the_detectors_corners(tmp_path):
    """Tuning seed 0's cam6 records the mat at two places on the floor (a clip, as the floor command reads it):
    by default the sightings' corners are the detector's; with fit_board they are the fitted board's, closer to the
    truth, and each sighting keeps the detector's own (for the command's check of the calibration against them)."""
    from calibrate.floor import find_sightings
    from synth.board import floor_clip, write_frames

    world = random_world(0)
    cam = world.cameras["cam6"]
    poses = [_floor_pose(4.377252893450217, 1.6129622192362363, -0.037530903369848795), _floor_pose(3.4, 2.4, 0.5)]
    clip = str(write_frames(floor_clip(BoardRenderer(cam, world.room, seed=0), MAT, poses), tmp_path / "cam6"))
    rough = rough_cameras(world.cameras)
    plain = find_sightings({"cam6": clip}, {"cam6": cam}, MAT, rough)
    fitted = find_sightings({"cam6": clip}, {"cam6": cam}, MAT, rough, fit_board=True)
    assert len(plain) == len(fitted) == 2
    for a, b, pose in zip(plain, fitted, poses):
        truth, _ = cam.project(corners_world(MAT, pose))
        e_plain = np.linalg.norm(a.corners - truth, axis=1).mean()
        e_fit = np.linalg.norm(b.corners - truth, axis=1).mean()
        print(f"place at {pose[1][:2]}: detector {e_plain:.3f} px, fitted {e_fit:.3f} px from the truth")
        assert a.detected is None
        assert np.array_equal(b.detected, a.corners)
        assert e_fit < 0.06 and e_fit < 0.6 * e_plain
