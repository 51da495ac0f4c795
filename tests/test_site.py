"""The site file: valid files load, bad ones stop with one clear message."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.site import EventSettings, SiteError, load_site, site_to_toml, write_site

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


def test_events_section_is_optional_and_sets_the_alarm_durations(tmp_path):
    site = load_site(_write(tmp_path, GOOD))
    assert site.events == EventSettings()
    assert (site.events.long_lie_s, site.events.inactivity_s) == (30.0, 1800.0)  # the reasoner's own defaults
    site = load_site(_write(tmp_path, GOOD + "\n[events]\nlong_lie_s = 60.0\ninactivity_s = 900\n"))
    assert (site.events.long_lie_s, site.events.inactivity_s) == (60.0, 900.0)
    assert "[events]" in site_to_toml(site)
    again = load_site(write_site(site, tmp_path / "copy" / "site.toml"))
    assert again.events == site.events


@pytest.mark.parametrize(
    ("line", "field", "problem"),
    [
        ("long_lie_s = 0", "events.long_lie_s", "greater than or equal to 5"),
        ("long_lie_s = 7200.0", "events.long_lie_s", "less than or equal to 3600"),
        ("long_lie_s = nan", "events.long_lie_s", "finite number"),
        ("inactivity_s = 10", "events.inactivity_s", "greater than or equal to 30"),
        ("inactivity_s = 100000", "events.inactivity_s", "less than or equal to 86400"),
        ("inactivity_s = inf", "events.inactivity_s", "finite number"),
        ('inactivity_s = "half an hour"', "events.inactivity_s", "valid number"),
        ("inactivity_min = 30", "events.inactivity_min", "unknown field"),
    ],
)
def test_bad_event_setting_names_the_field(tmp_path, line, field, problem):
    path = _write(tmp_path, GOOD + f"\n[events]\n{line}\n")
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


def test_lab_site_loads_every_calibration_into_the_world_frame(tmp_path, lab4cam):
    """The lab calibrations are in mm with -Z up; the site lands them in metres, Z up."""
    cams = "".join(
        f'\n[[cameras]]\nid = "cam{i}"\ncalibration = "{lab4cam / f"cam{i}" / "config.xml"}"\n'
        f'format = "opencv"\nunits = "mm"\nup = "-z"\nresolution = [644, 486]\n'
        for i in range(1, 5)
    )
    site = load_site(_write(tmp_path, 'name = "lab"\n[volume]\nmin_m = [-1.0, -1.5, 0.0]\nmax_m = [2.0, 1.5, 2.2]\n' + cams))
    cameras = site.load_cameras()
    assert sorted(cameras) == ["cam1", "cam2", "cam3", "cam4"]
    for cam in cameras.values():
        assert (cam.width, cam.height) == (644, 486)
        assert 1.0 < cam.center[2] < 3.0  # mounted above a person's head, below a lab ceiling
        # the chair near the world origin is in front of every camera and in its image
        _, valid = cam.project([[0.35, 0.0, 0.8]])
        assert valid[0]


def test_pets_camera_takes_its_size_from_the_calibration(tmp_path, pets_calibration):
    text = f'name = "pets"\n[[cameras]]\nid = "v1"\ncalibration = "{pets_calibration / "View_001.xml"}"\nformat = "pets-tsai"\nunits = "mm"\n'
    cam = load_site(_write(tmp_path, text)).load_camera("v1")
    assert (cam.width, cam.height) == (768, 576)
    assert cam.center[2] > 1.0
