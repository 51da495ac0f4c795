"""Camera models against OpenCV's own projection and against hand-worked geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.camera import Camera, TsaiIntrinsics, look_at, matrix_to_rodrigues, pixel_index, rodrigues_to_matrix

# A real wide-angle lens (lab4cam cam1): strong barrel distortion that folds back beyond ~50 degrees.
LAB_K = dict(fx=490.756439, fy=493.26358, cx=334.690674, cy=222.39888)
LAB_DIST = (-3.68704915e-01, 2.03186616e-01, 3.26540467e-04, 1.78072587e-05, -7.12014362e-02)

PINHOLE_DISTS = {
    4: (0.08, -0.05, 1e-3, -2e-3),
    5: LAB_DIST,
    8: (0.1, -0.05, 1e-3, -2e-3, 0.01, 0.02, -0.01, 0.005),
    12: (0.1, -0.05, 1e-3, -2e-3, 0.01, 0.02, -0.01, 0.005, 1e-3, -1e-3, 2e-3, -2e-3),
    14: (0.1, -0.05, 1e-3, -2e-3, 0.01, 0.02, -0.01, 0.005, 1e-3, -1e-3, 2e-3, -2e-3, 0.01, -0.02),
}
FISHEYE_DIST = (0.05, -0.01, 0.002, -0.0005)
PETS_TSAI = TsaiIntrinsics(focal_mm=5.5549183034, kappa1=5.1113043639e-3, dpx=5.1273271277e-3, dpy=4.65e-3,
                           sx=1.0937855397, cx=324.22149053, cy=282.56650051)


def _room_camera(model: str, dist=(), **kw) -> Camera:
    R, t = look_at((3.0, 1.0, 2.5), (0.0, 0.0, 0.8))
    if model == "pinhole":
        return Camera.pinhole("c", 644, 486, dist=dist, R=R, t=t, **(kw or LAB_K))
    if model == "fisheye":
        return Camera.fisheye("c", 800, 800, hfov_deg=170, dist=dist, R=R, t=t)
    return Camera.from_tsai("c", 768, 576, kw.get("tsai", PETS_TSAI), R=R, t=t)


def _points(rng: np.random.Generator, n: int = 5000) -> np.ndarray:
    return rng.uniform([-4.0, -4.0, 0.0], [4.0, 4.0, 2.5], (n, 3))


@pytest.mark.parametrize("n_coeffs", sorted(PINHOLE_DISTS))
def test_pinhole_matches_cv2_project_points(n_coeffs):
    cam = _room_camera("pinhole", PINHOLE_DISTS[n_coeffs])
    pts = _points(np.random.default_rng(n_coeffs))
    uv, valid = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, matrix_to_rodrigues(cam.R), cam.t, cam.K, cam.dist)
    ref = ref.reshape(-1, 2)
    assert valid.sum() > 1000
    np.testing.assert_allclose(uv[valid], ref[valid], rtol=0, atol=1e-6)


def test_fisheye_matches_cv2_fisheye_project_points():
    cam = _room_camera("fisheye", FISHEYE_DIST)
    pts = _points(np.random.default_rng(7))
    uv, valid = cam.project(pts)
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), matrix_to_rodrigues(cam.R), cam.t, cam.K, cam.dist)
    ref = ref.reshape(-1, 2)
    assert valid.sum() > 1000
    np.testing.assert_allclose(uv[valid], ref[valid], rtol=0, atol=1e-6)


def test_behind_camera_is_invalid_and_nan():
    cam = Camera.pinhole("c", 640, 480, fx=500.0)  # identity pose: camera frame = world frame
    uv, valid = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.1, 0.1, 1e-9], [0.0, 0.0, 2.0]]))
    assert valid.tolist() == [False, False, False, True]
    assert np.isnan(uv[:3]).all()
    np.testing.assert_allclose(uv[3], [319.5, 239.5])


def test_image_bounds_are_the_hull_of_pixel_centres():
    cam = Camera.pinhole("c", 640, 480, fx=500.0, cx=319.5, cy=239.5)
    # normalised x = (u - cx) / fx at depth 1: u = 0, 639 inside; -0.01 and 639.01 outside
    u = np.array([0.0, 639.0, -0.01, 639.01, 320.0, 320.0])
    v = np.array([240.0, 240.0, 240.0, 240.0, 479.0, 479.01])
    pts = np.stack([(u - 319.5) / 500.0, (v - 239.5) / 500.0, np.ones_like(u)], axis=1)
    uv, valid = cam.project(pts)
    assert valid.tolist() == [True, True, False, False, True, False]
    np.testing.assert_allclose(uv[:, 0], u, atol=1e-9)
    idx = pixel_index(uv[valid])
    assert idx[:, 0].min() >= 0 and idx[:, 0].max() <= 639 and idx[:, 1].max() <= 479


def test_wrap_around_of_strong_barrel_distortion_is_rejected():
    cam = Camera.pinhole("c", 644, 486, dist=LAB_DIST, **LAB_K)
    assert 1.15 < cam.max_radius < 1.25  # d(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6) peaks near r = 1.2
    # r = 1.6 (58 degrees off axis) is outside the ~41 degree half field of view, yet the polynomial
    # d(1.6) = 1.6 (1 - 0.944 + 1.331 - 1.195) = 0.31 folds it back to ~150 px from the centre.
    r = 1.6
    far = np.array([[r * np.cos(0.3), r * np.sin(0.3), 1.0]])
    ref, _ = cv2.projectPoints(far, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    u, v = ref.ravel()
    assert 0 <= u < 644 and 0 <= v < 486, "OpenCV folds the point back into the image"
    uv, valid = cam.project(far)
    assert not valid[0]
    assert np.isnan(uv).all()
    # just inside the monotonic range projections still agree with OpenCV
    near = np.array([[0.5, 0.3, 1.0], [-0.6, -0.4, 1.0]])
    uv, valid = cam.project(near)
    ref, _ = cv2.projectPoints(near, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_pixel_rays_leave_unreachable_corners_nan():
    cam = Camera.pinhole("c", 644, 486, dist=LAB_DIST, **LAB_K)
    rays = cam.pixel_rays()
    assert rays.shape == (486, 644, 3) and rays.dtype == np.float32
    nan = np.isnan(rays[..., 0])
    # the distorted radius peaks at d(max_radius) ~ 0.81 < the image corners' ~0.87: only corners are lost
    assert nan[0, 0] and nan[-1, 0] and nan[-1, -1]
    assert not nan[243, :].any() and not nan[:, 322].any()
    assert nan.mean() < 0.01
    # every ray that exists projects back to its own pixel (float32 rays: to 1e-3 px, so pixels on
    # the outermost rows and columns may land a hair outside the image)
    v, u = np.nonzero(~nan)
    sel = np.random.default_rng(3).choice(u.size, 4000, replace=False)
    pix = np.stack([u[sel], v[sel]], axis=1).astype(np.float64)
    back, valid = cam.project(cam.center + 3.0 * rays[v[sel], u[sel]].astype(np.float64))
    inner = (pix[:, 0] > 0) & (pix[:, 0] < 643) & (pix[:, 1] > 0) & (pix[:, 1] < 485)
    assert valid[inner].all()
    np.testing.assert_allclose(back, pix, atol=1e-3)


def test_pixel_rays_kept_for_the_same_camera_are_its_own_and_a_fresh_copy():
    cam = Camera.pinhole("c", 160, 120, dist=LAB_DIST, **LAB_K)
    first = cam.pixel_rays()
    first[:] = 7.0                                   # a caller's change stays its own
    again = Camera.pinhole("other id", 160, 120, dist=LAB_DIST, **LAB_K).pixel_rays()
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    direct = cam.rays(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(120, 160, 3).astype(np.float32)
    np.testing.assert_array_equal(again, direct)      # the same lens and pose: the same rays
    turned = Camera.pinhole("c", 160, 120, dist=LAB_DIST, R=rodrigues_to_matrix([0.0, 0.3, 0.0]), **LAB_K)
    assert not np.allclose(turned.pixel_rays(), direct, equal_nan=True)   # another pose: other rays


@pytest.mark.parametrize("model", ["pinhole", "fisheye", "tsai"])
def test_rays_and_project_round_trip(model):
    dist = {"pinhole": LAB_DIST, "fisheye": FISHEYE_DIST, "tsai": ()}[model]
    cam = _room_camera(model, dist)
    rng = np.random.default_rng(11)
    pix = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (3000, 2))
    rays = cam.rays(pix)
    ok = ~np.isnan(rays[:, 0])
    if model == "fisheye":
        # the 170-degree lens sees beyond 90 degrees off axis in the image corners; those rays point
        # behind the camera plane, which the model does not represent: exactly they are NaN
        k1, k2, k3, k4 = FISHEYE_DIST
        th = np.pi / 2
        theta_d_90 = th * (1 + k1 * th**2 + k2 * th**4 + k3 * th**6 + k4 * th**8)
        theta_d = np.hypot(*((pix - cam.K[:2, 2]) / np.diag(cam.K)[:2]).T)
        np.testing.assert_array_equal(ok, theta_d < theta_d_90)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.linalg.norm(rays[ok], axis=1), 1.0, atol=1e-12)
    depth = rng.uniform(0.5, 20.0, ok.sum())
    back, valid = cam.project(cam.center + depth[:, None] * rays[ok])
    assert valid.all()
    np.testing.assert_allclose(back, pix[ok], rtol=0, atol=1e-6)
    # and the other way: world points -> pixels -> rays point at the points
    pts = _points(rng)
    uv, valid = cam.project(pts)
    d = pts[valid] - cam.center
    np.testing.assert_allclose(cam.rays(uv[valid]), d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-9)


def test_tsai_distortion_hand_worked():
    # kappa1 = 0.01 /mm^2, f = 10 mm, dpx = dpy = 0.01 mm, sx = 1, centre (100, 50).
    ts = TsaiIntrinsics(focal_mm=10.0, kappa1=0.01, dpx=0.01, dpy=0.01, sx=1.0, cx=100.0, cy=50.0)
    cam = Camera.from_tsai("t", 400, 200, ts)
    # distorted sensor point Xd = 1 mm, Yd = 0: pixel u = 1 / 0.01 + 100 = 200, v = 50;
    # undistorted Xu = 1 * (1 + 0.01 * 1) = 1.01 mm, so the ray is (1.01, 0, 10).
    uv, valid = cam.project(np.array([[1.01, 0.0, 10.0]]))
    assert valid[0]
    np.testing.assert_allclose(uv[0], [200.0, 50.0], atol=1e-9)
    np.testing.assert_allclose(cam.rays(np.array([[200.0, 50.0]]))[0], np.array([1.01, 0, 10]) / np.hypot(1.01, 10), atol=1e-12)
    # sx stretches only u; Xd = 0.5 mm, Yd = -0.3 mm: r^2 = 0.34, factor 1.0034
    ts2 = TsaiIntrinsics(focal_mm=10.0, kappa1=0.01, dpx=0.01, dpy=0.02, sx=1.2, cx=100.0, cy=50.0)
    cam2 = Camera.from_tsai("t", 400, 200, ts2)
    uv, _ = cam2.project(np.array([[0.5 * 1.0034, -0.3 * 1.0034, 10.0]]))
    np.testing.assert_allclose(uv[0], [1.2 * 0.5 / 0.01 + 100.0, -0.3 / 0.02 + 50.0], atol=1e-9)


def test_tsai_negative_kappa_limits_the_radius():
    ts = TsaiIntrinsics(focal_mm=10.0, kappa1=-0.01, dpx=0.01, dpy=0.01, sx=1.0, cx=1000.0, cy=1000.0)
    cam = Camera.from_tsai("t", 2000, 2000, ts)
    # r_u(r_d) = r_d (1 - 0.01 r_d^2) peaks at r_d = 1/sqrt(0.03) with r_u = 2/3 r_d
    rd_max = 1 / np.sqrt(0.03)
    assert cam.max_radius == pytest.approx(2 / 3 * rd_max / 10.0)
    inside = np.array([[0.9 * cam.max_radius, 0.0, 1.0]])
    outside = np.array([[1.1 * cam.max_radius, 0.0, 1.0]])
    assert cam.project(inside)[1][0] and not cam.project(outside)[1][0]


def test_look_at_and_center():
    R, t = look_at((4.0, 0.0, 2.0), (0.0, 0.0, 1.0))
    cam = Camera.pinhole("c", 640, 480, fx=500.0, R=R, t=t)
    np.testing.assert_allclose(cam.center, [4.0, 0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(cam.R.T @ cam.R, np.eye(3), atol=1e-12)
    uv, valid = cam.project(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.5], [0.0, -1.0, 1.0]]))
    assert valid.all()
    np.testing.assert_allclose(uv[0], [319.5, 239.5], atol=1e-9)  # target on the principal point
    assert uv[1, 1] < uv[0, 1]  # higher in the world is higher in the image
    assert uv[2, 0] < uv[0, 0]  # looking along -X with Z up, right is forward x up = +Y: -Y is left
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 3), (0, 0, 0))


def test_with_world_maps_points_consistently():
    cam = _room_camera("pinhole", LAB_DIST)
    rng = np.random.default_rng(5)
    A = rodrigues_to_matrix([0.2, -0.4, 1.1])
    b = np.array([1.0, -2.0, 0.5])
    moved = cam.with_world(A, b, scale=0.001)  # current frame in mm, new one in metres
    pts_old = _points(rng) * 1000.0
    pts_new = 0.001 * pts_old @ A.T + b
    in_metres = cam.with_world(np.eye(3), np.zeros(3), 0.001)
    np.testing.assert_allclose(moved.project(pts_new)[0], in_metres.project(pts_old * 0.001)[0], atol=1e-9)
    np.testing.assert_allclose(moved.center, 0.001 * A @ cam.center + b, atol=1e-12)


@pytest.mark.parametrize("model", ["pinhole", "fisheye", "tsai"])
def test_resized_camera_follows_cv2_resize_geometry(model):
    dist = {"pinhole": LAB_DIST, "fisheye": FISHEYE_DIST, "tsai": ()}[model]
    cam = _room_camera(model, dist)
    small = cam.resized(cam.width // 2, cam.height // 4)
    sx, sy = small.width / cam.width, small.height / cam.height
    pts = _points(np.random.default_rng(2))
    uv, valid = cam.project(pts)
    uv2, _ = small.project(pts)
    np.testing.assert_allclose(uv2[valid], np.stack([sx * (uv[valid, 0] + 0.5) - 0.5, sy * (uv[valid, 1] + 0.5) - 0.5], 1), atol=1e-9)
    assert cam.scaled(0.5).width == cam.width // 2


def test_resized_camera_agrees_with_a_resized_image():
    # Render a dot pattern, shrink it with INTER_AREA, find the dot centroids: they sit where the
    # resized camera projects the dots.
    cam = Camera.pinhole("c", 640, 480, fx=400.0)
    pts = np.array([[x, y, 4.0] for x in (-1.5, 0.0, 1.2) for y in (-1.0, 0.4, 1.1)])
    uv, valid = cam.project(pts)
    assert valid.all()
    img = np.zeros((480, 640), np.float32)
    vv, uu = np.mgrid[0:480, 0:640]
    for u, v in uv:
        img += np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * 6.0**2))
    small_img = cv2.resize(img, (160, 120), interpolation=cv2.INTER_AREA)
    small = cam.resized(160, 120)
    uv_small, _ = small.project(pts)
    vs, us = np.mgrid[0:120, 0:160]
    for u, v in uv_small:
        win = (np.abs(us - u) < 6) & (np.abs(vs - v) < 6)
        w = small_img * win
        centroid = np.array([(w * us).sum() / w.sum(), (w * vs).sum() / w.sum()])
        np.testing.assert_allclose(centroid, [u, v], atol=0.02)


def test_camera_rejects_bad_fields():
    with pytest.raises(ValueError, match="K must have shape"):
        Camera(id="c", model="pinhole", width=10, height=10, K=np.eye(2), dist=(), R=np.eye(3), t=np.zeros(3))
    with pytest.raises(ValueError, match="R must be a rotation"):
        Camera(id="c", model="pinhole", width=10, height=10, K=np.eye(3), dist=(), R=np.diag([1.0, 1.0, -1.0]), t=np.zeros(3))
    with pytest.raises(ValueError, match="pinhole dist"):
        Camera(id="c", model="pinhole", width=10, height=10, K=np.eye(3), dist=(0.1, 0.2), R=np.eye(3), t=np.zeros(3))
    with pytest.raises(ValueError, match="fisheye dist"):
        Camera.fisheye("c", 10, 10, fx=5.0, dist=(0.1,))
    with pytest.raises(ValueError, match="t must be finite"):
        Camera.pinhole("c", 10, 10, fx=5.0, t=(0.0, np.nan, 0.0))
    with pytest.raises(ValueError, match="width"):
        Camera.pinhole("c", 0, 10, fx=5.0)
    with pytest.raises(ValueError, match="points_w"):
        Camera.pinhole("c", 10, 10, fx=5.0).project(np.zeros((4, 2)))


def test_camera_arrays_are_read_only():
    cam = Camera.pinhole("c", 10, 10, fx=5.0)
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0
