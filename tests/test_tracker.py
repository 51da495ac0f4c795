"""Tracker scenarios on synthesised voxel scenes at 15 fps (5 cm voxels)."""

from __future__ import annotations

import functools
import itertools
import re

import numpy as np
import pytest

from fusion_server.association import floor_distance_cost
from fusion_server.detection import detect_blobs
from fusion_server.grid import CarveResult, VoxelGrid, floor_maps
from fusion_server.particle_filter import ParticleFilter
from fusion_server.tracker import (
    AssociationParams,
    ConfirmationParams,
    MotionParams,
    PopulationParams,
    TrackEstimate,
    Tracker,
    _box_top,
)

GRID = VoxelGrid.from_bounds((0.0, 0.0, 0.0), (6.0, 4.0, 2.0), 0.05)
FRAME_NS = 1_000_000_000 // 15


def box(lo_m, hi_m) -> np.ndarray:
    """Voxels whose centres lie in [lo_m, hi_m), (N, 3) int32."""
    lo = np.ceil((np.asarray(lo_m) - GRID.origin_m) / GRID.voxel_m - 0.5 - 1e-9).astype(int)
    hi = np.ceil((np.asarray(hi_m) - GRID.origin_m) / GRID.voxel_m - 0.5 - 1e-9).astype(int)
    axes = [np.arange(max(a, 0), min(b, n)) for a, b, n in zip(lo, hi, GRID.shape)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.int32)


def cylinder(cx, cy, radius_m, z0_m, z1_m) -> np.ndarray:
    ijk = box((cx - radius_m, cy - radius_m, z0_m), (cx + radius_m, cy + radius_m, z1_m))
    c = GRID.centres(ijk)
    return ijk[(c[:, 0] - cx) ** 2 + (c[:, 1] - cy) ** 2 <= radius_m**2]


def person(cx, cy, height_m=1.75) -> np.ndarray:
    """Body r 0.2 m to the shoulders, head r 0.1 m."""
    return np.concatenate([cylinder(cx, cy, 0.2, 0.0, height_m - 0.3), cylinder(cx, cy, 0.1, height_m - 0.3, height_m)])


def frame(n: int, *parts) -> CarveResult:
    parts = [p for p in parts if len(p)] or [np.zeros((0, 3), np.int32)]
    ijk = np.unique(np.concatenate(parts), axis=0).astype(np.int32).reshape(-1, 3)
    return CarveResult(ijk=ijk, grid=GRID, floor=floor_maps(ijk, GRID), stamp_ns=n * FRAME_NS, cameras=("a", "b", "c"))


def run(tracker: Tracker, scenes, heads_apart=lambda n: ()) -> list[list[TrackEstimate]]:
    """The tracker's estimates on each scene; ``heads_apart(n)``: the pairs of target ids whose heads
    a camera sees apart on scene ``n`` (none by default)."""
    out = []
    for n, res in enumerate(scenes):
        out.append(tracker.step(res, detect_blobs(res), res.stamp_ns, heads_apart=heads_apart(n)))
    return out


def by_id(estimates: list[TrackEstimate]) -> dict[int, TrackEstimate]:
    return {e.id: e for e in estimates}


def reliability_oracle(hits: list[bool], l_max=0.3, l_min=0.05) -> list[float]:
    """Equations (1) and (2) of the paper, frame by frame, from creation."""
    r, out = 0.0, []
    for age, hit in enumerate(hits, start=1):
        r += min(l_max, 1.0 / age + l_min) * ((1.0 if hit else 0.0) - r)
        out.append(r)
    return out


def test_a_neighbours_head_in_the_box_is_not_the_targets_top():
    """A body lying on the floor (x 1.1-2.3 m, 0.3 m high) and a helper standing at (2.45, 2.0),
    1.75 m tall, whose body reaches into the lying target's box (half-size 0.6 m around
    (1.9, 2.0)). Over the whole box the top is the helper's head; over the cells nearer to the
    target than to the helper (x under 2.175 m) it is the body on the floor. A person 2.55 m away
    cuts nothing; the helper's own top is their head either way."""
    res = frame(0, box((1.1, 1.85, 0.0), (2.3, 2.15, 0.3)), person(2.45, 2.0, 1.75))
    assert _box_top(res, 1.9, 2.0, 0.6) == pytest.approx(1.75)
    assert _box_top(res, 1.9, 2.0, 0.6, np.array([[2.45, 2.0]])) == pytest.approx(0.3)
    assert _box_top(res, 1.9, 2.0, 0.6, np.array([[4.45, 2.0]])) == pytest.approx(1.75)
    assert _box_top(res, 2.45, 2.0, 0.6, np.array([[1.9, 2.0]])) == pytest.approx(1.75)


def test_learning_rate_follows_the_paper():
    tr = Tracker(rng=np.random.default_rng(0), confirmation=ConfirmationParams(learning_rate_max=0.3, learning_rate_min=0.05))
    assert tr.learning_rate(1) == 0.3
    assert tr.learning_rate(4) == pytest.approx(0.3)
    assert tr.learning_rate(5) == pytest.approx(0.25)
    assert tr.learning_rate(100) == pytest.approx(0.06)


def test_new_person_is_confirmed_on_the_third_frame():
    tr = Tracker(rng=np.random.default_rng(0))
    out = run(tr, [frame(n, person(2.0, 2.0)) for n in range(4)])
    assert [len(o) for o in out] == [1, 1, 1, 1]
    rel = [o[0].reliability for o in out]
    np.testing.assert_allclose(rel, [0.3, 0.51, 0.657, reliability_oracle([True] * 4)[3]])
    assert [o[0].confirmed for o in out] == [False, False, True, True]
    assert [o[0].age_frames for o in out] == [1, 2, 3, 4]


def test_a_one_frame_ghost_is_deleted_after_four_misses():
    tr = Tracker(rng=np.random.default_rng(0))
    out = run(tr, [frame(0, person(2.0, 2.0))] + [frame(n) for n in range(1, 7)])
    # r: 0.3 -> 0.21 -> 0.147 -> 0.1029 -> 0.0772 < 0.1 at the fourth miss.
    assert [len(o) for o in out] == [1, 1, 1, 1, 0, 0, 0]
    np.testing.assert_allclose([o[0].reliability for o in out[:4]], reliability_oracle([True, False, False, False]))
    assert not any(o[0].confirmed for o in out[:4])


def test_a_person_who_leaves_is_unconfirmed_then_deleted_with_the_stated_delays():
    present = 60
    scenes = [frame(n, person(2.0, 2.0)) for n in range(present)] + [frame(n) for n in range(present, present + 80)]
    tr = Tracker(rng=np.random.default_rng(1))
    out = run(tr, scenes)
    oracle = reliability_oracle([True] * present + [False] * 80)
    first_unconfirmed = next(n for n in range(present, len(oracle)) if oracle[n] < 0.6)
    first_deleted = next(n for n in range(present, len(oracle)) if oracle[n] < 0.1)
    assert first_unconfirmed - present == 7  # unconfirmed on the 8th missed frame (0.53 s at 15 fps)
    assert first_deleted - present == 35  # deleted on the 36th (2.4 s)
    for n, o in enumerate(out):
        if n < first_deleted:
            assert len(o) == 1 and o[0].id == 1
            assert o[0].reliability == pytest.approx(oracle[n])
            assert o[0].confirmed == (oracle[n] >= 0.6)
        else:
            assert o == []


def walk_past(n_frames: int = 100, lateral_m: float = 0.5, bridge=None, heights=(1.75, 1.75)):
    """Two people walking past each other in opposite directions along x.

    Their centres pass ``lateral_m`` apart; ``bridge`` (z0, z1) joins them
    with an arm at that height while they are closer than 0.6 m.
    """
    scenes, truth = [], []
    for n in range(n_frames):
        ax = 1.0 + 4.0 * n / (n_frames - 1)
        bx = 5.0 - 4.0 * n / (n_frames - 1)
        a, b = (ax, 2.0 - lateral_m / 2), (bx, 2.0 + lateral_m / 2)
        parts = [person(*a, heights[0]), person(*b, heights[1])]
        if bridge is not None and abs(ax - bx) < 0.6:
            mid = 0.5 * (ax + bx)
            parts.append(box((mid - 0.1, a[1] + 0.1, bridge[0]), (mid + 0.1, b[1] - 0.1, bridge[1])))
        scenes.append(frame(n, *parts))
        truth.append((a, b))
    return scenes, truth


# An arm over the shoulders at 1.25-1.4 m joins a 1.75 m adult and someone of 1.45 m whose head rises
# only 0.05 m over it, too little to stand apart as a head: the two carve one blob that they share.
# (Of 1.6 m, their head would rise 0.2 m and the detector would keep them apart.)
MERGING_BRIDGE = (1.25, 1.4)
SHORT_HEIGHTS = (1.75, 1.45)


@pytest.mark.parametrize("bridge, heights", [(None, (1.75, 1.6)), ((0.8, 0.95), (1.75, 1.6)),
                                             (MERGING_BRIDGE, SHORT_HEIGHTS)],
                         ids=["apart", "hands-below-tau1", "arm-over-a-shorter-head"])
def test_two_people_walking_past_keep_their_identities(bridge, heights):
    scenes, truth = walk_past(bridge=bridge, heights=heights)
    tr = Tracker(rng=np.random.default_rng(7))
    out = run(tr, scenes)
    ids = {e.id for o in out for e in o}
    assert ids == {1, 2}
    speed = 4.0 / (99 / 15)  # 0.606 m/s
    for n, (o, (a, b)) in enumerate(zip(out, truth)):
        est = by_id(o)
        assert set(est) == {1, 2}, n
        # Track 1 started on the left walker, track 2 on the right one.
        assert np.hypot(est[1].x - a[0], est[1].y - a[1]) < 0.05, n
        assert np.hypot(est[2].x - b[0], est[2].y - b[1]) < 0.05, n
        if n >= 2:
            assert est[1].confirmed and est[2].confirmed, n
        if n >= 15:
            assert est[1].vx == pytest.approx(speed, abs=0.12) and est[2].vx == pytest.approx(-speed, abs=0.12)
            assert abs(est[1].vy) < 0.12 and abs(est[2].vy) < 0.12
            assert not est[1].still and not est[2].still
        assert est[1].z_top_m == pytest.approx(heights[0]) and est[2].z_top_m == pytest.approx(heights[1])
    merged_frames = [o for o in out if len({id(e.blob) for e in o}) == 1]
    if bridge == MERGING_BRIDGE:
        assert len(merged_frames) >= 5  # they were one blob and shared it
        for o in merged_frames:
            a, b = o
            assert a.blob is b.blob
            assert a.height_profile.sum() * 0.05**3 == pytest.approx(a.volume_m3)
            assert a.volume_m3 + b.volume_m3 == pytest.approx(a.blob.volume_m3)
            assert a.height_profile[33] > 0 and b.height_profile[33] == 0  # only the taller head reaches 1.65-1.7 m
        # the same arm over a 1.6 m walker: their head rises 0.2 m over it and keeps them apart
        assert all(len(detect_blobs(res)) == 2 for res in walk_past(bridge=bridge, heights=(1.75, 1.6))[0])
    else:
        assert merged_frames == []


def test_strict_paper_association_starves_the_second_target_of_a_merged_blob():
    scenes, _ = walk_past(bridge=MERGING_BRIDGE, heights=SHORT_HEIGHTS)
    out = run(Tracker(rng=np.random.default_rng(7), association=AssociationParams(share_blobs=False)), scenes)
    assert min(e.reliability for o in out[40:60] for e in o) < 0.9
    out = run(Tracker(rng=np.random.default_rng(7), association=AssociationParams(share_blobs=True)), scenes)
    assert min(e.reliability for o in out[40:60] for e in o) > 0.99


def test_same_seed_same_tracks():
    scenes, _ = walk_past(n_frames=40)
    a = run(Tracker(rng=np.random.default_rng(3)), scenes)
    b = run(Tracker(rng=np.random.default_rng(3)), scenes)
    for oa, ob in zip(a, b):
        assert [(e.id, e.x, e.y, e.reliability) for e in oa] == [(e.id, e.x, e.y, e.reliability) for e in ob]


def test_duplicate_target_on_one_person_is_merged_into_the_older():
    # A bag held away from the body for one frame starts a second target,
    # whose filter then settles on the person: after merge_frames close
    # frames only the older track remains.
    bag = box((2.3, 1.85, 0.45), (2.5, 2.15, 0.85))  # 0.024 m^3, 0.4 m from the centre
    scenes = [frame(n, person(2.0, 2.0), bag if n == 5 else []) for n in range(40)]
    tr = Tracker(rng=np.random.default_rng(2), population=PopulationParams(merge_frames=8, merge_distance_m=0.3))
    out = run(tr, scenes)
    assert {e.id for e in out[5]} == {1, 2}
    merged_at = next(n for n in range(6, 40) if {e.id for e in out[n]} == {1})
    assert merged_at <= 5 + 8 + 6
    assert all({e.id for e in o} == {1} for o in out[merged_at:])
    assert out[-1][0].confirmed and out[-1][0].age_frames == 40


def test_merge_keeps_the_older_target():
    # A child walks into an adult's arms: from frame 7 on the two are one
    # mass and both targets follow it; the adult's older track is kept.
    scenes = [frame(0, person(2.0, 2.0))]
    scenes += [frame(n, person(2.0, 2.0), person(max(2.0, 2.7 - 0.1 * n), 2.0, 1.2)) for n in range(1, 40)]
    tr = Tracker(rng=np.random.default_rng(4), id_source=iter([10, 20, 30]))
    out = run(tr, scenes)
    assert {e.id for e in out[1]} == {10, 20}
    gone = next(n for n in range(len(out)) if n > 1 and {e.id for e in out[n]} == {10})
    assert gone <= 7 + 8 + 3
    assert all({e.id for e in o} == {10} for o in out[gone:])


def test_ids_come_from_the_injected_source():
    scenes = [frame(n, person(1.0, 1.0), person(3.0, 3.0) if n >= 2 else []) for n in range(4)]
    out = run(Tracker(rng=np.random.default_rng(0), id_source=itertools.count(500, 5)), scenes)
    assert [e.id for e in out[-1]] == [500, 505]
    counter = iter(range(7, 100))
    out = run(Tracker(rng=np.random.default_rng(0), id_source=lambda: next(counter)), scenes)
    assert [e.id for e in out[-1]] == [7, 8]


def test_still_after_a_window_without_motion():
    scenes = [frame(n, person(1.0 + min(n, 15) * 0.06, 2.0)) for n in range(45)]
    out = run(Tracker(rng=np.random.default_rng(5), motion=MotionParams(still_window_s=1.0, still_speed_mps=0.15)), scenes)
    still = [o[0].still for o in out]
    assert not any(still[:16])  # walking at 0.9 m/s, then the first second of standing
    assert all(still[40:])
    assert all(o[0].x == pytest.approx(1.9, abs=0.04) for o in out[30:])


def test_estimate_fields():
    out = run(Tracker(rng=np.random.default_rng(0)), [frame(n, person(3.0, 1.5, 1.7)) for n in range(3)])
    e = out[-1][0]
    assert isinstance(e, TrackEstimate)
    assert e.height_profile.shape == (GRID.shape[2],) and e.height_profile.dtype == np.int32
    assert e.blob is not None and e.volume_m3 == pytest.approx(e.blob.volume_m3)
    assert e.z_top_m == pytest.approx(1.7)
    assert e.stamp_ns == 2 * FRAME_NS
    assert 0.15 <= e.alpha_m <= 0.6
    assert isinstance(e.vx, float) and isinstance(e.x, float)


def test_stamps_must_not_go_back():
    tr = Tracker(rng=np.random.default_rng(0))
    res = frame(5, person(1.0, 1.0))
    tr.step(res, detect_blobs(res), res.stamp_ns)
    with pytest.raises(ValueError, match="stamp_ns"):
        tr.step(res, detect_blobs(res), res.stamp_ns - 1)


@pytest.mark.parametrize(
    "group, bad",
    [
        (AssociationParams, {"gate_m": -1.0}),
        (AssociationParams, {"low_top_m": float("nan")}),
        (AssociationParams, {"share_min_age_frames": -1}),
        (ConfirmationParams, {"learning_rate_max": 0.0}),
        (ConfirmationParams, {"learning_rate_min": 0.5}),
        (ConfirmationParams, {"confirm_reliability": 0.05}),
        (ConfirmationParams, {"delete_reliability": -0.1}),
        (ConfirmationParams, {"leave_margin_m": -0.1}),
        (PopulationParams, {"new_target_min_distance_m": -0.3}),
        (PopulationParams, {"new_target_min_volume_m3": float("inf")}),
        (PopulationParams, {"merge_distance_m": -1.0}),
        (PopulationParams, {"merge_frames": 0}),
        (MotionParams, {"velocity_tau_s": 0.0}),
        (MotionParams, {"still_speed_mps": -0.15}),
        (MotionParams, {"still_window_s": float("nan")}),
    ],
)
def test_bad_parameters_name_the_field_and_the_value(group, bad):
    ((name, value),) = bad.items()
    with pytest.raises(ValueError, match=rf"{name}.*got.*{re.escape(str(value))}"):
        group(**bad)


def test_parameter_groups_hold_the_types_they_state():
    merge_frames = PopulationParams(merge_frames=8.0).merge_frames
    assert merge_frames == 8 and type(merge_frames) is int
    assert type(AssociationParams(gate_m=1).gate_m) is float
    with pytest.raises(ValueError, match="frozen"):
        AssociationParams().gate_m = 1.0


@pytest.mark.parametrize(
    "bad, name",
    [
        ({"rng": None}, "rng"),
        ({"filter_factory": functools.partial(ParticleFilter, n_particles=0)}, "n_particles"),
        ({"filter_factory": functools.partial(ParticleFilter, alpha_range_m=(0.6, 0.15))}, "alpha_range_m"),
    ],
)
def test_bad_tracker_arguments_name_themselves(bad, name):
    with pytest.raises(ValueError, match=name):
        Tracker(**{"rng": np.random.default_rng(0), **bad})


def test_a_custom_cost_decides_the_assignment():
    """Two people 0.5 m apart, A at x = 2.0 and B at x = 2.5, stand still. The cost below is
    the floor distance except that the target on A may not take A's blob. Both swapped pairs
    cost 0.5 m, within the 0.6 m gate, and two matches beat one (the associator first makes as
    many admissible matches as it can), so A's target takes B's blob and B's target A's blob."""
    scenes = [frame(n, person(2.0, 2.0), person(2.5, 2.0)) for n in range(3)]
    seen = []

    def no_a_on_a(target_xy, blobs):
        seen.append((target_xy.shape, len(blobs)))
        cost = floor_distance_cost(target_xy, blobs)
        blob_on_a = np.array([b.x < 2.25 for b in blobs])
        cost[np.ix_(target_xy[:, 0] < 2.25, blob_on_a)] = np.inf
        return cost

    def blob_x_by_place(estimates):
        return {("A" if e.x < 2.25 else "B"): round(e.blob.x, 1) for e in estimates}

    default = run(Tracker(rng=np.random.default_rng(0)), scenes)
    custom = run(Tracker(rng=np.random.default_rng(0), cost_function=no_a_on_a), scenes)
    assert seen == [((0, 2), 2), ((2, 2), 2), ((2, 2), 2)]
    assert [blob_x_by_place(o) for o in default[1:]] == [{"A": 2.0, "B": 2.5}] * 2
    assert [blob_x_by_place(o) for o in custom[1:]] == [{"A": 2.5, "B": 2.0}] * 2
    # every target matched on every frame either way
    for out in (default, custom):
        np.testing.assert_allclose([e.reliability for e in out[2]], reliability_oracle([True] * 3)[2])


def test_a_cost_of_the_wrong_shape_is_refused():
    tr = Tracker(rng=np.random.default_rng(0), cost_function=lambda target_xy, blobs: np.zeros((1, 1)))
    res = frame(0, person(2.0, 2.0), person(4.0, 2.0))
    with pytest.raises(ValueError, match="cost_function"):
        tr.step(res, detect_blobs(res), res.stamp_ns)


def test_the_filter_factory_makes_every_filter():
    """Called once at construction (at the floor's origin, alpha 0), then once per new
    target at its blob's centroid with alpha = half the root of its footprint area."""
    calls = []

    def factory(x_m, y_m, alpha_m, *, rng):
        calls.append((x_m, y_m, alpha_m))
        return ParticleFilter(x_m, y_m, alpha_m, rng=rng, n_particles=50)

    tr = Tracker(rng=np.random.default_rng(0), filter_factory=factory)
    assert calls == [(0.0, 0.0, 0.0)]
    out = run(tr, [frame(n, person(2.0, 2.0)) for n in range(3)])
    assert len(calls) == 2
    blob = out[0][0].blob
    assert calls[1] == (blob.x, blob.y, pytest.approx(0.5 * np.sqrt(blob.footprint_area_m2)))
    assert out[2][0].confirmed and np.hypot(out[2][0].x - 2.0, out[2][0].y - 2.0) < 0.05


@pytest.mark.parametrize("drift_m, still", [(0.0, True), (0.05, True), (0.3, False)])
def test_a_target_whose_blob_stays_put_is_still_even_when_its_filter_jitters(drift_m, still):
    """The filter's estimate swings 0.2 m from frame to frame (its velocity between +-0.3 m/s, above
    the 0.15 m/s of stillness) while the blob matched every frame moves ``drift_m`` in all over
    1.5 s: still when the blobs stayed within 0.15 m (0.15 m/s over the 1 s window), not when the
    blob itself moved."""
    from types import SimpleNamespace

    from fusion_server.tracker import _Target

    target = _Target(id=1, pf=None, x=2.0, y=3.0, alpha_m=0.3)
    for k in range(23):  # 1.5 s at 15 frames/s
        target.vx = 0.3 if k % 2 else -0.3
        target.x = 2.1 if k % 2 else 1.9
        target.blob = SimpleNamespace(x=2.0 + drift_m * k / 22, y=3.0)
        target.update_stillness(int(k * 1e9 / 15), 1.0, 0.15)
    assert target.still is still
    target.blob = None  # a frame without a blob: the blobs no longer cover the window
    target.update_stillness(int(23 * 1e9 / 15), 1.0, 0.15)
    assert target.still is False


@pytest.mark.parametrize("wobble_m, still", [(0.0, True), (0.12, True), (0.2, False)])
def test_a_target_that_stays_put_is_still_though_its_blob_jumps(wobble_m, still):
    """A person standing where they stand while their hull splits and merges: the blob matched
    to them jumps 0.3 m every fifth frame, or is missing, and the estimate's velocity steps to
    0.4 m/s and back, but the estimate itself stays within ``wobble_m``: still when that is under
    0.15 m (0.15 m/s over the 1 s window). Someone who moves is not (walking at 0.3 m/s)."""
    from types import SimpleNamespace

    from fusion_server.tracker import _Target

    target = _Target(id=1, pf=None, x=2.0, y=3.0, alpha_m=0.3)
    for k in range(23):  # 1.5 s at 15 frames/s
        target.vx = 0.4 if k % 5 == 0 else 0.0
        target.x = 2.0 + (wobble_m if k % 3 == 0 else 0.0)
        target.blob = None if k % 7 == 0 else SimpleNamespace(x=2.0 + (0.3 if k % 5 == 0 else 0.0), y=3.0)
        target.update_stillness(int(k * 1e9 / 15), 1.0, 0.15)
    assert target.still is still
    walker = _Target(id=2, pf=None, x=2.0, y=3.0, alpha_m=0.3)
    for k in range(23):
        walker.x, walker.vx = 2.0 + 0.3 * k / 15, 0.3
        walker.update_stillness(int(k * 1e9 / 15), 1.0, 0.15)
    assert walker.still is False



def hug(gap_m: float = 0.35, n_frames: int = 150):
    """Two people (1.75 m and 1.45 m) walk towards each other from 2 m apart, stand ``gap_m`` apart
    (centre to centre; an arm over the shorter one's shoulders makes the two one blob) for frames
    40-109, and walk back apart."""
    scenes, truth = [], []
    for n in range(n_frames):
        half = 1.0 if n < 10 else max(gap_m / 2, 1.0 - (n - 10) * 0.05) if n < 110 else min(1.0, gap_m / 2 + (n - 110) * 0.05)
        a, b = (3.0 - half, 2.0), (3.0 + half, 2.0)
        parts = [person(*a, 1.75), person(*b, 1.45)]
        if half < 0.3:
            parts.append(box((a[0] + 0.1, 1.9, MERGING_BRIDGE[0]), (b[0] - 0.05, 2.1, MERGING_BRIDGE[1])))
        scenes.append(frame(n, *parts))
        truth.append((a, b))
    return scenes, truth


@pytest.mark.parametrize("apart_m, heads, hold_share, kept",
                         [(0.8, True, 0.5, True), (0.8, False, 0.5, True), (100.0, True, 0.5, False), (0.8, False, 1.1, False)],
                         ids=["two-heads-seen", "blob-holds-both", "never-seen-apart", "no-heads-nor-room"])
def test_two_people_seen_apart_stay_two_targets_while_they_hug(apart_m, heads, hold_share, kept):
    """Two targets confirmed 2 m apart are two people: while the two carve one blob (their floor
    counts one hump) and a camera sees their two heads, or the blob holds both their bodies (its
    volume is the larger body's and more than half the smaller one's), neither filter may take the
    other's place, so both stay on their own person and neither is merged away. Without heads or
    room (apart_m beyond the room; no camera told of two heads and a blob asked to hold more than
    both bodies) both filters climb the one hump and the younger target is merged into the older:
    one person is lost."""
    scenes, truth = hug()
    assert all(len(detect_blobs(scenes[n])) == 1 for n in range(40, 110))  # one blob while they hug
    tr = Tracker(rng=np.random.default_rng(5), population=PopulationParams(apart_m=apart_m, hold_share=hold_share))
    out = run(tr, scenes, lambda n: [(1, 2)] if heads else ())
    if not kept:
        assert any(len(o) == 1 for o in out[40:110])
        return
    for n, (o, (a, b)) in enumerate(zip(out, truth)):
        est = by_id(o)
        assert set(est) == {1, 2}, n
        assert np.hypot(est[1].x - a[0], est[1].y - a[1]) < 0.15, n
        assert np.hypot(est[2].x - b[0], est[2].y - b[1]) < 0.15, n


def test_a_neighbour_whose_head_was_seen_apart_keeps_out_of_the_targets_top():
    """A (1.5 m, at x 2.0 m) and B (1.9 m) come in side by side 0.7 m apart (never the 0.8 m that
    makes two confirmed targets two people) and the cameras see their heads apart on frames 5-14
    only; B then steps to 0.4 m beside A. B's shoulders (1.6 m) reach into A's box. Seen apart once,
    B is someone else for as long as both live: A's top stays their own 1.5 m. Never seen apart, A
    reads B's shoulders as their top."""
    def scene(n):
        return frame(n, person(2.0, 2.0, 1.5), person(max(2.4, 2.7 - 0.02 * max(n - 15, 0)), 2.0, 1.9))

    scenes = [scene(n) for n in range(40)]
    for heads in (True, False):
        out = run(Tracker(rng=np.random.default_rng(0)), scenes, lambda n: [(1, 2)] if heads and 5 <= n < 15 else ())
        tops = [by_id(o)[2].z_top_m for o in out[30:40]]
        assert all(abs(by_id(o)[2].x - 2.0) < 0.06 and by_id(o)[1].z_top_m == pytest.approx(1.9) for o in out[30:40])
        if heads:
            assert tops == pytest.approx([1.5] * 10)
        else:
            assert max(tops) == pytest.approx(1.6)


def test_a_target_left_on_a_person_whose_partner_vanished_merges_into_them():
    """Two people confirmed 2 m apart; one comes to stand 0.35 m beside the other (one blob) and
    vanishes there on frame 60 (walked out behind them, unseen). No camera sees two heads on the blob
    left any more: a second of that memory later, the vanished person's target is no longer kept
    beside the other, but merges away."""
    scenes = []
    for n in range(120):
        bx = max(2.85, 4.5 - 0.05 * n)
        parts = [person(2.5, 2.0, 1.75)]
        if n < 60:
            parts.append(person(bx, 2.0, 1.45))
            if bx - 2.5 < 0.6:
                parts.append(box((2.6, 1.9, MERGING_BRIDGE[0]), (bx - 0.05, 2.1, MERGING_BRIDGE[1])))
        scenes.append(frame(n, *parts))
    assert all(len(detect_blobs(scenes[n])) == 1 for n in range(35, 60))
    out = run(Tracker(rng=np.random.default_rng(5)), scenes, lambda n: [(1, 2)] if n < 60 else ())
    assert {e.id for e in out[59]} == {1, 2}
    assert all({e.id for e in o} == {1} for o in out[60 + 15 + 8 + 8:])  # memory, merge_frames, margin
    assert np.hypot(out[-1][0].x - 2.5, out[-1][0].y - 2.0) < 0.05


@pytest.mark.parametrize("body_min_m3, kept", [(0.1, False), (0.0, True)], ids=["column-is-no-body", "no-least-body"])
def test_a_column_of_hull_confirmed_apart_is_not_held_beside_a_person(body_min_m3, kept):
    """A person (1.75 m, 0.19 m^3) and a column of hull 1.3 m high (0.06 m^3, under the 0.1 m^3
    the least standing person carves) are confirmed 1.2 m apart: two targets known apart. The
    column drifts to 0.45 m beside the person and joins their blob through hull; no camera sees two
    heads. The blob has room for both volumes, but the column is no body: it is not held apart and
    merges into the person. Counted as a body however small (``body_min_m3`` 0), it is held beside
    them to the end."""
    scenes = []
    for n in range(100):
        gx = max(2.45, 3.2 - 0.02 * max(n - 20, 0))
        parts = [person(2.0, 2.0), cylinder(gx, 2.0, 0.12, 0.0, 1.3)]
        if gx - 2.0 < 0.6:
            parts.append(box((2.1, 1.9, MERGING_BRIDGE[0]), (gx - 0.05, 2.1, MERGING_BRIDGE[1])))
        scenes.append(frame(n, *parts))
    assert [len(detect_blobs(scenes[n])) for n in (20, 99)] == [2, 1]
    tr = Tracker(rng=np.random.default_rng(3), population=PopulationParams(body_min_m3=body_min_m3))
    out = run(tr, scenes)
    assert {e.id for e in out[20]} == {1, 2} and all(e.confirmed for e in out[20])
    assert all(np.hypot(by_id(o)[1].x - 2.0, by_id(o)[1].y - 2.0) < 0.1 for o in out)
    assert ({e.id for e in out[-1]} == {1, 2}) == kept


def test_a_target_never_seen_apart_from_the_person_does_not_live_on_their_blob():
    """With ``share_known_only``: a column of hull beside a standing person (0.5 m from their centre, too close ever to be
    two people, no head of its own) is followed as a target of its own for 30 frames; then it
    joins the person's blob through hull at 1.1-1.25 m, its hump 0.05 m over it, and the two carve
    one blob. Its target is no second person: it does not share the blob (the person's older
    target keeps it), loses its confirmation within 8 missed frames and is gone before the end."""
    p, g = (2.0, 2.0), (2.5, 2.0)
    scenes = []
    for n in range(90):
        parts = [person(*p), cylinder(*g, 0.12, 0.0, 1.3)]
        if n >= 30:
            parts.append(box((p[0] + 0.1, g[1] - 0.1, 1.1), (g[0] - 0.05, g[1] + 0.1, 1.25)))
        scenes.append(frame(n, *parts))
    assert [len(detect_blobs(s)) for s in scenes[29:31]] == [2, 1]
    tr = Tracker(rng=np.random.default_rng(7), association=AssociationParams(share_known_only=True))
    out = run(tr, scenes)
    assert {e.id for e in out[29]} == {1, 2} and all(e.confirmed for e in out[29])
    for n in range(30, 90):
        est = by_id(out[n])
        assert est[1].confirmed and est[1].blob is not None, n
        assert np.hypot(est[1].x - p[0], est[1].y - p[1]) < 0.1, n
        if 2 in est:
            assert est[2].blob is None, n
            assert est[2].confirmed == (n < 38), n
    assert set(by_id(out[-1])) == {1}


def hidden_still(hidden_body, walk_frames: int = 0, n_still: int = 60, n_hidden: int = 40):
    """A person 1.75 m tall walks ``walk_frames`` frames at 0.9 m/s to (2.0, 2.0) and stands there
    ``n_still`` frames, then the explanation refuses their blob for ``n_hidden`` frames while the
    hull ``hidden_body`` stays carved (blobs passed as ``hidden``). The estimates of the last frames."""
    tr = Tracker(rng=np.random.default_rng(3), motion=MotionParams(still_window_s=1.0, still_speed_mps=0.15))
    out = []
    for n in range(walk_frames + n_still):
        x = 2.0 - 0.06 * max(walk_frames - n, 0)
        res = frame(n, person(x, 2.0))
        out.append(tr.step(res, detect_blobs(res), res.stamp_ns))
    for n in range(walk_frames + n_still, walk_frames + n_still + n_hidden):
        res = frame(n, hidden_body)
        out.append(tr.step(res, [], res.stamp_ns, hidden=detect_blobs(res)))
    return out[walk_frames + n_still:]


def test_a_still_person_the_others_hide_is_held_up_by_the_refused_blob_of_their_body():
    """The refused blob of their own body (same place, same top) counts as a match: reliability goes
    on as if seen (the paper's equations), the target stays confirmed and where it stood. Without
    it, the target is unconfirmed on the 8th frame unmatched (as a person who left)."""
    held = hidden_still(person(2.0, 2.0))
    assert all(len(o) == 1 and o[0].confirmed for o in held)
    np.testing.assert_allclose([o[0].reliability for o in held], reliability_oracle([True] * 100)[60:])
    assert held[-1][0].x == pytest.approx(2.0, abs=0.05) and held[-1][0].y == pytest.approx(2.0, abs=0.05)
    alone = []
    tr = Tracker(rng=np.random.default_rng(3), motion=MotionParams(still_window_s=1.0, still_speed_mps=0.15))
    for n in range(100):
        res = frame(n, person(2.0, 2.0))
        alone.append(tr.step(res, detect_blobs(res) if n < 60 else [], res.stamp_ns))
    assert [o[0].confirmed for o in alone[60:68]] == [True] * 7 + [False]


def test_a_refused_blob_away_from_the_person_holds_nobody_up():
    """Hull 1 m away on the floor (where cones cross beside someone) holds nobody up: the target is
    unconfirmed on the 8th frame without a blob, as a person who left."""
    out = hidden_still(person(3.0, 2.0))
    assert [bool(o) and o[0].confirmed for o in out[:8]] == [True] * 7 + [False]


def test_a_refused_blob_whose_top_is_not_the_persons_does_not_hold_them_up():
    """A refused blob 0.45 m lower than the top read at the target on the frame set before (1.75 m)
    is not their body: that frame set is a miss (the paper's equations with one miss)."""
    out = hidden_still(person(2.0, 2.0, height_m=1.3))
    assert out[0][0].reliability == pytest.approx(reliability_oracle([True] * 60 + [False])[60])


def test_a_person_still_moving_is_not_held_up():
    """Walking until the frame before their blob is refused: not still, so a refused blob where
    the filter puts them holds nothing up (a track coasting after a walker is no one seated)."""
    out = hidden_still(person(2.0, 2.0), walk_frames=30, n_still=1)
    assert not out[7] or not out[7][0].confirmed
