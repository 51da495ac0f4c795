"""The synthetic house's walk at half size, for the range and thermal segmenters' tests: grey
renderers of two cameras, a person standing still, the hold box around a silhouette and the IoU of
a mask with the true silhouettes, and a still person's run through a segmenter."""

from __future__ import annotations

from typing import Callable

import numpy as np

from synth.body import BodyShape, pose_body, standing_pose
from synth.render import CameraRenderer
from synth.scenarios import get_scenario
from synth.scene import default_cameras

HALF = default_cameras(scale=0.5)
SCENARIO = get_scenario("walk", 0)


def half_renderers() -> dict[str, CameraRenderer]:
    """Renderers without colour of cam1 and cam3 at 320x240 in the walk's room."""
    return {cid: CameraRenderer(HALF[cid], SCENARIO.room, seed=0, colour=False) for cid in ("cam1", "cam3")}


def standing_person(x: float = 4.0, y: float = 3.0):
    """A 1.7 m person (id 1) standing at ``(x, y)`` metres of the world frame."""
    shape = BodyShape(height_m=1.7)
    return pose_body(shape, standing_pose(shape, x, y, 0.5), person_id=1)


def hold_box(labels: np.ndarray, margin_px: int = 4) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` (exclusive) around the labelled pixels of ``(H, W)`` ``labels``, ``margin_px`` wider."""
    ys, xs = np.nonzero(labels)
    m = margin_px
    return int(xs.min()) - m, int(ys.min()) - m, int(xs.max()) + m + 1, int(ys.max()) + m + 1


def iou(mask: np.ndarray, labels: np.ndarray) -> float:
    """Intersection over union of the non-zero pixels of two ``(H, W)`` arrays."""
    m, t = mask > 0, labels > 0
    return float((m & t).sum() / max((m | t).sum(), 1))


def still_person_ious(seg, empty_frame: Callable[[int], np.ndarray], frame: Callable[[int], np.ndarray],
                      labels: np.ndarray, *, holds: list, n_frames: int) -> tuple[float, float]:
    """Learn 20 frames ``empty_frame(i)`` of the empty room, then segment ``frame(i)`` for ``n_frames``
    frames with ``holds``: the IoU with ``labels`` at frame 5 and at the last."""
    for i in range(20):
        seg.learn(empty_frame(i))
    ious = []
    for i in range(n_frames):
        mask, _ = seg.apply(frame(i), holds=holds)
        if i in (5, n_frames - 1):
            ious.append(iou(mask, labels))
    return ious[0], ious[1]
