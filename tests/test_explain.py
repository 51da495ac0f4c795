"""Phantoms refused: carving of box-shaped people seen by a few level cameras, worked by hand.

Two people at (1, 1) and (2, 2), seen by one camera looking along +y and one
looking along +x: each camera sees two silhouettes, and the hull holds four
bodies, the two people and two phantoms at (1, 2) and (2, 1) where one
person's cone from the first camera crosses the other's from the second.
Each phantom lies farther from one camera than the person whose silhouette
it hides in, so it covers only part of it: the people explain every
foreground pixel, the phantoms none of their own.
"""

from __future__ import annotations

import numpy as np
import pytest

from common.camera import Camera, look_at
from fusion_server.carving.carver import Carver
from fusion_server.detection import detect_blobs
from fusion_server.explain import explain_blobs

VOLUME = ((0.0, 0.0, 0.0), (4.0, 4.0, 2.0))


def level_camera(cam_id: str, centre, target) -> Camera:
    R, t = look_at(centre, target)
    return Camera.pinhole(cam_id, 320, 240, fx=220.0, R=R, t=t)


def box_masks(cameras, people, *, size=(0.4, 0.4, 1.7)):
    """Masks of upright boxes standing at ``people`` (x, y), drawn as the filled hull of each
    box's projected corners."""
    import cv2

    out = {}
    sx, sy, sz = size
    for cid, cam in cameras.items():
        m = np.zeros((cam.height, cam.width), np.uint8)
        for x, y in people:
            corners = np.array([[x + dx, y + dy, z] for dx in (-sx / 2, sx / 2) for dy in (-sy / 2, sy / 2)
                                for z in (0.0, sz)])
            uv, ok = cam.project(corners)
            hull = cv2.convexHull(np.round(uv[ok]).astype(np.int32))
            cv2.fillConvexPoly(m, hull, 255)
        out[cid] = m
    return out


def carve_and_explain(cameras, people, tmp_path):
    carver = Carver(cameras=cameras, volume_min_m=VOLUME[0], volume_max_m=VOLUME[1], cache_dir=tmp_path)
    masks = box_masks(cameras, people)
    carve = carver.carve(masks, 0)
    blobs = detect_blobs(carve)
    return blobs, explain_blobs(blobs, masks, cameras, carve.grid)


def near(blobs, xy, tol=0.2) -> bool:
    return any(abs(b.x - xy[0]) < tol and abs(b.y - xy[1]) < tol for b in blobs)


def test_two_people_seen_by_two_cameras_make_two_phantoms_which_are_refused(tmp_path):
    cams = {
        "south": level_camera("south", (1.5, -2.5, 1.2), (1.5, 2.0, 0.9)),
        "west": level_camera("west", (-2.5, 1.5, 1.2), (2.0, 1.5, 0.9)),
    }
    people = [(1.0, 1.0), (2.0, 2.0)]
    blobs, verdict = carve_and_explain(cams, people, tmp_path)
    # the hull: two people and two phantoms where the cones cross
    assert len(blobs) == 4
    assert near(blobs, (1.0, 2.0)) and near(blobs, (2.0, 1.0))
    assert len(verdict.people) == 2 and all(near(verdict.people, p) for p in people)
    assert len(verdict.phantoms) == 2
    assert near(verdict.phantoms, (1.0, 2.0)) and near(verdict.phantoms, (2.0, 1.0))


def test_three_people_in_a_row_are_three_people(tmp_path):
    # three people on a diagonal seen by three cameras: two of them see the row end-on or across,
    # and every person still has foreground of their own in at least two cameras
    cams = {
        "south": level_camera("south", (2.0, -2.5, 1.2), (2.0, 2.0, 0.9)),
        "west": level_camera("west", (-2.5, 2.0, 1.2), (2.0, 2.0, 0.9)),
        "corner": level_camera("corner", (-1.5, -1.5, 2.2), (2.0, 2.0, 0.8)),
    }
    people = [(1.0, 1.0), (2.0, 2.0), (3.0, 3.0)]
    blobs, verdict = carve_and_explain(cams, people, tmp_path)
    assert len(verdict.people) == 3 and all(near(verdict.people, p) for p in people)
    # whatever else the hull held is refused
    assert len(verdict.phantoms) == len(blobs) - 3


def test_one_camera_cannot_tell_and_keeps_everything(tmp_path):
    cams = {"south": level_camera("south", (1.5, -2.5, 1.2), (1.5, 2.0, 0.9))}
    masks = box_masks(cams, [(1.0, 1.0)])
    carver = Carver(cameras=cams, volume_min_m=VOLUME[0], volume_max_m=VOLUME[1], min_cameras=1, cache_dir=tmp_path)
    carve = carver.carve(masks, 0)
    blobs = detect_blobs(carve)
    verdict = explain_blobs(blobs, masks, cams, carve.grid)
    assert verdict.people == blobs and verdict.phantoms == []


def test_bad_share_is_refused():
    with pytest.raises(ValueError, match="min_new"):
        explain_blobs([], {}, {}, None, min_new=0.0)


def _exact_cover(splats, shapes, min_cameras, min_new):
    """The greedy cover counted plainly: every candidate counted anew at every step (the oracle of the
    order of choices; what one candidate covers anew is counted by the same ``new_cover``)."""
    from fusion_server.explain import new_cover

    covered = {c: np.zeros(shape, dtype=bool) for c, shape in shapes.items()}
    remaining, accepted = list(range(len(splats))), []
    while remaining:
        best, best_new, best_cams = None, -1, ()
        for k in remaining:
            new_total, cams_ok = new_cover(splats[k], covered, min_new)
            if len(cams_ok) >= min_cameras and new_total > best_new:
                best, best_new, best_cams = k, new_total, tuple(cams_ok)
        if best is None:
            break
        remaining.remove(best)
        accepted.append((best, best_cams))
        for c, s in splats[best].items():
            if s is not None:
                (y0, y1, x0, x1), hit, _ = s
                covered[c][y0:y1, x0:x1] |= hit
    return accepted


@pytest.mark.parametrize("seed", range(40))
def test_lazy_greedy_cover_takes_what_the_plain_greedy_takes(seed):
    from fusion_server.explain import greedy_cover

    rng = np.random.default_rng(seed)
    shapes = {f"c{i}": (60, 80) for i in range(int(rng.integers(2, 6)))}
    splats = []
    for _ in range(int(rng.integers(2, 25))):  # crowds of overlapping candidates, some seen by few cameras
        sp = {}
        for c, (h, w) in shapes.items():
            if rng.random() < 0.2:
                sp[c] = None
                continue
            y0, x0 = int(rng.integers(0, h - 10)), int(rng.integers(0, w - 10))
            y1, x1 = y0 + int(rng.integers(4, 20)), x0 + int(rng.integers(4, 20))
            y1, x1 = min(y1, h), min(x1, w)
            hit = rng.random((y1 - y0, x1 - x0)) < rng.uniform(0.3, 1.0)
            sp[c] = ((y0, y1, x0, x1), hit, int(hit.sum())) if hit.any() else None
        splats.append(sp)
    for min_new in (0.2, 0.3, 0.6):
        lazy = greedy_cover(splats, shapes, min_cameras=2, min_new=min_new)
        assert lazy == _exact_cover(splats, shapes, 2, min_new)



@pytest.mark.parametrize("offset_m, people", [pytest.param(0.35, 1, marks=pytest.mark.slow), (0.4, 1), (1.0, 2)])
def test_a_low_piece_beside_a_standing_person_is_part_of_them_not_a_person(lut_cache, offset_m, people):
    """A person whose legs are hidden (a body from 0.7 to 1.75 m) and a low piece (0.1 m radius,
    0.5 m tall, carved as 0.03-0.04 m^3 under 0.6 m) ``offset_m`` from their axis, five cameras:
    the piece is carved apart (a gap of 0.2 m in height) and covers foreground of its own in
    every camera. Within 0.45 m of the person's top it is a piece of them; 1 m away it is
    someone crouching."""
    from evaluation.carving_bench import Cylinder, MaskRenderer, room_rig

    rig = room_rig(n_cameras=5, width=320, height=240)
    carver = Carver(cameras=rig, volume_min_m=(0, 0, 0), volume_max_m=(8, 6, 2.5), cache_dir=lut_cache)
    masks = MaskRenderer(rig).render([Cylinder(3.0, 3.0, 0.2, 1.05, z0_m=0.7), Cylinder(3.0 + offset_m, 3.0, 0.1, 0.5)])
    carve = carver.carve(masks, 0)
    blobs = detect_blobs(carve)
    assert len(blobs) == 2 and near(blobs, (3.0 + offset_m, 3.0))
    found = explain_blobs(blobs, masks, rig, carve.grid).people
    assert len(found) == people
    assert near(found, (3.0, 3.0))


def _box_splat(y0, y1, x0, x1, depth):
    """A splat covering the whole box (y0, y1, x0, x1) of foreground, at ``depth`` metres."""
    hit = np.ones((y1 - y0, x1 - x0), dtype=bool)
    return (y0, y1, x0, x1), hit, int(hit.sum()), float(depth)


@pytest.mark.parametrize("behind_m, taken", [(3.0, [0, 1, 2]), (2.2, [0, 1]), (1.0, [0, 1])])
def test_a_person_hidden_behind_one_taken_is_judged_on_what_the_camera_shows_of_her(behind_m, taken):
    """Camera c1 sees candidate 2's 400 pixels as 240 over candidate 0's silhouette, 100 over candidate
    1's and 60 of its own (15 %, under ``min_new`` = 20 %); camera c2 sees it apart. 0 and 1 are taken
    first. When 2 lies 1 m behind 0 (farther than HIDDEN_MARGIN_M) and in front of 1, the 240 are
    hidden from c1, which sees 160 of it (40 %, over MIN_SEEN): 60 of those are its own (37.5 %), so
    c1 speaks for it too. Within the margin (0.2 m behind 0) or in front of 0, c1 speaks against it."""
    from fusion_server.explain import greedy_cover

    shapes = {"c1": (40, 40), "c2": (40, 40)}
    splats = [
        {"c1": _box_splat(0, 20, 0, 12, 2.0), "c2": _box_splat(0, 20, 0, 20, 2.0)},
        {"c1": _box_splat(0, 20, 12, 17, 6.0), "c2": _box_splat(20, 40, 0, 20, 6.0)},
        {"c1": _box_splat(0, 20, 0, 20, behind_m), "c2": _box_splat(0, 5, 20, 40, behind_m)},
    ]
    assert [k for k, _ in greedy_cover(splats, shapes, min_cameras=2, min_new=0.2, hideable=[True] * 3)] == taken
    # without the depth order (or for a candidate it does not speak for) the one behind is refused
    assert [k for k, _ in greedy_cover(splats, shapes, min_cameras=2, min_new=0.2)] == [0, 1]
    assert [k for k, _ in greedy_cover(splats, shapes, min_cameras=2, min_new=0.2, hideable=[True, True, False])] == [0, 1]


def test_a_candidate_hidden_but_for_a_rim_is_not_spoken_for_by_the_rim():
    """A phantom behind a person: in c1, 240 of its 280 pixels are the person's, who stands 1 m
    nearer; the 40 at the rim (what the person's splat leaves of their silhouette) are its own. The
    camera sees 14 % of it, under MIN_SEEN: c1 neither speaks for it nor against it, and with c2
    alone it is refused."""
    from fusion_server.explain import greedy_cover

    shapes = {"c1": (40, 40), "c2": (40, 40)}
    splats = [
        {"c1": _box_splat(0, 20, 0, 12, 2.0), "c2": _box_splat(0, 20, 0, 20, 2.0)},
        {"c1": _box_splat(0, 20, 0, 14, 3.0), "c2": _box_splat(20, 30, 20, 40, 3.0)},
    ]
    assert [k for k, _ in greedy_cover(splats, shapes, min_cameras=2, min_new=0.2, hideable=[True, True])] == [0]


def test_a_candidate_refused_is_offered_again_once_a_body_in_front_of_it_is_taken():
    """Three cameras. Candidate 0 (800 pixels, 5 m away) is taken first. Candidate 1 (800, 3 m) is
    then refused: in c1, 360 of its 400 pixels are 0's, which lies behind it, so nothing hides them.
    Candidate 2 (480, 1 m: nearest of all) is taken on c2 and c3. In c1 it covers 240 of 1's pixels
    from in front: offered again, 1 is taken (c1 sees 160 of its pixels, 40 of them its own)."""
    from fusion_server.explain import greedy_cover

    shapes = {c: (40, 40) for c in ("c1", "c2", "c3")}
    splats = [
        {"c1": _box_splat(0, 20, 0, 20, 5.0), "c2": _box_splat(20, 40, 0, 20, 5.0), "c3": None},
        {"c1": _box_splat(0, 20, 2, 22, 3.0), "c2": _box_splat(0, 20, 20, 40, 3.0), "c3": None},
        {"c1": _box_splat(0, 20, 0, 14, 1.0), "c2": _box_splat(0, 5, 0, 20, 1.0), "c3": _box_splat(0, 5, 0, 20, 1.0)},
    ]
    assert greedy_cover(splats, shapes, min_cameras=2, min_new=0.2, hideable=[True] * 3) == [
        (0, ("c1", "c2")), (2, ("c2", "c3")), (1, ("c1", "c2"))]
    assert greedy_cover(splats, shapes, min_cameras=2, min_new=0.2) == [(0, ("c1", "c2")), (2, ("c2", "c3"))]
