"""Foreground segmentation: hand-worked schedule and clean-up, shadows, fast start-up,
light changes and hold regions on drawn scenes with known silhouettes, and the real
lab recording (lab4cam-seated) against hand-checked person boxes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from camera_worker.segmentation import (
    ForegroundSegmenter,
    fill_holes,
    learning_rate_schedule,
    remove_small_components,
    scale_box,
)

W, H = 320, 240


# --- a drawn room with known silhouettes -----------------------------------------------------------


class Room:
    """A smoothly textured room; people are textured boxes, shadows darken the floor by 0.65."""

    def __init__(self, seed: int = 1, width: int = W, height: int = H) -> None:
        self.rng = np.random.default_rng(seed)
        base = self.rng.normal(0, 1, (height // 8, width // 8, 3)).astype(np.float32)
        smooth = cv2.resize(cv2.GaussianBlur(base, (0, 0), 1.5), (width, height))
        self.bg = np.clip(120 + 50 * smooth / np.abs(smooth).max(), 0, 255).astype(np.float32)
        self.texture = self.rng.uniform(30, 220, (height, width, 3)).astype(np.float32)
        self.size = (width, height)

    def frame(self, people=(), *, gain: float = 1.0, shadow=None, extra=None) -> tuple[np.ndarray, np.ndarray]:
        """``(bgr, truth)``: truth is 255 on people (not on shadows)."""
        img = self.bg.copy()
        if shadow is not None:
            x0, y0, x1, y1 = shadow
            img[y0:y1, x0:x1] *= 0.65
        if extra is not None:   # a static object that is not a person (a moved chair)
            x0, y0, x1, y1 = extra
            img[y0:y1, x0:x1] = (200, 40, 40)
        truth = np.zeros(img.shape[:2], np.uint8)
        for x0, y0, x1, y1 in people:
            img[y0:y1, x0:x1] = self.texture[:y1 - y0, :x1 - x0]   # the clothes move with the person
            truth[y0:y1, x0:x1] = 255
        img = img * gain + self.rng.normal(0, 2.0, img.shape)
        return np.clip(img, 0, 255).astype(np.uint8), truth


def recall_precision(mask: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    m, t = mask > 0, truth > 0
    tp = np.count_nonzero(m & t)
    return tp / max(np.count_nonzero(t), 1), tp / max(np.count_nonzero(m), 1)


def small_segmenter(**kw) -> ForegroundSegmenter:
    return ForegroundSegmenter(min_area_px=50, **kw)


PERSON = (100, 60, 140, 200)


# --- pure pieces ---------------------------------------------------------------------------------


def test_learning_rate_schedule_is_one_over_n_then_alpha():
    assert learning_rate_schedule(1, window_frames=100, alpha=0.01) == 1.0
    assert learning_rate_schedule(4, window_frames=100, alpha=0.01) == 0.25
    assert learning_rate_schedule(99, window_frames=100, alpha=0.01) == pytest.approx(1 / 99)
    assert learning_rate_schedule(100, window_frames=100, alpha=0.01) == 0.01
    assert learning_rate_schedule(5000, window_frames=100, alpha=0.01) == 0.01
    # never below alpha, even inside the window
    assert learning_rate_schedule(50, window_frames=100, alpha=0.05) == 0.05
    with pytest.raises(ValueError, match="n must be"):
        learning_rate_schedule(0, window_frames=100, alpha=0.01)


@pytest.mark.parametrize("kw, name", [
    (dict(window_frames=0), "window_frames"),
    (dict(alpha=0.0), "alpha"),
    (dict(alpha=1.5), "alpha"),
    (dict(mask_scale=0.0), "mask_scale"),
    (dict(mask_scale=2.0), "mask_scale"),
    (dict(min_area_px=-1), "min_area_px"),
    (dict(open_px=1.5), "open_px"),
    (dict(shadow_threshold=1.0), "shadow_threshold"),
    (dict(light_change_fraction=0.0), "light_change_fraction"),
    (dict(relearn_frames=-1), "relearn_frames"),
    (dict(background_ratio=0.0), "background_ratio"),
])
def test_constructor_names_the_bad_argument(kw, name):
    with pytest.raises(ValueError, match=name):
        ForegroundSegmenter(**kw)


def test_remove_small_components_keeps_only_large_blobs():
    mask = np.zeros((50, 60), np.uint8)
    mask[5:15, 5:15] = 255          # 100 px: kept
    mask[30:33, 40:43] = 255        # 9 px: removed
    mask[40, 10] = 255              # 1 px: removed
    out, kept = remove_small_components(mask, 10)
    assert kept == 1
    assert np.count_nonzero(out) == 100 and out[10, 10] == 255 and out[31, 41] == 0 and out[40, 10] == 0
    empty, kept = remove_small_components(np.zeros((5, 5), np.uint8), 1)
    assert kept == 0 and not empty.any()


def test_fill_holes_fills_enclosed_background_only():
    ring = np.zeros((40, 40), np.uint8)
    cv2.rectangle(ring, (5, 5), (25, 25), 255, 3)       # closed ring: its inside is a hole
    cup = np.zeros((40, 40), np.uint8)
    cup[10:30, 10:13] = 255
    cup[27:30, 10:30] = 255
    cup[10:30, 27:30] = 255                              # open at the top: not a hole
    out = fill_holes(ring | cup)
    assert out[15, 15] == 255                            # inside the ring: filled
    assert np.count_nonzero(out[6:25, 6:25]) == 19 * 19
    assert out[15, 20] == 255 and out[20, 20] == 255
    cup_only = fill_holes(cup)
    assert np.array_equal(cup_only, cup)                 # the cup's inside reaches the border


def test_scale_box_covers_every_touched_pixel_and_clips():
    assert scale_box((10, 20, 31, 41), 0.5, (100, 100)) == (5, 10, 16, 21)
    assert scale_box((-5, -5, 10, 10), 1.0, (8, 8)) == (0, 0, 8, 8)
    assert scale_box((50, 50, 60, 60), 1.0, (40, 40)) is None
    with pytest.raises(ValueError, match="hold box"):
        scale_box((1, 2, 3), 1.0, (10, 10))


# --- behaviour on drawn scenes -------------------------------------------------------------------


def test_first_frame_gives_an_empty_mask_of_the_scaled_size():
    room = Room()
    seg = small_segmenter(mask_scale=0.5)
    mask, stats = seg.apply(room.frame([PERSON])[0])
    assert mask.shape == (H // 2, W // 2) and mask.dtype == np.uint8 and not mask.any()
    assert stats.frame_index == 1 and stats.learning_rate == 1.0
    assert seg.mask_size == (W // 2, H // 2) and seg.full_size == (W, H)


def test_mask_is_binary_and_finds_a_person_at_half_scale():
    room = Room()
    seg = small_segmenter(mask_scale=0.5)
    for _ in range(20):
        seg.apply(room.frame()[0])
    img, truth = room.frame([PERSON])
    mask, stats = seg.apply(img)
    assert set(np.unique(mask)) <= {0, 255}
    half_truth = cv2.resize(truth, (W // 2, H // 2), interpolation=cv2.INTER_NEAREST)
    recall, precision = recall_precision(mask, half_truth)
    assert recall >= 0.97 and precision >= 0.97
    assert stats.fg_fraction == pytest.approx(np.count_nonzero(mask) / mask.size)
    assert stats.components == 1


def test_shadows_are_removed_from_the_mask():
    room = Room()
    shadow = (140, 150, 230, 205)             # a cast shadow on the floor next to the person
    with_test, without_test = small_segmenter(), small_segmenter(detect_shadows=False)
    for _ in range(30):
        img = room.frame()[0]
        with_test.apply(img)
        without_test.apply(img)
    img, truth = room.frame([PERSON], shadow=shadow)
    mask, stats = with_test.apply(img)
    recall, precision = recall_precision(mask, truth)
    assert recall >= 0.98 and precision >= 0.98
    shadow_area = (shadow[2] - shadow[0]) * (shadow[3] - shadow[1]) / (W * H)
    assert stats.shadow_fraction >= 0.9 * shadow_area
    # the same frame without the shadow test: the shadow becomes foreground
    mask_off, _ = without_test.apply(img)
    assert recall_precision(mask_off, truth)[1] < 0.7


def test_fast_startup_clears_a_ghost_within_three_frames():
    """Someone in view when the camera starts leaves after 10 frames.

    With the window schedule (1/n) the revealed background is learned at
    once; with the settled rate from the start (no fast start-up) the
    ghost is still there 40 frames later."""
    room = Room()
    fast, slow = small_segmenter(window_frames=500), small_segmenter(window_frames=1, alpha=0.002)
    for _ in range(10):
        img = room.frame([PERSON])[0]
        fast.apply(img)
        slow.apply(img)
    fast_fg, slow_fg = [], []
    for _ in range(40):
        img = room.frame()[0]
        fast_fg.append(fast.apply(img)[1].fg_fraction)
        slow_fg.append(slow.apply(img)[1].fg_fraction)
    assert max(fast_fg[3:]) == 0.0
    assert min(slow_fg) > 0.05


def test_background_clip_then_live_frames_use_the_settled_rate():
    room = Room()
    seg = small_segmenter(window_frames=200)
    for _ in range(30):
        seg.learn(room.frame()[0])
    assert seg.frames_seen == 30
    assert seg.next_learning_rate() == pytest.approx(1 / 200)
    img, truth = room.frame([PERSON])
    mask, stats = seg.apply(img)
    assert stats.learning_rate == pytest.approx(1 / 200)
    assert min(recall_precision(mask, truth)) >= 0.97


def test_learn_false_leaves_the_model_unchanged():
    room = Room()
    seg = small_segmenter(window_frames=20)
    for _ in range(30):
        seg.apply(room.frame()[0])
    for _ in range(100):
        mask, stats = seg.apply(room.frame([PERSON])[0], learn=False)
        assert stats.learning_rate == 0.0
    assert min(recall_precision(mask, room.frame([PERSON])[1])) >= 0.97


def test_a_frame_of_another_size_is_refused():
    seg = small_segmenter()
    seg.apply(np.zeros((H, W, 3), np.uint8))
    with pytest.raises(ValueError, match="differs"):
        seg.apply(np.zeros((H // 2, W // 2, 3), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        seg.apply(np.zeros((H, W, 3), np.float32))
    seg.reset()
    seg.apply(np.zeros((H // 2, W // 2, 3), np.uint8))


@pytest.mark.parametrize("gain", [1.5, 1.25, 0.6])
def test_sudden_light_change_recovers_on_the_frame_of_the_change(gain):
    """Stated recovery: 0 frames. The mask of the frame where the light changes, and of
    every frame after it, has the walking person at recall and precision >= 0.97."""
    room = Room()
    seg = small_segmenter(relearn_frames=10)
    for _ in range(60):
        seg.learn(room.frame()[0])
    flags = []
    for i in range(20):
        person = (100 + 4 * i, 60, 140 + 4 * i, 200)
        img, truth = room.frame([person], gain=gain)
        mask, stats = seg.apply(img)
        flags.append((stats.light_change, stats.relearning))
        recall, precision = recall_precision(mask, truth)
        assert recall >= 0.97 and precision >= 0.97, (i, recall, precision)
    assert flags[0] == (True, True)
    assert not any(change for change, _ in flags[1:])
    assert all(relearning for _, relearning in flags[:11]) and not any(r for _, r in flags[11:])


def test_a_person_close_to_the_lens_is_not_a_light_change():
    room = Room()
    seg = small_segmenter()
    for _ in range(60):
        seg.apply(room.frame()[0])
    close = (0, 0, 180, H)                    # 56 % of the image
    for _ in range(5):
        img, truth = room.frame([close])
        mask, stats = seg.apply(img)
        assert not stats.light_change
    assert min(recall_precision(mask, truth)) >= 0.97


def _still_person_run(hold: bool, *, frames: int = 300, mask_scale: float = 1.0):
    """A person stands still from frame 0 of the live run; a chair is moved in at frame 20."""
    room = Room()
    seg = small_segmenter(window_frames=100, mask_scale=mask_scale)
    for _ in range(40):
        seg.learn(room.frame()[0])
    chair = (230, 150, 280, 200)
    box = (PERSON[0] - 6, PERSON[1] - 6, PERSON[2] + 6, PERSON[3] + 6)
    recalls, chair_fg = [], []
    for i in range(frames):
        img, truth = room.frame([PERSON], extra=chair if i >= 20 else None)
        mask, stats = seg.apply(img, holds=[box] if hold else ())
        assert stats.holds == (1 if hold else 0)
        if mask_scale != 1.0:
            truth = cv2.resize(truth, mask.shape[::-1], interpolation=cv2.INTER_NEAREST)
        recalls.append(recall_precision(mask, truth)[0])
        s = mask_scale
        cx0, cy0, cx1, cy1 = (int(v * s) for v in chair)
        chair_fg.append(np.count_nonzero(mask[cy0:cy1, cx0:cx1]) / ((cx1 - cx0) * (cy1 - cy0)))
    return np.array(recalls), np.array(chair_fg)


def test_without_hold_a_still_person_is_absorbed():
    """alpha = 1/100: absorbed after about ln(1/0.9) * 100 = 11 frames."""
    recalls, _ = _still_person_run(hold=False)
    assert recalls[0] >= 0.97
    assert recalls[30:].max() < 0.05


@pytest.mark.parametrize("mask_scale", [pytest.param(1.0, marks=pytest.mark.slow), 0.5])
def test_hold_keeps_a_still_person_while_the_rest_keeps_learning(mask_scale):
    recalls, chair_fg = _still_person_run(hold=True, mask_scale=mask_scale)
    assert recalls.min() >= 0.95                      # 300 frames = 27 absorption times
    assert chair_fg[20] >= 0.9                        # the moved chair appears ...
    assert chair_fg[60:].max() < 0.05                 # ... and is learned outside the hold


# --- the real recording ---------------------------------------------------------------------------

# Hand-checked on frames 0, 210 and 420 of each camN/video.avi (644x486): the person with the chair,
# and a box inside the torso that must be foreground in every frame.
LAB_PERSON = {1: (326, 140, 436, 342), 2: (286, 226, 392, 454), 3: (124, 194, 288, 460), 4: (218, 176, 324, 369)}
LAB_TORSO = {1: (370, 196, 400, 250), 2: (310, 286, 365, 340), 3: (145, 280, 182, 340), 4: (240, 240, 280, 290)}
# The background clips differ from the videos beyond the person (a moved checkerboard in cam3,
# a cable in cam1, a slightly shifted cam2): those static changes are learned at the normal rate
# (window 500) in about 0.105 * 500 = 53 frames; outside-the-box bounds apply after SETTLE_FRAMES.
SETTLE_FRAMES = 60
MAX_OUTSIDE = 0.01      # fraction of mask pixels outside the person's box (0.000 measured after frame 56)
MIN_TORSO = 0.95        # fraction of the torso box covered, every frame (0.999 measured)
MIN_BOX = 0.40          # fraction of the person's box covered, every frame (person + chair: 0.43-0.51 measured)


def _frames(path: Path, limit: int | None = None):
    cap = cv2.VideoCapture(str(path))
    try:
        n = 0
        while limit is None or n < limit:
            ok, img = cap.read()
            if not ok:
                return
            yield img
            n += 1
    finally:
        cap.release()


def _lab_run(lab4cam: Path, cam: int, *, frames: int | None, hold: bool):
    seg = ForegroundSegmenter()
    for img in _frames(lab4cam / f"cam{cam}" / "background.avi"):
        seg.learn(img)
    box, torso = LAB_PERSON[cam], LAB_TORSO[cam]
    outside, torso_cov, box_cov = [], [], []
    for img in _frames(lab4cam / f"cam{cam}" / "video.avi", frames):
        # the hold stands in for the fusion's HoldRegions message for the tracked, seated person
        mask, _ = seg.apply(img, holds=[box] if hold else ())
        total = np.count_nonzero(mask)
        x0, y0, x1, y1 = box
        inside = np.count_nonzero(mask[y0:y1, x0:x1])
        outside.append((total - inside) / max(total, 1))
        box_cov.append(inside / ((x1 - x0) * (y1 - y0)))
        x0, y0, x1, y1 = torso
        torso_cov.append(np.count_nonzero(mask[y0:y1, x0:x1]) / ((x1 - x0) * (y1 - y0)))
    return np.array(outside), np.array(torso_cov), np.array(box_cov)


def _check_lab(lab4cam: Path, frames: int | None, cameras: tuple[int, ...] = (1, 2, 3, 4)) -> None:
    for cam in cameras:
        outside, torso, box = _lab_run(lab4cam, cam, frames=frames, hold=True)
        assert torso.min() >= MIN_TORSO, (cam, torso.min())
        assert box.min() >= MIN_BOX, (cam, box.min())
        assert outside[SETTLE_FRAMES:].max() <= MAX_OUTSIDE, (cam, outside[SETTLE_FRAMES:].max())


@pytest.mark.realdata
def test_lab_recording_masks_cover_the_seated_person_and_little_else(lab4cam):
    """Background clip learned, then the first 120 frames of the videos of cam2 (in front of the chair)
    and cam3 (at its side); every frame of every camera in the slow set."""
    _check_lab(lab4cam, frames=120, cameras=(2, 3))


@pytest.mark.realdata
@pytest.mark.slow
def test_lab_recording_every_frame(lab4cam):
    _check_lab(lab4cam, frames=None)


@pytest.mark.realdata
def test_lab_recording_without_hold_absorbs_the_seated_person(lab4cam):
    """The same run without the hold: the still person fades into the background."""
    _, torso, _ = _lab_run(lab4cam, 1, frames=150, hold=False)
    assert torso[:5].min() >= MIN_TORSO
    assert torso[120:].max() < 0.1


# --- the synthetic house: exact silhouettes ---------------------------------------------------------

HOUSE_CAMERAS = ("cam1", "cam2", "cam3", "cam4", "cam5")


def _house_camera(scenario: str, cam: str, *, shadows: bool = True):
    source = pytest.importorskip("synth.source")
    return source.SyntheticCamera(scenario, cam, 0, shadows=shadows)


def _learned(camera, **kw) -> ForegroundSegmenter:
    seg = ForegroundSegmenter(**kw)
    for i in range(camera.n_background_frames):
        seg.learn(camera.background_frame(i))
    return seg


class Score:
    """Pixel counts summed over frames; ``precision``/``recall`` of the sums, and the worst frame."""

    def __init__(self) -> None:
        self.tp = self.fp = self.fn = 0
        self.frames: list[tuple[float, float]] = []

    def add(self, mask: np.ndarray, truth: np.ndarray) -> None:
        m, t = mask > 0, truth > 0
        tp, fp, fn = np.count_nonzero(m & t), np.count_nonzero(m & ~t), np.count_nonzero(~m & t)
        self.tp, self.fp, self.fn = self.tp + tp, self.fp + fp, self.fn + fn
        if t.any():
            self.frames.append((tp / max(tp + fp, 1), tp / max(tp + fn, 1)))

    @property
    def precision(self) -> float:
        return self.tp / max(self.tp + self.fp, 1)

    @property
    def recall(self) -> float:
        return self.tp / max(self.tp + self.fn, 1)


# 'walk', 60 frames after the empty-room clip, measured per camera (cam1..cam5):
#   shadows rendered, shadow test on:  precision 0.92-0.97, recall 0.975-0.995
#   shadows rendered, shadow test off: precision 0.70-0.87 (the cast shadows become foreground)
#   no shadows rendered, test on:      the same as with shadows (the test removes them all)
HOUSE_MIN_PRECISION = 0.90
HOUSE_MIN_RECALL = 0.96
SHADOW_PRECISION_GAIN = 0.06


@pytest.mark.parametrize("cam", [c if c == "cam1" else pytest.param(c, marks=pytest.mark.slow)
                                 for c in HOUSE_CAMERAS])
def test_house_precision_and_recall_with_cast_shadows(cam):
    camera = _house_camera("walk", cam)
    with_test, without_test = _learned(camera), _learned(camera, detect_shadows=False)
    on, off = Score(), Score()
    for i in range(60):
        img, truth = camera.frame(i)
        on.add(with_test.apply(img)[0], truth)
        off.add(without_test.apply(img)[0], truth)
    assert on.precision >= HOUSE_MIN_PRECISION and on.recall >= HOUSE_MIN_RECALL, (on.precision, on.recall)
    assert off.precision <= on.precision - SHADOW_PRECISION_GAIN, (on.precision, off.precision)


@pytest.mark.slow
@pytest.mark.parametrize("cam", HOUSE_CAMERAS)
def test_house_precision_and_recall_without_rendered_shadows(cam):
    camera = _house_camera("walk", cam, shadows=False)
    seg, score = _learned(camera), Score()
    for i in range(150):
        img, truth = camera.frame(i)
        score.add(seg.apply(img)[0], truth)
    assert score.precision >= HOUSE_MIN_PRECISION and score.recall >= HOUSE_MIN_RECALL


# 'lights': a lamp raises the scene gain by 28 % at 20 s (frame 300, over 0.1 s). The oracle is the
# same scenario without the lamp. Stated recovery: 0 frames -- from the change on, every frame's
# precision and recall are those of the lamp-less run (within 0.03; measured: equal to 0.01).
LIGHT_FRAMES = range(285, 330)
LIGHT_AT = 301


def _per_frame(camera, seg: ForegroundSegmenter) -> tuple[list[tuple[float, float]], list[int]]:
    scores, flagged = [], []
    for i in LIGHT_FRAMES:
        img, truth = camera.frame(i)
        mask, stats = seg.apply(img)
        scores.append(recall_precision(mask, truth))
        flagged += [i] if stats.light_change else []
    return scores, flagged


@pytest.mark.parametrize("cam", [c if c == "cam1" else pytest.param(c, marks=pytest.mark.slow)
                                 for c in HOUSE_CAMERAS])
def test_house_lamp_switched_on_recovers_at_once(cam):
    import dataclasses

    scenarios = pytest.importorskip("synth.scenarios")
    source = pytest.importorskip("synth.source")
    spec = scenarios.SCENARIOS["lights"]()
    lamp = source.SyntheticCamera(spec, cam, 0)
    no_lamp = source.SyntheticCamera(dataclasses.replace(spec, lights=()), cam, 0)
    with_lamp, flagged = _per_frame(lamp, _learned(lamp))
    without, unflagged = _per_frame(no_lamp, _learned(no_lamp))
    assert flagged and all(LIGHT_AT <= i <= LIGHT_AT + 1 for i in flagged), flagged
    assert not unflagged
    for i, ((r, p), (r0, p0)) in enumerate(zip(with_lamp, without)):
        assert abs(r - r0) <= 0.03 and abs(p - p0) <= 0.03, (LIGHT_FRAMES[i], (r, p), (r0, p0))
    assert min(r for r, _ in with_lamp) >= 0.9


def test_house_lamp_without_light_handling_ruins_the_masks():
    """The same change with the light test off: for the 28 frames shown, the mask is mostly wrong."""
    camera = _house_camera("lights", "cam1")
    scores, flagged = _per_frame(camera, _learned(camera, light_change_fraction=None))
    assert not flagged
    assert max(p for _, p in scores[LIGHT_AT + 1 - LIGHT_FRAMES.start:]) < 0.2


def _truth_box(truth: np.ndarray, pad: int = 12) -> list[tuple[int, int, int, int]]:
    ys, xs = np.nonzero(truth)
    return [(int(xs.min()) - pad, int(ys.min()) - pad, int(xs.max()) + 1 + pad, int(ys.max()) + 1 + pad)]


@pytest.mark.slow  # holds and light changes are each in the default run; together, 160 frames twice
@pytest.mark.parametrize("cam", ["cam2", "cam5"])
def test_house_still_person_held_through_a_light_change(cam):
    """'lights' from frame 540: the person stands still; the lamp goes off at 45 s (frame 675).

    Without holds they are absorbed; with holds (the truth's box, standing in for the fusion's
    HoldRegions) they stay foreground for all 160 frames, the light change included."""
    camera = _house_camera("lights", cam)
    free, held = _learned(camera), _learned(camera)
    free_recall, held_recall, changes = [], [], []
    for i in range(540, 700):
        img, truth = camera.frame(i)
        mask, _ = free.apply(img)
        free_recall.append(recall_precision(mask, truth)[0])
        mask, stats = held.apply(img, holds=_truth_box(truth))
        held_recall.append(recall_precision(mask, truth)[0])
        changes += [i] if stats.light_change else []
    assert min(held_recall) >= 0.95
    assert max(free_recall[100:130]) < 0.05          # absorbed well before the lamp goes off
    assert any(675 <= i <= 677 for i in changes)
