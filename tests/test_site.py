"""The site file: valid files load, bad ones stop with one clear message."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.site import SiteError, load_site, site_to_toml, write_site

GOOD = """\
name = "flat-3"
residents = 2
utc_offset_hours = 1.0

[volume]
min_m = [0.0, 0.0, 0.0]
max_m = [6.0, 4.0, 2.5]

[carving]
voxel_sizes_m = [0.4, 0.2, 0.1, 0.05]
min_cameras = 3

[zenoh]
listen = ["tcp/127.0.0.1:7447"]

[[cameras]]
id = "hall"
calibration = "calib/hall.xml"
format = "opencv"
units = "mm"
up = "-z"
resolution = [644, 486]

[[cameras]]
id = "ceiling"
calibration = "/abs/ceiling.toml"
resolution = [640, 480]

[[hotspots]]
name = "sofa"
kind = "sofa"
polygon_m = [[0.5, 0.5], [2.5, 0.5], [2.5, 1.4], [0.5, 1.4]]

[[doors]]
name = "front door"
polygon_m = [[0.0, 3.0], [0.5, 3.0], [0.5, 4.0]]
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "site.toml"
    path.write_text(text)
    return path


def test_good_file_loads_with_defaults_and_resolved_paths(tmp_path):
    site = load_site(_write(tmp_path, GOOD))
    assert site.name == "flat-3"
    assert site.prefix == "voxelwatch/flat-3"
    assert site.camera_ids == ["hall", "ceiling"]
    assert site.camera("hall").units == "mm" and site.camera("hall").up == "-z"
    assert site.camera("ceiling").format == "voxelwatch"  # the default format
    assert site.carving.min_cameras == 3 and site.carving.min_ratio == 0.75
    assert site.calibration_path("hall") == (tmp_path / "calib" / "hall.xml").resolve()
    assert site.calibration_path("ceiling") == Path("/abs/ceiling.toml")
    assert site.volume.size_m == (6.0, 4.0, 2.5)


def test_written_site_reads_back_equal(tmp_path):
    site = load_site(_write(tmp_path, GOOD))
    again = load_site(write_site(site, tmp_path / "copy" / "site.toml"))
    assert again.model_dump(exclude={"base_dir"}) == site.model_dump(exclude={"base_dir"})
    assert "[[cameras]]" in site_to_toml(site)


@pytest.mark.parametrize(
    ("old", "new", "field", "problem"),
    [
        ('resolution = [644, 486]', 'resolution = [644]', "cameras[0].resolution", ""),
        ('units = "mm"', 'units = "inch"', "cameras[0].units", "'m', 'cm' or 'mm'"),
        ("min_cameras = 3", "min_cameras = 0", "carving.min_cameras", "greater than or equal to 1"),
        ("voxel_sizes_m = [0.4, 0.2, 0.1, 0.05]", "voxel_sizes_m = [0.4, 0.1]", "carving.voxel_sizes_m", "halve"),
        ("max_m = [6.0, 4.0, 2.5]", "max_m = [6.0, -4.0, 2.5]", "volume", "must exceed"),
        ('id = "hall"', 'id = "ceiling"', "cameras", "unique"),
        ('id = "hall"', 'id = "hall/1"', "cameras[0].id", "pattern"),
        ("residents = 2", "residents = 2\ncolour = 1", "colour", "unknown field"),
        ('name = "sofa"', "", "hotspots[0].name", "missing"),
        ("polygon_m = [[0.0, 3.0], [0.5, 3.0], [0.5, 4.0]]", "polygon_m = [[0.0, 3.0], [0.5, 3.0]]", "doors[0].polygon_m", "at least 3"),
    ],
)
def test_bad_field_names_file_field_and_problem(tmp_path, old, new, field, problem):
    assert old in GOOD
    path = _write(tmp_path, GOOD.replace(old, new, 1))
    with pytest.raises(SiteError) as err:
        load_site(path)
    message = str(err.value)
    assert str(path) in message
    assert f"field {field}" in message
    assert problem in message


def test_missing_and_unparsable_files(tmp_path):
    with pytest.raises(SiteError, match="not found"):
        load_site(tmp_path / "nope.toml")
    with pytest.raises(SiteError, match="not valid TOML"):
        load_site(_write(tmp_path, "name = \n"))


def test_unknown_camera_lists_the_known_ones(tmp_path):
    site = load_site(_write(tmp_path, GOOD))
    with pytest.raises(SiteError, match=r"no camera 'door'.*\['hall', 'ceiling'\]"):
        site.camera("door")
