"""Randomised worlds: deterministic per seed, masks that agree with the bodies, and the commands taking them unchanged.

Every world here comes from the tuning seeds (0-999); the evaluation seeds are
only ever run by ``voxelwatch eval --suite --world random`` for the README.

slow: the ``synth``, ``replay`` and ``eval`` commands on one world (the world
suite's own test runs the same stages in the default run).
"""

from __future__ import annotations

import dataclasses
import filecmp
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.camera import Camera
from common.site import load_site
from synth.body import pose_body
from synth.degrade import MaskFaults
from synth.render import CameraRenderer, raycast_room
from synth.scenario import Scenario
from synth.crowd import STEP_OUT_AWAY_S
from synth.truth import derive_truth
from synth.world import (
    ADULT_M, EVALUATION_SEEDS, TUNING_SEEDS, random_world, render_masks, seed_set, write_world,
)

SYNTHETIC_SEEDS = (2, 9, 10, 11, 24, 33)
"""Drawn rigs: high corners with a fisheye, L-shaped rooms, level walls, up to 11 people, one video world."""


VOXELWATCH = Path(sys.executable).with_name("voxelwatch")


def voxelwatch(*args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess:
    if not VOXELWATCH.is_file():
        pytest.skip(f"the voxelwatch command is not installed beside {sys.executable}")
    return subprocess.run([str(VOXELWATCH), *args], capture_output=True, text=True, timeout=timeout_s, check=False)


def test_seed_sets_are_declared_once_and_apart():
    assert set(TUNING_SEEDS).isdisjoint(range(EVALUATION_SEEDS.start, EVALUATION_SEEDS.start + 5000))
    assert seed_set(0) == seed_set(999) == "tuning"
    assert seed_set(1000) == "evaluation"
    with pytest.raises(ValueError, match="seed"):
        seed_set(-1)
    with pytest.raises(ValueError, match="seed"):
        random_world(-3)


def test_the_same_seed_gives_the_same_world_and_another_seed_another():
    a, b, c = random_world(11), random_world(11), random_world(12)
    assert a.summary() == b.summary()
    assert a.spec == b.spec
    assert all(np.array_equal(a.cameras[k].R, b.cameras[k].R) for k in a.cameras)
    assert a.summary() != c.summary()


def test_the_same_seed_writes_the_same_files(tmp_path):
    for name in ("a", "b"):
        write_world(random_world(28), tmp_path / name, frames=30)
    cmp = filecmp.dircmp(tmp_path / "a", tmp_path / "b")
    mismatched = []

    def walk(d):
        mismatched.extend(f"{d.left}/{f}" for f in d.diff_files + d.left_only + d.right_only)
        for sub in d.subdirs.values():
            walk(sub)

    walk(cmp)
    assert not mismatched
    assert len(list((tmp_path / "a").glob("cam*/masks/*.png"))) == 30 * len(random_world(28).cameras)


def test_mask_worlds_write_the_colour_of_the_people_beside_masks_left_as_they_were(tmp_path):
    world = random_world(3)  # one person; cam5 is two frames late
    n = 30
    out = write_world(world, tmp_path / "w", frames=n)
    sc = world.scenario
    for cam_id in ("cam1", "cam5"):
        # the masks are those of render_masks (written from the colour render's person ids)
        expected = render_masks(world, cam_id, range(n))
        for i in range(n):
            got = cv2.imread(str(out.out_dir / cam_id / "masks" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
            np.testing.assert_array_equal(got, expected[i], err_msg=f"{cam_id} frame {i}")
        cap = cv2.VideoCapture(str(out.out_dir / cam_id / "colour.avi"))
        frames = []
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(frame)
        cap.release()
        cam = world.cameras[cam_id].scaled(world.mask_scale)
        assert len(frames) == n and frames[0].shape == (cam.height, cam.width, 3)
        # the person is drawn where the true silhouette (no lag) is, the empty room elsewhere
        renderer = CameraRenderer(cam, world.room, seed=world.seed, shadows=False)
        for i in (0, n - 1):
            person = render_masks(world, cam_id, [i], faults=False)[0] > 0
            diff = np.abs(frames[i].astype(int) - renderer.background(sc.gain(i), (0, i)).astype(int)).sum(axis=2)
            assert person.sum() > 50
            assert np.median(diff[person]) > 30 and np.median(diff[~person]) < 10, (cam_id, i)
    assert not (out.out_dir / "cam1" / "video.avi").exists()


@pytest.mark.slow
def test_worlds_span_the_rooms_rigs_and_people_asked_for():
    worlds = [random_world(s).summary() for s in range(40)]
    rigs = {w["rig"] for w in worlds}
    assert rigs == {"high-corners", "level-walls", "real-lab", "real-pets"}
    drawn = [w for w in worlds if not w["rig"].startswith("real")]
    assert {w["room"]["shape"] for w in drawn} == {"rect", "L"}
    assert {w["fisheye"] for w in drawn} == {True, False}
    for w in drawn:
        x, y, h = w["room"]["size_m"]
        assert 3.0 <= x <= 12.0 and 3.0 <= y <= 10.0 and 2.3 <= h <= 3.0
        assert 3 <= w["cameras"] <= 8
    assert all(1 <= w["people"] <= 12 for w in worlds)
    assert max(w["people"] for w in worlds) >= 10 and min(w["people"] for w in worlds) == 1
    assert {w["media"] for w in worlds} == {"masks", "video"}
    assert all(w["people"] <= 6 for w in worlds if w["media"] == "video")
    behaviours = set().union(*(w["behaviours"] for w in worlds))
    assert {"group_walk", "cross", "talk_cluster", "hug", "sit_side_by_side", "help_fallen", "fall", "sit",
            "kneel", "bend", "enter", "leave"} <= behaviours
    assert {"1280x720", "320x240"} <= set().union(*(w["resolutions"] for w in worlds))
    assert any(w["children"] for w in worlds)


@pytest.mark.slow
def test_one_world_in_four_dresses_every_adult_alike_and_changes_nothing_else():
    dress = [random_world(s).dress for s in range(60)]
    assert set(dress) == {"alike", "distinct"} and 8 <= dress.count("alike") <= 24
    world = random_world(29)  # level walls, seven people, one a child
    assert world.summary()["dress"] == "alike"
    shapes = {p.person_id: p.shape for p in world.scenario.people}
    adults = [s for s in world.spec.people if s.height_m >= ADULT_M]
    assert len(adults) >= 2 and len(adults) < len(world.spec.people)
    assert len({(shapes[s.person_id].shirt_bgr, shapes[s.person_id].trousers_bgr, shapes[s.person_id].long_sleeves)
                for s in adults}) == 1
    assert len({shapes[s.person_id].skin_bgr for s in adults} | {shapes[s.person_id].hair_bgr for s in adults}) > 1
    assert all(s.clothes is None for s in world.spec.people if s.height_m < ADULT_M)
    # the same people, doing the same, as when dressed as they would be: only the clothes differ
    plain = Scenario(dataclasses.replace(world.spec, people=tuple(dataclasses.replace(s, clothes=None)
                                                                  for s in world.spec.people)), world.seed,
                     room=world.room)
    for a, b in zip(plain.states, world.scenario.states):
        np.testing.assert_array_equal(a["q"], b["q"])
    assert [p.shape.height_m for p in plain.people] == [shapes[s.person_id].height_m for s in world.spec.people]


def test_people_step_out_through_a_door_and_come_back_after_a_pause():
    world = random_world(4)
    summary = world.summary()
    assert summary["step_outs"] == 1 and "step_out" in summary["behaviours"] and world.room.doors
    pid, = world.cast.step_outs
    fps = world.scenario.fps
    events = [e for e in derive_truth(world.scenario).events if e.track == pid and e.kind in ("enter", "exit")]
    kinds = [e.kind for e in events]
    k = kinds.index("exit")
    assert kinds[k + 1] == "enter"
    gap_s = (events[k + 1].frame - events[k].frame) / fps
    # away 3-20 s, plus the walks between the volume's edge and the corridor
    assert STEP_OUT_AWAY_S[0] < gap_s < STEP_OUT_AWAY_S[1] + 8.0
    # back for long enough to be seen again
    assert world.scenario.n_frames - events[k + 1].frame > 3 * fps


@pytest.mark.slow  # forty worlds drawn: about 10 s
def test_about_a_third_of_the_worlds_have_someone_step_out():
    shares = [bool(random_world(s).cast.step_outs) for s in range(40)]
    assert 6 <= sum(shares) <= 20


def test_people_of_a_real_rig_step_out_over_an_open_edge_and_back(data_dir):
    world = random_world(6, data_dir=data_dir)
    assert world.rig == "real-lab" and not world.room.doors and world.cast.step_outs == (1,)
    kinds = [e.kind for e in derive_truth(world.scenario).events if e.track == 1 and e.kind in ("enter", "exit")]
    assert kinds[:2] == ["exit", "enter"]


@pytest.mark.parametrize("seed", SYNTHETIC_SEEDS)
def test_walking_people_stay_off_the_furniture(seed):
    world = random_world(seed)
    room = world.room
    solid = [b for b in room.boxes if b.min_m[2] < 1.0]
    sc = world.scenario
    for person, st in zip(sc.people, sc.states):
        walking = st["present"] & st["moving"]
        xy = st["xy"][walking]
        for box in solid:
            inside = ((xy[:, 0] > box.min_m[0] + 0.05) & (xy[:, 0] < box.max_m[0] - 0.05)
                      & (xy[:, 1] > box.min_m[1] + 0.05) & (xy[:, 1] < box.max_m[1] - 0.05))
            assert not inside.any(), f"world {seed}: person {person.person_id} walks through {box.name}"
        # inside the room, or in a doorway's corridor
        out = ~((xy[:, 0] >= 0) & (xy[:, 0] <= room.size_m[0]) & (xy[:, 1] >= 0) & (xy[:, 1] <= room.size_m[1]))
        for d in room.doors:
            out &= ~((xy[:, 0] >= d.corridor_min_m[0]) & (xy[:, 0] <= d.corridor_max_m[0])
                     & (xy[:, 1] >= d.corridor_min_m[1]) & (xy[:, 1] <= d.corridor_max_m[1]))
        assert not out.any(), f"world {seed}: person {person.person_id} walks through a wall"


@pytest.mark.slow  # the renderer against brute-force ray casting of the house is in the default run (test_synth_render)
@pytest.mark.parametrize("seed", (10, 24))
def test_true_silhouettes_match_rays_cast_at_the_bodies(seed):
    """Oracle: a pixel is a person in the true mask exactly when its ray meets a body (Body.intersect)
    before the room or its furniture (raycast_room), each computed on its own."""
    world = random_world(seed)
    frames = (60, 200, 400)
    for cam_id, cam in world.cameras.items():
        small = cam.scaled(world.mask_scale)
        masks = render_masks(world, cam_id, frames, faults=False)
        for f, mask in zip(frames, masks):
            bodies = [pose_body(p.shape, st["q"][f], p.person_id)
                      for p, st in zip(world.scenario.people, world.scenario.states) if st["present"][f]]
            expected = _ray_cast_mask(small, world.room, bodies)
            differ = np.count_nonzero((mask > 0) != expected)
            both = max(1, np.count_nonzero(expected) + np.count_nonzero(mask))
            # only rays grazing a body's edge may disagree (float32 against float64)
            assert differ <= 0.01 * both + 3, f"world {seed} {cam_id} frame {f}: {differ} pixels differ"


@pytest.mark.parametrize("seed", [pytest.param(s, marks=pytest.mark.slow) for s in SYNTHETIC_SEEDS])
def test_every_person_projects_inside_the_mask_of_every_camera_that_sees_them(seed):
    """The middle of each person's trunk, where a camera's ray to it meets that body first (not a wall,
    furniture or somebody else), is foreground within a pixel in that camera: always in the true masks,
    and in the degraded masks except where the camera is dark or runs late."""
    world = random_world(seed)
    sc = world.scenario
    frames = np.linspace(0, sc.n_frames - 1, 6).round().astype(int)
    checked = hit_true = hit_degraded = checked_degraded = 0
    for cam_id, cam in world.cameras.items():
        small = cam.scaled(world.mask_scale)
        true = render_masks(world, cam_id, frames, faults=False)
        faults = world.faults.get(cam_id, MaskFaults())
        degraded = render_masks(world, cam_id, frames)
        for f, t_mask, d_mask in zip(frames, true, degraded):
            bodies = [pose_body(p.shape, st["q"][f], p.person_id) for p, st in zip(sc.people, sc.states)
                      if st["present"][f]]
            for body in bodies:
                centre = body.centers_m[1]  # the trunk's middle part
                uv, ok = small.project(centre[None])
                if not ok[0]:
                    continue
                ray = centre - small.center
                t_body = [b.intersect(small.center, ray[None])[0][0] for b in bodies]
                if int(np.argmin(t_body)) != bodies.index(body):
                    continue  # somebody else is in front
                wall = raycast_room(world.room, small.center, (ray / np.linalg.norm(ray))[None]).t[0]
                if wall < np.linalg.norm(ray):
                    continue  # furniture or a wall is in front
                # within a pixel of the projection (the pixel grid rounds a thin part away)
                u, v = np.round(uv[0]).astype(int)
                near = (slice(max(v - 1, 0), v + 2), slice(max(u - 1, 0), u + 2))
                checked += 1
                hit_true += t_mask[near].any()
                late = faults.lag_frames > 0
                dark = faults.dark is not None and faults.dark[0] <= f <= faults.dark[1]
                if not (late or dark):
                    checked_degraded += 1
                    hit_degraded += d_mask[near].any()
    assert checked > 0
    assert hit_true == checked, f"world {seed}: {checked - hit_true} of {checked} trunk centres outside the true mask"
    # a hole in the clothes may fall on the very pixel now and then
    assert hit_degraded >= 0.9 * checked_degraded
    print(f"world {seed}: {checked} visible trunk centres all in the true masks; {hit_degraded} of "
          f"{checked_degraded} in the degraded masks of cameras neither dark nor late")


def test_real_rigs_are_read_from_the_recordings_as_they_are(data_dir, tmp_path):
    lab = random_world(6, data_dir=data_dir)
    assert lab.rig == "real-lab" and lab.refs["cam1"].format == "opencv"
    out = write_world(lab, tmp_path / "lab", frames=5)
    site = load_site(out.site)
    spec = site.camera("cam1")
    assert (spec.format, spec.units, spec.up) == ("opencv", "mm", "-z")
    # the site file's camera equals the one the world was drawn with
    assert np.allclose(site.load_camera("cam1").center, lab.cameras["cam1"].center, atol=1e-9)
    # all four cameras see the middle of the monitored area, 1 m up
    (x0, y0), (x1, y1) = lab.room.volume_rect_m
    mid = np.array([[(x0 + x1) / 2, (y0 + y1) / 2, 1.0]])
    assert all(cam.project(mid)[1][0] for cam in site.load_cameras().values())
    assert site.volume.open_edges
    pets = random_world(12, data_dir=data_dir)
    assert pets.rig == "real-pets" and len(pets.cameras) == 7 and pets.refs["view1"].format == "pets-tsai"


def test_a_missing_recording_folder_is_named(tmp_path):
    with pytest.raises(ValueError, match="lab4cam-seated.*not found"):
        random_world(6, data_dir=tmp_path)


@pytest.mark.slow
def test_synth_replay_and_eval_take_a_random_world_unchanged(tmp_path):
    world_dir, run_dir = tmp_path / "world", tmp_path / "run"
    r = voxelwatch("synth", "--world", "random", "--seed", "7", "--out", str(world_dir), "--frames", "45")
    assert r.returncode == 0, r.stderr
    assert "world-7 (tuning seed)" in r.stdout
    meta = json.loads((world_dir / "truth" / "meta.json").read_text())
    assert meta["world"]["seed"] == 7 and meta["n_frames"] == 45
    r = voxelwatch("replay", "--site", str(world_dir / "site.toml"), "--input", str(world_dir), "--out",
                   str(run_dir), "--quiet", "--cache-dir", str(tmp_path / "cache"))
    assert r.returncode == 0, r.stderr
    assert "45 frame sets" in r.stdout
    r = voxelwatch("eval", "--truth", str(world_dir), "--run", str(run_dir))
    assert r.returncode == 0, r.stderr
    assert "by people present" in r.stdout and "MOTA" in r.stdout
    print(r.stdout)


def test_synth_random_refuses_house_options(tmp_path):
    r = voxelwatch("synth", "--world", "random", "--seed", "7", "--scenario", "walk", "--out", str(tmp_path))
    assert r.returncode != 0 and "--scenario" in r.stderr and "Traceback" not in r.stderr


# ---------------------------------------------------------------------- helpers


def _ray_cast_mask(cam: Camera, room, bodies) -> np.ndarray:
    """(H, W) bool: the ray of the pixel meets a body before the room. Only pixels in the box of
    each body's projected surface (sampled densely, plus a margin) are cast; the rest see no body."""
    rays = cam.pixel_rays()
    ok = np.all(np.isfinite(rays), axis=2)
    consider = np.zeros((cam.height, cam.width), dtype=bool)
    rng = np.random.default_rng(0)
    for body in bodies:
        uv, seen = cam.project(body.sample_points(4000, rng, surface_fraction=1.0))
        if not seen.any():
            continue
        lo = np.floor(uv[seen].min(axis=0)).astype(int) - 6
        hi = np.ceil(uv[seen].max(axis=0)).astype(int) + 7
        consider[max(lo[1], 0):max(hi[1], 0), max(lo[0], 0):max(hi[0], 0)] = True
    consider &= ok
    d = rays[consider].astype(np.float64)
    near = np.full(d.shape[0], np.inf)
    for body in bodies:
        near = np.minimum(near, body.intersect(cam.center, d)[0])
    out = np.zeros((cam.height, cam.width), dtype=bool)
    hit = np.isfinite(near)
    wall = raycast_room(room, cam.center, d[hit]).t
    got = np.zeros(d.shape[0], dtype=bool)
    got[hit] = near[hit] < wall
    out[consider] = got
    return out


# ---------------------------------------------------------------------- mixed rigs


@pytest.mark.parametrize("seed", (2, 3, 9))
def test_a_mixed_rig_turns_two_wall_cameras_into_sensors_and_leaves_the_world_as_it_was(seed):
    colour = random_world(seed)
    mixed = random_world(seed, sensors="mixed")
    assert colour.modalities == {} and random_world(seed, sensors="colour").summary() == colour.summary()
    for name in ("room", "spec", "cast", "media", "mask_scale", "rig", "dress"):
        assert getattr(mixed, name) == getattr(colour, name), name
    assert list(mixed.cameras) == list(colour.cameras)
    for cam in colour.cameras:
        a, b = colour.cameras[cam], mixed.cameras[cam]
        assert (a.model, a.width, a.height) == (b.model, b.width, b.height)
        assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("K", "dist", "R", "t"))
    assert sorted(mixed.modalities.values()) == ["depth", "thermal"]
    assert all(mixed.cameras[c].model != "fisheye" for c in mixed.modalities)
    assert mixed.faults == {c: f for c, f in colour.faults.items() if c not in mixed.modalities}
    # the depth camera is (within the 0.25 m a draw decides) the wall camera nearest the floor's middle
    depth = next(c for c, m in mixed.modalities.items() if m == "depth")
    (x0, y0), (x1, y1) = mixed.room.volume_rect_m
    middle = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 1.0])
    dist = {c: np.linalg.norm(cam.center - middle) for c, cam in mixed.cameras.items() if cam.model != "fisheye"}
    assert dist[depth] <= min(dist.values()) + 0.25
    s_colour, s_mixed = colour.summary(), mixed.summary()
    assert set(s_mixed["sensors"]["why"]) == set(mixed.modalities)
    assert {k: v for k, v in s_mixed.items() if k not in ("sensors", "faults")} == \
        {k: v for k, v in s_colour.items() if k != "faults"}
    with pytest.raises(ValueError, match="sensors"):
        random_world(seed, sensors="thermal")


@pytest.mark.slow
def test_a_mixed_world_writes_sixteen_bit_frames_and_replay_segments_them(tmp_path):
    from synth.render import CameraRenderer
    from synth.world import SENSOR_FOLDERS, sensor_frame
    from fusion_server.pipeline import FusionPipeline
    from fusion_server.replay import replay

    world = random_world(3, sensors="mixed")
    n = 30
    out = write_world(world, tmp_path / "w", frames=n)
    site = load_site(out.site)
    for cam, modality in world.modalities.items():
        assert site.camera(cam).modality == modality
        frames = sorted((out.out_dir / cam / SENSOR_FOLDERS[modality]).glob("*.png"))
        backs = sorted((out.out_dir / cam / "background").glob("*.png"))
        assert len(frames) == n and len(backs) == 45
        assert not (out.out_dir / cam / "masks").exists()
        image = cv2.imread(str(frames[12]), cv2.IMREAD_UNCHANGED)
        renderer = CameraRenderer(world.cameras[cam], world.room, seed=world.seed, colour=False)
        assert image.dtype == np.uint16
        assert np.array_equal(image, sensor_frame(world, renderer, cam, world.scenario.bodies(12), 12))
    for cam in world.cameras:
        if cam not in world.modalities:
            assert site.camera(cam).modality == "colour" and (out.out_dir / cam / "masks").is_dir()

    class Recording(FusionPipeline):
        def step(self, masks, stamp_ns, frame, looks=None, *, depths=None):
            self.depths.append(depths)
            self.masks.append(masks)
            return super().step(masks, stamp_ns, frame, looks, depths=depths)

    pipeline = Recording.from_site(site, cache_dir=tmp_path / "cache")
    pipeline.depths, pipeline.masks = [], []
    summary = replay(site, tmp_path / "run", input_dir=out.out_dir, pipeline=pipeline)
    assert summary.frames == n
    depth_cam = next(c for c, m in world.modalities.items() if m == "depth")
    shipped = 0
    for i, (depths, masks) in enumerate(zip(pipeline.depths, pipeline.masks)):
        assert set(depths) == {depth_cam}
        d, mask = depths[depth_cam], masks[depth_cam]
        assert d.shape == mask.shape and d.dtype == np.uint16
        assert np.all(mask[d > 0] > 0)
        frame = cv2.imread(str(out.out_dir / depth_cam / "range" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        small = cv2.resize(frame, (mask.shape[1], mask.shape[0]), interpolation=cv2.INTER_NEAREST)
        assert np.array_equal(d[d > 0], small[d > 0])   # the camera's own readings
        shipped += int(np.count_nonzero(d))
    assert shipped > 0 or not any(world.scenario.states[0]["present"][:n])


def test_synth_command_writes_a_mixed_rig_and_says_which_camera_is_which(tmp_path, capsys):
    from voxelwatch.cli import main

    assert main(["synth", "--world", "random", "--seed", "3", "--sensors", "mixed", "--frames", "3",
                 "--out", str(tmp_path / "w")]) == 0
    out = capsys.readouterr().out
    world = random_world(3, sensors="mixed")
    for cam, modality in world.modalities.items():
        assert f"{cam} {modality}:" in out
        assert load_site(tmp_path / "w" / "site.toml").camera(cam).modality == modality
    meta = json.loads((tmp_path / "w" / "truth" / "meta.json").read_text())
    assert meta["world"]["sensors"]["modalities"] == world.modalities
    assert main(["synth", "--scenario", "walk", "--sensors", "mixed", "--out", str(tmp_path / "h")]) != 0
