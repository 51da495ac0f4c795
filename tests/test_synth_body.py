"""Articulated ellipsoid bodies: proportions, kinematics, containment, sampling, ray hits."""

from __future__ import annotations

import numpy as np
import pytest

from synth.body import (
    N_PARTS, N_Q, Q_HIP_FLEX, Q_KNEE, Q_PITCH, BodyShape, forward_kinematics, highest_point_m, lowest_point_m,
    pose_body, standing_pose,
)


@pytest.mark.parametrize("height", [1.5, 1.75, 1.95])
def test_standing_body_has_its_height_and_stands_on_the_floor(height):
    shape = BodyShape(height_m=height)
    body = pose_body(shape, standing_pose(shape, 2.0, 3.0, 0.3), person_id=4)
    assert body.person_id == 4
    assert body.z_top_m == pytest.approx(height, abs=0.01 * height)
    assert lowest_point_m(shape, standing_pose(shape))[0] == pytest.approx(0.0, abs=0.01)
    np.testing.assert_allclose(body.pelvis_m, [2.0, 3.0, shape.hip_height_m])
    lo, hi = body.aabb()
    assert hi[0] - lo[0] < 0.8 and hi[1] - lo[1] < 0.8


def test_random_shapes_vary_within_the_documented_range():
    rng = np.random.default_rng(3)
    shapes = [BodyShape.random(rng) for _ in range(200)]
    heights = np.array([s.height_m for s in shapes])
    assert heights.min() >= 1.5 and heights.max() <= 1.95 and heights.std() > 0.1
    assert len({s.shirt_bgr for s in shapes}) > 5
    with pytest.raises(ValueError, match="height_m"):
        BodyShape(height_m=3.0)


def test_batched_kinematics_equal_single_poses():
    shape = BodyShape(height_m=1.8, width=1.1)
    rng = np.random.default_rng(0)
    q = np.repeat(standing_pose(shape)[None, :], 5, axis=0) + rng.normal(0, 0.3, (5, N_Q)) * (np.arange(N_Q) >= 3)
    centers, axes = forward_kinematics(shape, q)
    assert centers.shape == (5, N_PARTS, 3) and axes.shape == (5, N_PARTS, 3, 3)
    for i in range(5):
        b = pose_body(shape, q[i])
        np.testing.assert_allclose(b.centers_m, centers[i])
        np.testing.assert_allclose(b.axes, axes[i])
    np.testing.assert_allclose(highest_point_m(shape, q), [pose_body(shape, qi).z_top_m for qi in q])


def test_joint_angles_move_the_limbs_the_documented_way():
    shape = BodyShape()
    q = standing_pose(shape)
    q[Q_HIP_FLEX[0]] = np.pi / 2  # left thigh forward (+x)
    b = pose_body(shape, q)
    assert b.centers_m[8, 0] > 0.15 and abs(b.centers_m[9, 0]) < 0.05
    q = standing_pose(shape)
    q[Q_KNEE[1]] = np.pi / 2  # right shank backward (-x)
    assert pose_body(shape, q).centers_m[11, 0] < -0.15
    q = standing_pose(shape)
    q[Q_PITCH] = np.pi / 2  # body tipped forward: the head goes to +x
    assert pose_body(shape, q).centers_m[3, 0] > 0.6


def test_samples_are_inside_and_containment_is_exact():
    shape = BodyShape(height_m=1.7)
    body = pose_body(shape, standing_pose(shape, 1.0, 1.0))
    rng = np.random.default_rng(1)
    pts = body.sample_points(4000, rng, surface_fraction=0.3)
    assert body.contains(pts).all()
    far = pts + np.array([0.0, 0.0, 3.0])
    assert not body.contains(far).any()
    # Volume of the body by Monte Carlo over its box agrees with the parts' union (< sum of parts).
    lo, hi = body.aabb()
    box = rng.uniform(lo, hi, size=(60000, 3))
    vol = np.prod(hi - lo) * body.contains(box).mean()
    assert 0.04 < vol < body.volumes_m3().sum()


def test_ray_hits_land_on_the_surface():
    shape = BodyShape()
    body = pose_body(shape, standing_pose(shape, 0.0, 0.0))
    origin = np.array([3.0, 0.5, 1.5])
    rng = np.random.default_rng(2)
    targets = body.sample_points(500, rng)
    d = targets - origin
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, part = body.intersect(origin, d)
    assert np.all(np.isfinite(t)) and np.all(part >= 0)
    hit = origin + t[:, None] * d
    assert not body.contains(hit - 1e-4 * d).any()
    assert body.contains(hit + 1e-4 * d).all()
    t_miss, part_miss = body.intersect(origin, np.array([[1.0, 0.0, 0.0]]))
    assert np.isinf(t_miss[0]) and part_miss[0] == -1
