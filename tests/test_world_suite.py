"""The random-world suite: short tuning worlds written, replayed and scored, tables and JSON.

The figures are printed, not held to targets: these worlds are the test bed
the pipeline is measured on, and a few seconds of two tuning worlds say
little. What is held: every world is run and scored, the totals are the sums
of the worlds, the bands by people present add up to the whole, and the
command line gives one clear message for bad seeds. Running the two worlds takes about 20 s: the tests
that need them are in the slow set, the seeds and the command line's messages in the default run.
"""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import pytest

from evaluation.world_suite import parse_seeds, run_world_suite

VOXELWATCH = Path(sys.executable).with_name("voxelwatch")
SEEDS = (20, 21)
"""Tuning worlds: five people dressed alike under four high-corner cameras in a 10.4 x 3.9 m room, three
people under five level-wall cameras in a 3.1 x 5.6 m one (small rooms and rigs: the suite's cost is
mostly each camera's carving tables and renderer, which grow with the room's volume and the image)."""
FRAMES = 30


def test_parse_seeds():
    assert parse_seeds("1000-1003") == [1000, 1001, 1002, 1003]
    assert parse_seeds("3,7,20-22,7") == [3, 7, 20, 21, 22]
    for bad in ("", "a-b", "5-2", "-4"):
        with pytest.raises(ValueError, match="--seeds"):
            parse_seeds(bad)


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    out = tmp_path_factory.mktemp("worlds")
    stream = io.StringIO()
    report = run_world_suite(seeds=SEEDS, out_dir=out, frames=FRAMES, json_path=out / "suite.json", stream=stream)
    print(stream.getvalue())
    return out, report, stream.getvalue()


@pytest.mark.slow  # two worlds written, carved and scored: about 20 s (the suite fixture)
def test_every_world_is_run_and_scored(suite):
    out, report, text = suite
    assert [w["seed"] for w in report["worlds"]] == list(SEEDS)
    assert report["seed_sets"] == ["tuning"]
    for w in report["worlds"]:
        assert w["frames"] == FRAMES and w["scores"]["frames"]["count"] == FRAMES
        assert w["fuse_s"] > 0
        assert (out / "runs" / f"world-{w['seed']}" / "tracks.csv").is_file()
        # the media are gone once scored, the truth stays
        assert not list((out / "worlds" / f"world-{w['seed']}").glob("cam*"))
        assert (out / "worlds" / f"world-{w['seed']}" / "truth" / "meta.json").is_file()
    assert "tuning seeds 20-21" in text
    for seed in SEEDS:
        assert any(line.startswith(f"{seed} ") for line in text.splitlines())


@pytest.mark.slow  # two worlds written, carved and scored: about 20 s (the suite fixture)
def test_totals_are_the_sums_of_the_worlds(suite):
    _, report, _ = suite
    total = report["total"]
    worlds = [w["scores"] for w in report["worlds"]]
    assert total["frames"]["count"] == FRAMES * len(SEEDS)
    for key in ("gt", "fp", "fn", "id_switches"):
        assert total["tracking"][key] == sum(w["tracking"][key] for w in worlds)
    bands = total["by_people"]
    assert sum(b["frames"] for b in bands.values()) == FRAMES * len(SEEDS)
    assert sum(b["gt"] for b in bands.values()) == total["tracking"]["gt"]
    assert sum(b["fp"] for b in bands.values()) == total["tracking"]["fp"]
    # the five people of world 20 are in the 4-7 band for at least part of the run
    assert "4-7" in bands
    groups = report["groups"]
    assert sum(g["frames"]["count"] for label, g in groups.items() if label in ("high corners", "level walls")) == \
        total["frames"]["count"]
    for key in ("reentries", "same_id"):
        assert total["identity"][key] == sum(w["identity"][key] for w in worlds)
    # world 20 dresses its people alike
    assert sum(g["frames"]["count"] for g in report["dress"].values()) == total["frames"]["count"]
    assert report["dress"]["alike"]["frames"]["count"] == FRAMES


@pytest.mark.slow  # two worlds written, carved and scored: about 20 s (the suite fixture)
def test_the_report_is_written_as_json(suite):
    out, report, _ = suite
    saved = json.loads((out / "suite.json").read_text())
    assert saved["seeds"] == list(SEEDS)
    assert saved["total"]["tracking"]["gt"] == report["total"]["tracking"]["gt"]


def test_the_command_needs_seeds_and_says_so(tmp_path):
    if not VOXELWATCH.is_file():
        pytest.skip(f"the voxelwatch command is not installed beside {sys.executable}")
    r = subprocess.run([str(VOXELWATCH), "eval", "--suite", "--world", "random", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode != 0 and "--seeds" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([str(VOXELWATCH), "eval", "--suite", "--world", "random", "--seeds", "1x", "--out",
                        str(tmp_path)], capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode != 0 and "'1x'" in r.stderr and "Traceback" not in r.stderr
