"""A restarted fusion server forgets no one (:mod:`fusion_server.snapshot`).

The snapshot travels as the live server keeps it (text in the event store), and the
restart is played through the pipeline on rendered, segmented frames of the synthetic
house: a person walks in, falls and lies still; the first server stops 3 s after the fall
(its last snapshot at most a second older), the cameras go on for 5 s holding the boxes in
force as the workers do while no server is live, and a second server starts from the
snapshot. Judged against the truth's fall and the site's ``long_lie_s``, and against the
same restart without the snapshot, which must not do as well (the test can fail).
"""

from __future__ import annotations

import math

import pytest

import synth
from camera_worker.segmentation import ForegroundSegmenter, window_frames_for
from common.site import site_from_dict
from fusion_server.event_store import EventStore
from fusion_server.pipeline import FusionPipeline
from fusion_server.snapshot import SNAPSHOT_EVERY_S, Snapshot, Watched
from synth import ScenarioSpec, SyntheticCamera, get_scenario
from synth.behaviour import Fall, PersonScript, Walk, Wait

SEED = 0
HALF = 0.5
SEGMENTER_PX = {"open_px": 2, "close_px": 4, "min_area_px": 100}
LONG_LIE_S = 10.0
STOP_AFTER_FALL_S = 3.0
DOWN_S = 5.0


def test_a_snapshot_survives_the_event_store_and_refuses_what_it_cannot_read(tmp_path):
    snap = Snapshot(stamp_ns=123, people=(
        Watched(label=2, x=1.5, y=2.25, posture="lying", name="Ada", model=None,
                fall={"low_since_ns": 100, "floor_since_ns": 110, "drop": {"fall_stamp_ns": 95}, "drop_series": 4,
                      "fall_emitted": True, "long_lie_emitted": False, "upright_ns": 5}),),
        holds={"cam1": [(1, 2, 3, 4)], "cam2": []})
    with EventStore(tmp_path / "events.sqlite") as store:
        assert store.load_snapshot() is None
        store.save_snapshot(snap.stamp_ns, snap.to_json())
        store.save_snapshot(snap.stamp_ns, snap.to_json())     # one kept, the newest
    with EventStore(tmp_path / "events.sqlite") as store:      # read back by the next process
        stamp, body = store.load_snapshot()
    assert stamp == 123 and Snapshot.from_json(body) == snap
    for bad, why in (("{", "snapshot: "), ('{"format": 9}', "format must be 1"),
                     ('{"format": 1, "stamp_ns": 1, "holds": {}}', "missing field 'people'"),
                     ('{"format": 1, "stamp_ns": 1, "holds": {}, "people": [{"label": 0, "x": 1, "y": 1}]}',
                      "positive label")):
        with pytest.raises(ValueError, match=why):
            Snapshot.from_json(bad)


def _fall_and_lie() -> ScenarioSpec:
    return ScenarioSpec(
        "restart_fall", "Walks to the middle of the room, falls forward and lies still.", 22.0,
        (PersonScript(1, (Walk(("centre",)), Wait(1.0), Fall("forward"), Wait(30.0)), start=(4.2, 4.2, -90.0)),),
    )


@pytest.fixture(scope="module")
def fallen(tmp_path_factory, lut_cache):
    """The scene's site, cameras, scenario and folder (with the run's carving-table cache)."""
    root = tmp_path_factory.mktemp("restart")
    (root / "cache").symlink_to(lut_cache, target_is_directory=True)
    cameras = synth.default_cameras(scale=HALF)
    base = synth.default_site(root / "site", cameras=cameras)
    raw = base.model_dump(mode="json", exclude={"base_dir"})
    raw["carving"]["mask_scale"] = 1.0
    raw["events"] = {"long_lie_s": LONG_LIE_S}
    site = site_from_dict(raw, base_dir=base.base_dir, source="synthetic house")
    scenario = get_scenario(_fall_and_lie(), SEED, utc_offset_hours=site.utc_offset_hours)
    return site, cameras, scenario, root


def _pipeline(fallen) -> FusionPipeline:
    site, cameras, _, root = fallen
    return FusionPipeline.from_site(site, cameras=cameras, cache_dir=root / "cache", seed=SEED)


def _play(fallen, *, restore: bool) -> dict:
    """The first server to 3 s after its fall, 5 s with no server, then a second one (from the
    first's last snapshot when ``restore``): what each raised and when, and who it tracked."""
    site, cameras, scenario, root = fallen
    fps = scenario.fps
    sources = {cam: SyntheticCamera(scenario, cam, SEED, camera=camera) for cam, camera in cameras.items()}
    segmenters = {}
    for cam, source in sources.items():
        segmenters[cam] = ForegroundSegmenter(window_frames=window_frames_for(fps), **SEGMENTER_PX)
        for i in range(source.n_background_frames):
            segmenters[cam].learn(source.background_frame(i))
    first, second = _pipeline(fallen), None
    events, tracks = [], {}
    holds: dict[str, list] = {}
    snap_json, snap_stamp, stop_frame, back_frame, fall_stamp = None, -math.inf, None, None, None
    for i in range(scenario.n_frames):
        masks = {cam: segmenters[cam].apply(source.frame(i)[0], holds=holds.get(cam, ()))[0]
                 for cam, source in sources.items()}
        stamp = scenario.stamp_ns(i)
        if stop_frame is not None and i < back_frame:
            continue   # no server: the workers hold the boxes in force when it went
        server = first if stop_frame is None else second
        fused = server.step(masks, stamp, i)
        # the workers take the first server's holds; the boxes held while no server was live last one
        # time-to-live (2 s) after the second comes, unless it sends its own
        if server is first or any(fused.holds.values()) or i >= back_frame + 2 * fps:
            holds = fused.holds
        events += [(i, server is first, e) for e in fused.events]
        tracks[i] = [(t.id, t.posture) for t in fused.tracks]
        if server is first:
            if fall_stamp is None and any(e.kind == "fall" for e in fused.events):
                fall_stamp = stamp
            if stamp - snap_stamp >= SNAPSHOT_EVERY_S * 1e9:
                snap_json, snap_stamp = first.snapshot().to_json(), stamp
            if fall_stamp is not None and stamp - fall_stamp >= STOP_AFTER_FALL_S * 1e9:
                stop_frame, back_frame = i, i + int(round(DOWN_S * fps))
                second = _pipeline(fallen)
                if restore:
                    second.restore(Snapshot.from_json(snap_json))
    return {"events": events, "tracks": tracks, "stop": stop_frame, "back": back_frame, "fps": fps,
            "fall_stamp": fall_stamp, "scenario": scenario}


@pytest.mark.slow
def test_a_restarted_server_finds_the_person_on_the_floor_and_raises_the_long_lie_at_its_time(fallen):
    run = _play(fallen, restore=True)
    fps, back = run["fps"], run["back"]
    assert run["fall_stamp"] is not None and run["stop"] is not None, "the first server saw no fall"
    falls = [(i, first, e) for i, first, e in run["events"] if e.kind == "fall"]
    lies = [(i, first, e) for i, first, e in run["events"] if e.kind == "long_lie"]
    (fall,) = falls
    label = fall[2].track
    assert fall[1], "the fall is the first server's"           # raised once, not again after the restart
    # found again within 2 s of the restart, under the label the first server gave
    found = [i for i in range(back, back + int(2 * fps)) if any(t == (label, "lying") for t in run["tracks"].get(i, []))]
    assert found, {i: run["tracks"].get(i) for i in range(back, back + int(2 * fps))}
    # one long lie, the second server's, at the first one's fall + long_lie_s
    (lie,) = lies
    assert not lie[1] and lie[2].track == label
    since = lie[2].details["lying_since_ns"]
    assert since == fall[2].details["fall_stamp_ns"]
    assert (lie[2].stamp_ns - since) * 1e-9 == pytest.approx(LONG_LIE_S, abs=0.2)
    assert not [e for _, first, e in run["events"] if not first and e.kind in ("enter", "fall")]


@pytest.mark.slow
def test_without_the_snapshot_the_long_lie_is_late_or_someone_else_s(fallen):
    """The control: the same restart from nothing (what the server did before) finds a stranger
    lying there and counts the long lie from the restart."""
    run = _play(fallen, restore=False)
    (fall,) = [e for _, first, e in run["events"] if e.kind == "fall"]
    lies = [e for _, first, e in run["events"] if e.kind == "long_lie"]
    assert not lies or lies[0].track != fall.track or \
        (lies[0].stamp_ns - fall.details["fall_stamp_ns"]) * 1e-9 > LONG_LIE_S + 1.0
