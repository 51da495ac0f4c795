"""Voxel carving on the synthetic house: the carved volume covers the true bodies.

The synthetic house knows every person's body exactly (14 ellipsoids per
person), so carving can be scored voxel by voxel:

* the true body voxels are the finest (5 cm) voxels whose centre lies inside
  a body (``Body.contains``) and inside the monitored volume;
* recall is the fraction of them that the carve keeps;
* excess is the carved voxels farther than one voxel (26-neighbourhood) from
  every true body voxel, as a multiple of the true body volume: the wedges of
  the visual hull that no camera can rule out, plus anything spurious.

Carving gets the renderer's true person masks here, which isolates carving
from segmentation; one case feeds it the camera worker's segmented masks of
the same frames instead. The carver is configured as the synthetic house's
site file configures it (octree 40/20/10/5 cm, ``min_cameras`` 2,
``min_ratio`` 0.75), with masks and lookup tables at the cameras' full
640 x 480 (the site's half-size masks are the scenario tests' business). Bounds
are the figures measured on this scene with a modest margin; each case prints
its figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy import ndimage

from camera_worker.segmentation import ForegroundSegmenter, window_frames_for
from common.camera import pixel_index
from synth import SyntheticCamera, default_cameras, default_site, get_scenario
from fusion_server.carving import Carver
from fusion_server.carving.distance import needed_votes
from fusion_server.grid import CarveResult, VoxelGrid
from evaluation.suite import cameras_for

FRAMES: dict[str, tuple[int, ...]] = {
    "walk": (60, 110, 150, 240),  # walking a loop through the middle and the south side; standing by the hall
    "sit_stand": (250, 700),  # seated on a dinner chair, then on the sofa
    "fall_forward": (200, 450),  # lying on the floor in the middle of the room
    "two_pass": (40, 47, 54),  # two people passing 0.55 m apart (closest at frame 47)
    "behind_sofa": (160, 300),  # bending, then kneeling behind the sofa (partly hidden)
}
"""Scenario -> frames scored; what each frame shows."""

CAMERA_COUNTS = (5, 4, 3)
"""All five cameras; without the ceiling fisheye; without it and one corner camera
(the order of :func:`evaluation.suite.cameras_for`). The site's vote stays: found in
``max(2, ceil(0.75 * seeing))`` cameras, so 4 of 5, 3 of 4 and 3 of 3."""

# Measured with the renderer's true masks (worst frame per scenario; seed 0):
#
#   recall          5 cams  4 cams  3 cams     excess (body volumes)  5 cams  4 cams  3 cams
#   walk             0.833   0.833   0.586                             1.54    3.69    1.57
#   sit_stand        0.434   0.434   0.433                             1.01    1.78    1.18
#   fall_forward     0.730   0.730   0.208                             0.11    0.30    0.06
#   two_pass         0.995   0.995   0.962                             2.86    7.36    2.67
#   behind_sofa      0.749   0.749   0.683                             1.11    1.47    0.57
#
# Every lost voxel is one that furniture hides from more cameras than the vote allows
# (recall of the visible voxels is 1.000 in every case): the sofa back hides a seated
# person's legs from the two cameras behind it, the table and chairs hide a person lying
# beside them. Without the fisheye the hull between the corner views widens (excess up
# to 2.6 times that of five cameras); with three cameras the vote is unanimous, which
# keeps the hull tight but drops every voxel one camera cannot see.

RECALL_MIN: dict[str, dict[int, float]] = {
    "walk": {5: 0.80, 4: 0.80, 3: 0.55},
    "sit_stand": {5: 0.40, 4: 0.40, 3: 0.40},
    "fall_forward": {5: 0.70, 4: 0.70, 3: 0.18},
    "two_pass": {5: 0.97, 4: 0.97, 3: 0.93},
    "behind_sofa": {5: 0.72, 4: 0.72, 3: 0.65},
}
"""Lowest recall allowed per scenario (worst frame) and camera count."""

VISIBLE_RECALL_MIN = 0.99
"""Lowest recall of the voxels that enough cameras see (the octree may miss a few)."""

EXCESS_MAX: dict[str, dict[int, float]] = {
    "walk": {5: 2.0, 4: 4.6, 3: 2.0},
    "sit_stand": {5: 1.3, 4: 2.3, 3: 1.5},
    "fall_forward": {5: 0.2, 4: 0.4, 3: 0.1},
    "two_pass": {5: 3.6, 4: 9.2, 3: 3.4},
    "behind_sofa": {5: 1.4, 4: 1.9, 3: 0.75},
}
"""Highest excess allowed (worst frame), in true body volumes."""


@dataclass(frozen=True)
class CarveScore:
    """How one carve covers the true bodies of its frame.

    true_voxels: finest voxels whose centre lies inside a body. carved_voxels: the carve's.
    recall: carved true voxels / true voxels.
    visible_recall: the same over the true voxels that enough cameras see unhidden (their
        centre falls on the true mask of at least as many cameras as the vote needs): what
        carving can keep at all; furniture hides the rest.
    excess: carved voxels farther than one voxel from every true voxel / true voxels.
    """

    true_voxels: int
    carved_voxels: int
    recall: float
    visible_recall: float
    excess: float


def true_body_occupancy(bodies, grid: VoxelGrid) -> np.ndarray:
    """(nx, ny, nz) bool: finest voxels whose centre lies inside one of ``bodies``."""
    occ = np.zeros(grid.shape, dtype=bool)
    shape = np.asarray(grid.shape)
    for body in bodies:
        lo, hi = body.aabb()
        i0 = np.clip(np.floor((lo - grid.origin_m) / grid.voxel_m).astype(int), 0, shape)
        i1 = np.clip(np.ceil((hi - grid.origin_m) / grid.voxel_m).astype(int) + 1, 0, shape)
        if np.any(i1 <= i0):
            continue  # entirely outside the volume (in the corridor)
        axes = [np.arange(a, b) for a, b in zip(i0, i1)]
        ijk = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        inside = body.contains(grid.centres(ijk))
        occ[tuple(ijk[inside].T)] = True
    return occ


def visible_voxels(truth: np.ndarray, grid: VoxelGrid, cameras, masks, carver: Carver) -> np.ndarray:
    """(nx, ny, nz) bool: the true voxels whose centre lands on the true person mask of at least
    as many of the present cameras as the carver's vote needs from the cameras that see it."""
    ijk = np.argwhere(truth)
    centres = grid.centres(ijk)
    seeing = np.zeros(len(ijk), dtype=int)
    found = np.zeros(len(ijk), dtype=int)
    for cam_id, mask in masks.items():
        uv, valid = cameras[cam_id].project(centres)
        px = pixel_index(uv[valid])
        seeing[valid] += 1
        found[np.flatnonzero(valid)[mask[px[:, 1], px[:, 0]] > 0]] += 1
    need = needed_votes(len(carver.camera_ids), carver.min_cameras, carver.min_ratio)[seeing]
    visible = np.zeros_like(truth)
    visible[tuple(ijk[found >= need].T)] = True
    return visible


def score_carve(carve: CarveResult, truth: np.ndarray, visible: np.ndarray | None = None) -> CarveScore:
    """Recall of the true voxels (and of the visible ones) and the excess beyond one voxel of them."""
    carved = carve.occupancy()
    n_true = int(truth.sum())
    near = ndimage.binary_dilation(truth, structure=np.ones((3, 3, 3), dtype=bool))
    n_visible = int(visible.sum()) if visible is not None else 0
    return CarveScore(
        true_voxels=n_true,
        carved_voxels=int(carved.sum()),
        recall=float((carved & truth).sum() / n_true),
        visible_recall=float((carved & visible).sum() / n_visible) if n_visible else float("nan"),
        excess=float((carved & ~near).sum() / n_true),
    )


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    return default_site(tmp_path_factory.mktemp("site"))


@pytest.fixture(scope="module")
def cameras():
    return default_cameras()


@pytest.fixture(scope="module")
def carver_for(site, cameras, lut_cache):
    """Camera count -> carver over those cameras (tables built once, cached on disk)."""
    cache = lut_cache
    built: dict[int, Carver] = {}

    def get(count: int) -> Carver:
        if count not in built:
            ids = cameras_for(count, site.camera_ids)
            built[count] = Carver(
                cameras={c: cameras[c] for c in ids},
                volume_min_m=site.volume.min_m,
                volume_max_m=site.volume.max_m,
                voxel_sizes_m=site.carving.voxel_sizes_m,
                min_cameras=min(site.carving.min_cameras, len(ids)),
                min_ratio=site.carving.min_ratio,
                cache_dir=cache,
            )
        return built[count]

    return get


@pytest.fixture(scope="module")
def walk_cameras(cameras):
    """Camera id -> the synthetic camera of the 'walk' scenario."""
    scenario = get_scenario("walk", 0)
    return {c: SyntheticCamera(scenario, c, 0, camera=cam) for c, cam in cameras.items()}


@pytest.fixture(scope="module")
def true_masks(walk_cameras):
    """(scenario, frame) -> camera id -> the renderer's true person mask (rendered once).
    Every scenario plays in the same room, so one renderer per camera serves them all."""
    rendered: dict[tuple[str, int], dict[str, np.ndarray]] = {}

    def get(name: str, frame: int) -> dict[str, np.ndarray]:
        if (name, frame) not in rendered:
            scenario = get_scenario(name, 0)
            bodies, gain = scenario.bodies(frame), scenario.gain(frame)
            rendered[(name, frame)] = {
                c: np.where(src.renderer.render(bodies, gain, (0, frame))[1] > 0, np.uint8(255), np.uint8(0))
                for c, src in walk_cameras.items()
            }
        return rendered[(name, frame)]

    return get


def carve_and_score(
    carver: Carver, cameras, name: str, frame: int, all_masks: dict[str, np.ndarray], true_masks=None
) -> CarveScore:
    """Carve frame ``frame`` of scenario ``name`` from the masks of the carver's cameras and
    score it; visibility comes from ``true_masks`` (default: the masks carved)."""
    scenario = get_scenario(name, 0)
    masks = {c: m for c, m in all_masks.items() if c in carver.camera_ids}
    truth = true_body_occupancy(scenario.bodies(frame), carver.grid)
    assert truth.sum() > 300, f"{name} frame {frame}: nobody inside the volume"
    seen = masks if true_masks is None else {c: m for c, m in true_masks.items() if c in carver.camera_ids}
    visible = visible_voxels(truth, carver.grid, cameras, seen, carver)
    return score_carve(carver.carve(masks, scenario.stamp_ns(frame)), truth, visible)


def _figures(scores: list[CarveScore]) -> str:
    return (
        "recall " + ", ".join(f"{s.recall:.3f}" for s in scores)
        + "; visible recall " + ", ".join(f"{s.visible_recall:.3f}" for s in scores)
        + "; excess " + ", ".join(f"{s.excess:.2f}" for s in scores)
        + " body volumes (" + ", ".join(str(s.true_voxels) for s in scores) + " true voxels)"
    )


@pytest.mark.parametrize("count", CAMERA_COUNTS)
@pytest.mark.parametrize("name", list(FRAMES))
def test_true_masks_carve_covers_bodies(name, count, carver_for, cameras, true_masks):
    carver = carver_for(count)
    scores = [carve_and_score(carver, cameras, name, f, true_masks(name, f)) for f in FRAMES[name]]
    print(f"\n{name}, {count} cameras, frames {FRAMES[name]}: {_figures(scores)}")
    assert min(s.visible_recall for s in scores) >= VISIBLE_RECALL_MIN
    assert min(s.recall for s in scores) >= RECALL_MIN[name][count]
    assert max(s.excess for s in scores) <= EXCESS_MAX[name][count]


def test_fisheye_narrows_the_hull(carver_for, cameras, true_masks):
    """The ceiling fisheye cuts the wedges the corner cameras leave between them: without it
    the excess grows on every walking frame while the recall stays the same."""
    for frame in FRAMES["walk"]:
        masks = true_masks("walk", frame)
        five = carve_and_score(carver_for(5), cameras, "walk", frame, masks)
        four = carve_and_score(carver_for(4), cameras, "walk", frame, masks)
        assert four.excess > five.excess, (frame, five, four)
        assert four.recall >= five.recall - 0.01, (frame, five, four)


def test_three_cameras_two_votes_trade_tightness_for_recall(site, cameras, carver_for, true_masks, lut_cache):
    """With three cameras the site's vote is unanimous. Asking two of three instead keeps
    what furniture hides from one camera (the lying person's recall rises from about 0.2
    to about 0.9) but lets the hull of two views through: many body volumes of excess."""
    ids = cameras_for(3, site.camera_ids)
    lenient = Carver(
        cameras={c: cameras[c] for c in ids}, volume_min_m=site.volume.min_m, volume_max_m=site.volume.max_m,
        min_cameras=2, min_ratio=0.6, cache_dir=lut_cache,
    )
    for name, frame in (("fall_forward", 200), ("walk", 150), ("walk", 60)):
        masks = true_masks(name, frame)
        strict = carve_and_score(carver_for(3), cameras, name, frame, masks)
        loose = carve_and_score(lenient, cameras, name, frame, masks)
        print(f"\n{name} {frame}, 3 cameras, 3 of 3: {_figures([strict])}; 2 of 3: {_figures([loose])}")
        assert loose.recall > strict.recall + 0.05
        assert loose.visible_recall >= VISIBLE_RECALL_MIN
        assert loose.excess > strict.excess


SEGMENTED_FRAMES = (60, 150, 240)
SEGMENTED_RECALL_MIN = 0.80  # measured 0.967, 0.827, 1.000 (true masks: 0.969, 0.833, 1.000)
SEGMENTED_EXCESS_MAX = 1.7  # measured 0.82, 0.94, 1.39 (true masks: 0.82, 0.93, 1.37)
SEGMENTED_RECALL_LOSS_MAX = 0.02  # below the true masks' carve, per frame


@pytest.mark.slow  # 81 frames of five cameras rendered and segmented at full resolution: about 11 s
def test_segmented_masks_carve_covers_bodies(carver_for, cameras, walk_cameras, true_masks):
    """The camera worker's own segmentation (learned on the empty room, shadows removed) in
    place of the true masks: a walking person, all five cameras, full resolution. Scored
    against the same truth, and against the carve of the true masks."""
    carver = carver_for(5)
    scenario = get_scenario("walk", 0)
    window = window_frames_for(scenario.fps)
    segmenters, sources = {}, walk_cameras
    for c, src in sources.items():
        seg = ForegroundSegmenter(window_frames=window)
        for i in range(src.n_background_frames):
            seg.learn(src.background_frame(i))
        segmenters[c] = seg
    scores, oracle = [], []
    # Every third frame up to the last scored one: the model sees the person move as it would live.
    for frame in range(0, max(SEGMENTED_FRAMES) + 1, 3):
        masks = {c: segmenters[c].apply(sources[c].frame(frame)[0])[0] for c in cameras}
        if frame in SEGMENTED_FRAMES:
            truth_masks = true_masks("walk", frame)
            scores.append(carve_and_score(carver, cameras, "walk", frame, masks, truth_masks))
            oracle.append(carve_and_score(carver, cameras, "walk", frame, truth_masks))
    print(f"\nwalk, segmented masks, 5 cameras, frames {SEGMENTED_FRAMES}: {_figures(scores)}")
    print(f"walk, true masks, 5 cameras, frames {SEGMENTED_FRAMES}: {_figures(oracle)}")
    assert min(s.recall for s in scores) >= SEGMENTED_RECALL_MIN
    assert max(s.excess for s in scores) <= SEGMENTED_EXCESS_MAX
    for seg, true in zip(scores, oracle):
        assert seg.recall >= true.recall - SEGMENTED_RECALL_LOSS_MAX
