"""Settings declared once (:mod:`common.settings`): every value a site file accepts is accepted by
the process that uses it, and the command line fills the same declaration.

Every site file the project ships or writes (``deploy/site.toml``, the synthetic house, random
worlds on each rig kind drawn by seeds 0-3) is loaded with ``carving.mask_scale`` at the bottom
of its declared range, at 0.2 and at 1; from each, every camera worker's settings and
segmenter, the fusion server's settings and the carver's parameters are built as the processes
build them at start.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from common.settings import SettingError, check_setting, default_of, validated
from common.site import Carving, EventSettings, IdentitySettings, load_site, with_settings, write_site

ROOT = Path(__file__).resolve().parents[1]
LOWEST = Carving.model_fields["mask_scale"].metadata[0].ge   # the declared bottom of the range


def test_one_value_is_checked_against_its_declaration_with_one_message() -> None:
    assert LOWEST == 0.125
    assert check_setting(Carving, "mask_scale", 0.2, flag="--mask-scale") == 0.2
    with pytest.raises(SettingError, match=r"^--mask-scale: Input should be greater than or equal to 0.125, got 0.1$"):
        check_setting(Carving, "mask_scale", 0.1, flag="--mask-scale")
    with pytest.raises(SettingError, match=r"^min_ratio: Input should be greater than 0, got 0$"):
        validated(Carving, min_ratio=0)
    assert default_of(EventSettings, "long_lie_s") == 30.0 and default_of(Carving, "voxel_sizes_m") == [0.4, 0.2, 0.1, 0.05]


def test_the_stages_take_their_defaults_and_ranges_from_the_site_files_declaration() -> None:
    """One default and one range per setting: the runtime groups' defaults are the site's, and a
    value the site refuses the stage refuses with the same words."""
    from camera_worker.segmentation import ForegroundSegmenter
    from fusion_server.events.falls import FallParams
    from fusion_server.identity import IdentityParams

    assert FallParams().long_lie_s == EventSettings().long_lie_s
    assert IdentityParams().rate_hz == IdentitySettings().rate_hz
    assert IdentityParams().reid_window_s == IdentitySettings().reid_window_s
    for make, bad, words in [
        (lambda v: FallParams(long_lie_s=v), 4.0, "long_lie_s: Input should be greater than or equal to 5"),
        (lambda v: IdentityParams(reid_window_s=v), -1.0, "reid_window_s: Input should be greater than 0"),
        (lambda v: ForegroundSegmenter(mask_scale=v), 0.1, "mask_scale: Input should be greater than or equal to 0.125"),
    ]:
        with pytest.raises(ValueError, match=words):
            make(bad)
    assert ForegroundSegmenter(mask_scale=LOWEST).mask_scale == LOWEST


def _shipped_and_written_sites(root: Path) -> list[Path]:
    import synth
    from synth.world import random_world, write_world_site

    import shutil

    shutil.copytree(ROOT / "deploy", root / "deploy", ignore=shutil.ignore_patterns("systemd", "zenoh", "Container*"))
    sites = [root / "deploy" / "site.toml", synth.default_site(root / "house").base_dir / "site.toml"]
    for seed in range(4):   # tuning seeds: high corners, level walls, fisheyes, the real rigs
        world = random_world(seed)
        sites.append(write_world_site(world, root / f"world-{seed}", frames=1).site)
    return sites


@pytest.fixture(scope="module")
def site_files(tmp_path_factory) -> list[Path]:
    return _shipped_and_written_sites(tmp_path_factory.mktemp("sites"))


@pytest.mark.parametrize("mask_scale", [LOWEST, 0.2, 1.0])
def test_every_site_file_builds_every_process_at_every_mask_scale_it_accepts(site_files, tmp_path, mask_scale) -> None:
    from camera_worker.cli import _configure, build_parser as camera_parser
    from camera_worker.segmenters import segmenter_for
    from fusion_server.carving.carver import Carver
    from fusion_server.cli import build_parser as fusion_parser, settings_from_args

    assert len(site_files) == 6
    for path in site_files:
        site = with_settings(load_site(path), [f"carving.mask_scale={mask_scale}"])
        changed = write_site(site, path.parent / f"scaled-{mask_scale}.toml")
        site = load_site(changed)
        assert site.carving.mask_scale == mask_scale
        for cam in site.camera_ids:
            args = camera_parser().parse_args(["--site", str(changed), "--camera", cam, "--source", "synthetic",
                                               "--no-view-check"])
            settings, _, _ = _configure(args)
            assert settings.segmenter["mask_scale"] == mask_scale, path
            segmenter_for(settings.modality, window_frames=500, **{k: v for k, v in settings.segmenter.items()
                                                                   if k != "window_frames"})
            flagged, _, _ = _configure(camera_parser().parse_args(
                ["--site", str(changed), "--camera", cam, "--source", "synthetic", "--no-view-check",
                 "--mask-scale", str(mask_scale)]))
            assert flagged.segmenter["mask_scale"] == mask_scale
        fusion = settings_from_args(fusion_parser().parse_args(["--site", str(changed)]))
        assert fusion.site.carving.mask_scale == mask_scale
        # the carver as the fusion server builds it, over a small box of the room (small tables)
        c = site.carving
        lo = site.volume.min_m
        carver = Carver(cameras=site.load_cameras(), volume_min_m=lo, volume_max_m=(lo[0] + 0.8, lo[1] + 0.8, lo[2] + 0.8),
                        voxel_sizes_m=c.voxel_sizes_m[:2], min_cameras=min(c.min_cameras, len(site.cameras)),
                        min_ratio=c.min_ratio, mask_scale=c.mask_scale, fusion=c.fusion, smoothing=c.smoothing,
                        free_space=c.free_space, cache_dir=tmp_path / "cache")
        assert carver.mask_scale == mask_scale


def test_a_mask_scale_below_the_declared_range_stops_the_camera_worker_with_the_flag_named(tmp_path) -> None:
    import subprocess
    import sys

    import synth

    site = synth.default_site(tmp_path / "house")
    result = subprocess.run([sys.executable, "-m", "camera_worker.cli", "--site", str(site.base_dir / "site.toml"),
                             "--camera", "cam1", "--source", "synthetic", "--mask-scale", "0.1"],
                            cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip() == ("voxelwatch-camera: --mask-scale: Input should be greater than or equal to 0.125, "
                                     "got 0.1")
