"""Free space from depth cameras: hand-worked verdicts and footprints, and a phantom carved away.

The worked scene: a 6 x 6 x 2 m room, two people at (2, 2) and (4, 4). A
camera in the south and one in the west see both; their silhouettes cross
in a phantom at about (1.9, 3.7), between the people. A depth camera in the
north looks down the line x = 2: its ray through the phantom ends on the
person at (2, 2), 5 m away, so the phantom 1.6 m nearer is free space.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from common.camera import Camera, look_at
from common.site import load_site
from fusion_server.carving import Carver
from evaluation.carving_bench import Cylinder, MaskRenderer, body_voxels
from fusion_server.pipeline import FusionPipeline
from tinysite import BOX_XY, box_mask, write_site
from fusion_server.carving.freespace import (
    BEHIND, BODY_DEPTH_M, FREE, NO_MEASUREMENT, SURFACE, apply_verdicts, depth_tolerance_m, depth_verdicts,
    footprint_depth, footprint_level,
)

PEOPLE = [Cylinder(2.0, 2.0, 0.25, 1.7), Cylinder(4.0, 4.0, 0.25, 1.7)]
PHANTOM = Cylinder(1.9, 3.7, 0.35, 1.6)  # holds the silhouettes' crossing, clear of both people


def _camera(cid: str, pos, target) -> Camera:
    R, t = look_at(np.asarray(pos, dtype=np.float64), np.asarray(target, dtype=np.float64))
    return Camera.pinhole(cid, 320, 240, hfov_deg=70.0, R=R, t=t)


@pytest.fixture(scope="module")
def scene():
    cams = {
        "south": _camera("south", (3.0, -3.0, 1.0), (3.0, 3.0, 0.85)),
        "west": _camera("west", (-3.0, 3.0, 1.0), (3.0, 3.0, 0.85)),
        "north": _camera("north", (2.0, 9.0, 1.0), (2.0, 3.0, 0.85)),
    }
    carver = Carver(cameras=cams, volume_min_m=(0.0, 0.0, 0.0), volume_max_m=(6.0, 6.0, 2.0),
                    voxel_sizes_m=(0.4, 0.2, 0.1), cache_dir=None)
    renderer = MaskRenderer(cams)
    return carver, renderer.render(PEOPLE), renderer.render_depth(PEOPLE, ["north"]), cams


def _occupied(carver, result) -> np.ndarray:
    occ = np.zeros(carver.grid.shape, dtype=bool)
    occ[tuple(result.ijk.T)] = True
    return occ


# ---------------------------------------------------------------------- by hand


def test_tolerance_by_hand():
    # half the diagonal of a 10 cm voxel, plus 3 sigma of 1 cm + 1 % of 4 m
    assert depth_tolerance_m(np.array([4.0]), 0.1)[0] == pytest.approx(math.sqrt(3) * 0.05 + 3 * (0.01 + 0.04))


def test_verdicts_by_hand():
    tol = math.sqrt(3) * 0.05 + 3 * (0.01 + 0.04)  # 0.2366 at 4 m
    ranges = np.array([3.0, 4.0 - tol - 0.01, 4.0 - tol + 0.01, 4.0, 4.5, 4.0 + BODY_DEPTH_M + tol - 0.01,
                       4.0 + BODY_DEPTH_M + tol + 0.01, 2.0])
    measured = np.array([4.0] * 7 + [0.0])
    assert depth_verdicts(ranges, measured, 0.1).tolist() == [
        FREE, FREE, SURFACE, SURFACE, SURFACE, SURFACE, BEHIND, NO_MEASUREMENT]


def test_verdicts_overrule_only_cameras_that_see_the_voxel():
    verdicts = np.array([FREE, SURFACE, BEHIND, NO_MEASUREMENT, NO_MEASUREMENT, FREE])
    hit = np.array([True, False, True, True, False, False])
    seen = np.array([True, True, True, True, True, False])
    apply_verdicts(hit, seen, verdicts)
    assert hit.tolist() == [False, True, False, True, False, False]
    assert seen.tolist() == [True, True, False, True, True, False]


def test_footprint_is_the_nearest_measurement_ignoring_zeros():
    depth = np.zeros((9, 9), dtype=np.uint16)
    depth[4, 4] = 3000
    depth[4, 6] = 2500
    fp = footprint_depth(depth)
    # half-width 1: the 3 x 3 square about each pixel
    assert fp[0, 4, 4] == 3000 and fp[0, 4, 5] == 2500 and fp[0, 3, 3] == 3000
    assert fp[0, 0, 0] == 0 and fp[0, 4, 2] == 0
    # half-width 2: the 5 x 5 square reaches the nearer pixel from the centre
    assert fp[1, 4, 4] == 2500 and fp[1, 4, 2] == 3000 and fp[1, 0, 0] == 0
    # the widest squares cover the whole image
    assert np.all(fp[-1] == 2500)


def test_footprint_level_is_the_smallest_square_holding_the_circle():
    assert footprint_level(np.array([0.3, 1.0, 1.01, 3.9, 16.0, 31.5, 40.0, np.inf])).tolist() == [0, 0, 1, 2, 4, 5, 5, 5]


# ---------------------------------------------------------------------- the worked scene


def test_silhouettes_alone_keep_the_phantom(scene):
    carver, masks, _, _ = scene
    occ = _occupied(carver, carver.carve(masks, 0))
    assert np.count_nonzero(occ & body_voxels(carver, [PHANTOM]) & ~body_voxels(carver, PEOPLE)) > 100


def test_depth_removes_the_phantom_and_keeps_both_people(scene):
    carver, masks, depths, cams = scene
    plain = _occupied(carver, carver.carve(masks, 0))
    occ = _occupied(carver, carver.carve(masks, 0, depths=depths))
    phantom = body_voxels(carver, [PHANTOM]) & ~body_voxels(carver, PEOPLE)
    assert np.count_nonzero(occ & phantom) == 0
    for person in PEOPLE:
        inside = body_voxels(carver, [person])
        assert np.count_nonzero(occ & inside) == np.count_nonzero(inside)
        # nothing the silhouettes kept near a person is lost
        near = body_voxels(carver, [Cylinder(person.x_m, person.y_m, person.radius_m + 0.15, 1.8)])
        assert np.array_equal(occ & near, plain & near)
    assert not np.any(occ & ~plain)  # depth only ever removes


def test_depth_in_the_dense_carve_and_the_graph_cut_agree(scene):
    carver, masks, depths, cams = scene
    octree = carver.carve(masks, 0, depths=depths)
    dense = carver.carve_dense(masks, 0, depths=depths)
    assert set(map(tuple, octree.ijk.tolist())) <= set(map(tuple, dense.ijk.tolist()))
    cut = Carver(cameras=cams, grid=carver.grid, voxel_sizes_m=carver.voxel_sizes_m, cache_dir=None, fusion="graphcut",
                 smoothing=0.0)
    phantom = body_voxels(carver, [PHANTOM]) & ~body_voxels(carver, PEOPLE)
    assert np.count_nonzero(_occupied(cut, cut.carve(masks, 0, depths=depths)) & phantom) == 0


def test_missing_measurements_leave_the_silhouette_vote(scene):
    carver, masks, depths, cams = scene
    plain = carver.carve(masks, 0)
    none = carver.carve(masks, 0, depths={"north": np.zeros_like(depths["north"])})
    assert np.array_equal(plain.ijk, none.ijk)
    # the person behind the phantom unmeasured: the phantom stays
    holed = depths["north"].copy()
    holed[:, 100:220] = 0
    occ = _occupied(carver, carver.carve(masks, 0, depths={"north": holed}))
    phantom = body_voxels(carver, [PHANTOM]) & ~body_voxels(carver, PEOPLE)
    assert np.array_equal(occ & phantom, _occupied(carver, plain) & phantom)


def test_free_space_off_ignores_depth(scene):
    carver, masks, depths, cams = scene
    off = Carver(cameras=cams, grid=carver.grid,
                 voxel_sizes_m=carver.voxel_sizes_m, cache_dir=None, free_space=False)
    assert np.array_equal(off.carve(masks, 0, depths=depths).ijk, carver.carve(masks, 0).ijk)


@pytest.mark.parametrize(
    ("depths", "message"),
    [
        ({"east": np.zeros((240, 320), np.uint16)}, "depths['east']: unknown camera"),
        ({"north": np.zeros((240, 320), np.float32)}, "depths['north']: expected uint16"),
        ({"north": np.zeros((120, 160), np.uint16)}, "depths['north']: shape (120, 160) differs"),
    ],
)
def test_bad_depth_images_name_the_camera(scene, depths, message):
    carver, masks, _, _ = scene
    with pytest.raises(ValueError, match=re.escape(message)):
        carver.carve(masks, 0, depths=depths)


def test_depth_of_a_camera_without_a_mask_is_ignored(scene):
    carver, masks, depths, cams = scene
    without = {cid: m for cid, m in masks.items() if cid != "north"}
    assert np.array_equal(carver.carve(without, 0, depths=depths).ijk, carver.carve(without, 0).ijk)


def test_pipeline_passes_depth_images_to_the_carver(tmp_path):
    site_path, cams = write_site(tmp_path)
    pipeline = FusionPipeline.from_site(load_site(site_path), cameras=cams, cache_dir=tmp_path / "lut")
    masks = {cid: box_mask(cam, *BOX_XY) for cid, cam in cams.items()}
    # c1 measures a surface 1.5 m behind the box: the box is free space to it, and two of
    # three cameras are below min_ratio 0.75
    cam = cams["c1"]
    box_range_m = float(np.linalg.norm(np.array([*BOX_XY, 0.85]) - cam.center))
    far = np.where(masks["c1"] > 0, int((box_range_m + 1.5) * 1000), 0).astype(np.uint16)
    assert len(pipeline.step(masks, 0, 0).carve.ijk) > 0
    assert len(pipeline.step(masks, 33_000_000, 1, depths={"c1": far}).carve.ijk) == 0
