"""Hot spots: point-in-polygon against OpenCV, variance of position, dwelling."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fusion_server.hotspots import (
    DwellDetector,
    Hotspot,
    PositionWindow,
    hotspot_at,
    hotspot_index,
    points_in_polygon,
    polygon_area,
    position_variance,
)

FPS = 15
NS = 1_000_000_000


def _star(rng: np.random.Generator, n: int = 9) -> np.ndarray:
    """A concave star-shaped polygon around (2, 1)."""
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    r = rng.uniform(0.3, 1.5, n)
    return np.column_stack([2 + r * np.cos(ang), 1 + r * np.sin(ang)])


@pytest.mark.parametrize("seed", range(5))
def test_points_in_polygon_matches_opencv(seed):
    rng = np.random.default_rng(seed)
    poly = _star(rng)
    if seed % 2:
        poly = poly[::-1]  # orientation must not matter
    pts = rng.uniform([0.0, -1.0], [4.0, 3.0], size=(2000, 2))
    contour = poly.astype(np.float32).reshape(-1, 1, 2)
    dist = np.array([cv2.pointPolygonTest(contour, (float(x), float(y)), True) for x, y in pts.astype(np.float32)])
    clear = np.abs(dist) > 1e-4  # points on an edge may fall either side
    ours = points_in_polygon(pts, poly)
    np.testing.assert_array_equal(ours[clear], dist[clear] > 0)
    assert ours[clear].any() and (~ours[clear]).any()


def test_single_point_and_square():
    sq = np.array([[0, 0], [2, 0], [2, 1], [0, 1]], float)
    assert points_in_polygon(np.array([1.0, 0.5]), sq).tolist() == [True]
    assert points_in_polygon(np.array([[2.5, 0.5], [1.0, -0.1], [0.1, 0.9]]), sq).tolist() == [False, False, True]
    assert polygon_area(sq) == pytest.approx(2.0)
    assert polygon_area(sq[::-1]) == pytest.approx(-2.0)


def test_distance_to_a_hotspot_hand_worked():
    # an L: the square (0..2, 0..1) with (1..2, 1..2) on top; concave corner at (1, 1)
    ell = Hotspot("L", np.array([[0, 0], [2, 0], [2, 2], [1, 2], [1, 1], [0, 1]], float))
    assert ell.distance_m(1.5, 1.5) == 0.0 and ell.distance_m(0.5, 0.5) == 0.0  # inside
    assert ell.distance_m(3.0, 0.5) == pytest.approx(1.0)      # beside the right side
    assert ell.distance_m(0.5, 1.4) == pytest.approx(0.4)      # above the low arm, in the notch
    assert ell.distance_m(0.7, 1.4) == pytest.approx(0.3)      # nearer the notch's wall than its floor
    assert ell.distance_m(-0.3, -0.4) == pytest.approx(0.5)    # off a corner: 0.3, 0.4, 0.5


def test_hotspot_validation_and_label_default():
    h = Hotspot("sofa", [[0, 0], [2, 0], [2, 1], [0, 1]], kind="sofa")
    assert h.label == "sofa"
    np.testing.assert_allclose(h.centroid_m, [1.0, 0.5])
    with pytest.raises(ValueError, match="name"):
        Hotspot("", [[0, 0], [1, 0], [0, 1]])
    with pytest.raises(ValueError, match="K >= 3"):
        Hotspot("a", [[0, 0], [1, 0]])
    with pytest.raises(ValueError, match="non-finite"):
        Hotspot("a", [[0, 0], [1, np.nan], [0, 1]])
    with pytest.raises(ValueError, match="no area"):
        Hotspot("a", [[0, 0], [1, 1], [2, 2]])


def test_first_hotspot_wins_where_they_overlap():
    a = Hotspot("table", [[0, 0], [2, 0], [2, 2], [0, 2]])
    b = Hotspot("chair", [[1, 1], [3, 1], [3, 3], [1, 3]])
    idx = hotspot_index([a, b], np.array([[0.5, 0.5], [1.5, 1.5], [2.5, 2.5], [5, 5]]))
    assert idx.tolist() == [0, 0, 1, -1]
    assert hotspot_at([b, a], 1.5, 1.5) is b
    assert hotspot_at([a, b], 9, 9) is None


def test_position_variance_hand_worked():
    # mean (1, 0); squared distances 1 and 1 -> 1
    assert position_variance(np.array([[0, 0], [2, 0]], float)) == pytest.approx(1.0)
    # square corners around (0.5, 0.5): each at distance^2 0.5
    assert position_variance(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        position_variance(np.zeros((0, 2)))


def test_position_window_span():
    w = PositionWindow(window_s=1.0)
    for i in range(10):
        w.add(i * NS // 10, 0.0, 0.0)
    assert not w.full and w.span_s == pytest.approx(0.9)
    w.add(NS, 0.0, 0.0)
    assert w.full and w.span_s == pytest.approx(1.0)
    for i in range(11, 40):
        w.add(i * NS // 10, float(i), 0.0)
    assert w.span_s == pytest.approx(1.0) and len(w) == 11
    with pytest.raises(ValueError, match="older"):
        w.add(0, 0.0, 0.0)


SOFA = Hotspot("sofa", [[4.0, 1.0], [6.0, 1.0], [6.0, 2.0], [4.0, 2.0]], label="the sofa", kind="sofa")
TABLE = Hotspot("dinner table", [[1.0, 3.0], [2.5, 3.0], [2.5, 4.5], [1.0, 4.5]], kind="table")


def _run(det: DwellDetector, path_xy: np.ndarray, rng: np.random.Generator, jitter_m: float = 0.03):
    changes = []
    for i, (x, y) in enumerate(path_xy):
        jx, jy = rng.normal(0, jitter_m, 2)
        changes += det.update(i * NS // FPS, x + jx, y + jy)
    return changes


def _walk(a, b, speed_mps: float = 1.0) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(int(np.linalg.norm(b - a) / speed_mps * FPS), 1)
    return a + (b - a) * (np.arange(1, n + 1) / n)[:, None]


def _stay(p, seconds: float) -> np.ndarray:
    return np.repeat(np.asarray(p, float)[None], int(seconds * FPS), axis=0)


def test_dwell_start_and_end_at_named_hotspot():
    rng = np.random.default_rng(1)
    walk_in = _walk([0.5, 0.5], [5.0, 1.5])
    path = np.concatenate([walk_in, _stay([5.0, 1.5], 30.0), _walk([5.0, 1.5], [5.0, 5.0])])
    det = DwellDetector(hotspots=[TABLE, SOFA], window_s=10.0)
    changes = _run(det, path, rng)
    assert [c.kind for c in changes] == ["dwell_start", "dwell_end"]
    start, end = changes
    arrive_s = len(walk_in) / FPS
    leave_s = arrive_s + 30.0
    assert start.hotspot is SOFA and end.hotspot is SOFA
    # the still window must first cover window_s; the window starts at about the arrival
    assert start.stamp_ns * 1e-9 == pytest.approx(arrive_s + 10.0, abs=1.0)
    assert start.start_ns * 1e-9 == pytest.approx(arrive_s, abs=1.0)
    assert 0 < end.stamp_ns * 1e-9 - leave_s < 1.2  # 0.5 m from where they settled, at 1 m/s
    assert end.reason in ("moved", "left")
    assert end.duration_s == pytest.approx(30.0, abs=3.0)


def test_no_dwell_when_still_outside_or_moving_inside():
    rng = np.random.default_rng(2)
    det = DwellDetector(hotspots=[SOFA], window_s=10.0)
    assert _run(det, _stay([2.0, 1.5], 40.0), rng) == []
    det = DwellDetector(hotspots=[SOFA], window_s=10.0)
    pacing = np.concatenate([_walk([4.1, 1.5], [5.9, 1.5], 0.5), _walk([5.9, 1.5], [4.1, 1.5], 0.5)] * 5)
    assert _run(det, pacing, rng) == []


def test_dwell_survives_jitter_and_ends_when_track_lost():
    rng = np.random.default_rng(3)
    det = DwellDetector(hotspots=[SOFA], window_s=5.0)
    changes = _run(det, _stay([5.0, 1.5], 60.0), rng, jitter_m=0.08)
    assert [c.kind for c in changes] == ["dwell_start"]
    lost = det.lost(61 * NS)
    assert len(lost) == 1 and lost[0].reason == "lost" and lost[0].kind == "dwell_end"
    assert det.current is None and det.lost(62 * NS) == []


def test_slow_drift_out_does_not_flicker():
    rng = np.random.default_rng(4)
    det = DwellDetector(hotspots=[SOFA], window_s=10.0)
    path = np.concatenate([_stay([5.5, 1.5], 20.0), _walk([5.5, 1.5], [7.0, 1.5], 0.02)])
    changes = _run(det, path, rng, jitter_m=0.01)
    assert [c.kind for c in changes] == ["dwell_start", "dwell_end"]


def test_dwell_detector_validation():
    with pytest.raises(ValueError, match="move_std_m"):
        DwellDetector(hotspots=[SOFA], still_std_m=0.3, move_std_m=0.1)
    with pytest.raises(ValueError, match="window_s"):
        DwellDetector(hotspots=[SOFA], window_s=0)
    with pytest.raises(ValueError, match="Hotspot"):
        DwellDetector(hotspots=[{"name": "sofa"}])
