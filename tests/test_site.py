"""The site file: valid files load, bad ones stop with one clear message."""

from __future__ import annotations

import json
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
        ("min_cameras = 3", 'min_cameras = 3\nfusion = "cut"', "carving.fusion", "'vote' or 'graphcut'"),
        ("min_cameras = 3", "min_cameras = 3\nsmoothing = -0.1", "carving.smoothing", "greater than or equal to 0"),
        ("min_cameras = 3", "min_cameras = 3\nsmoothing = 2.0", "carving.smoothing", "less than or equal to 1"),
        ("min_cameras = 3", 'min_cameras = 3\nfree_space = "yes"', "carving.free_space", "boolean"),
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


def test_a_finest_voxel_too_small_for_the_volume_is_refused_with_the_tables_size(tmp_path):
    """6 x 4 x 2.5 m at 5 mm: 480 million finest voxels (548 million on all four levels), 6 bytes each
    for each of 2 cameras: 6.1 GiB of carving tables, over the 2 GiB the fusion server may build;
    at 1 cm (68.6 million voxels, 0.77 GiB) the file loads."""
    path = _write(tmp_path, GOOD.replace("voxel_sizes_m = [0.4, 0.2, 0.1, 0.05]",
                                         "voxel_sizes_m = [0.04, 0.02, 0.01, 0.005]", 1))
    with pytest.raises(SiteError) as err:
        load_site(path)
    message = str(err.value)
    assert str(path) in message and "carving.voxel_sizes_m: a finest voxel of 0.005 m" in message
    assert "548,445,000 voxels" in message and "6.1 GiB for 2 cameras" in message
    site = load_site(_write(tmp_path, GOOD.replace("voxel_sizes_m = [0.4, 0.2, 0.1, 0.05]",
                                                   "voxel_sizes_m = [0.08, 0.04, 0.02, 0.01]", 1)))
    assert site.carving.voxel_sizes_m[-1] == 0.01


def test_carving_fusion_options_default_to_the_vote_and_read_back(tmp_path):
    site = load_site(_write(tmp_path, GOOD))
    assert (site.carving.fusion, site.carving.smoothing, site.carving.free_space) == ("vote", 0.1, True)
    text = GOOD.replace("min_cameras = 3", 'min_cameras = 3\nfusion = "graphcut"\nsmoothing = 0.05\nfree_space = false')
    site = load_site(_write(tmp_path, text))
    assert (site.carving.fusion, site.carving.smoothing, site.carving.free_space) == ("graphcut", 0.05, False)
    again = load_site(write_site(site, tmp_path / "copy" / "site.toml"))
    assert again.carving == site.carving


def test_events_section_is_optional_and_sets_the_alarm_durations(tmp_path):
    site = load_site(_write(tmp_path, GOOD))
    assert site.events == EventSettings()
    assert (site.events.long_lie_s, site.events.inactivity_s) == (30.0, 1800.0)  # the reasoner's own defaults
    site = load_site(_write(tmp_path, GOOD + "\n[events]\nlong_lie_s = 60.0\ninactivity_s = 900\n"))
    assert (site.events.long_lie_s, site.events.inactivity_s) == (60.0, 900.0)
    assert "[events]" in site_to_toml(site)
    again = load_site(write_site(site, tmp_path / "copy" / "site.toml"))
    assert again.events == site.events
    assert (site.events.decisions, site.events.viterbi_lag_s) == ("frame", 0.6)
    site = load_site(_write(tmp_path, GOOD + '\n[events]\ndecisions = "viterbi"\nviterbi_lag_s = 0.8\n'))
    assert (site.events.decisions, site.events.viterbi_lag_s) == ("viterbi", 0.8)


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
        ('decisions = "hmm"', "events.decisions", "'frame' or 'viterbi'"),
        ("viterbi_lag_s = 1.5", "events.viterbi_lag_s", "less than or equal to 1"),
        ("viterbi_lag_s = -0.1", "events.viterbi_lag_s", "greater than or equal to 0"),
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
    text = (f'name = "pets"\n[[cameras]]\nid = "v1"\ncalibration = "{pets_calibration / "View_001.xml"}"\n'
            'format = "pets-tsai"\nunits = "mm"\n')
    cam = load_site(_write(tmp_path, text)).load_camera("v1")
    assert (cam.width, cam.height) == (768, 576)
    assert cam.center[2] > 1.0


# ---------------------------------------------------------------- identity and enrolled residents


def _model_file(path: Path, *, torso_frames: int = 40, height_m: float | None = 1.7, **changes) -> Path:
    """An appearance model as ``voxelwatch enrol`` writes it."""
    from common.appearance import AppearanceModel

    model = AppearanceModel()
    model.hist[1, 2] = 1.0
    model.frames[1] = torso_frames
    model.height_m = float("nan") if height_m is None else height_m
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"name": "whoever", **model.to_dict(), **changes}))
    return path


ENROLLED = '\n[[enrolled]]\nname = "Ada"\nmodel = "residents/ada.json"\n'


def test_identity_section_and_enrolled_residents_load(tmp_path):
    site = load_site(_write(tmp_path, GOOD))
    assert (site.identity.reid_window_s, site.identity.rate_hz) == (600.0, 3.0)  # the identity keeper's defaults
    assert site.enrolled == [] and site.load_residents() == []
    _model_file(tmp_path / "residents" / "ada.json", torso_frames=40)
    _model_file(tmp_path / "bob.json", torso_frames=55, height_m=None)
    text = GOOD + "\n[identity]\nreid_window_s = 120\nrate_hz = 5\n" + ENROLLED + \
        '\n[[enrolled]]\nname = "Bob the Builder"\nmodel = "bob.json"\n'
    site = load_site(_write(tmp_path, text))
    assert (site.identity.reid_window_s, site.identity.rate_hz) == (120.0, 5.0)
    residents = site.load_residents()
    # the site's names, not the files': a file can be renamed in the site without enrolling again
    assert [r.name for r in residents] == ["Ada", "Bob the Builder"]
    assert residents[0].model.frames[1] == 40 and residents[0].model.height_m == 1.7
    assert residents[1].model.frames[1] == 55 and residents[1].model.height_m != residents[1].model.height_m
    again = load_site(write_site(site, tmp_path / "site.toml"))  # written back where it was: same paths
    assert again.enrolled == site.enrolled and again.identity == site.identity


@pytest.mark.parametrize(
    ("extra", "field", "problem"),
    [
        ("[identity]\nrate_hz = 0\n", "identity.rate_hz", "greater than 0"),
        ("[identity]\nrate_hz = 100\n", "identity.rate_hz", "less than or equal to 30"),
        ("[identity]\nreid_window_s = -5\n", "identity.reid_window_s", "greater than 0"),
        ("[identity]\nreid_window = 60\n", "identity.reid_window", "unknown field"),
        ('[[enrolled]]\nname = ""\nmodel = "a.json"\n', "enrolled[0].name", "must not be empty"),
        ('[[enrolled]]\nname = "   "\nmodel = "a.json"\n', "enrolled[0].name", "must not be empty"),
        ('[[enrolled]]\nname = "' + "x" * 65 + '"\nmodel = "a.json"\n', "enrolled[0].name", "at most 64 characters, got 65"),
        ('[[enrolled]]\nname = "Ada"\n', "enrolled[0].model", "required field is missing"),
        ('[[enrolled]]\nname = "Ada"\nmodel = "a.json"\n[[enrolled]]\nname = "Ada"\nmodel = "b.json"\n',
         "enrolled", "unique, repeated: ['Ada']"),
        ('[[enrolled]]\nname = "A"\nmodel = "a.json"\n[[enrolled]]\nname = "B"\nmodel = "b.json"\n'
         '[[enrolled]]\nname = "C"\nmodel = "c.json"\n', "enrolled", "3 people enrolled but residents = 2"),
    ],
)
def test_bad_identity_or_enrolment_names_the_field(tmp_path, extra, field, problem):
    path = _write(tmp_path, GOOD + "\n" + extra)
    with pytest.raises(SiteError) as err:
        load_site(path)
    message = str(err.value)
    assert str(path) in message and f"field {field}" in message and problem in message


def test_exactly_64_characters_is_a_name(tmp_path):
    site = load_site(_write(tmp_path, GOOD + '\n[[enrolled]]\nname = "' + "é" * 64 + '"\nmodel = "a.json"\n'))
    assert len(site.enrolled[0].name) == 64


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (None, "not found (make it with voxelwatch enrol)"),
        ("{not json", "not valid JSON"),
        ("[1, 2]", "expected a JSON object, got list"),
        (json.dumps({"name": "Ada"}), "missing field 'bands'"),
        ("hist", "hist must be 3x"),
        ("frames", "finite and non-negative"),
    ],
)
def test_a_bad_model_file_names_the_file_and_the_problem(tmp_path, content, problem):
    path = _write(tmp_path, GOOD + ENROLLED)
    model = tmp_path / "residents" / "ada.json"
    if content == "hist":
        _model_file(model, hist=[[0.5, 0.5]])
    elif content == "frames":
        _model_file(model, frames=[1, -2, 3])
    elif content is not None:
        model.parent.mkdir(parents=True, exist_ok=True)
        model.write_text(content)
    site = load_site(path)  # the file is read when the residents are loaded
    with pytest.raises(SiteError) as err:
        site.load_residents()
    message = str(err.value)
    assert str(path) in message and "field enrolled[0].model" in message and str(model) in message
    assert problem in message


def test_the_pipeline_of_a_site_recognises_its_residents_with_its_identity_settings(tmp_path):
    from fusion_server.pipeline import FusionPipeline
    from tests.tinysite import write_site as write_tiny

    path, cams = write_tiny(tmp_path)
    _model_file(tmp_path / "residents" / "ada.json")
    path.write_text(path.read_text().replace('name = "tiny"\n', 'name = "tiny"\nresidents = 1\n\n'
                                              '[identity]\nreid_window_s = 90\nrate_hz = 7.5\n', 1) + ENROLLED)
    pipeline = FusionPipeline.from_site(load_site(path), cameras=cams)
    keeper = pipeline.identity
    assert (keeper.p.reid_window_s, keeper.p.rate_hz) == (90.0, 7.5)
    assert keeper.name_of(1) == "Ada" and keeper.models()[1].frames[1] == 40  # label 1 waits for Ada
    assert FusionPipeline.from_site(load_site(path), cameras=cams, residents=()).identity.models() == {}
    (tmp_path / "residents" / "ada.json").unlink()
    with pytest.raises(SiteError, match="ada.json: not found"):
        FusionPipeline.from_site(load_site(path), cameras=cams)


def test_site_check_loads_the_enrolled_residents(tmp_path, capsys):
    from voxelwatch import cli
    from tests.tinysite import write_site as write_tiny

    path, _ = write_tiny(tmp_path)
    path.write_text(path.read_text().replace('name = "tiny"\n', 'name = "tiny"\nresidents = 1\n', 1) + ENROLLED)
    assert cli.main(["site", "check", str(path)]) == 2  # the model file is not there yet
    assert "field enrolled[0].model" in capsys.readouterr().err
    _model_file(tmp_path / "residents" / "ada.json", torso_frames=40, height_m=1.7)
    assert cli.main(["site", "check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "1 residents, 1 enrolled" in out
    assert "enrolled Ada: frames learnt head 0, torso 40, legs 0; 1.70 m tall" in out


def test_settings_change_a_site_and_are_validated_like_the_file(tmp_path):
    from common.site import with_settings
    from synth import default_site

    site = default_site(tmp_path / "site")
    changed = with_settings(site, ["carving.min_ratio=0.5", "carving.min_cameras = 3"])
    assert changed.carving.min_ratio == 0.5 and changed.carving.min_cameras == 3
    assert site.carving.min_ratio != 0.5  # the site itself is unchanged
    assert changed.base_dir == site.base_dir and changed.camera_ids == site.camera_ids
    with pytest.raises(SiteError, match=r"carving\.min_ratio"):
        with_settings(site, ["carving.min_ratio=2"])
    with pytest.raises(SiteError, match="no section \\[carve\\]"):
        with_settings(site, ["carve.min_ratio=0.5"])
    with pytest.raises(SiteError, match="SECTION.KEY=VALUE"):
        with_settings(site, ["min_ratio=0.5"])


def test_site_check_refuses_what_the_processes_would_refuse(tmp_path, capsys):
    """More carving cameras than the site has, or a mistyped endpoint: ``site check`` says so in one
    line naming the field, as the fusion server and the workers would at start."""
    import re

    from voxelwatch import cli
    from tests.tinysite import write_site as write_tiny

    path, _ = write_tiny(tmp_path)
    text = path.read_text()
    path.write_text(re.sub(r"min_cameras = \d+", "min_cameras = 9", text))
    assert cli.main(["site", "check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "carving.min_cameras: 9 exceeds the site's 3 cameras" in err and len(err.strip().splitlines()) == 1
    path.write_text(text.replace('name = "tiny"\n', 'name = "tiny"\n[zenoh]\nconnect = ["tpc/10.0.0.2:7447"]\n', 1))
    assert cli.main(["site", "check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "zenoh.connect" in err and "'tpc'" in err and len(err.strip().splitlines()) == 1
    path.write_text(text)
    assert cli.main(["site", "check", str(path)]) == 0
