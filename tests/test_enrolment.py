"""Enrolment: a resident's model from a clip of them alone, then their name on tracks and events.

The choice of the model is worked by hand on made-up models. The rest runs
``voxelwatch enrol`` and replays on short clips of the synthetic house, whose
person 1 wears the same clothes in every scenario of a seed: enrolled from
``walk``, they must be named in ``two_pass`` and ``sit_stand``, the other
person of ``two_pass`` never, and their events must carry the name. The test
site asks for colours at 15 Hz (the default is 3) so that a few seconds of
clip learn enough.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from voxelwatch import cli
from evaluation import evaluate, read_events, read_tracks
from common.site import load_site, site_from_dict, write_site
from fusion_server.enrolment import EnrolmentError, choose_model
from fusion_server.event_store import EventStore, parse_history_selector
from common.appearance import AppearanceModel

ENROL_FRAMES = 60
"""4 s of ``walk``: person 1 confirmed within a few frames, then asked for their colours every frame."""


def _model(head: int, torso: int, legs: int) -> AppearanceModel:
    return AppearanceModel(frames=np.array([head, torso, legs], dtype=float))


@pytest.mark.parametrize(
    ("frames", "chosen"),
    [
        ({1: (30, 30, 30)}, 1),                      # exactly enough
        ({1: (60, 60, 60), 2: (29, 29, 29)}, 1),     # a second person under half as much
        ({4: (5, 10, 5), 2: (70, 60, 70)}, 2),       # the label does not matter
        ({1: (100, 10, 100), 2: (0, 40, 0)}, 2),     # ranked by the torso
    ],
)
def test_the_person_learnt_most_is_chosen(frames, chosen):
    models = {label: _model(*f) for label, f in frames.items()}
    label, model = choose_model(models)
    assert label == chosen and model is models[chosen]


@pytest.mark.parametrize(
    ("frames", "needle"),
    [
        ({}, "nobody was learnt well enough: the person seen the most has 0 torso frames, 30 are needed"),
        ({1: (90, 29, 90)}, "has 29 torso frames, 30 are needed"),
        ({1: (60, 60, 60), 2: (30, 30, 30)}, "a second person was learnt from 30 torso frames against 60"),
        ({1: (40, 40, 40), 3: (45, 45, 45)}, "a second person was learnt from 40 torso frames against 45"),
    ],
)
def test_nobody_or_two_people_is_refused(frames, needle):
    with pytest.raises(EnrolmentError, match=needle):
        choose_model({label: _model(*f) for label, f in frames.items()})


# ---------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def house(tmp_path_factory) -> Path:
    """The synthetic house's site, asking for colours every frame."""
    from synth import default_site

    folder = tmp_path_factory.mktemp("house")
    raw = default_site(folder).model_dump(mode="json", exclude={"base_dir"})
    raw["identity"]["rate_hz"] = 15.0
    return write_site(site_from_dict(raw, base_dir=folder.resolve()), folder / "site.toml")


@pytest.fixture(scope="module")
def cache(lut_cache) -> Path:
    return lut_cache


def _enrol(site: Path, cache: Path, scenario: str, frames: int, out: Path) -> int:
    return cli.main(["enrol", "--site", str(site), "--synthetic", scenario, "--frames", str(frames), "--name", "Ada",
                     "--out", str(out), "--cache-dir", str(cache), "--quiet"])


@pytest.fixture(scope="module")
def enrolled(house, cache) -> Path:
    """``voxelwatch enrol`` of person 1 from the start of ``walk``, and the site enrolling them."""
    model = house.parent / "residents" / "ada.json"
    assert _enrol(house, cache, "walk", ENROL_FRAMES, model) == 0
    site = house.parent / "enrolled.toml"
    site.write_text(house.read_text() + '\n[[enrolled]]\nname = "Ada"\nmodel = "residents/ada.json"\n')
    return site


def test_enrol_writes_the_model_of_the_person_in_the_clip(enrolled, capsys):
    data = json.loads((enrolled.parent / "residents" / "ada.json").read_text())
    assert data["name"] == "Ada" and data["bands"] == ["head", "torso", "legs"]
    assert data["frames"][1] >= 30  # enough to be accepted
    assert abs(data["height_m"] - 1.9) < 0.15  # person 1 of seed 0 is 1.90 m
    # only histograms and numbers: nothing like an image
    assert set(data) == {"name", "bands", "hist", "frames", "height_m", "height_frames"}
    assert np.allclose(np.asarray(data["hist"]).sum(axis=1), 1.0, atol=0.01)
    residents = load_site(enrolled).load_residents()
    assert [r.name for r in residents] == ["Ada"]


@pytest.mark.slow
def test_enrol_refuses_a_clip_with_two_people_and_one_with_nobody(house, cache, tmp_path, capsys):
    out = tmp_path / "ada.json"
    assert _enrol(house, cache, "two_pass", ENROL_FRAMES, out) == 2
    err = capsys.readouterr().err
    assert "voxelwatch enrol: the clip shows more than one person" in err and "resident alone" in err
    assert not out.exists()
    assert _enrol(house, cache, "walk", 4, out) == 2  # nobody confirmed yet
    assert "voxelwatch enrol: nobody was learnt well enough" in capsys.readouterr().err
    assert not out.exists()
    assert cli.main(["enrol", "--site", str(house), "--synthetic", "walk", "--name", " ", "--out", str(out)]) == 2
    assert "--name: a name must not be empty" in capsys.readouterr().err


@pytest.mark.slow
def test_the_resident_is_named_on_their_track_and_nobody_else_is(enrolled, cache, tmp_path):
    import synth
    from fusion_server.replay import replay

    site = load_site(enrolled)
    frames = 75  # they pass each other at about frame 40, 0.55 m apart
    replay(site, tmp_path / "run", synthetic="two_pass", max_frames=frames, cache_dir=cache)
    synth.write_truth(synth.get_scenario("two_pass", 0), tmp_path / "truth", n_frames=frames)
    tracks = read_tracks(tmp_path / "run" / "tracks.csv")
    assert set(tracks.person.tolist()) == {"Ada", ""}
    assert set(tracks.track_id[tracks.person == "Ada"].tolist()) == {"1"}  # residents take labels from 1
    res = evaluate(tmp_path / "truth", tmp_path / "run", resident=("1", "Ada"))["resident"]
    assert res["false_named"] == 0 and res["named_unmatched"] == 0
    assert res["named_ratio"] >= 0.9  # named from the frame the track is reported


@pytest.mark.slow
def test_an_event_about_the_resident_carries_the_name_into_the_history(enrolled, cache, tmp_path):
    from fusion_server.replay import replay

    # sit_stand: person 1 walks to a dinner chair and sits down (the truth's sit_down is at frame 110)
    replay(load_site(enrolled), tmp_path / "run", synthetic="sit_stand", max_frames=130, cache_dir=cache)
    events = read_events(tmp_path / "run" / "events.jsonl")
    sat = [e for e in events if e.kind == "sit_down"]
    assert len(sat) == 1 and sat[0].details["person"] == "Ada" and sat[0].track == 1
    assert set(read_tracks(tmp_path / "run" / "tracks.csv").person.tolist()) == {"Ada"}
    with EventStore(tmp_path / "history.sqlite") as store:
        store.add_many(events)
    with EventStore(tmp_path / "history.sqlite") as store:  # as a restarted server answers
        (back,) = store.query_filter(parse_history_selector("kind=sit_down"))
    assert back.details["person"] == "Ada" and back.track == 1
