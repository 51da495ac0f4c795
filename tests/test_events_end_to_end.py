"""Dwelling, visits, long lies and inactivity, end to end on the synthetic house.

``test_events.py`` and ``test_hotspots.py`` feed the event reasoner true
positions; here the same events must come out of the whole chain. Each case
scripts a short scene in the test (a :class:`~synth.ScenarioSpec`),
renders it into the house's five cameras at half size (320 x 240), segments
every camera with the camera worker's own segmenter after it has learnt the
empty room (the hold regions of still people going back to it, as in
``fusion_server.replay``), and fuses the masks with
:class:`~fusion_server.pipeline.FusionPipeline` built from the site file.
Tracks and events are written by the server's own writers and scored with
:func:`evaluation.evaluate` against :func:`synth.derive_truth`:
every true event of every kind matched one to one within +-30 frames, and no
event that matches nothing, whatever the case is about.

Inactivity has no truth event. Its case (slow: 705 frames) sets ``[events] inactivity_s = 40``
in the site file and checks the alarm against an expectation worked out by
hand from the script (see the test).

Measured (seed 0; frame offsets are run minus truth; CPU seconds of the whole
case, rendering and segmenting included, on the shared two-core machine)::

    case                     frames  matched events: truth frame, offset              MOTA   CPU s
    sofa_visit                  315  dwell_start 178 -14, 201 -17; visit 201 -17;     0.994     14
                                     dwell_end 270 +13
    long_lie                    540  fall 57 +14; long_lie 507 -3                     0.996     15
    seated_still (40 s)         705  sit_down 67 +12; dwell_start 186 +28;            0.997     17
                                     inactivity due 667, raised at 679 (+12)
    kitchen_visit               330  enter 33 +13; dwell_start 190 -18, 214 -17;      0.995     13
                                     visit 214 -17; dwell_end 287 +14

The default cases take about 50 s. Slow: the library's complete
``dinner_visit`` and ``hotspot_dwell`` replayed as the scenario suite runs them
(640 x 480 cameras, half-size masks): dinner_visit's 4 dwell starts (+6..+27),
3 dwell ends (+14..+16) and the visit (+14) all matched (215 s CPU);
hotspot_dwell is an expected failure (102 s CPU).

Dwell starts come about 1 s early against the truth when a person stops
walking and stands:
the variance test passes a 10 s window that still holds the last slow steps
of the walk. After sitting down on the sofa they come 27-38 frames late: the
truth counts the stay from the end of the walk, before the turn and the
sit-down, while the seated track moves 0.8 m back onto the seat and the still
window counts from there. seated_still's +28 is two frames inside the window;
hotspot_dwell's +38 is outside it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from camera_worker.segmentation import ForegroundSegmenter, window_frames_for
import synth
from evaluation import ALARM_KINDS, Event, evaluate, read_events, read_tracks, score_events
from common.site import Site, site_from_dict
from synth import ScenarioSpec, SyntheticCamera, derive_truth, get_scenario
from synth.behaviour import Enter, Face, Fall, PersonScript, Sit, Stand, Wait, Walk
from fusion_server.detection import Blob
from fusion_server.outputs import RunOutputs
from fusion_server.pipeline import FusionPipeline
from fusion_server.replay import replay
from fusion_server.tracker import TrackEstimate

SEED = 0
HALF = 0.5
SEGMENTER_PX = {"open_px": 2, "close_px": 4, "min_area_px": 100}
"""The camera worker's clean-up sizes (3, 7 and 400 px at 640 x 480) at half size, as
its ``mask_scale = 0.5`` makes them: the frames are rendered at 320 x 240 here."""
INACTIVITY_S = 40.0
"""The site's ``[events] inactivity_s`` in the inactivity case (the default is 30 minutes)."""


@dataclass(frozen=True)
class Scene:
    """One scripted scene run through the pipeline, and its scores."""

    name: str
    frames: int
    truth_dir: Path
    run_dir: Path
    results: dict
    cpu_s: float

    @property
    def events(self) -> dict:
        return self.results["events"]

    def kind(self, kind: str) -> dict:
        return self.events["per_kind"][kind]

    def run_events(self, kind: str) -> list[Event]:
        return [e for e in read_events(self.run_dir / "events.jsonl") if e.kind == kind]

    def truth_events(self, kind: str) -> list[Event]:
        return [e for e in read_events(self.truth_dir / "events.jsonl") if e.kind == kind]

    def describe(self) -> str:
        t = self.results["tracking"]
        kinds = {k: (v["truth"], v["tp"], v["fp"], v["fn"]) for k, v in self.events["per_kind"].items()
                 if v["truth"] or v["run"]}
        offsets = [(m["kind"], m["truth_frame"], m["run_frame"] - m["truth_frame"]) for m in self.events["matched"]]
        return (
            f"{self.name}, {self.frames} frames, {self.cpu_s:.1f} s CPU: MOTA {t['mota']:.3f} "
            f"IDF1 {t['idf1']:.3f} IDSW {t['id_switches']}; events (truth, tp, fp, fn) {kinds}; "
            f"matched (kind, truth frame, offset) {offsets}; missed {self.events['missed']}; "
            f"spurious {self.events['spurious']}"
        )


@pytest.fixture(scope="module")
def house(tmp_path_factory, lut_cache):
    """Half-size cameras of the synthetic house, a folder with their calibrations, and a
    function giving the house's site with an ``[events]`` section (validated as a site
    file is). ``root / "cache"`` is the run's shared carving-table cache."""
    root = tmp_path_factory.mktemp("events_e2e")
    (root / "cache").symlink_to(lut_cache, target_is_directory=True)
    cameras = synth.default_cameras(scale=HALF)
    base = synth.default_site(root / "site", cameras=cameras)

    def site(**events: float) -> Site:
        raw = base.model_dump(mode="json", exclude={"base_dir"})
        raw["carving"]["mask_scale"] = 1.0  # the frames are half size already
        raw["events"] = dict(events)
        return site_from_dict(raw, base_dir=base.base_dir, source="synthetic house")

    return cameras, site, root


def run_scene(spec: ScenarioSpec, house, **events: float) -> Scene:
    """Render, segment, fuse and score ``spec``; ``events`` go into the site's ``[events]``."""
    cameras, make_site, root = house
    t0 = time.process_time()
    site = make_site(**events)
    scenario = get_scenario(spec, SEED, utc_offset_hours=site.utc_offset_hours)
    truth_dir, run_dir = root / spec.name / "truth", root / spec.name / "run"
    synth.write_truth(scenario, truth_dir)
    pipeline = FusionPipeline.from_site(site, cameras=cameras, cache_dir=root / "cache", seed=SEED)
    sources = {cam: SyntheticCamera(scenario, cam, SEED, camera=camera) for cam, camera in cameras.items()}
    segmenters = {}
    for cam, source in sources.items():
        segmenters[cam] = ForegroundSegmenter(window_frames=window_frames_for(scenario.fps), **SEGMENTER_PX)
        for i in range(source.n_background_frames):
            segmenters[cam].learn(source.background_frame(i))
    holds: dict[str, list] = {}
    with RunOutputs(run_dir, fresh=True) as outputs:
        for i in range(scenario.n_frames):
            masks = {cam: segmenters[cam].apply(source.frame(i)[0], holds=holds.get(cam, ()))[0]
                     for cam, source in sources.items()}
            fused = pipeline.step(masks, scenario.stamp_ns(i), i)
            holds = fused.holds
            outputs.write_frame(fused.frame, fused.stamp_ns, fused.tracks)
            for event in fused.events:
                outputs.write_event(event)
    scene = Scene(spec.name, scenario.n_frames, truth_dir, run_dir, evaluate(truth_dir, run_dir),
                  time.process_time() - t0)
    print(f"\n{scene.describe()}")
    return scene


def check_events_match_truth(
    scene: Scene, kinds: tuple[str, ...], *, ignore: tuple[str, ...] = (), only: tuple[str, ...] | None = None
) -> None:
    """The truth has events of ``kinds``; every true event is matched and no run event is
    left over, of any kind but ``ignore`` (of the kinds ``only``, when given)."""
    for kind in kinds:
        assert scene.kind(kind)["truth"] > 0, f"{scene.name} has no {kind} to detect"
    for kind, score in scene.events["per_kind"].items():
        if kind in ignore or (only is not None and kind not in only):
            continue
        assert (score["tp"], score["fp"], score["fn"]) == (score["truth"], 0, 0), f"{scene.name} {kind}: {score}"


# --------------------------------------------------------------------------- dwelling and visits


def _sofa_visit() -> ScenarioSpec:
    return ScenarioSpec(
        "sofa_visit", "The resident and a visitor stand chatting in front of the sofa at tea time; the "
        "resident walks off.", 21.0,
        (
            PersonScript(1, (Walk(((4.3, 1.35), (5.1, 1.35))), Face(facing_deg=0.0), Stand(13.0),
                             Walk(((4.3, 0.8),))), start=(4.1, 3.3, -90.0)),
            PersonScript(2, (Walk(((6.3, 1.4),)), Face(facing_deg=180.0), Stand(60.0)),
                         start=(7.3, 0.8, 150.0), resident=False),
        ),
        start_local="16:00:00",
    )


@pytest.mark.slow
def test_dwelling_and_a_visit_at_the_sofa(house):
    scene = run_scene(_sofa_visit(), house)
    check_events_match_truth(scene, ("dwell_start", "dwell_end", "visit"))
    assert scene.kind("dwell_start")["truth"] == 2 and scene.kind("dwell_end")["truth"] == 1
    (truth,), (run,) = scene.truth_events("visit"), scene.run_events("visit")
    assert run.details["hotspot"] == truth.details["hotspot"] == "sofa"
    assert run.details["reason"] == truth.details["reason"] == "for tea"
    assert run.details["people"] == 2
    for kind in ("dwell_start", "dwell_end"):
        assert {e.details["hotspot"] for e in scene.run_events(kind)} == {"sofa"}


def _kitchen_visit() -> ScenarioSpec:
    return ScenarioSpec(
        "kitchen_visit", "A visitor comes in and stands at the kitchen counter by the resident, who then "
        "walks off.", 22.0,
        (
            PersonScript(1, (Walk(((3.0, 4.95),)), Face(facing_deg=90.0), Stand(14.0, activity="work"),
                             Walk(("centre",))), start=(4.2, 4.2, 180.0)),
            PersonScript(2, (Enter(to=((1.5, 4.9),)), Face(facing_deg=90.0), Stand(60.0)), resident=False),
        ),
        start_local="16:00:00",
    )


@pytest.mark.slow  # a long scene (hot-spot dwelling itself is tested in test_hotspots.py)
def test_dwelling_and_a_visit_at_the_kitchen_counter(house):
    scene = run_scene(_kitchen_visit(), house)
    check_events_match_truth(scene, ("enter", "dwell_start", "dwell_end", "visit"))


# --------------------------------------------------------------------------- lying on the floor


def _long_lie() -> ScenarioSpec:
    return ScenarioSpec(
        "long_lie", "Walks to the middle of the room, falls forward and lies still.", 36.0,
        (PersonScript(1, (Walk(("centre",)), Wait(1.0), Fall("forward")), start=(4.2, 4.2, -90.0)),),
    )


@pytest.mark.slow  # a 40-s scene; the long lie after a fall is also held in test_events.py
def test_long_lie_after_a_fall(house):
    scene = run_scene(_long_lie(), house)
    check_events_match_truth(scene, ("fall", "long_lie"))
    (run,) = scene.run_events("long_lie")
    assert run.details["after_fall"] is True
    assert run.details["duration_s"] == pytest.approx(30.0, abs=0.2)  # the site's default long_lie_s


# --------------------------------------------------------------------------- inactivity


def _inactivity() -> ScenarioSpec:
    return ScenarioSpec(
        "seated_still", "Walks to the sofa, sits down and sits still to the end.", 47.0,
        (PersonScript(1, (Sit("sofa middle", None),), start=(4.05, 0.7, 0.0)),),
        start_local="14:00:00",
    )


def test_site_event_settings_reach_the_reasoner(house):
    cameras, make_site, root = house
    default = FusionPipeline.from_site(make_site(), cameras=cameras, cache_dir=root / "cache")
    reasoner = default.reasoner
    assert (reasoner.falls.params.long_lie_s, reasoner.inactivity.params.inactivity_s) == (30.0, 1800.0)
    tuned = FusionPipeline.from_site(make_site(long_lie_s=90.0, inactivity_s=600.0), cameras=cameras,
                                     cache_dir=root / "cache")
    reasoner = tuned.reasoner
    assert (reasoner.falls.params.long_lie_s, reasoner.inactivity.params.inactivity_s) == (90.0, 600.0)


def test_site_posture_decisions_reach_the_estimators(house):
    cameras, make_site, root = house
    default = FusionPipeline.from_site(make_site(), cameras=cameras, cache_dir=root / "cache")
    assert (default.posture_settings["decisions"], default.posture_settings["viterbi_lag_s"]) == ("frame", 0.6)
    tuned = FusionPipeline.from_site(make_site(decisions="viterbi", viterbi_lag_s=0.8), cameras=cameras,
                                     cache_dir=root / "cache")
    assert (tuned.posture_settings["decisions"], tuned.posture_settings["viterbi_lag_s"]) == ("viterbi", 0.8)


def test_the_sites_solid_furniture_reaching_a_seated_trunk_are_the_backs_seats_are_judged_by(house):
    cameras, make_site, root = house
    pipeline = FusionPipeline.from_site(make_site(), cameras=cameras, cache_dir=root / "cache")
    # the house's occluders from 0 or 0.42 m up to 0.9 m and more; not the seats, the sofa's arms
    # (0.42-0.62 m), the TV stand (0.5 m) or the table top (0.71-0.76 m)
    assert sorted(b.name for b in pipeline.postures.backs) == ["bookshelf", "fridge", "kitchen counter", "sofa back"]


@pytest.mark.slow
def test_inactivity_of_a_seated_person_after_the_sites_inactivity_s(house):
    """Worked out by hand from the script: the person walks to the sofa, sits down (the
    truth's sit_down frame, half-way down) and sits still to the end, on the sofa, which
    is no bed. The reasoner starts its clock when their posture changes to sitting, about
    that frame, so one inactivity alarm is due ``INACTIVITY_S`` later, for this person,
    seated, in the sofa hot spot; none before."""
    scene = run_scene(_inactivity(), house, inactivity_s=INACTIVITY_S)
    check_events_match_truth(scene, ("sit_down", "dwell_start"), ignore=("inactivity",))
    (sat,) = scene.truth_events("sit_down")
    scenario = get_scenario(_inactivity(), SEED)
    due = sat.frame + int(round(INACTIVITY_S * scenario.fps))
    truth = derive_truth(scenario)
    row = truth.rows_at(due)[0]
    expected = Event.from_dict(dict(kind="inactivity", frame=due, stamp_ns=int(truth.stamp_ns[row]), track=sat.track,
                                    x=float(truth.x[row]), y=float(truth.y[row])))
    run = scene.run_events("inactivity")
    score = score_events([expected], run, kinds=("inactivity",)).per_kind["inactivity"]
    print(f"inactivity due at frame {due}: run at {[e.frame for e in run]}; (tp, fp, fn) "
          f"{(score.tp, score.fp, score.fn)}")
    assert (score.tp, score.fp, score.fn) == (1, 0, 0)
    (alarm,) = run
    assert alarm.details["posture"] == "sitting" and alarm.details["hotspot"] == "sofa"
    assert alarm.details["duration_s"] >= INACTIVITY_S
    tracks = read_tracks(scene.run_dir / "tracks.csv")
    assert set(np.unique(tracks.track_id).tolist()) == {str(alarm.track)}  # the one person, tracked throughout
    assert np.hypot(alarm.x - expected.x, alarm.y - expected.y) <= 0.5


# --------------------------------------------------------------------------- complete library scenarios

LIBRARY = {"hotspot_dwell": ("dwell_start", "dwell_end"), "dinner_visit": ("dwell_start", "dwell_end", "visit")}
"""Library scenarios and the event kinds checked in them (test_scenarios.py checks the others)."""


@pytest.fixture(scope="module")
def library_house(tmp_path_factory, lut_cache):
    """The synthetic house's own site: full-size cameras, half-size masks, as the suite runs it."""
    root = tmp_path_factory.mktemp("events_library")
    (root / "cache").symlink_to(lut_cache, target_is_directory=True)   # the run's shared tables
    return synth.default_site(root / "site"), root


def replay_library(name: str, library_house) -> Scene:
    site, root = library_house
    t0 = time.process_time()
    scenario = get_scenario(name, SEED, utc_offset_hours=site.utc_offset_hours)
    truth_dir, run_dir = root / name / "truth", root / name / "run"
    synth.write_truth(scenario, truth_dir)
    summary = replay(site, run_dir, synthetic=name, seed=SEED, cache_dir=root / "cache")
    assert summary.frames == scenario.n_frames
    scene = Scene(name, summary.frames, truth_dir, run_dir, evaluate(truth_dir, run_dir), time.process_time() - t0)
    print(f"\n{scene.describe()}")
    return scene


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    "dinner_visit",
    pytest.param("hotspot_dwell", marks=pytest.mark.xfail(
        strict=True,
        reason="the dwell on the sofa starts 38 frames (2.5 s) after the truth's frame 1073, outside the "
        "+-30 window: the truth counts the stay from the end of the walk, before the turn and the "
        "sit-down, while the seated track moves 0.8 m back onto the seat and the 10 s still window "
        "counts from there (the other three dwell starts -17/-18, the four ends -23..+17, all matched)",
    )),
])
def test_library_scenario_dwells_and_visits_match_the_truth(name, library_house):
    scene = replay_library(name, library_house)
    check_events_match_truth(scene, LIBRARY[name], only=LIBRARY[name] + ALARM_KINDS)


def _lying(x0_m: float, x1_m: float) -> TrackEstimate:
    """A confirmed target lying still at (3.0, 2.5) on the floor whose blob spans x0..x1 m (0.4 m wide, 0.3 m high)."""
    bbox = np.array([[x0_m, 2.3, 0.0], [x1_m, 2.7, 0.3]])
    blob = Blob(x=(x0_m + x1_m) / 2, y=2.5, z_top_m=0.3, volume_voxels=100, ijk=np.zeros((0, 3), np.int32),
                footprint=np.zeros((0, 2), np.int32), height_profile=np.zeros(4, np.int32), bbox_m=bbox, voxel_m=0.05)
    return TrackEstimate(id=1, x=3.0, y=2.5, z_top_m=0.3, volume_m3=0.05, reliability=1.0, confirmed=True, age_frames=50,
                         vx=0.0, vy=0.0, height_profile=np.zeros(4, np.int32), blob=blob, still=True, alpha_m=0.3,
                         stamp_ns=0)


def test_a_held_body_keeps_its_hold_where_its_carve_shrinks(house):
    """Someone lies still on the floor, their blob 1.8 m long (x 2.1-3.9 m); then only the end by their
    head is carved (x 2.6-3.2 m: the rest faded from the masks). Their hold keeps covering the whole
    body they had while they stay held (every camera's box the same as on the first frame), for up to
    1 m from their place; held afresh, with no earlier body, it covers only the piece and the square of
    ``hold_radius_m`` around them."""
    cameras, make_site, root = house
    pipeline = FusionPipeline.from_site(make_site(), cameras=cameras, cache_dir=root / "cache", seed=SEED)
    whole = pipeline.hold_regions([_lying(2.1, 3.9)])
    assert pipeline.hold_regions([_lying(2.6, 3.2)]) == whole
    assert pipeline.hold_regions([_lying(2.6, 3.2)]) == whole
    pipeline.hold_regions([])  # nobody held: what they covered is forgotten
    piece = pipeline.hold_regions([_lying(2.6, 3.2)])
    area = {cam: sum((b[2] - b[0]) * (b[3] - b[1]) for b in boxes) for cam, boxes in piece.items()}
    assert all(area[cam] < sum((b[2] - b[0]) * (b[3] - b[1]) for b in whole[cam]) for cam in whole if whole[cam])
    far = pipeline.hold_regions([_lying(1.0, 5.0)])  # a blob reaching 2 m either way is held as it is carved now
    kept = pipeline.hold_regions([_lying(2.6, 3.2)])
    pipeline.hold_regions([])
    assert kept != far and kept == pipeline.hold_regions([_lying(2.0, 4.0)])  # what it covered, cut at 1 m from (3.0, 2.5)
