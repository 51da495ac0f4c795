"""Furniture that hides people: lines of sight by hand, the site's ``[[occluders]]``, and a
person behind a kitchen counter carved whole only when the counter is known."""

from __future__ import annotations

import numpy as np
import pytest

from common.site import SiteError, is_convex, site_from_dict
from fusion_server.carving import Carver
from evaluation.carving_bench import Box, Cylinder, MaskRenderer, body_voxels, room_rig
from fusion_server.carving.lut import HIDDEN, compute_lut, load_or_compute_lut, lut_key
from fusion_server.carving.occlusion import Occluder, blocked
from fusion_server.carving.octree import octree_layout
from fusion_server.grid import VoxelGrid

VOLUME = dict(volume_min_m=(0.0, 0.0, 0.0), volume_max_m=(8.0, 6.0, 2.5))
# a box from x 1..2, y 0..1, 1 m tall
BOX = Occluder("box", ((1.0, 0.0), (2.0, 0.0), (2.0, 1.0), (1.0, 1.0)), 0.0, 1.0)


def test_lines_of_sight_by_hand():
    eye = np.array([0.0, 0.5, 0.5])
    points = np.array([
        [3.0, 0.5, 0.5],   # straight through the box: hidden
        [0.5, 0.5, 0.5],   # in front of it: seen
        [3.0, 0.5, 2.5],   # the line rises over it (z 1.2-1.7 above the box): seen
        [3.0, 0.5, 1.0],   # z 0.67-0.83 over the box's footprint: hidden
        [1.5, 0.5, 0.5],   # inside the box: hidden
        [3.0, 3.0, 0.5],   # beside it: seen
        [1.5, 0.5, 2.0],   # above its top, over its near side at z 1.55: seen
        [1.5, 0.5, 1.2],   # above its top, but the line cuts its near side at z 0.99: hidden
    ])
    assert blocked(eye, points, [BOX]).tolist() == [True, False, False, True, True, False, False, True]


def test_a_line_grazing_a_side_within_the_margin_is_seen_and_winding_does_not_matter():
    eye = np.array([0.0, 0.97, 0.5])
    far = np.array([[3.0, 0.97, 0.5], [3.0, 0.9, 0.5]])  # 3 cm inside the side y = 1, then 10 cm
    assert blocked(eye, far, [BOX]).tolist() == [False, True]
    assert blocked(eye, far, [BOX], margin_m=0.0).tolist() == [True, True]
    clockwise = Occluder("box", tuple(reversed(BOX.polygon_m)), 0.0, 1.0)
    assert blocked(eye, far, [clockwise]).tolist() == [False, True]


def test_convexity_by_hand():
    assert is_convex([(0, 0), (1, 0), (1, 1), (0, 1)])
    assert is_convex([(0, 0), (0, 1), (1, 1), (1, 0)])  # clockwise
    assert is_convex([(0, 0), (0.5, 0), (1, 0), (1, 1), (0, 1)])  # a collinear point
    assert not is_convex([(0, 0), (2, 0), (2, 2), (1, 0.5), (0, 2)])  # a notch
    assert not is_convex([(0, 0), (1, 0), (2, 0)])  # no area
    with pytest.raises(ValueError, match="convex"):
        Occluder("notch", ((0, 0), (2, 0), (2, 2), (1, 0.5), (0, 2)), 0.0, 1.0)
    with pytest.raises(ValueError, match="z_min_m < z_max_m"):
        Occluder("flat", BOX.polygon_m, 1.0, 1.0)


def _site(occluders):
    return {"name": "flat", "cameras": [{"id": "cam1", "calibration": "calib/cam1.toml"}], "occluders": occluders}


def test_site_occluders_are_read_and_bad_ones_stop_start_up(tmp_path):
    site = site_from_dict(_site([{"name": "counter", "polygon_m": [[0, 0], [2, 0], [2, 0.6], [0, 0.6]],
                                  "z_m": [0.0, 0.9]}]), base_dir=tmp_path)
    assert site.occluders[0].name == "counter" and site.occluders[0].z_m == (0.0, 0.9)
    with pytest.raises(SiteError, match=r"occluders\[0\]\.polygon_m.*convex"):
        site_from_dict(_site([{"name": "L", "polygon_m": [[0, 0], [2, 0], [2, 2], [1, 0.5], [0, 2]], "z_m": [0, 1]}]),
                       base_dir=tmp_path)
    with pytest.raises(SiteError, match=r"occluders\[0\]\.z_m.*bottom < top"):
        site_from_dict(_site([{"name": "counter", "polygon_m": [[0, 0], [2, 0], [2, 1]], "z_m": [0.9, 0.2]}]),
                       base_dir=tmp_path)


@pytest.fixture(scope="module")
def rig():
    return room_rig(n_cameras=5, width=320, height=240)


def test_tables_hide_exactly_the_voxels_seen_through_an_occluder(rig):
    """Finest voxels by the line to their centre (not visible); a coarse voxel when the line to
    its centre or to any of its 8 corners is blocked (HIDDEN: it may reach behind the counter and
    still hold free space, so the camera lets its children decide)."""
    grid = VoxelGrid.from_bounds(np.array([0.0, 0.0, 0.0]), np.array([8.0, 6.0, 2.5]), 0.1)
    layout = octree_layout(grid.shape, 2)
    counter = Occluder("counter", ((3.0, 2.0), (5.0, 2.0), (5.0, 2.6), (3.0, 2.6)), 0.0, 0.9)
    corners = np.array([(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=float)
    for cam in rig.values():
        plain, hidden = compute_lut(cam, grid, layout), compute_lut(cam, grid, layout, [counter])
        assert lut_key(cam, grid, layout) != lut_key(cam, grid, layout, [counter])
        assert lut_key(cam, grid, layout, ()) == plain.key
        for level, factor in enumerate(layout.factors):
            finest = level == len(layout.factors) - 1
            gone = (plain.pixel[level] >= 0) & (hidden.pixel[level] < 0)
            kept = hidden.pixel[level] >= 0
            assert np.all(plain.pixel[level][kept] == hidden.pixel[level][kept])  # nothing else changes
            assert np.all(hidden.pixel[level][gone] == (-1 if finest else HIDDEN))
            size = grid.voxel_m * factor
            low = grid.origin_m + np.stack(np.unravel_index(np.arange(len(gone)), layout.dims[level]), axis=1) * size
            expect = blocked(cam.center, low + 0.5 * size, [counter])
            if not finest:
                for off in corners:
                    expect |= blocked(cam.center, low + off * size, [counter])
            assert np.array_equal(gone, expect & (plain.pixel[level] >= 0))
            assert gone.any()


def test_tables_with_hidden_voxels_are_read_back_from_the_cache(rig, tmp_path):
    """Coarse voxels partly behind an occluder hold HIDDEN (-2): the cached file is read back as it
    was written, not taken for a corrupt one and computed again at every start (it was: a fusion
    server on the synthetic house spent 13.5 s of processor time on its tables at each start)."""
    grid = VoxelGrid.from_bounds(np.array([0.0, 0.0, 0.0]), np.array([8.0, 6.0, 2.5]), 0.1)
    layout = octree_layout(grid.shape, 2)
    counter = Occluder("counter", ((3.0, 2.0), (5.0, 2.0), (5.0, 2.6), (3.0, 2.6)), 0.0, 0.9)
    for cam in rig.values():
        written, first = load_or_compute_lut(cam, grid, layout, tmp_path, [counter])
        read, again = load_or_compute_lut(cam, grid, layout, tmp_path, [counter])
        assert first.status == "miss" and again.status == "hit", again.detail
        assert all(np.array_equal(a, b) for a, b in zip(read.pixel + read.radius_q, written.pixel + written.radius_q))
    assert any(np.any(p == HIDDEN) for p in written.pixel)


def test_a_person_behind_a_counter_is_carved_whole_only_when_the_counter_is_known(rig, lut_cache):
    """A person 0.25 m from a 1.1 m counter that hides their legs from the cameras on the other
    side: without the counter those cameras vote against the legs, with it they do not vote."""
    person = Cylinder(3.0, 3.0, 0.25, 1.75)
    counter = Box((3.3, 1.5, 0.0), (3.9, 4.5, 1.1))
    masks = MaskRenderer(rig).render([person], hidden_by=[counter])
    known = Occluder("counter", ((3.3, 1.5), (3.9, 1.5), (3.9, 4.5), (3.3, 4.5)), 0.0, 1.1)
    plain = Carver(cameras=rig, cache_dir=lut_cache, **VOLUME)
    aware = Carver(cameras=rig, cache_dir=lut_cache, occluders=[known], **VOLUME)
    truth = body_voxels(plain, [person])
    legs = truth.copy()
    legs[:, :, int(1.0 / plain.grid.voxel_m):] = False
    before = plain.carve(masks, 0).occupancy()
    after = aware.carve(masks, 0).occupancy()
    assert (before & legs).sum() < 0.5 * legs.sum()  # the counter costs the legs
    # all but the edge facing the counter, whose lines of sight graze it within the 5 cm margin
    assert (after & truth).sum() >= 0.95 * truth.sum()
    assert (after & legs).sum() >= 0.9 * legs.sum()
    assert (after & ~truth).sum() <= 2.0 * truth.sum()
    inside = body_voxels(plain, [Box((3.35, 1.55, 0.0), (3.85, 4.45, 1.1))])
    assert not (after & inside).any()  # nothing is carved inside the counter, but for its 5 cm margin
