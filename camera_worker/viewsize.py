"""How small a person can look in a camera's view: the smallest foreground blob worth keeping.

The segmenter drops foreground components smaller than ``min_area_px`` (pixels
of a 640x480 frame, scaled to the frame's size): specks of noise that survive
the opening. A fixed size suits a camera in a small room, where everyone is
large in the picture; in a hall watched from 20 m off, or for a child at the
far end of a long room, a whole person can be smaller than that and would be
dropped with the noise before any other camera can vouch for them.

So the size follows the view: the smallest body the room is watched for
(:data:`SMALLEST_BODY_M`, a child 1 m tall) is stood on every point of the
watched volume's floor that the camera sees whole, and the smallest outline it
makes there (the convex hull of the box's corners) sets the bound:
:data:`SEEN_FRACTION` of it, so that a body partly hidden by furniture or by
someone nearer still counts. The result is never above the fixed default (a
close view keeps its noise filter as it was) and never below
:data:`FLOOR_PX` (what the opening leaves of pixel noise). One camera's noise
that gets through is not a person: the fusion server keeps only what enough
cameras agree on.

A blob under the fixed default is kept only apart from larger ones
(:data:`camera_worker.segmentation.DEFAULT_MIN_AREA_PX`): beside someone near, it is
a piece of them (a hand, a blotch of their shadow) that the carve would turn
into a second body beside theirs, not someone far.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from camera_worker.segmentation import DEFAULT_MIN_AREA_PX, REFERENCE_AREA_PX
from common.camera import Camera
from common.site import Volume

__all__ = ["DEFAULT_MIN_AREA_PX", "FLOOR_PX", "SEEN_FRACTION", "SMALLEST_BODY_M", "min_area_for_view",
           "min_area_for_site"]

log = logging.getLogger(__name__)

SMALLEST_BODY_M = (0.3, 0.3, 1.0)
"""Width, depth and height of the smallest body the room is watched for: a child 1 m tall."""
SEEN_FRACTION = 0.25
"""The part of that body's outline that must be foreground for the blob to be kept."""
FLOOR_PX = 50
"""The smallest component of any view (640x480 pixels): below it, pixel noise."""
_STEP_M = 0.25   # floor points sampled every 0.25 m


def min_area_for_view(camera: Camera, volume: Volume, *, default_px: int = DEFAULT_MIN_AREA_PX) -> int:
    """``min_area_px`` (pixels of a 640x480 frame) for ``camera`` watching ``volume``: a quarter of the
    smallest outline of :data:`SMALLEST_BODY_M` stood anywhere on the volume's floor in full view,
    within ``[min(FLOOR_PX, default_px), default_px]``; ``default_px`` when no such place is in view."""
    area = smallest_body_area_px(camera, volume)
    if area is None:
        return default_px
    ref = SEEN_FRACTION * area * REFERENCE_AREA_PX / float(camera.width * camera.height)
    return int(min(default_px, max(min(FLOOR_PX, default_px), round(ref))))


def smallest_body_area_px(camera: Camera, volume: Volume) -> float | None:
    """The smallest outline, in the camera's pixels, of :data:`SMALLEST_BODY_M` standing on the floor
    of ``volume`` where all its corners are in view (None: nowhere)."""
    w, d, h = SMALLEST_BODY_M
    (x0, y0, _), (x1, y1, _) = volume.min_m, volume.max_m
    xs = np.arange(x0 + w / 2, x1 - w / 2 + 1e-9, _STEP_M)
    ys = np.arange(y0 + d / 2, y1 - d / 2 + 1e-9, _STEP_M)
    if not len(xs) or not len(ys):
        return None
    gx, gy = np.meshgrid(xs, ys)
    feet = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    corners = np.array([[sx * w / 2, sy * d / 2, z] for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, h)])
    uv, ok = camera.project((feet[:, None, :] + corners[None]).reshape(-1, 3))
    uv = uv.reshape(len(feet), len(corners), 2)
    whole = np.flatnonzero(ok.reshape(len(feet), len(corners)).all(axis=1))
    if not len(whole):
        return None
    return float(min(cv2.contourArea(cv2.convexHull(uv[i].astype(np.float32))) for i in whole))


def min_area_for_site(site, cam_id: str, *, default_px: int = DEFAULT_MIN_AREA_PX) -> int:
    """:func:`min_area_for_view` for one camera of a site; ``default_px``, said in a warning naming
    the file, when its calibration cannot be read (a worker may run before the room is calibrated)."""
    try:
        camera = site.load_camera(cam_id)
    except (OSError, ValueError) as exc:
        log.warning("camera %s: calibration %s not usable (%s): smallest foreground blob %d px by default",
                    cam_id, site.calibration_path(cam_id), exc, default_px)
        return default_px
    return min_area_for_view(camera, site.volume, default_px=default_px)
