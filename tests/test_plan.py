"""The floor plan (:mod:`view.plan`): fields of view against hand-worked cases, and the SVG."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import synth
from common.camera import Camera, look_at
from common.messages import Event
from view.plan import floor_fov, image_outlines, plan_of, plan_svg

SVG = "{http://www.w3.org/2000/svg}"


def _area(poly):
    n = len(poly)
    return 0.5 * sum(poly[i][0] * poly[(i + 1) % n][1] - poly[(i + 1) % n][0] * poly[i][1] for i in range(n))


def _bbox(poly):
    xs, ys = zip(*poly)
    return min(xs), min(ys), max(xs), max(ys)


CELL_M = 0.04
"""The tolerance of a field of view: a little more than one grid cell of floor_fov."""


def test_a_camera_looking_straight_down_sees_a_rectangle_of_height_times_half_width_over_fx():
    # 2.5 m above (4, 3), fx = fy = 200 px, 641 x 481 px: pixel centres 0..640 span x_n = +-320/200 = +-1.6,
    # 0..480 span y_n = +-1.2; on the floor 2.5 m below: x 4 +- 4.0, y 3 +- 3.0
    R, t = look_at((4.0, 3.0, 2.5), (4.0, 3.0, 0.0), up=(0.0, 1.0, 0.0))
    cam = Camera.pinhole("down", 641, 481, fx=200.0, R=R, t=t)
    fov = floor_fov(cam, (-1.0, -1.0), (9.0, 7.0))
    assert _bbox(fov) == pytest.approx((0.0, 0.0, 8.0, 6.0), abs=CELL_M)
    assert len(fov) == 4 and _area(fov) == pytest.approx(48.0, rel=0.02)  # counter-clockwise
    # a 5 x 4 m room inside the footprint is seen whole
    room = floor_fov(cam, (2.0, 1.0), (7.0, 5.0))
    assert _bbox(room) == pytest.approx((2.0, 1.0, 7.0, 5.0), abs=CELL_M)


def test_a_tilted_camera_sees_a_trapezium_from_the_depression_angles_of_its_top_and_bottom_rows():
    # at (0, 0, 2) looking along +y, 45 degrees down; fy = 400 px and 401 rows: top and bottom rows are
    # atan(200 / 400) = 26.57 degrees off the axis, so they meet the floor at 2 / tan(45 -+ 26.57 degrees)
    pitch, half = math.radians(45.0), math.atan(200 / 400)
    R, t = look_at((0.0, 0.0, 2.0), (0.0, 2.0, 0.0))
    cam = Camera.pinhole("tilt", 601, 401, fx=400.0, R=R, t=t)
    fov = floor_fov(cam, (-6.0, -1.0), (6.0, 8.0))
    near, far = 2 / math.tan(pitch + half), 2 / math.tan(pitch - half)
    # the corners are 300 px / 400 px sideways of the axis at their depth along the axis
    x_near = math.hypot(near, 2.0) * math.cos(half) * 300 / 400
    x_far = math.hypot(far, 2.0) * math.cos(half) * 300 / 400
    assert _bbox(fov) == pytest.approx((-x_far, near, x_far, far), abs=CELL_M)
    assert _area(fov) == pytest.approx((x_near + x_far) * (far - near), rel=0.02)
    assert len(fov) == 4


def test_a_level_camera_sees_from_where_its_bottom_row_meets_the_floor_to_the_far_wall_and_one_looking_up_nothing():
    R, t = look_at((0.0, 3.0, 1.0), (5.0, 3.0, 1.0))
    level = Camera.pinhole("level", 640, 480, hfov_deg=60.0, R=R, t=t)
    fov = floor_fov(level, (0.0, 0.0), (8.0, 6.0))
    near = 1.0 / (level.K[1, 2] / level.K[1, 1])  # the bottom row's depression: tan = cy / fy
    x0, _, x1, _ = _bbox(fov)
    assert x0 == pytest.approx(near, abs=CELL_M) and x1 == pytest.approx(8.0, abs=CELL_M)
    R, t = look_at((4.0, 3.0, 1.0), (4.0, 3.0, 5.0), up=(0.0, 1.0, 0.0))
    assert floor_fov(Camera.pinhole("up", 640, 480, hfov_deg=60.0, R=R, t=t), (0.0, 0.0), (8.0, 6.0)) == []


@pytest.fixture(scope="module")
def house(tmp_path_factory):
    return synth.default_site(tmp_path_factory.mktemp("plan") / "site")


def test_the_house_plan_has_every_camera_in_a_corner_or_the_ceiling_seeing_the_middle_of_the_room(house):
    plan = plan_of(house)
    assert [c.id for c in plan.cameras] == house.camera_ids
    assert [h.name for h in plan.hotspots] == ["sofa", "dinner table", "kitchen", "TV"]
    assert plan.doors[0].name == "front door" and len(plan.occluders) == len(house.occluders)
    for cam in plan.cameras:
        assert len(cam.fov) >= 3
        x0, y0, x1, y1 = _bbox(cam.fov)
        assert 0.0 <= x0 and x1 <= 8.0 and 0.0 <= y0 and y1 <= 6.0
        # the room's middle is seen by every camera: inside its floor polygon
        assert _inside((4.0, 3.0), cam.fov), cam.id
    ceiling = next(c for c in plan.cameras if c.id == "cam5")
    assert ceiling.heading_deg is None and _area(ceiling.fov) > 0.8 * 48.0  # the fisheye sees nearly all
    corner = next(c for c in plan.cameras if c.id == "cam1")
    assert corner.heading_deg == pytest.approx(math.degrees(math.atan2(0.564, 0.762)), abs=0.5)
    data = plan.to_dict()
    assert data["outline"] == [[0.0, 0.0], [8.0, 0.0], [8.0, 6.0], [0.0, 6.0]]
    assert data["cameras"][0]["position_m"] == [0.15, 0.15, 2.4]


def test_image_outlines_put_the_room_corner_below_a_corner_camera_out_of_view_and_the_sofa_in_it(house):
    cam = house.load_camera("cam1")
    out = image_outlines(house, cam)
    assert out["width"] == 640 and out["height"] == 480
    points = [p for line in out["floor"] for p in line]
    assert points and all(0 <= u <= 639 and 0 <= v <= 479 for u, v in points)
    sofa = next(h for h in out["hotspots"] if h["name"] == "sofa")
    # the sofa's centre projects inside the image; its outline surrounds that point
    ((u, v),), ok = cam.project(np.array([[5.7, 1.85, 0.0]]))
    assert ok[0]
    sofa_pts = np.array([p for line in sofa["lines"] for p in line])
    assert sofa_pts[:, 0].min() < u < sofa_pts[:, 0].max() and sofa_pts[:, 1].min() < v < sofa_pts[:, 1].max()


def test_plan_svg_draws_paths_by_posture_event_marks_and_the_truth(house):
    rows = [(f, 1_000 + f, "1", 1.0 + 0.1 * f, 2.0, 1.7 if f < 5 else 0.3, "standing" if f < 5 else "lying", "Ada")
            for f in range(10)]
    fall = Event(id="1-fall-1", kind="fall", track=1, stamp_ns=1005, frame=5, x=1.5, y=2.0)
    lost = Event(id="2-camera_lost-1", kind="camera_lost", track=-1, stamp_ns=1006, frame=6, x=0.0, y=0.0,
                 details={"camera": "cam1"})
    truth = [{"frame": f, "id": "p1", "x": 1.0 + 0.1 * f, "y": 2.05, "posture": "standing"} for f in range(10)]
    svg = plan_svg(house, rows, [fall, lost], truth=truth)
    root = ET.fromstring(svg)
    paths = root.findall(f".//{SVG}g[@class='path']")
    assert len(paths) == 1 and paths[0].get("data-track") == "1"
    lines = paths[0].findall(f"{SVG}polyline")
    assert [p.get("data-posture") for p in lines] == ["standing", "lying"]
    # the two runs meet: standing ends on frame 5's point, where lying begins
    assert lines[0].get("points").split()[-1] == lines[1].get("points").split()[0]
    assert len(lines[0].get("points").split()) == 6 and len(lines[1].get("points").split()) == 5
    marks = root.findall(f".//{SVG}g[@class='event']")
    assert [m.get("data-kind") for m in marks] == ["fall"]  # the camera event has no place
    # plan coordinates: x right from the volume's x0 less a 0.4 m margin, y flipped, 90 px per metre
    circle = marks[0].find(f"{SVG}circle")
    assert float(circle.get("cx")) == pytest.approx((1.5 + 0.4) * 90, abs=0.1)
    assert float(circle.get("cy")) == pytest.approx((6.0 - 2.0 + 0.4) * 90, abs=0.1)
    assert len(root.findall(f".//{SVG}polyline[@class='truth']")) == 1
    assert len(root.findall(f".//{SVG}circle[@class='camera']")) == 5
    assert "Ada" in svg and "sofa" in svg


def _inside(p, poly) -> bool:
    x, y = p
    inside = False
    for i in range(len(poly)):
        (ax, ay), (bx, by) = poly[i], poly[i - 1]
        if (ay > y) != (by > y) and x < ax + (y - ay) * (bx - ax) / (by - ay):
            inside = not inside
    return inside
