"""Graph-cut occupancy against hand-worked energies, brute force over every labelling, and the vote."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_server.carving import Carver
from evaluation.carving_bench import Cylinder, MaskRenderer, body_voxels, room_rig
from fusion_server.carving.distance import needed_votes
from fusion_server.carving.graphcut import (
    ENERGY_SCALE, benefits, graphcut_labels, labelling_energy, neighbour_pairs, potts_cut,
)

VOLUME = dict(volume_min_m=(0.0, 0.0, 0.0), volume_max_m=(8.0, 6.0, 2.5))


def _all_labellings(m: int) -> np.ndarray:
    """(2^m, m) bool: every labelling of m voxels."""
    codes = np.arange(2**m, dtype=np.int64)
    return ((codes[:, None] >> np.arange(m)) & 1).astype(bool)


# ---------------------------------------------------------------------- pieces by hand


def test_benefits_by_hand():
    # min_ratio 0.75, min_cameras 2: 2 (found - need + 1/2) / seeing in thousandths;
    # need is 4 of 5, 3 of 4, 2 of 2, 6 of 8
    found = np.array([5, 4, 3, 1, 3, 2, 2, 6, 5, 8])
    seeing = np.array([5, 5, 5, 5, 4, 4, 2, 8, 8, 8])
    assert benefits(found, seeing, n_cameras=8, min_cameras=2, min_ratio=0.75).tolist() == [
        600, 200, -200, -1000, 250, -250, 500, 125, -125, 625]


def test_neighbour_pairs_by_hand():
    shape = (3, 3, 2)
    # (0,0,0), (0,0,1), (0,2,1): one pair; 2, 2 and 3 in-grid neighbours outside
    pairs, outside = neighbour_pairs(np.array([0, 1, 5]), shape)
    assert pairs.tolist() == [[0, 1]]
    assert outside.tolist() == [2, 2, 3]
    pairs, outside = neighbour_pairs(np.arange(18), shape)
    assert len(pairs) == 2 * 3 * 2 + 3 * 2 * 2 + 3 * 3 * 1 and not outside.any()


def test_potts_cut_on_a_hand_worked_chain():
    # a chain of three voxels, benefits 5, -3, 2, each pair costs 4:
    # 111 -> 3, 110 -> 2 + 4 = 6, 100 -> 2 + 4 = 6, 101 -> 8, 000 -> 7: all occupied
    pairs = np.array([[0, 1], [1, 2]])
    assert potts_cut(np.array([5, -3, 2]), pairs, 4).tolist() == [True, True, True]
    # pairs costing 1: 111 -> 3, 101 -> two cuts = 2, 100 -> 2 + 1 = 3: the middle is dropped
    assert potts_cut(np.array([5, -3, 2]), pairs, 1).tolist() == [True, False, True]


# ---------------------------------------------------------------------- brute force


@pytest.mark.parametrize("seed", range(6))
def test_potts_cut_reaches_the_brute_force_minimum_on_a_3x3x2_grid(seed):
    rng = np.random.default_rng(seed)
    shape = (3, 3, 2)
    pairs, _ = neighbour_pairs(np.arange(18), shape)
    unary = rng.integers(-60, 61, size=18)
    unary[unary == 0] = 1
    pair_cost = int(rng.integers(1, 40))
    labels = potts_cut(unary, pairs, pair_cost)
    energies = labelling_energy(_all_labellings(18), unary, pairs, pair_cost)
    assert labelling_energy(labels, unary, pairs, pair_cost) == energies.min()


@pytest.mark.parametrize("seed", range(4))
def test_graphcut_labels_equal_brute_force_with_fixed_voxels(seed):
    """A region of a 3x3x2 grid: voxels outside it and voxels fewer than min_cameras find
    are empty; the cut's labelling minimises the energy over the whole grid."""
    rng = np.random.default_rng(100 + seed)
    shape = (3, 3, 2)
    n_cams, min_cameras, min_ratio, smoothing = 4, 2, 0.75, float(rng.choice([0.02, 0.05, 0.1, 0.3]))
    region = np.sort(rng.choice(18, size=13, replace=False))
    seeing = rng.integers(2, n_cams + 1, size=13)
    found = np.minimum(rng.integers(0, n_cams + 1, size=13), seeing)
    labels = graphcut_labels(region, found, seeing, shape, n_cameras=n_cams, min_cameras=min_cameras,
                             min_ratio=min_ratio, smoothing=smoothing)

    all_pairs, _ = neighbour_pairs(np.arange(18), shape)
    need = needed_votes(n_cams, min_cameras, min_ratio)
    margin = 2 * (found - need[seeing].astype(int) + 0.5) / seeing
    unary = np.zeros(18, dtype=np.int64)
    unary[region] = np.rint(margin * ENERGY_SCALE).astype(np.int64)
    free = np.zeros(18, dtype=bool)
    free[region[found >= min_cameras]] = True
    free_idx = np.flatnonzero(free)
    full = np.zeros((2 ** free_idx.size, 18), dtype=bool)
    full[:, free_idx] = _all_labellings(free_idx.size)
    pair_cost = round(smoothing * ENERGY_SCALE)
    energies = labelling_energy(full, unary, all_pairs, pair_cost)
    mine = np.zeros(18, dtype=bool)
    mine[region[labels]] = True
    assert not np.any(mine & ~free)
    assert labelling_energy(mine, unary, all_pairs, pair_cost) == energies.min()


@pytest.mark.parametrize("pair_cost", [5, 40, 150])
def test_fixing_dominant_voxels_keeps_the_minimum(pair_cost):
    """The cut after fixing the voxels whose data term outweighs their neighbours reaches the
    energy of the cut over every voxel, on a noisy 12x12x12 block."""
    from fusion_server.carving.graphcut import _reduced_cut

    rng = np.random.default_rng(pair_cost)
    shape = (12, 12, 12)
    pairs, _ = neighbour_pairs(np.arange(12**3), shape)
    inside = np.zeros(shape, dtype=bool)
    inside[3:9, 3:9, 2:11] = True
    unary = np.where(inside.ravel(), 300, -300) + rng.integers(-400, 401, size=12**3)
    unary[unary == 0] = 1
    full = potts_cut(unary, pairs, pair_cost)
    reduced = _reduced_cut(unary, pairs, pair_cost)
    assert labelling_energy(reduced, unary, pairs, pair_cost) == labelling_energy(full, unary, pairs, pair_cost)


def test_lambda_zero_is_the_hard_vote():
    rng = np.random.default_rng(7)
    shape = (10, 8, 6)
    region = np.sort(rng.choice(480, size=300, replace=False))
    seeing = rng.integers(0, 6, size=300)
    found = np.minimum(rng.integers(0, 6, size=300), seeing)
    for min_cameras, min_ratio in ((2, 0.75), (1, 0.5), (3, 0.7501), (2, 0.7499)):
        labels = graphcut_labels(region, found, seeing, shape, n_cameras=5, min_cameras=min_cameras,
                                 min_ratio=min_ratio, smoothing=0.0)
        assert np.array_equal(labels, found >= needed_votes(5, min_cameras, min_ratio)[seeing])


# ---------------------------------------------------------------------- what lambda does


def _block(found_centre: int, found_around: int, *, seeing: int = 5):
    """A 5x5x5 region ``seeing`` cameras see: the centre voxel ``found_centre`` of them find,
    every other voxel ``found_around``."""
    shape = (5, 5, 5)
    region = np.arange(125)
    found = np.full(125, found_around)
    centre = np.ravel_multi_index((2, 2, 2), shape)
    found[centre] = found_centre
    return region, found, np.full(125, seeing), shape, centre


@pytest.mark.parametrize(("smoothing", "kept"), [(0.0, True), (0.033, True), (0.034, False)])
def test_a_speck_goes_when_six_lambda_exceeds_its_margin(smoothing, kept):
    # 4 of 5 cameras, the vote's need: margin 2 (4 - 4 + 1/2) / 5 = 0.2; around it 2 of 5
    region, found, seeing, shape, centre = _block(4, 2)
    labels = graphcut_labels(region, found, seeing, shape, n_cameras=5, min_cameras=2, min_ratio=0.75,
                             smoothing=smoothing)
    assert labels[centre] == kept
    assert labels.sum() == int(kept)


@pytest.mark.parametrize(("smoothing", "filled"), [(0.0, False), (0.020, False), (0.021, True)])
def test_a_one_voxel_hole_fills_when_six_lambda_exceeds_its_margin(smoothing, filled):
    # 5 of 8 cameras, one short of the need of 6: margin 2 (5 - 6 + 1/2) / 8 = -0.125;
    # the voxels around it all 8 cameras find
    region, found, seeing, shape, centre = _block(5, 8, seeing=8)
    labels = graphcut_labels(region, found, seeing, shape, n_cameras=8, min_cameras=2, min_ratio=0.75,
                             smoothing=smoothing)
    assert labels[centre] == filled
    assert labels.sum() == 124 + int(filled)


def test_a_hole_fewer_than_min_cameras_find_stays_empty():
    region, found, seeing, shape, centre = _block(1, 5)
    labels = graphcut_labels(region, found, seeing, shape, n_cameras=5, min_cameras=2, min_ratio=0.75, smoothing=1.0)
    assert not labels[centre] and labels.sum() == 124


# ---------------------------------------------------------------------- in the carver


BODIES = [Cylinder(2.0, 1.5, 0.25, 1.8), Cylinder(5.5, 4.0, 0.22, 1.6), Cylinder(3.0, 4.6, 0.2, 1.5)]


@pytest.fixture(scope="module")
def rig_and_masks():
    rig = room_rig(n_cameras=5, width=320, height=240)
    masks = MaskRenderer(rig).render(BODIES)
    rng = np.random.default_rng(3)
    for m in masks.values():  # salt and pepper: specks and holes for the smoothing to act on
        flip = rng.random(m.shape) < 0.01
        m[flip] = 255 - m[flip]
    return rig, masks


def test_carver_graph_cut_at_lambda_zero_is_the_vote_on_its_region(rig_and_masks, lut_cache):
    rig, masks = rig_and_masks
    cache = lut_cache
    vote = Carver(cameras=rig, voxel_sizes_m=(0.4, 0.2, 0.1), cache_dir=cache, **VOLUME)
    cut = Carver(cameras=rig, voxel_sizes_m=(0.4, 0.2, 0.1), cache_dir=cache, fusion="graphcut", smoothing=0.0,
                 **VOLUME)
    voted = {tuple(v) for v in vote.carve(masks, 0).ijk.tolist()}
    dense = {tuple(v) for v in vote.carve_dense(masks, 0).ijk.tolist()}
    labelled = {tuple(v) for v in cut.carve(masks, 0).ijk.tolist()}
    # the region adds the neighbours the octree skipped: what the cut adds passes the vote
    assert voted <= labelled <= dense


def test_carver_graph_cut_removes_noise_and_keeps_the_bodies(rig_and_masks, lut_cache):
    rig, masks = rig_and_masks
    cache = lut_cache
    vote = Carver(cameras=rig, voxel_sizes_m=(0.4, 0.2, 0.1), cache_dir=cache, **VOLUME)
    # 6 lambda = 0.9 outweighs even a speck all five cameras find (margin 2 (5 - 4 + 1/2) / 5 = 0.6)
    cut = Carver(cameras=rig, voxel_sizes_m=(0.4, 0.2, 0.1), cache_dir=cache, fusion="graphcut", smoothing=0.15,
                 **VOLUME)
    inside = body_voxels(vote, BODIES)
    near = body_voxels(vote, [Cylinder(b.x_m, b.y_m, b.radius_m + 0.3, b.height_m + 0.3) for b in BODIES])
    counts = []
    for carver in (vote, cut):
        ijk = tuple(carver.carve(masks, 0).ijk.T)
        counts.append((np.count_nonzero(inside[ijk]), np.count_nonzero(~near[ijk])))
    (vote_in, vote_far), (cut_in, cut_far) = counts
    assert cut_in >= 0.97 * np.count_nonzero(inside) and vote_in >= 0.97 * np.count_nonzero(inside)
    assert cut_far < 0.2 * vote_far  # the specks the noise carved far from anyone


@pytest.mark.parametrize(("kw", "name"), [({"fusion": "cut"}, "fusion"), ({"smoothing": -1.0}, "smoothing"),
                                          ({"smoothing": float("nan")}, "smoothing"), ({"free_space": 1}, "free_space")])
def test_bad_fusion_settings_name_the_argument(kw, name):
    rig = room_rig(n_cameras=2, width=64, height=48, fisheye=False)
    with pytest.raises(ValueError, match=name):
        Carver(cameras=rig, voxel_sizes_m=(0.4,), cache_dir=None, **VOLUME, **kw)
