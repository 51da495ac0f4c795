"""Top-down blob detection on hand-built voxel scenes (5 cm voxels)."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_server.detection import Blob, body_top_layers, detect_blobs
from fusion_server.grid import CarveResult, VoxelGrid, floor_maps

GRID = VoxelGrid.from_bounds((0.0, 0.0, 0.0), (4.0, 4.0, 2.0), 0.05)


def box(lo_m, hi_m, grid: VoxelGrid = GRID) -> np.ndarray:
    """Voxels whose centres lie in the axis-aligned box [lo_m, hi_m), (N, 3) int32."""
    lo = np.ceil((np.asarray(lo_m) - grid.origin_m) / grid.voxel_m - 0.5 - 1e-9).astype(int)
    hi = np.ceil((np.asarray(hi_m) - grid.origin_m) / grid.voxel_m - 0.5 - 1e-9).astype(int)
    axes = [np.arange(max(a, 0), min(b, n)) for a, b, n in zip(lo, hi, grid.shape)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.int32)


def cylinder(cx, cy, radius_m, z0_m, z1_m, grid: VoxelGrid = GRID) -> np.ndarray:
    """Voxels of an upright cylinder (centres inside), (N, 3) int32."""
    ijk = box((cx - radius_m, cy - radius_m, z0_m), (cx + radius_m, cy + radius_m, z1_m), grid)
    c = grid.centres(ijk)
    return ijk[(c[:, 0] - cx) ** 2 + (c[:, 1] - cy) ** 2 <= radius_m**2]


def standing(cx, cy, height_m=1.75) -> np.ndarray:
    """Body r 0.2 m up to the shoulders, head r 0.1 m above."""
    return np.concatenate([cylinder(cx, cy, 0.2, 0.0, height_m - 0.3), cylinder(cx, cy, 0.1, height_m - 0.3, height_m)])


def seated(cx, cy) -> np.ndarray:
    """A person on a stool facing +x: lower legs, thighs, knees that rise above the thighs, torso, head."""
    return np.concatenate(
        [
            cylinder(cx, cy, 0.18, 0.45, 1.05),  # torso from the seat up
            cylinder(cx, cy, 0.1, 1.05, 1.3),  # head
            box((cx, cy - 0.15, 0.45), (cx + 0.45, cy + 0.15, 0.52)),  # thighs
            box((cx + 0.35, cy - 0.15, 0.45), (cx + 0.47, cy + 0.15, 0.6)),  # knees
            box((cx + 0.35, cy - 0.15, 0.0), (cx + 0.45, cy + 0.15, 0.45)),  # lower legs
        ]
    )


def scene(*parts, grid: VoxelGrid = GRID, stamp_ns: int = 0) -> CarveResult:
    ijk = np.unique(np.concatenate(parts), axis=0).astype(np.int32)
    return CarveResult(ijk=ijk, grid=grid, floor=floor_maps(ijk, grid), stamp_ns=stamp_ns, cameras=("a", "b"))


def test_empty_scene_has_no_blobs():
    assert detect_blobs(scene(np.zeros((0, 3), np.int32))) == []


def test_single_person_blob_fields():
    res = scene(standing(1.0, 2.0))
    (b,) = detect_blobs(res)
    assert isinstance(b, Blob)
    assert b.x == pytest.approx(1.0, abs=0.03) and b.y == pytest.approx(2.0, abs=0.03)
    assert b.z_top_m == pytest.approx(1.75)
    assert b.volume_voxels == len(res.ijk) == b.ijk.shape[0]
    assert b.volume_m3 == pytest.approx(len(res.ijk) * 0.05**3)
    assert b.height_profile.shape == (GRID.shape[2],) and b.height_profile.dtype == np.int32
    assert b.height_profile.sum() == b.volume_voxels
    assert b.height_profile[34] == len(cylinder(1.0, 2.0, 0.1, 1.45, 1.75)) // 6  # a head layer
    assert b.height_profile[35:].sum() == 0
    assert np.array_equal(np.unique(b.footprint, axis=0), b.footprint)
    assert set(map(tuple, b.footprint)) == set(map(tuple, res.ijk[:, [1, 0]]))
    assert np.allclose(b.bbox_m, [[0.8, 1.8, 0.0], [1.2, 2.2, 1.75]])


def test_two_people_touching_only_below_tau1_stay_two():
    a, b = standing(1.0, 2.0), standing(1.6, 2.0)
    hands = box((1.15, 1.95, 0.8), (1.45, 2.05, 0.95))  # hands joined at 0.8-0.95 m
    feet = box((1.15, 1.9, 0.0), (1.45, 2.1, 0.1))  # shadow between the feet
    res = scene(a, b, hands, feet)
    blobs = detect_blobs(res, tau1_m=1.0)
    assert len(blobs) == 2
    xs = sorted(bl.x for bl in blobs)
    assert xs[0] == pytest.approx(1.0, abs=0.05) and xs[1] == pytest.approx(1.6, abs=0.05)
    # Every voxel lands in exactly one blob; the bridge is split at the middle.
    assert sum(bl.volume_voxels for bl in blobs) == len(res.ijk)
    assert np.unique(np.concatenate([bl.ijk for bl in blobs]), axis=0).shape[0] == len(res.ijk)
    left = min(blobs, key=lambda bl: bl.x)
    assert GRID.centres(left.ijk)[:, 0].max() < 1.31


def test_two_people_joined_above_tau1_stay_two_by_their_heads():
    # an arm over the shoulder joins them at 1.2-1.35 m, above tau1; each head rises 0.4 m above that
    a, b = standing(1.0, 2.0), standing(1.6, 2.0)
    shoulders = box((1.15, 1.95, 1.2), (1.45, 2.05, 1.35))
    blobs = detect_blobs(scene(a, b, shoulders), tau1_m=1.0)
    assert sorted(round(bl.x, 1) for bl in blobs) == [1.0, 1.6]
    assert len(detect_blobs(scene(a, b, shoulders), tau1_m=1.0, head_m=0.5)) == 1  # heads too low to count
    assert len(detect_blobs(scene(a, b, shoulders), tau1_m=1.4)) == 2


def test_two_people_shoulder_to_shoulder_are_split_at_the_middle():
    # 0.45 m apart: the bodies (r 0.2 m) overlap up to the shoulders (1.45 m) and only the heads
    # (r 0.1 m, 1.45-1.75 m) stand apart, 0.3 m over the meeting
    a, b = standing(1.0, 2.0), standing(1.45, 2.0)
    res = scene(a, b)
    left, right = sorted(detect_blobs(res), key=lambda bl: bl.x)
    assert left.x == pytest.approx(1.0, abs=0.05) and right.x == pytest.approx(1.45, abs=0.05)
    assert left.volume_voxels + right.volume_voxels == len(res.ijk)
    assert GRID.centres(left.ijk)[:, 0].max() < 1.26 and GRID.centres(right.ijk)[:, 0].min() > 1.19


def test_a_bump_near_the_head_is_not_a_second_person():
    # a raised hand 0.2 m beside the head, higher than it: closer than head_sep_m to the head
    person = standing(1.0, 2.0)
    hand = box((1.15, 1.95, 1.5), (1.25, 2.05, 1.85))
    (blob,) = detect_blobs(scene(person, hand), min_volume_m3=0.0)
    assert blob.z_top_m == pytest.approx(1.85)
    assert len(detect_blobs(scene(person, hand), min_volume_m3=0.0, head_sep_m=0.1)) == 2


def test_a_carving_gap_across_the_body_does_not_cut_it_in_two():
    # holes in the masks at 0.5-0.6 m leave the legs 0.1 m under the torso
    body = standing(2.0, 2.0)
    cut = GRID.centres(body)[:, 2]
    res = scene(body[(cut < 0.5) | (cut > 0.6)])
    (blob,) = detect_blobs(res)
    assert blob.volume_voxels == len(res.ijk) and blob.z_top_m == pytest.approx(1.75)
    assert len(detect_blobs(res, gap_m=0.0)) == 2  # without bridging: legs and torso apart
    # a gap wider than gap_m is not bridged
    wide = scene(body[(cut < 0.4) | (cut > 0.6)])
    assert len(detect_blobs(wide)) == 2


def test_seated_persons_knees_join_the_body_by_tau2():
    res = scene(seated(2.0, 2.0))
    (b,) = detect_blobs(res)
    assert b.volume_voxels == len(res.ijk)
    assert b.z_top_m == pytest.approx(1.3)
    # Without the rule the knees, born above the thighs and meeting the torso
    # at 0.5 m (below tau1), become a separate target.
    assert len(detect_blobs(res, tau2_m=0.0, min_volume_m3=0.0)) == 2


def test_seated_person_touching_a_table_is_merged():
    person = seated(2.0, 2.0)
    table = np.concatenate(
        [box((1.3, 1.6, 0.7), (1.75, 2.4, 0.8)), box((1.3, 1.6, 0.0), (1.35, 1.65, 0.7)), box((1.3, 2.35, 0.0), (1.35, 2.4, 0.7))]
    )  # table top 0.8 m, 7 cm in front of the torso
    forearm = box((1.6, 1.95, 0.6), (1.85, 2.05, 0.7))  # from the torso to under the table top
    res = scene(person, table, forearm)
    (b,) = detect_blobs(res)
    assert b.volume_voxels == len(res.ijk)
    assert b.z_top_m == pytest.approx(1.3)
    assert len(detect_blobs(res, tau2_m=0.0, min_volume_m3=0.0)) == 3  # person, knees, table


def test_person_lying_in_pieces_is_one_blob():
    head = cylinder(1.0, 2.0, 0.1, 0.0, 0.3)
    torso = box((1.15, 1.8, 0.0), (1.75, 2.2, 0.35))
    legs = box((1.75, 1.85, 0.0), (2.6, 2.15, 0.12))
    feet = box((2.6, 1.85, 0.0), (2.7, 2.15, 0.25))
    neck = box((1.05, 1.95, 0.0), (1.15, 2.05, 0.15))
    res = scene(head, torso, legs, feet, neck)
    (b,) = detect_blobs(res)
    assert b.volume_voxels == len(res.ijk)
    assert b.z_top_m == pytest.approx(0.35)
    assert len(detect_blobs(res, tau2_m=0.0, min_volume_m3=0.0)) == 3  # head, torso, feet


def test_a_thin_tent_of_hull_over_a_lying_body_is_not_its_top():
    """A body lying on the floor (torso 0.35 m high) under a ridge of hull 0.2 x 0.1 m up to 1.2 m,
    where the cameras' cones cross above it: one blob, its top 1.2 m, its body's top 0.35 m. Layer
    areas (voxels) 198, 198, 96 x 5, then 8 to the ridge's top; as 3-layer running means the widest
    is 164 (layer 1), and the highest at least a quarter of that is layer 6 ((96 + 96 + 8) / 3),
    whose top face is at 0.35 m; layer 7 ((96 + 8 + 8) / 3 = 37.3) is under 41."""
    head = cylinder(1.0, 2.0, 0.1, 0.0, 0.3)
    torso = box((1.15, 1.8, 0.0), (1.75, 2.2, 0.35))
    legs = box((1.75, 1.85, 0.0), (2.6, 2.15, 0.12))
    tent = box((1.35, 1.95, 0.35), (1.55, 2.05, 1.2))
    (b,) = detect_blobs(scene(head, torso, legs, tent))
    assert b.z_top_m == pytest.approx(1.2)
    assert list(b.height_profile[:8]) == [198, 198, 96, 96, 96, 96, 96, 8]
    assert b.body_top_m == pytest.approx(0.35)
    assert body_top_layers(b.height_profile) == 7


def test_a_standing_persons_body_top_is_at_their_chin():
    """The standing body of these tests (52 voxels a layer to 1.45 m, a head of 12 above, to 1.75 m):
    the first head layer's running mean (52 + 12 + 12) / 3 = 25.3 is at least a quarter of 52, the
    next (12) is not: the body's top is 1.5 m. An empty profile has no body."""
    (b,) = detect_blobs(scene(standing(1.0, 2.0)))
    assert list(b.height_profile[28:31]) == [52, 12, 12]
    assert b.body_top_m == pytest.approx(1.5)
    assert body_top_layers(np.zeros(40, np.int32)) == 0
    with pytest.raises(ValueError, match=r"height_profile must be 1-D.*\(2, 20\)"):
        body_top_layers(np.ones((2, 20), np.int32))


def test_tau2_is_relative_to_the_meeting_height():
    # A seated person's head is 0.4 m above the hands where they touch a
    # standing neighbour: two people, not one.
    stand = standing(1.0, 2.0)
    sit = seated(1.6, 2.0)
    hands = box((1.15, 1.95, 0.8), (1.45, 2.05, 0.9))
    blobs = detect_blobs(scene(stand, sit, hands))
    assert len(blobs) == 2
    assert sorted(round(b.z_top_m, 2) for b in blobs) == [1.3, 1.75]
    assert len(detect_blobs(scene(stand, sit, hands), tau2_m=0.45)) == 1


def test_noise_under_min_volume_is_ignored():
    person = standing(1.0, 1.0)
    speck = box((3.0, 3.0, 0.0), (3.2, 3.2, 0.2))  # 64 voxels = 0.008 m^3
    floater = box((2.0, 1.0, 1.0), (2.1, 1.1, 1.1))  # 8 voxels in the air
    res = scene(person, speck, floater)
    blobs = detect_blobs(res, min_volume_m3=0.02)
    assert len(blobs) == 1 and blobs[0].x == pytest.approx(1.0, abs=0.03)
    assert len(detect_blobs(res, min_volume_m3=0.005)) == 2
    assert len(detect_blobs(res, min_volume_m3=0.0)) == 3


def test_three_people_in_a_row_touching_low():
    people = [standing(1.0, 2.0), standing(1.55, 2.0, 1.6), standing(2.1, 2.0)]
    bridges = [box((1.15, 1.9, 0.0), (1.4, 2.1, 0.9)), box((1.7, 1.9, 0.0), (1.95, 2.1, 0.9))]
    blobs = detect_blobs(scene(*people, *bridges))
    xs = sorted(b.x for b in blobs)
    assert np.allclose(xs, [1.0, 1.55, 2.1], atol=0.05)
    assert sorted(round(b.z_top_m, 2) for b in blobs) == [1.6, 1.75, 1.75]


def test_grid_with_offset_origin():
    grid = VoxelGrid.from_bounds((-2.0, -1.0, 0.0), (2.0, 3.0, 2.0), 0.05)
    res = scene(box((-1.2, 0.3, 0.0), (-0.8, 0.7, 1.6), grid), grid=grid)
    (b,) = detect_blobs(res)
    assert b.x == pytest.approx(-1.0, abs=1e-9) and b.y == pytest.approx(0.5, abs=1e-9)
    assert b.z_top_m == pytest.approx(1.6)


@pytest.mark.parametrize("bad", [{"tau1_m": -1.0}, {"tau2_m": float("nan")}, {"min_volume_m3": -0.1}, {"head_m": -0.1},
                                 {"head_sep_m": float("inf")}, {"gap_m": -0.05}])
def test_bad_parameters_name_themselves(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        detect_blobs(scene(standing(1.0, 1.0)), **bad)


def test_separate_groups_are_detected_as_if_alone():
    # The detector packs separate groups of columns side by side; each group's
    # blobs must equal those found with the group alone in the room.
    groups = [
        [standing(0.5, 0.5)],
        [standing(1.5, 0.6), standing(2.1, 0.6), box((1.65, 0.55, 0.8), (1.95, 0.65, 0.95))],
        [seated(3.0, 3.0)],
        [box((0.3, 3.0, 0.0), (1.5, 3.4, 0.3))],
        [box((3.6, 0.3, 0.0), (3.7, 0.4, 0.1))],
    ]
    together = detect_blobs(scene(*[p for g in groups for p in g]))
    alone = [b for g in groups for b in detect_blobs(scene(*g))]
    def key(b):
        return (b.volume_voxels, round(b.x, 9), round(b.y, 9), b.z_top_m)

    assert sorted(map(key, together)) == sorted(map(key, alone))
    assert len(together) == 5
    for b in together:
        twin = next(a for a in alone if key(a) == key(b))
        assert np.array_equal(np.unique(b.ijk, axis=0), np.unique(twin.ijk, axis=0))
        assert np.array_equal(b.height_profile, twin.height_profile)
