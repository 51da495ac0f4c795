"""``voxelwatch demo``: the synthetic house as real processes on loopback.

slow: ``--secure`` end to end: certificates made in the output folder, the
router (the demo process) enforcing the site's access control over mutual
TLS, five camera workers and the fusion server as processes with their own
certificates, and the demo listening as a reader.
"""

from __future__ import annotations

import io
import json
import re
import shutil
import stat
from collections import Counter
from pathlib import Path

import pytest

import synth
from common import messages
from common.certs import read_common_name
from voxelwatch.demo import run_demo
from common.site import load_site
from evaluation import evaluate, read_events
from tests.procs import ROOT


@pytest.fixture
def heard(monkeypatch):
    """frame -> cameras of every fused frame the demo's reader hears on the tracks key (each
    fused frame set is published there, with the cameras whose masks it fused, even when it
    holds no track). The demo's own callback still runs: this only records what it is given."""
    from voxelwatch import demo

    frames: dict[int, list[str]] = {}
    real = demo._on_tracks

    def on_tracks(sample, live, t_launch):
        try:
            msg = messages.decode(sample.payload.to_bytes(), messages.TrackFrame)
        except messages.WireError:
            pass
        else:
            frames[msg.frame] = list(msg.cameras)
        real(sample, live, t_launch)

    monkeypatch.setattr(demo, "_on_tracks", on_tracks)
    return frames


def _cut(src: Path, dst: Path, frames: set[int]) -> None:
    """``src``'s tracks.csv rows of ``frames`` only, and its events, into ``dst``."""
    dst.mkdir(parents=True)
    lines = (src / "tracks.csv").read_text(encoding="utf-8").splitlines()
    kept = [lines[0]] + [line for line in lines[1:] if int(line.split(",", 1)[0]) in frames]
    (dst / "tracks.csv").write_text("\n".join(kept) + "\n", encoding="utf-8")
    shutil.copy(src / "events.jsonl", dst / "events.jsonl")


def score_fused(scenario, demo_dir: Path, frames: set[int], out: Path) -> dict:
    """The demo's run scored against the scenario's truth on ``frames`` only (both cut to them).

    A live run plays each camera on the host clock: a worker that falls behind skips the frames it
    is late for, and the fusion server drops the oldest frame sets it cannot keep up with, so on a
    loaded machine frames of the scenario are never fused, and a worker that skipped can play past
    the demo's last frame. The truth is written again from the same scenario up to the last frame
    fused (the demo's own truth, to its frame count, is checked to be the same rows)."""
    full = out / "truth-all"
    n_demo = json.loads((demo_dir / "truth" / "meta.json").read_text(encoding="utf-8"))["n_frames"]
    synth.write_truth(scenario, full, n_frames=min(scenario.n_frames, max(n_demo, max(frames) + 1)))
    own = (demo_dir / "truth" / "tracks.csv").read_text(encoding="utf-8").splitlines()
    again = (full / "tracks.csv").read_text(encoding="utf-8").splitlines()
    assert own == again[:1] + [line for line in again[1:] if int(line.split(",", 1)[0]) < n_demo]
    _cut(full, out / "truth", frames)
    shutil.copy(full / "meta.json", out / "truth" / "meta.json")
    _cut(demo_dir / "run", out / "run", frames)
    return evaluate(out / "truth", out / "run")


def scores(scenario, demo_dir: Path, heard: dict[int, list[str]], cameras: list[str], tmp_path: Path,
           text: str) -> tuple[dict, dict]:
    """(the tracking score on the frames fused, figures to print)."""
    score = score_fused(scenario, demo_dir, set(heard), tmp_path)["tracking"]
    demo_mota = re.search(r"MOTA (-?[\d.]+) %", text)
    measured = {
        "frames_fused_heard": len(heard), "last_frame": max(heard, default=None),
        "with_every_camera": sum(set(cams) == set(cameras) for cams in heard.values()),
        "first_frame_of_each_camera": {c: min((f for f, cams in heard.items() if c in cams), default=None)
                                       for c in cameras},
        "demo_mota_on_every_truth_frame": demo_mota and round(float(demo_mota.group(1)) / 100, 3),
        "mota_on_frames_fused": round(score["mota"], 3), "idf1_on_frames_fused": round(score["idf1"], 3),
        "fp": score["fp"], "fn": score["fn"], "id_switches": score["id_switches"],
    }
    print("measured:", measured)
    return score, measured


def events_heard(text: str) -> Counter:
    """Event kinds the demo printed as its reader heard them (one line each: ``[  t s] KIND ...``)."""
    return Counter(m.lower() for m in re.findall(r"\[\s*-?[\d.]+ s\] (\S+)", text))


def events_written(demo_dir: Path) -> Counter:
    """Event kinds the fusion server wrote (each written before it is published)."""
    return Counter(e.kind for e in read_events(demo_dir / "run" / "events.jsonl"))


@pytest.mark.slow
def test_secure_demo_tracks_the_person_over_tls_and_access_control(tmp_path, monkeypatch, heard, lut_cache,
                                                                    machine_to_itself):
    """Masks, tracks and events cross a TLS router enforcing access control, and the person is
    tracked: scored against the truth on the frames the fusion server fused (as its reader heard
    them on the tracks key), not on every frame of the scenario.

    The demo plays each camera in real time on the host clock. On a loaded machine (two cores,
    another test session running) a worker that falls behind skips the frames it is late for, the
    fusion server drops the oldest frame sets it cannot keep up with (32-66 here) and fuses others
    without a camera whose mask came too late, and a worker that skipped plays on past the demo's
    150th frame. The demo's own figure counts every frame never fused as missed people and every
    track past frame 149 as false: it read 89.3 % on a clean clone with two tests at once, and
    between -27 % and +22 % here, runs whose frames fused scored MOTA 0.896 to 0.977. Scoring
    what was fused keeps the bound of an unloaded run (where every frame is fused the two are
    the same) without loosening it. What it does not remove: when the server drops sets in long
    runs, the tracker, fed frames up to a second apart, confirms a person late. In the run that
    scored 0.896 only frames 64, 78, 79, 87 and 88 of the 42 as the person came in were fused,
    and 10 of the 96 person-frames scored were missed there and just after. Which events the
    pipeline raises depends on the same frames (the entrance at frame 47 was missed whenever its
    sets were dropped), so what is held of events is that the reader heard every event the
    fusion server stored."""
    monkeypatch.setenv("PYTHONPATH", str(ROOT))  # the workers and the server run this tree's code
    out = io.StringIO()
    code = run_demo(out_dir=tmp_path / "demo", frames=150, secure=True, stream=out, cache_dir=lut_cache)
    text = out.getvalue()
    assert code == 0, text
    assert re.search(r"zenoh router tls/localhost:\d+ \(TLS, access control", text), text
    site = load_site(tmp_path / "demo" / "site" / "site.toml")
    assert site.zenoh.tls is not None and site.zenoh.tls.access_control
    certs = tmp_path / "demo" / "certs"
    assert read_common_name(certs / "cam3.pem") == "camera-cam3"
    assert all(stat.S_IMODE(k.stat().st_mode) == 0o600 for k in certs.glob("*-key.pem"))
    scenario = synth.get_scenario(synth.DEFAULT_SCENARIO, 0, utc_offset_hours=site.utc_offset_hours)
    fused = int(re.search(r"summary: (\d+) fused frames", text).group(1))
    assert fused >= 100, text  # masks crossed the router from every camera to the fusion server
    score, measured = scores(scenario, tmp_path / "demo", heard, site.camera_ids, tmp_path / "score", text)
    assert all(f is not None for f in measured["first_frame_of_each_camera"].values()), measured
    written = events_written(tmp_path / "demo")
    assert written and events_heard(text) == written, (text, written)  # every event crossed the router
    assert score["mota"] >= 0.90, measured


@pytest.mark.slow
def test_demo_of_a_mixed_rig_carries_masks_and_range_from_separate_workers(tmp_path, monkeypatch, heard,
                                                                           machine_to_itself):
    """World 5 (tuning seed) with a depth and a thermal camera: each worker process renders and
    segments its own modality, and the depth camera's range crosses zenoh with its masks.

    Scored, as the secure demo is, on the frames the fusion server fused: on a loaded machine
    the demo's own figure against every truth frame read 58.9 % on a clean clone, and -32 % and
    +23 % here, runs whose frames fused scored MOTA 0.88 and 0.78 (sets missing a camera whose
    mask came too late are fused and scored as they are). The range is held per set, for the
    same reason:
    every fused set that holds the depth camera's mask carries its range (here 100 of 172 sets
    held it, the depth worker having fallen behind; the bound it replaces, range in 80 % of all
    sets, failed with 115 of 209 when the workers joined 1-12 s after the demo's 10 s start).

    Played at half real time (``speed=0.5``): at full speed the four workers' rendering and
    segmenting, the router and the server need more than this 2-core machine has, and the depth
    worker, the costliest, fell behind (sets with every camera 18 to 94 of about 150, MOTA on
    them 0.57 to 0.88 over the runs of 2026-11-27/28; 0.70 failed a CI run at 0.57, and 20 sets
    with every camera failed the next at 18). At half speed 142, 143 and 144 of 150 sets held every
    camera, MOTA on them 0.88, 0.87 and 0.79 (the same 150 frames replayed from their true masks: 0.83).
    Left to the tracker: the person who starts a step in front of the depth camera is followed by
    a track that stays in the corner for 1-3 s, live and replayed alike."""

    from synth.world import random_world

    monkeypatch.setenv("PYTHONPATH", str(ROOT))
    out = io.StringIO()
    code = run_demo(world="random", seed=5, sensors="mixed", out_dir=tmp_path / "demo", frames=150, speed=0.5,
                    stream=out)
    text = out.getvalue()
    assert code == 0, text
    assert "cam1 depth, cam2 thermal" in text, text
    site = load_site(tmp_path / "demo" / "site" / "site.toml")
    assert (site.camera("cam1").modality, site.camera("cam2").modality) == ("depth", "thermal")
    log = (tmp_path / "demo" / "logs" / "fusion.log").read_text()
    fused, ranged = map(int, re.search(r"(\d+) frames fused \((\d+) with range\)", log).groups())
    assert fused >= 100, log[-2000:]
    scenario = random_world(5, sensors="mixed").scenario
    score, measured = scores(scenario, tmp_path / "demo", heard, site.camera_ids, tmp_path / "score", text)
    with_depth = sum("cam1" in cams for cams in heard.values())
    # the tracking, judged on the sets fused with every camera's mask: what the mixed rig gives the server
    # (on a loaded machine the depth worker, the costliest, falls behind and sets go without its mask)
    whole = {f for f, cams in heard.items() if set(cams) == set(site.camera_ids)}
    whole_score = score_fused(scenario, tmp_path / "demo", whole, tmp_path / "score-whole")["tracking"]
    print("measured:", {"fused": fused, "with_range": ranged, "heard_with_depth_camera": with_depth,
                        "sets_with_every_camera": len(whole), "mota_on_them": round(whole_score["mota"], 3)})
    assert all(f is not None for f in measured["first_frame_of_each_camera"].values()), measured
    assert len(heard) == fused and ranged == with_depth > 0, log[-2000:]
    assert len(whole) >= 0.8 * fused, measured
    assert whole_score["mota"] >= 0.75, (measured, whole_score)
