"""Two heads or one, from the masks (fusion_server.heads): real cameras, masks drawn from boxes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.camera import Camera, look_at
from fusion_server.heads import HeadGaps

HEIGHT_M = 1.7


def camera(cam_id: str, centre, target, size=(320, 240), fx=220.0) -> Camera:
    R, t = look_at(centre, target)
    return Camera.pinhole(cam_id, size[0], size[1], fx=fx, R=R, t=t)


def box(mask, cam, lo, hi):
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv, ok = cam.project(corners)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.round(uv[ok]).astype(np.int32)), 255)


def masks_of(cameras, people):
    """Masks of people standing at ``people`` (x, y): a body 0.4 m wide up to 1.45 m, a head 0.2 m
    wide over it up to HEIGHT_M."""
    out = {}
    for cid, cam in cameras.items():
        m = np.zeros((cam.height, cam.width), np.uint8)
        for x, y in people:
            box(m, cam, (x - 0.2, y - 0.2, 0.0), (x + 0.2, y + 0.2, 1.45))
            box(m, cam, (x - 0.1, y - 0.1, 1.45), (x + 0.1, y + 0.1, HEIGHT_M))
        out[cid] = m
    return out


# Two people side by side along x, 0.35 m apart centre to centre: bodies touching, heads 0.15 m apart.
A, B = (2.0, 2.0), (2.35, 2.0)
ACROSS = camera("across", (2.2, -1.5, 2.5), (2.2, 2.0, 1.2))   # looks along y: the gap between the heads shows
FACING = camera("facing", (2.6, 5.5, 2.8), (2.2, 2.0, 1.2))    # looks back along -y, from higher up: the gap shows
ALONG = camera("along", (-1.5, 2.0, 1.6), (2.2, 2.0, 1.6))     # looks along x at head height: one behind the other


def heads(*xy):
    return tuple((x, y, HEIGHT_M) for x, y in xy)


def test_two_cameras_looking_across_the_gap_see_two_heads_one_is_not_enough():
    cams = {"across": ACROSS, "facing": FACING}
    assert HeadGaps(cams).seen_apart([heads(A, B)], masks_of(cams, [A, B])) == [True]
    for one in cams:
        assert HeadGaps({one: cams[one]}).seen_apart([heads(A, B)], masks_of({one: cams[one]}, [A, B])) == [False]


def test_a_camera_looking_along_the_line_of_the_two_cannot_tell():
    cams = {"along": ALONG, "across": ACROSS}
    assert HeadGaps(cams).seen_apart([heads(A, B)], masks_of(cams, [A, B])) == [False]
    cams = {"along": ALONG, "across": ACROSS, "facing": FACING}
    assert HeadGaps(cams).seen_apart([heads(A, B)], masks_of(cams, [A, B])) == [True]


def test_someone_standing_behind_is_not_a_head_there():
    """The line's end lands on a taller person standing behind in one camera: over the end the mask
    is foreground, so that camera cannot tell (and with one other camera seeing the gap, too few)."""
    cams = {"across": ACROSS, "facing": FACING}
    tall_behind = (2.35, 3.2)   # behind B as the 'across' camera sees it
    masks = masks_of(cams, [A, B])
    box(masks["across"], ACROSS, (tall_behind[0] - 0.2, tall_behind[1] - 0.2, 0.0), (tall_behind[0] + 0.2, tall_behind[1] + 0.2, 2.3))
    assert HeadGaps(cams).seen_apart([heads(A, B)], masks) == [False]


@pytest.mark.parametrize("offset", [(0.35, 0.0), (0.0, 0.35), (0.25, 0.25)])
def test_a_target_beside_one_person_has_no_head_of_its_own(offset):
    """One person at A; a second target 0.35 m beside them (it slid onto their body): no camera shows
    a head at its place with a gap between."""
    cams = {"across": ACROSS, "facing": FACING, "along": ALONG, "above": camera("above", (4.5, 4.5, 2.6), (2.0, 2.0, 0.8))}
    other = (A[0] + offset[0], A[1] + offset[1])
    assert HeadGaps(cams).seen_apart([heads(A, other)], masks_of(cams, [A])) == [False]


def test_masks_at_a_lower_resolution_and_cameras_not_in_the_site():
    cams = {"across": ACROSS, "facing": FACING}
    full = masks_of(cams, [A, B])
    half = {c: cv2.resize(m, (160, 120), interpolation=cv2.INTER_NEAREST) for c, m in full.items()}
    half["elsewhere"] = np.full((120, 160), 255, np.uint8)
    gaps = HeadGaps(cams)
    assert gaps.seen_apart([heads(A, B), heads(A, (2.0, 3.0))], half) == [True, False]
    assert gaps.seen_apart([], half) == []
