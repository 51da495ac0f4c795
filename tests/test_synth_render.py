"""Rendering: silhouettes agree with the true body volumes through each calibration, the fast
renderer equals brute-force ray casting, and noise, drift, light switches and shadows are there."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from synth.render import CameraRenderer
from synth.scenarios import get_scenario
from synth.scene import CAMERA_IDS, default_cameras, default_site
from synth.source import SyntheticCamera

HALF = default_cameras(scale=0.5)


@pytest.fixture(scope="module")
def sources():
    """Half-resolution sources of a few scenarios, built once."""
    out = {}
    for name in ("demo", "behind_sofa", "four_people"):
        sc = get_scenario(name, 0)
        out[name] = {cid: SyntheticCamera(sc, cid, 0, camera=cam) for cid, cam in HALF.items()}
    return out


@pytest.fixture(scope="module")
def quiet_renderers():
    """Noise-free half-resolution renderers of the default room, with and without shadows."""
    room = get_scenario("walk").room
    return {cid: (CameraRenderer(cam, room, seed=0, noise_std=0.0),
                  CameraRenderer(cam, room, seed=0, noise_std=0.0, shadows=False)) for cid, cam in HALF.items()}


def _projection_check(src: SyntheticCamera, frame: int, rng):
    """Project sample points of the true bodies; returns (inside, coverage, visible fraction)."""
    cam = src.camera
    _, labels = src.frame_labels(frame)
    mask = labels > 0
    pts = np.concatenate([b.sample_points(8000, rng, surface_fraction=0.3) for b in src.scenario.bodies(frame)])
    uv, valid = cam.project(pts)
    pix = np.rint(uv[valid]).astype(int)
    dist = np.linalg.norm(pts[valid] - cam.center, axis=1)
    depth = src.renderer.bg_depth
    kernel = np.ones((3, 3), np.uint8)
    # Visible: nearer than the background all around the pixel (furniture edges are left out).
    nearest_bg = cv2.erode(depth, kernel)[pix[:, 1], pix[:, 0]]
    visible = dist < nearest_bg - 0.01
    grown = cv2.dilate(mask.astype(np.uint8), kernel) > 0
    inside = grown[pix[visible, 1], pix[visible, 0]].mean()
    splat = np.zeros(mask.shape, np.uint8)
    splat[pix[:, 1], pix[:, 0]] = 1
    splat = cv2.dilate(splat, np.ones((5, 5), np.uint8)) > 0
    coverage = splat[mask].mean()
    return inside, coverage, visible.mean(), int(mask.sum())


@pytest.mark.parametrize("name, frames", [("demo", (200, 600)), ("behind_sofa", (200, 400)), ("four_people", (3000,))])
def test_silhouettes_match_projected_body_volumes(sources, name, frames):
    rng = np.random.default_rng(7)
    hidden_somewhere = False
    for cid in CAMERA_IDS:
        for f in frames:
            inside, coverage, visible, area = _projection_check(sources[name][cid], f, rng)
            assert area > 0, (name, cid, f)
            assert inside >= 0.99, (name, cid, f, inside)
            assert coverage >= 0.95, (name, cid, f, coverage)
            hidden_somewhere |= visible < 0.9
    assert hidden_somewhere  # furniture hides part of the body in some view


def test_full_resolution_silhouettes_of_the_fisheye_and_a_corner_camera():
    sc = get_scenario("demo", 0)
    rng = np.random.default_rng(3)
    for cid in ("cam2", "cam5"):
        src = SyntheticCamera(sc, cid, 0)
        assert (src.width, src.height) == (640, 480)
        inside, coverage, _, area = _projection_check(src, 300, rng)
        assert area > 300 and inside >= 0.99 and coverage >= 0.95


def test_fast_renderer_equals_brute_force_ray_casting():
    cams = default_cameras(scale=0.25)
    for name, frame in (("two_pass", 150), ("fall_sideways", 500), ("demo", 300)):
        sc = get_scenario(name, 1)
        bodies = sc.bodies(frame)
        for cid, cam in cams.items():
            r = CameraRenderer(cam, sc.room, seed=1)
            _, labels = r.render(bodies, 1.0, (0, frame))
            rays = cam.pixel_rays().reshape(-1, 3).astype(np.float64)
            ok = np.all(np.isfinite(rays), axis=1)
            best = np.full(rays.shape[0], np.inf)
            who = np.zeros(rays.shape[0], dtype=np.uint8)
            for b in bodies:
                t, _ = b.intersect(cam.center, np.where(ok[:, None], rays, 0.0))
                closer = ok & (t < best)
                best[closer] = t[closer]
                who[closer] = b.person_id
            expected = np.where(best < r.bg_depth.ravel(), who, 0).reshape(labels.shape)
            wrong = int(np.sum(expected != labels))
            assert wrong <= max(2, 0.005 * np.sum(expected > 0)), (name, cid, wrong)
            assert np.sum(expected > 0) > 0 or name == "two_pass"


def _static_region(src, frames, margin_px=25):
    """Valid pixels far from every person in all the given frames."""
    busy = np.zeros((src.height, src.width), np.uint8)
    for f in frames:
        busy |= src.frame(f)[1]
    busy = cv2.dilate(busy, np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)) > 0
    return src.renderer.valid & ~busy & (src.renderer.bg_depth > 0)


def test_sensor_noise_is_present_and_frame_to_frame():
    src = SyntheticCamera("long_still", "cam1", 0, camera=HALF["cam1"])
    still = _static_region(src, (100, 101))
    a = src.frame(100)[0].astype(np.float64)
    b = src.frame(101)[0].astype(np.float64)
    diff = (b - a)[still]
    assert diff.std() > 1.0
    assert abs(diff.mean()) < 0.5
    bg0 = src.background_frame(0).astype(np.float64)
    bg1 = src.background_frame(1).astype(np.float64)
    assert (bg1 - bg0)[src.renderer.valid].std() > 1.0


def test_illumination_drift_and_light_switch_are_measurable():
    src = SyntheticCamera("lights", "cam3", 0, camera=HALF["cam3"])
    sc = src.scenario
    frames = (30, 280, 320, 600, 700)
    still = _static_region(src, frames)

    def mean(f):
        return src.frame(f)[0][still].astype(np.float64).mean()

    # Slow drift before the lamp: brightness follows the scene gain.
    m30, m280 = mean(30), mean(280)
    assert abs(sc.gain(280) / sc.gain(30) - 1) > 0.005
    assert m280 / m30 == pytest.approx(sc.gain(280) / sc.gain(30), abs=0.006)
    # The lamp at 20 s brightens everything by ~28 %, switching it off at 45 s undoes it.
    assert mean(320) / m280 == pytest.approx(1.28, abs=0.03)
    assert mean(700) / mean(600) == pytest.approx(1 / 1.28, abs=0.03)


@pytest.mark.parametrize("name, frame", [("walk", 100), ("long_still", 900), ("bend_kneel", 190)])
def test_shadows_darken_the_floor_near_the_feet(quiet_renderers, name, frame):
    sc = get_scenario(name, 0)
    bodies = sc.bodies(frame)
    pelvis = bodies[0].pelvis_m
    away = pelvis[:2] - np.asarray(sc.room.light_m[:2])
    away /= np.linalg.norm(away)
    # Floor points in a wedge behind the feet, seen from the ceiling light.
    r, a = np.meshgrid(np.linspace(0.2, 0.7, 6), np.radians(np.linspace(-25, 25, 7)))
    ca, sa = np.cos(a).ravel(), np.sin(a).ravel()
    dirs = np.c_[away[0] * ca - away[1] * sa, away[0] * sa + away[1] * ca]
    wedge = np.c_[pelvis[:2] + dirs * r.ravel()[:, None], np.zeros(r.size)]
    samples = []
    for cid, cam in HALF.items():
        rend, no_shadows = quiet_renderers[cid]
        bgr, labels = rend.render(bodies, 1.0, (0, frame))
        empty = rend.render([], 1.0, (0, frame))[0]
        darker = empty.astype(np.float64).mean(axis=2) - bgr.astype(np.float64).mean(axis=2)
        uv, valid = cam.project(wedge)
        pix = np.rint(uv[valid]).astype(int)
        seen = np.abs(rend.bg_depth[pix[:, 1], pix[:, 0]] - np.linalg.norm(wedge[valid] - cam.center, axis=1)) < 0.05
        free = seen & (labels[pix[:, 1], pix[:, 0]] == 0)
        samples.append(darker[pix[free, 1], pix[free, 0]])
        assert np.all(darker[labels == 0] >= -0.51)  # shadows only darken
        # Far from the person nothing changes (but for a rare pixel at a depth edge next to a shadow).
        far = (np.linalg.norm(rend.bg_points[..., :2] - pelvis[:2], axis=2) > 2.5) & (labels == 0) & rend.valid
        assert np.mean(np.abs(darker[far]) <= 0.5) > 0.999
        # The switch turns them off.
        plain = no_shadows.render(bodies, 1.0, (0, frame))[0]
        assert np.array_equal(plain[labels == 0], empty[labels == 0])
    near = np.concatenate(samples)
    assert near.size > 30
    assert near.mean() > 5.0 and near.max() > 12.0


def test_frames_are_a_pure_function_of_scenario_seed_camera_and_index():
    a = SyntheticCamera("two_pass", "cam2", 3, camera=HALF["cam2"])
    b = SyntheticCamera("two_pass", "cam2", 3, camera=HALF["cam2"])
    fa = [a.frame(i) for i in (40, 41, 40)]
    fb = b.frame(40)
    assert np.array_equal(fa[0][0], fb[0]) and np.array_equal(fa[0][1], fb[1])
    assert np.array_equal(fa[0][0], fa[2][0])  # random access: frame 41 in between changes nothing
    assert not np.array_equal(fa[0][0], fa[1][0])
    c = SyntheticCamera("two_pass", "cam2", 4, camera=HALF["cam2"])
    assert not np.array_equal(c.frame(40)[0], fb[0])


def test_source_interface_and_background_clip(tmp_path):
    src = SyntheticCamera("enter_exit", "cam4", 0, camera=HALF["cam4"])
    assert src.fps == 15.0 and src.n_frames == 750 and src.n_background_frames == 45
    assert src.stamp_ns(15) - src.stamp_ns(0) == 1_000_000_000
    bgr, mask = src.frame(0)
    assert bgr.shape == (240, 320, 3) and bgr.dtype == np.uint8
    assert mask.shape == (240, 320) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
    assert not mask.any()  # nobody has come in yet
    bg = src.background_frame(44)
    assert bg.shape == bgr.shape
    with pytest.raises(ValueError, match="frame index"):
        src.frame(750)
    with pytest.raises(ValueError, match="frame index"):
        src.background_frame(45)
    with pytest.raises(ValueError, match="cameras are"):
        SyntheticCamera("walk", "cam9")
    # A site file's calibration gives the same images as the built-in camera.
    default_site(tmp_path)
    from_site = SyntheticCamera("walk", "cam5", 0, site=tmp_path / "site.toml")
    built_in = SyntheticCamera("walk", "cam5", 0)
    assert np.array_equal(from_site.frame(60)[0], built_in.frame(60)[0])
