"""Range and thermal rendering: the range image is the true range within the model's noise, its
gaps fall where a time-of-flight camera has them, and the thermal image shows a room at its air
temperature, warmer people and no shadows."""

from __future__ import annotations

import numpy as np
import pytest

from synth.body import BodyShape, pose_body, standing_pose
from synth.render import SURF_CEILING, CameraRenderer, frame_for, raycast_room
from synth.scenarios import get_scenario
from synth.scene import default_cameras
from synth.sensors import RangeModel, ThermalModel, agc8, ck_to_celsius, range_frame_mm

HALF = default_cameras(scale=0.5)
ROOM = get_scenario("walk").room


@pytest.fixture(scope="module")
def renderer():
    return CameraRenderer(HALF["cam1"], ROOM, seed=3, colour=False)


@pytest.fixture(scope="module")
def person():
    shape = BodyShape(height_m=1.75)
    return pose_body(shape, standing_pose(shape, 4.0, 3.0, 0.3), person_id=1)


def test_range_is_the_true_range_within_the_noise_model(renderer):
    model = RangeModel()
    mm = renderer.range_mm([], (0, 1), model=model)
    assert mm.dtype == np.uint16 and mm.shape == renderer.bg_depth.shape
    true_m = renderer.bg_depth
    sb = renderer._sensor_background()
    ok = mm > 0
    assert ok.mean() > 0.7
    err = mm[ok].astype(np.float64) / 1000.0 - true_m[ok]
    sigma = model.sigma_mm(true_m[ok], sb.reflectance[ok], sb.cos[ok]) / 1000.0
    z = err / sigma
    edge_free = np.abs(z) < 10   # flying pixels at the depth edges are mixtures, not noise
    assert edge_free.mean() > 0.98
    assert abs(np.median(z[edge_free])) < 0.1
    assert 0.85 < np.std(z[edge_free]) < 1.15


def test_range_noise_grows_with_range():
    """A mid-grey wall facing the camera: about 1 cm of noise at 1 m, about 5 cm at 5 m."""
    h, w = 100, 100
    rng = np.random.default_rng(1)
    draws = np.stack([rng.standard_normal((h, w)), rng.random((h, w))]).astype(np.float32)
    ones = np.ones((h, w), np.float32)
    spread = {}
    for r in (1.0, 5.0):
        mm = range_frame_mm(ones * r, ones * 0.5, ones, np.ones((h, w), bool), draws, RangeModel())
        assert np.all(mm > 0)
        spread[r] = float(np.std(mm / 1000.0 - r))
    assert 0.007 < spread[1.0] < 0.013
    assert 0.035 < spread[5.0] < 0.065


def test_range_gaps_beyond_range_at_grazing_angles_and_outside_the_lens(renderer):
    model = RangeModel(max_range_m=4.0)
    mm = renderer.range_mm([], (0, 2), model=model)
    sb = renderer._sensor_background()
    assert np.all(mm[renderer.bg_depth > 4.0] == 0)
    assert np.all(mm[sb.cos < model.min_cos] == 0)
    assert np.all(mm[~renderer.valid] == 0)


def test_range_is_deterministic_per_key(renderer, person):
    a = renderer.range_mm([person], (0, 5))
    assert np.array_equal(a, renderer.range_mm([person], (0, 5)))
    assert not np.array_equal(a, renderer.range_mm([person], (0, 6)))


def test_a_person_is_nearer_than_the_room_where_the_silhouette_is(renderer, person):
    mm, labels = renderer.range_labels([person], (0, 3))
    assert np.array_equal(labels, renderer.labels([person]))
    on = (labels > 0) & (mm > 0)
    assert on.sum() > 200
    nearer = mm[on].astype(np.float64) / 1000.0 < renderer.bg_depth[on] - 0.1
    assert nearer.mean() > 0.95
    # the person stands about 3-4 m from the camera
    cam = HALF["cam1"]
    dist = float(np.linalg.norm(cam.center[:2] - np.array([4.0, 3.0])))
    assert abs(np.median(mm[on]) / 1000.0 - dist) < 0.8


def test_dark_surfaces_drop_out_and_depth_edges_fly_between_the_surfaces():
    h, w = 60, 80
    r = np.full((h, w), 3.0, np.float32)
    r[:, 40:] = 1.5   # a step from 3 m to 1.5 m
    refl = np.full((h, w), 0.6, np.float32)
    refl[:30] = 0.03   # a black upper half
    cos = np.ones((h, w), np.float32)
    rng = np.random.default_rng(0)
    draws = np.stack([rng.standard_normal((h, w)), rng.random((h, w))]).astype(np.float32)
    model = RangeModel()
    mm = range_frame_mm(r, refl, cos, np.ones((h, w), bool), draws, model)
    away = np.ones((h, w), bool)
    away[:, 37:43] = False
    dark_gone = np.mean(mm[:30][away[:30]] == 0)
    bright_gone = np.mean(mm[30:][away[30:]] == 0)
    assert dark_gone > 0.35 and bright_gone == 0.0
    edge = mm[30:, 39:41].astype(np.float64) / 1000.0
    # edge pixels are one surface, the other, a mixture between them, or missing: never outside
    vals = edge[edge > 0]
    assert np.all((vals > 1.3) & (vals < 3.3))
    between = np.mean((vals > 1.7) & (vals < 2.8))
    assert between > 0.1
    assert np.mean(edge == 0) > 0.05


def test_thermal_room_at_its_air_temperature_and_people_warmer(renderer, person):
    ck, labels = renderer.thermal_labels([person], (0, 1), ambient_c=21.0)
    assert ck.dtype == np.uint16
    c = ck_to_celsius(ck)
    room = (labels == 0) & renderer.valid
    assert abs(float(np.median(c[room])) - 21.0) < 1.0
    body = labels > 0
    # a person some metres off at 320x240: clothes, the face and hands a few pixels, the optics' blur
    assert 26.0 < float(np.median(c[body])) < 34.5
    assert float(np.percentile(c[body], 95)) > 29.5
    # every part of the person is warmer than the room behind them
    inner = body & (np.roll(labels, 2, 0) > 0) & (np.roll(labels, -2, 0) > 0) & (np.roll(labels, 2, 1) > 0) \
        & (np.roll(labels, -2, 1) > 0)
    assert np.all(c[inner] > 24.0)


def test_thermal_follows_the_air_and_has_no_shadows(renderer, person):
    a = ck_to_celsius(renderer.thermal([], (0, 7), ambient_c=21.0))
    b = ck_to_celsius(renderer.thermal([], (0, 7), ambient_c=23.0))
    assert abs(float(np.median(b - a)) - 2.0) < 0.01
    # the same noise draw with and without the person: the room changes only at the person
    empty = ck_to_celsius(renderer.thermal([], (0, 9), ambient_c=21.0))
    full, labels = renderer.thermal_labels([person], (0, 9), ambient_c=21.0)
    diff = np.abs(ck_to_celsius(full) - empty)
    import cv2

    near = cv2.dilate((labels > 0).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    assert float(diff[~near].max()) < 0.011   # the rounding to centi-kelvin, nothing else
    assert float(np.median(diff[labels > 0])) > 5.0


def test_thermal_noise_and_fixed_pattern(renderer):
    quiet = ThermalModel(netd_k=0.0, fpn_k=0.0, column_k=0.0, radial_k=0.0, blur_px=0.0)
    a = ck_to_celsius(renderer.thermal([], (0, 1), model=quiet))
    assert np.array_equal(a, ck_to_celsius(renderer.thermal([], (0, 2), model=quiet)))
    model = ThermalModel()
    f1 = ck_to_celsius(renderer.thermal([], (0, 1), model=model))
    f2 = ck_to_celsius(renderer.thermal([], (0, 2), model=model))
    temporal = (f1 - f2)[renderer.valid] / np.sqrt(2.0)
    assert 0.8 * model.netd_k < np.std(temporal) < 1.3 * model.netd_k
    # the fixed pattern stays: the mean of many frames still differs from the noiseless room
    mean = np.mean([ck_to_celsius(renderer.thermal([], (0, k), model=model)) for k in range(8)], axis=0)
    assert np.std((mean - a)[renderer.valid]) > 0.05


def test_the_lamp_warms_the_ceiling_around_it(renderer):
    hits = raycast_room(ROOM, renderer.center, renderer.rays.reshape(-1, 3).astype(np.float64))
    c = ck_to_celsius(renderer.thermal([], (0, 1), ambient_c=20.0)).ravel()
    ceiling = hits.surface == SURF_CEILING
    if not ceiling.any():
        pytest.skip("the camera sees no ceiling")
    d = np.linalg.norm(hits.point - np.asarray(ROOM.light_m), axis=1)
    nearest = float(d[ceiling].min())
    assert nearest < 0.3
    assert np.median(c[ceiling & (d < nearest + 0.1)]) > np.median(c[ceiling & (d > 1.0)]) + 1.0


def test_frame_for_every_modality(renderer, person):
    colour = CameraRenderer(HALF["cam1"], ROOM, seed=3)
    labels = renderer.labels([person])
    for modality, shape, dtype in (("colour", (240, 320, 3), np.uint8), ("infrared", (240, 320, 3), np.uint8),
                                   ("thermal", (240, 320), np.uint16), ("depth", (240, 320), np.uint16)):
        image, lab = frame_for(colour, modality, [person], (0, 1))
        assert image.shape == shape and image.dtype == dtype, modality
        assert np.array_equal(lab, labels), modality
    grey, _ = frame_for(colour, "infrared", [person], (0, 1))
    assert np.array_equal(grey[..., 0], grey[..., 2])
    with pytest.raises(ValueError, match="modality"):
        frame_for(colour, "sonar", [person], (0, 1))


def test_agc8_fixed_span_and_automatic():
    ck = ((np.array([[15.0, 27.5, 40.0, 50.0]]) + 273.15) * 100).astype(np.uint16)
    fixed = agc8(ck, lo_c=15.0, hi_c=40.0).astype(int)
    assert fixed[0, 0] == 0 and abs(fixed[0, 1] - 128) <= 1 and fixed[0, 2] == 255 and fixed[0, 3] == 255
    auto = agc8(ck)
    assert auto.dtype == np.uint8 and auto[0, 0] < auto[0, 1] < auto[0, 3]
    with pytest.raises(ValueError):
        agc8(ck, lo_c=15.0)
