"""Evaluation pictures: files exist, have the asked size, are not blank, and show what they claim."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from evaluation import io
from evaluation.io import Event
from evaluation.plots import plan_view, site_geometry, timeline
from fusion_server.outputs import mask_overlay
from common.site import site_from_dict

NS = 66_666_667

needs_matplotlib = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None,
    reason="matplotlib is not installed (the plots extra: pip install 'voxelwatch[plots]')",
)

SITE = {
    "name": "test-flat",
    "volume": {"min_m": [0.0, 0.0, 0.0], "max_m": [8.0, 6.0, 2.5]},
    "cameras": [{"id": "cam1", "calibration": "calib/cam1.toml"}],
    "hotspots": [{"name": "sofa", "kind": "sofa", "polygon_m": [[1.0, 1.0], [3.0, 1.0], [3.0, 2.0], [1.0, 2.0]]}],
    "doors": [{"name": "front door", "polygon_m": [[0.0, 4.6], [0.5, 4.6], [0.5, 5.6], [0.0, 5.6]]}],
}
FALL_RGB = (0xD6, 0x27, 0x28)  # the fall marker's colour


@pytest.fixture()
def scenario(tmp_path) -> tuple[Path, Path]:
    """Two people for 150 frames; the run follows them, says lying after A falls, and reports the fall."""
    truth_rows, run_rows = [], []
    for f in range(150):
        ax, ay = 1.0 + 0.03 * f, 3.0
        bx, by = 6.0, 1.0 + 0.02 * f
        a_post = "lying" if f >= 100 else "standing"
        truth_rows += [(f, f * NS, "21", ax, ay, 1.7, a_post), (f, f * NS, "22", bx, by, 1.6, "sitting" if f > 60 else "standing")]
        run_rows += [(f, f * NS, "1", ax + 0.05, ay, 1.7, a_post), (f, f * NS, "2", bx, by - 0.05, 1.6, "standing")]
    truth_dir, run_dir = tmp_path / "truth", tmp_path / "run"
    io.write_tracks(truth_dir / "truth" / "tracks.csv", truth_rows)
    io.write_tracks(run_dir / "tracks.csv", run_rows)
    def ev(kind: str, frame: int, track: int, x: float, y: float) -> Event:
        return Event.from_dict(dict(kind=kind, frame=frame, stamp_ns=frame * NS, track=track, x=x, y=y))

    io.write_events(truth_dir / "truth" / "events.jsonl", [ev("fall", 100, 21, 4.0, 3.0), ev("sit_down", 61, 22, 6.0, 2.2)])
    io.write_events(run_dir / "events.jsonl", [ev("fall", 105, 1, 4.15, 3.0), ev("enter", 0, 2, 6.0, 1.0)])
    return truth_dir, run_dir


def load(path: Path) -> np.ndarray:
    assert path.is_file(), path
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None, f"{path} is not a readable PNG"
    return image


def count_colour(image_bgr: np.ndarray, rgb: tuple[int, int, int], tol: int = 30) -> int:
    target = np.array(rgb[::-1], dtype=np.int32)
    return int((np.abs(image_bgr.astype(np.int32) - target).max(axis=2) <= tol).sum())


@needs_matplotlib
@pytest.mark.parametrize("site_kind", ["pydantic", "dict", "none"])
def test_plan_view(scenario, tmp_path, site_kind: str) -> None:
    truth_dir, run_dir = scenario
    site = {"pydantic": site_from_dict(SITE, base_dir=tmp_path), "dict": SITE, "none": None}[site_kind]
    out = plan_view(run_dir, site, tmp_path / "pics" / f"plan_{site_kind}.png", truth_dir=truth_dir, size_px=(900, 700))
    image = load(out)
    assert image.shape == (700, 900, 3)
    assert image.std() > 10.0  # not blank
    assert count_colour(image, FALL_RGB) > 20  # the fall marker is drawn


@needs_matplotlib
def test_plan_view_shows_the_site(scenario, tmp_path) -> None:
    _, run_dir = scenario
    with_site = load(plan_view(run_dir, SITE, tmp_path / "a.png"))
    without = load(plan_view(run_dir, None, tmp_path / "b.png"))
    assert with_site.shape == without.shape == (800, 1000, 3)  # the default size
    assert np.abs(with_site.astype(int) - without.astype(int)).mean() > 1.0


@needs_matplotlib
def test_plan_view_of_an_empty_run(tmp_path) -> None:
    io.write_tracks(tmp_path / "run" / "tracks.csv", [])
    image = load(plan_view(tmp_path / "run", SITE, tmp_path / "empty.png", size_px=(400, 300)))
    assert image.shape == (300, 400, 3) and image.std() > 5.0  # room outline, hot spot and door still drawn


@needs_matplotlib
def test_timeline(scenario, tmp_path) -> None:
    truth_dir, run_dir = scenario
    image = load(timeline(run_dir, truth_dir, tmp_path / "timeline.png"))
    assert image.shape == (120 + 180 * 2, 1200, 3)  # the default: one row per truth person
    assert image.std() > 10.0
    assert count_colour(image, FALL_RGB) > 20  # the fall line and marker
    image = load(timeline(run_dir, truth_dir, tmp_path / "t2.png", size_px=(800, 500)))
    assert image.shape == (500, 800, 3)


def test_mask_overlay(tmp_path) -> None:
    frame = np.full((480, 640, 3), 90, dtype=np.uint8)
    frame[:, :320] = 40
    mask = np.zeros((240, 320), dtype=np.uint8)  # half-resolution mask
    mask[50:150, 100:160] = 255
    mask[150:170, 100:200] = 127  # shadow
    image = load(mask_overlay(frame, mask, tmp_path / "cam1" / "overlay.png"))
    assert image.shape == frame.shape
    assert image.std() > 5.0
    # the foreground (rows 100..300, cols 200..320 at full size) is tinted red, the background untouched
    inside = image[150:250, 220:300].astype(int)
    assert (inside[..., 2] - inside[..., 0]).mean() > 50
    assert np.array_equal(image[400:, 500:], frame[400:, 500:])
    # shadows are grey, not red
    shadow = image[305:335, 220:380].astype(int)
    assert np.abs(shadow[..., 2] - shadow[..., 0]).mean() < 5 and shadow.mean() > 40


def test_mask_overlay_grey_frame_and_bool_mask(tmp_path) -> None:
    frame = np.full((120, 160), 128, dtype=np.uint8)
    mask = np.zeros((120, 160), dtype=bool)
    mask[20:60, 30:90] = True
    image = load(mask_overlay(frame, mask, tmp_path / "o.png"))
    assert image.shape == (120, 160, 3) and image.std() > 5.0
    with pytest.raises(ValueError, match="frame_bgr must be"):
        mask_overlay(np.zeros((10, 10, 4), dtype=np.uint8), mask, tmp_path / "x.png")
    with pytest.raises(ValueError, match="mask must be"):
        mask_overlay(frame, np.zeros((2, 2, 2), dtype=np.uint8), tmp_path / "x.png")


def test_site_geometry_from_each_form(tmp_path) -> None:
    a = site_geometry(site_from_dict(SITE, base_dir=tmp_path))
    b = site_geometry(SITE)
    assert a.min_xy_m == b.min_xy_m == (0.0, 0.0) and a.max_xy_m == (8.0, 6.0)
    assert [h[0] for h in a.hotspots] == ["sofa"] and [d[0] for d in b.doors] == ["front door"]
    assert site_geometry(None).hotspots == []
    with pytest.raises(ValueError, match=r"doors\[0\].polygon_m"):
        site_geometry({"doors": [{"name": "d", "polygon_m": [[0, 0], [1, 1]]}]})


def test_missing_matplotlib_says_which_extra(scenario, tmp_path, monkeypatch) -> None:
    _, run_dir = scenario
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` fail
    with pytest.raises(ImportError, match=r"plan_view draws with matplotlib.*voxelwatch\[plots\]"):
        plan_view(run_dir, None, tmp_path / "p.png")
