"""Shared test fixtures: where the real recordings are."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DATA_DIR = Path(os.environ.get("VOXELWATCH_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data")).resolve()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared recordings; tests that need them skip with a reason when absent."""
    if not DATA_DIR.is_dir():
        pytest.skip(f"real recordings not found at {DATA_DIR} (set VOXELWATCH_DATA)")
    return DATA_DIR


@pytest.fixture(scope="session")
def lab4cam(data_dir: Path) -> Path:
    path = data_dir / "lab4cam-seated"
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path


@pytest.fixture(scope="session")
def pets_calibration(data_dir: Path) -> Path:
    path = data_dir / "pets2009-calibration"
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path


@pytest.fixture(scope="module")
def house(tmp_path_factory):
    """(site, site file, carving-table cache dir) of the synthetic house, for tests that run it
    as processes (modules with a house of their own override this one)."""
    import synth

    root = tmp_path_factory.mktemp("house")
    site = synth.default_site(root / "site")
    return site, site.base_dir / "site.toml", root / "cache"
