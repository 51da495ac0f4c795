"""Randomised worlds: other rooms, camera rigs and groups of people, each a pure function of a seed.

``voxelwatch synth --world random --seed N --out DIR`` writes the same layout
as the synthetic house (site file, calibrations, per-camera media, truth), so
``voxelwatch replay --site DIR/site.toml --input DIR`` and ``voxelwatch eval
--truth DIR --run RUN`` take it unchanged:

    DIR/site.toml, DIR/calib/<cam>.*      the room, its rig and calibrations
    DIR/<cam>/masks/000000.png ...        mask worlds: degraded true silhouettes
    DIR/<cam>/colour.avi                  mask worlds: the people's colours at the mask size, MJPG,
                                          one frame per mask (no shadows; for appearance only)
    DIR/<cam>/video.avi, background.avi   video worlds: rendered frames (segmented on replay)
    DIR/<cam>/thermal/000000.png ...      mixed rigs' thermal camera: 16-bit centi-kelvin frames
    DIR/<cam>/range/000000.png ...        mixed rigs' depth camera: 16-bit range frames, mm (0 = none)
    DIR/<cam>/background/000000.png ...   beside either: the empty room before the scenario
    DIR/truth/tracks.csv, events.jsonl    ground truth
    DIR/truth/meta.json                   fps, frames, people, and ``world``: what the world holds

A world draws (:func:`random_world`): a rig kind (high corners, level wall
cameras, or one of the real rigs of the recordings), a number of people
(1 to 12, from four bands), a room big enough for them (:mod:`synth.rooms`),
the cameras (:mod:`synth.rigs`), who does what (:mod:`synth.crowd`),
and how its masks are made: most worlds go from the true silhouettes through
the faults of :mod:`synth.degrade` straight to masks; three in ten of
those with up to six people render video that replay segments with the camera
worker's own segmenter, as the house does.
Video worlds also run on the camera workers (each camera's source is its video).

Two draws come from generators of their own, so that they leave the rest of a
world as it was: the dress (one world in four dresses every adult alike: the
same shirt, sleeves and trousers; ``summary()['dress']`` 'alike' or 'distinct')
and step-outs (in two of five worlds with doors or open edges, one or two
people walk out and come back 3-20 s later, :mod:`synth.crowd`).

Sensors (``sensors=``): ``'colour'`` (the default) gives the worlds above,
unchanged. ``'mixed'`` turns two cameras of the same world into other sensors
(a generator of its own, so the rest of the world stays as it was): a depth
camera (time of flight, reading to 7 m) where a wall camera is nearest the
middle of the monitored floor, so that most of it lies within its range, and a
thermal camera drawn among the other wall cameras (fisheyes stay colour). Their
frames come from :mod:`synth.sensors` and are segmented on replay by the
camera worker's own thermal and range segmenters; the room's air drifts
(:func:`synth.sensors.ambient_c`). The site file gives each camera its
``modality``; ``summary()['sensors']`` says which camera is which and why.

Seeds: :data:`TUNING_SEEDS` are for changing the pipeline; :data:`EVALUATION_SEEDS`
are only for reporting. Every table of figures on random worlds says which.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from common.calibration import save_voxelwatch
from common.camera import Camera
from synth.body import SHIRT_COLOURS, TROUSER_COLOURS, pose_body
from synth.crowd import Cast, random_people
from synth.degrade import CameraMove, MaskFaults, degrade, random_faults
from synth.house import open_video_writer
from synth.render import CameraRenderer, frame_for
from synth.rigs import CalibrationRef, real_rig, random_rig
from synth.rooms import FloorPlan, random_room, summarise_room
from synth.scenario import Scenario, ScenarioSpec
from synth.scene import Box, HotSpot, Room, Seat, site_dict
from synth.sensors import RangeModel, ambient_c
from synth.source import BACKGROUND_S, SyntheticCamera
from synth.truth import derive_truth, write_truth

TUNING_SEEDS = range(0, 1000)
"""Seeds to look at while changing the pipeline."""
EVALUATION_SEEDS = range(1000, 100_000)
"""Seeds only for reporting; never looked at while changing the pipeline."""
WORLD_FPS = 15.0
PEOPLE_BANDS = ((1, 1), (2, 3), (4, 7), (8, 12))
RIG_LABELS = {"high-corners": "high corners", "level-walls": "level walls", "real-lab": "real: lab",
              "real-pets": "real: PETS 2009"}
_BAND_P = (0.2, 0.3, 0.3, 0.2)
_RIG_P = {"high-corners": 0.4, "level-walls": 0.35, "real-lab": 0.125, "real-pets": 0.125}
_OVERLAP_M = 0.3
_COLOUR_STREAM = 2  # noise stream of the colour frames beside the masks (0, 1: video worlds' frames, backgrounds)
_ATTEMPTS = 8
ALIKE_P = 0.25
"""Share of worlds whose adults all wear the same clothes."""
STEP_OUT_P = 0.4
"""Share of worlds with doors or open edges where people step out and come back."""
ADULT_M = 1.45
"""People this tall or taller are adults (the dress of an 'alike' world)."""
SENSOR_RIGS = ("colour", "mixed")
"""What a world's cameras are: all colour, or a mixed rig (one depth and one thermal camera)."""
SENSOR_FOLDERS = {"thermal": "thermal", "depth": "range"}
"""Each non-colour camera's frame folder under ``DIR/<cam>/``."""
DEPTH_RANGE_M = 7.0
"""A mixed rig's depth camera reads to this range (:class:`synth.sensors.RangeModel`)."""


def seed_set(seed: int) -> str:
    """'tuning' or 'evaluation': which declared set ``seed`` belongs to."""
    if seed in TUNING_SEEDS:
        return "tuning"
    if seed in EVALUATION_SEEDS:
        return "evaluation"
    raise ValueError(f"world seed must lie in {TUNING_SEEDS.start}..{EVALUATION_SEEDS.stop - 1}, got {seed}")


def default_data_dir() -> Path:
    """The recordings' folder: ``$VOXELWATCH_DATA``, else ``../shared/data`` beside the project."""
    env = os.environ.get("VOXELWATCH_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


@dataclass(frozen=True)
class World:
    """One randomised world (see the module text). ``rig``: a key of :data:`RIG_LABELS`;
    ``media``: 'masks' or 'video'; ``faults``: per camera, mask worlds only; ``dress``: 'alike'
    (every adult wears the same clothes) or 'distinct'."""

    seed: int
    room: Room
    cameras: dict[str, Camera]
    refs: dict[str, CalibrationRef]
    rig: str
    fisheye: bool
    spec: ScenarioSpec
    cast: Cast
    media: str
    mask_scale: float
    faults: dict[str, MaskFaults]
    open_edges: bool
    dress: str = "distinct"
    modalities: dict[str, str] = dataclasses.field(default_factory=dict)
    """Camera id -> 'thermal' or 'depth' for the cameras that are not colour (mixed rigs)."""
    sensor_notes: dict[str, str] = dataclasses.field(default_factory=dict)
    """Camera id -> why it was made that sensor (mixed rigs)."""

    def modality(self, cam_id: str) -> str:
        """The camera's modality: 'colour', 'thermal' or 'depth'."""
        return self.modalities.get(cam_id, "colour")

    @property
    def name(self) -> str:
        return f"world-{self.seed}"

    @cached_property
    def scenario(self) -> Scenario:
        return Scenario(self.spec, self.seed, room=self.room)

    def summary(self) -> dict:
        """What the world holds, as plain JSON values (stored in ``truth/meta.json`` as ``world``)."""
        room = summarise_room(self.room)
        truth_rows = self._present_counts()
        lenses = []
        for cam in self.cameras.values():
            if cam.model == "fisheye":
                lenses.append("fisheye")
            else:
                hfov = 2 * math.degrees(math.atan(cam.width / 2 / cam.K[0, 0]))
                lenses.append("wide" if hfov > 85 else "normal")
        return {
            "seed": self.seed,
            "seed_set": seed_set(self.seed),
            "rig": self.rig,
            "rig_label": RIG_LABELS[self.rig],
            "fisheye": self.fisheye,
            "cameras": len(self.cameras),
            "resolutions": sorted({f"{c.width}x{c.height}" for c in self.cameras.values()}),
            "lenses": lenses,
            "room": {"shape": room.shape, "size_m": list(room.size_m), "floor_area_m2": room.floor_area_m2,
                     "furniture": list(room.furniture), "doors": room.doors,
                     "volume_xy_m": [list(v) for v in self.room.volume_rect_m]},
            "people": len(self.cast.scripts),
            "people_per_frame_max": int(truth_rows.max(initial=0)),
            "people_per_frame_mean": round(float(truth_rows.mean()) if truth_rows.size else 0.0, 3),
            "children": sum(1 for s in self.cast.scripts if s.height_m is not None and s.height_m < ADULT_M),
            "behaviours": sorted(set(self.cast.behaviours) | ({"step_out"} if self.cast.step_outs else set())),
            "step_outs": len(self.cast.step_outs),
            "dress": self.dress,
            "media": self.media,
            "mask_scale": self.mask_scale,
            "faults": {cam: f.describe() for cam, f in self.faults.items() if f.describe()},
            "duration_s": self.spec.duration_s,
            **({"sensors": {"rig": "mixed", "modalities": dict(self.modalities), "why": dict(self.sensor_notes)}}
               if self.modalities else {}),
        }

    def _present_counts(self) -> np.ndarray:
        """(F,) int people inside the monitored volume per frame."""
        sc = self.scenario
        counts = np.zeros(sc.n_frames, dtype=int)
        for st in sc.states:
            counts += st["present"] & self.room.inside_volume(st["xy"])
        return counts


def random_world(seed: int, *, data_dir: str | Path | None = None, sensors: str = "colour",
                 duration_s: float | None = None) -> World:
    """The world of ``seed`` (deterministic). The real rigs need the recordings' calibrations in
    ``data_dir`` (default :func:`default_data_dir`): ValueError naming the missing file otherwise.
    ``sensors``: 'colour' or 'mixed' (see the module text; the same world either way).
    ``duration_s``: the scenario's length instead of the drawn 30-50 s (the same room, rig and
    people, who then do more; for checks that need minutes, like the moved-camera alarm's)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an int, got {seed!r}")
    if sensors not in SENSOR_RIGS:
        raise ValueError(f"sensors must be one of {', '.join(SENSOR_RIGS)}, got {sensors!r}")
    seed = int(seed)
    seed_set(seed)
    rng = np.random.default_rng([seed, 11])
    kinds = list(_RIG_P)
    rig = kinds[int(rng.choice(len(kinds), p=list(_RIG_P.values())))]
    band = PEOPLE_BANDS[int(rng.choice(len(PEOPLE_BANDS), p=_BAND_P))]
    count = int(rng.integers(band[0], band[1] + 1))
    duration = float(np.round(rng.uniform(30.0, 50.0)))
    if duration_s is not None:
        if not (isinstance(duration_s, (int, float)) and math.isfinite(duration_s) and 5.0 <= duration_s <= 3600.0):
            raise ValueError(f"duration_s must lie in 5..3600 s, got {duration_s!r}")
        duration = float(duration_s)
    residents = int(rng.integers(1, 3))
    fisheye = False
    open_edges = False
    if rig in ("real-lab", "real-pets"):
        real = real_rig("lab" if rig == "real-lab" else "pets", data_dir or default_data_dir())
        if rig == "real-lab":
            count = min(count, 4)
        else:
            count = max(count, 4)
        room = _real_room(real)
        cameras, refs = real.cameras, real.refs
        (x0, y0), (x1, y1) = real.volume_xy_m
        # people keep near the monitored area and now and then step out of it: the lab's
        # area is most of its free floor, the PETS square is surrounded by more of the same
        m = 0.5 if rig == "real-lab" else 1.5
        plan = FloorPlan(room, region=((x0 - m, y0 - m), (x1 + m, y1 + m)))
        open_edges = True
    else:
        room = random_room(rng, min_area_m2=max(9.0, 3.0 * count + 6.0))
        fisheye = bool(rng.random() < 0.5)
        n_cams = int(rng.integers(3, 9))
        cameras = random_rig(rng, room, kind=rig, fisheye=fisheye, count=n_cams)
        refs = {cam: CalibrationRef(None) for cam in cameras}
        plan = FloorPlan(room)
    media = "video" if (count <= 6 and rng.random() < 0.3) else "masks"
    widths = sorted(c.width for c in cameras.values())
    mask_scale = 0.5 if widths[len(widths) // 2] >= 640 else 1.0
    start_hour = int(rng.integers(7, 22))
    fault_rng = np.random.default_rng([seed, 17])
    n_frames = int(round(duration * WORLD_FPS))
    faults = random_faults(fault_rng, cameras, n_frames, WORLD_FPS) if media == "masks" else {}
    step_rng = np.random.default_rng([seed, 29])
    step_outs = 0
    if (room.doors or open_edges) and step_rng.random() < STEP_OUT_P:
        step_outs = 1 if count <= 2 else int(step_rng.integers(1, 3))
    cast, spec = _best_cast(seed, room, plan, count, duration, residents, start_hour, step_outs=step_outs,
                            open_edges=open_edges)
    dress_rng = np.random.default_rng([seed, 23])
    dress = "alike" if dress_rng.random() < ALIKE_P else "distinct"
    if dress == "alike":
        cast, spec = _dress_alike(dress_rng, cast, spec)
    modalities: dict[str, str] = {}
    notes: dict[str, str] = {}
    if sensors == "mixed":
        modalities, notes = _mixed_sensors(np.random.default_rng([seed, 31]), room, cameras)
        faults = {cam: f for cam, f in faults.items() if cam not in modalities}
    return World(seed=seed, room=room, cameras=cameras, refs=refs, rig=rig, fisheye=fisheye, spec=spec, cast=cast,
                 media=media, mask_scale=mask_scale, faults=faults, open_edges=open_edges, dress=dress,
                 modalities=modalities, sensor_notes=notes)


def with_camera_moved(world: World, cam_id: str, move: CameraMove) -> World:
    """``world`` with camera ``cam_id`` knocked out of place as ``move`` says (its masks and
    videos are rendered through the moved camera from ``move.first``; the site file keeps the
    calibration of the camera as it was)."""
    if cam_id not in world.cameras:
        raise ValueError(f"no camera {cam_id!r} in {world.name}; cameras are {sorted(world.cameras)}")
    faults = dict(world.faults)
    faults[cam_id] = dataclasses.replace(faults.get(cam_id, MaskFaults()), moved=move)
    return dataclasses.replace(world, faults=faults)


@dataclass(frozen=True)
class WorldOutput:
    """What :func:`write_world` wrote (absolute paths)."""

    out_dir: Path
    site: Path
    truth_dir: Path
    n_frames: int
    media: str


def write_world(world: World, out_dir: str | Path, *, frames: int | None = None) -> WorldOutput:
    """Write ``world`` into ``out_dir`` (layout in the module text); ``frames``: only the first N frames."""
    written = write_world_site(world, out_dir, frames=frames)
    out, n, sc = written.out_dir, written.n_frames, world.scenario
    colour = [c for c in world.cameras if world.modality(c) == "colour"]
    bodies = [_bodies_at(sc, i) for i in range(n)] if world.media != "video" or world.modalities else None
    if world.media == "video":
        for cam_id in colour:
            _write_video(world, cam_id, world.cameras[cam_id], out / cam_id, n)
    else:
        for cam_id in colour:
            _write_masks(world, cam_id, out / cam_id / "masks", out / cam_id / "colour.avi", bodies)
    for cam_id, modality in world.modalities.items():
        _write_sensor(world, cam_id, modality, out / cam_id, bodies)
    return written


def write_world_site(world: World, out_dir: str | Path, *, frames: int | None = None) -> WorldOutput:
    """The site file, calibrations and truth of :func:`write_world`, without the media: for camera
    workers that render their own views live (source ``world:SEED``)."""
    sc = world.scenario
    n = sc.n_frames if frames is None else int(frames)
    if not 1 <= n <= sc.n_frames:
        raise ValueError(f"frames must lie in 1..{sc.n_frames} for {world.name}, got {frames!r}")
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    site_path = _write_site(world, out)
    truth_dir = out / "truth"
    paths = write_truth(sc, truth_dir, derive_truth(sc), n_frames=n)
    meta = json.loads(paths["meta"].read_text(encoding="utf-8"))
    meta["world"] = world.summary()
    paths["meta"].write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    return WorldOutput(out_dir=out, site=site_path, truth_dir=truth_dir, n_frames=n, media=world.media)


def render_masks(world: World, cam_id: str, frames, *, faults: bool = True) -> list[np.ndarray]:
    """The masks (H, W) uint8 0/255 of camera ``cam_id`` for frame indices ``frames``, at the site's
    mask size; ``faults=False`` gives the true silhouettes (furniture and people occlude) of the
    camera as it stands (a :class:`~synth.degrade.CameraMove` is kept: it is no mask fault)."""
    return list(iter_masks(world, cam_id, frames, faults=faults))


def iter_masks(world: World, cam_id: str, frames, *, faults: bool = True, bodies: list | None = None):
    """Yield the masks of :func:`render_masks` one by one; ``bodies``: the people of every frame
    (``bodies[i]`` for frame ``i``), when already posed."""
    sc = world.scenario
    f = world.faults.get(cam_id, MaskFaults())
    f = f if faults else MaskFaults(moved=f.moved)  # a moved camera sees from its new place either way
    renderers = _Renderers(world, cam_id, f, colour=False)
    posed = (lambda i: bodies[i]) if bodies is not None else (lambda i: _bodies_at(sc, i))
    for i in frames:
        i = int(i)
        renderer = renderers.at(i)
        labels = renderer.labels(posed(max(0, i - f.lag_frames)))
        yield _mask(world, cam_id, renderer.camera, labels, f, i, posed(i), faults=faults)


# ---------------------------------------------------------------------- helpers


def _best_cast(seed: int, room: Room, plan: FloorPlan, count: int, duration: float, residents: int,
               start_hour: int, *, step_outs: int = 0, open_edges: bool = False) -> tuple[Cast, ScenarioSpec]:
    """People for the world: of a few draws, the one where people who are not together walk through
    each other least (pelvises closer than 0.3 m). Step-outs are then added to that draw (the same
    main behaviours; the people who step out go on differently once back)."""
    best = None
    for attempt in range(_ATTEMPTS):
        rng = np.random.default_rng([seed, 13, attempt])
        cast = random_people(rng, room, plan, count, duration, residents=min(residents, count))
        spec = ScenarioSpec(
            name=f"world-{seed}",
            description=f"random world {seed}: {count} people, " + ", ".join(sorted(set(cast.behaviours))),
            duration_s=duration, people=cast.scripts, start_local=f"{start_hour:02d}:{int(rng.integers(60)):02d}:00",
            drift=0.02, residents=min(residents, count),
        )
        overlap = _overlap_frames(Scenario(spec, seed, room=room), cast)
        if best is None or overlap < best[0]:
            best = (overlap, cast, spec, attempt)
        if overlap == 0:
            break
    _, cast, spec, attempt = best
    if step_outs:
        cast = random_people(np.random.default_rng([seed, 13, attempt]), room, plan, count, duration,
                             residents=min(residents, count), step_outs=step_outs,
                             step_rng=np.random.default_rng([seed, 29, attempt]), open_edges=open_edges)
        spec = dataclasses.replace(spec, people=cast.scripts)
    return cast, spec


def _dress_alike(rng: np.random.Generator, cast: Cast, spec: ScenarioSpec) -> tuple[Cast, ScenarioSpec]:
    """The cast with every adult in one shirt (and sleeve length) and one pair of trousers drawn
    from the body's tables; children keep their own clothes."""
    shirt = SHIRT_COLOURS[int(rng.integers(len(SHIRT_COLOURS)))]
    trousers = TROUSER_COLOURS[int(rng.integers(len(TROUSER_COLOURS)))]
    clothes = (shirt, trousers, bool(rng.random() < 0.6))
    scripts = tuple(dataclasses.replace(s, clothes=clothes) if s.height_m is None or s.height_m >= ADULT_M else s
                    for s in cast.scripts)
    return dataclasses.replace(cast, scripts=scripts), dataclasses.replace(spec, people=scripts)


def _overlap_frames(sc: Scenario, cast: Cast) -> int:
    states = sc.states
    total = 0
    for a in range(len(states)):
        for b in range(a + 1, len(states)):
            if cast.groups[a] and cast.groups[a] == cast.groups[b]:
                continue
            both = states[a]["present"] & states[b]["present"]
            if both.any():
                d = np.linalg.norm(states[a]["xy"][both] - states[b]["xy"][both], axis=1)
                total += int(np.count_nonzero(d < _OVERLAP_M))
    return total


def _bodies_at(sc: Scenario, i: int):
    states = sc.states
    return [pose_body(p.shape, st["q"][i], p.person_id) for p, st in zip(sc.people, states) if st["present"][i]]


def _mask(world: World, cam_id: str, camera: Camera, labels: np.ndarray, f: MaskFaults, i: int, bodies: list, *,
          faults: bool) -> np.ndarray:
    """Mask ``i`` from the true person ids per pixel (of frame ``i - f.lag_frames``)."""
    if faults:
        return degrade(labels, f, i, camera=camera, bodies=bodies, light_m=world.room.light_m,
                       seed=_cam_seed(world.seed, cam_id))
    return np.where(labels > 0, np.uint8(255), np.uint8(0))


class _Renderers:
    """The renderer of one camera's masks (at the mask size), and of the camera as it stands
    after its :class:`~synth.degrade.CameraMove`, from that move's frame on."""

    def __init__(self, world: World, cam_id: str, faults: MaskFaults, *, colour: bool) -> None:
        self.world, self.cam_id, self.move, self.colour = world, cam_id, faults.moved, colour
        self.before = self._renderer(world.cameras[cam_id])
        self.after: CameraRenderer | None = None

    def at(self, i: int) -> CameraRenderer:
        if self.move is None or i < self.move.first:
            return self.before
        if self.after is None:
            self.after = self._renderer(self.move.apply(self.world.cameras[self.cam_id]))
        return self.after

    def _renderer(self, camera: Camera) -> CameraRenderer:
        cam = camera.scaled(self.world.mask_scale)
        if self.colour:
            return CameraRenderer(cam, self.world.room, seed=self.world.seed, shadows=False)
        return CameraRenderer(cam, self.world.room, colour=False)


def _cam_seed(seed: int, cam_id: str) -> int:
    return seed * 1000 + sum(cam_id.encode("utf-8"))


def _real_room(real) -> Room:
    (x0, y0), (x1, y1) = real.volume_xy_m
    boxes, seats, hotspots = [], [], []
    if real.chair_xy_m is not None:
        cx, cy = real.chair_xy_m
        wood = (70, 104, 140)
        boxes += [Box("chair seat", "chair", (cx - 0.22, cy - 0.22, 0.42), (cx + 0.22, cy + 0.22, 0.46), wood),
                  Box("chair back", "chair", (cx + 0.18, cy - 0.22, 0.46), (cx + 0.22, cy + 0.22, 0.92), wood)]
        for lx in (cx - 0.21, cx + 0.17):
            for ly in (cy - 0.21, cy + 0.17):
                boxes.append(Box("chair leg", "chair", (lx, ly, 0.0), (lx + 0.04, ly + 0.04, 0.42), wood))
        seats.append(Seat("chair", "chair", (cx + 0.05, cy), 0.46, 180.0, (cx - 0.55, cy)))
        hotspots.append(HotSpot("chair", "chair", ((cx - 0.7, cy - 0.5), (cx + 0.3, cy - 0.5), (cx + 0.3, cy + 0.5),
                                                   (cx - 0.7, cy + 0.5)), (cx - 0.55, cy), 180.0))
    w, d, h = real.room_size_m
    light = ((x0 + x1) / 2, (y0 + y1) / 2, min(h - 0.05, 2.55))
    return Room(size_m=real.room_size_m, boxes=tuple(boxes), seats=tuple(seats), hotspots=tuple(hotspots), doors=(),
                light_m=light, volume_xy_m=real.volume_xy_m)


def _write_site(world: World, out: Path) -> Path:
    from common.site import load_site, site_from_dict, write_site

    (out / "calib").mkdir(parents=True, exist_ok=True)
    video = world.media == "video"
    cams = world.cameras
    content = site_dict(world.room, cams, name=world.name.replace("_", "-"), fps=WORLD_FPS,
                        residents=world.spec.residents,
                        sources={c: f"{c}/video.avi" for c in cams} if video else None,
                        backgrounds={c: f"{c}/background.avi" for c in cams} if video else None)
    content["carving"]["mask_scale"] = world.mask_scale
    content["volume"]["open_edges"] = world.open_edges
    content["utc_offset_hours"] = 0.0
    for entry in content["cameras"]:
        modality = world.modality(entry["id"])
        if modality != "colour":
            entry.update(modality=modality, source=f"{entry['id']}/{SENSOR_FOLDERS[modality]}",
                         background=f"{entry['id']}/background")
        ref = world.refs[entry["id"]]
        if ref.source is None:
            save_voxelwatch(cams[entry["id"]], out / "calib" / f"{entry['id']}.toml")
            continue
        # a real rig's own calibration file, read as it is
        name = f"calib/{entry['id']}{ref.source.suffix}"
        shutil.copyfile(ref.source, out / name)
        entry.update(calibration=name, format=ref.format, units=ref.units, up=ref.up, origin_m=list(ref.origin_m))
    site = site_from_dict(content, base_dir=out)
    path = write_site(site, out / "site.toml")
    load_site(path)  # what replay will read: fail here, not there
    return path


def _write_masks(world: World, cam_id: str, folder: Path, colour_path: Path, bodies: list) -> None:
    """The masks of :func:`iter_masks` and the colour frames beside them: the true bodies (no lag, no
    faults) at the mask size without shadows. One render gives both (its person ids are those of
    ``CameraRenderer.labels``), so the colour costs the shading and the encoding only."""
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.png"):
        old.unlink()
    sc = world.scenario
    f = world.faults.get(cam_id, MaskFaults())
    renderers = _Renderers(world, cam_id, f, colour=True)
    cam = renderers.at(0).camera
    recent: dict[int, np.ndarray] = {}  # person ids of the last frames, for a late camera
    writer = open_video_writer(colour_path, "MJPG", WORLD_FPS, (cam.width, cam.height))
    try:
        for i, people in enumerate(bodies):
            renderer = renderers.at(i)
            bgr, recent[i] = renderer.render(people, sc.gain(i), (_COLOUR_STREAM, i))
            recent.pop(i - f.lag_frames - 1, None)
            writer.write(bgr)
            mask = _mask(world, cam_id, renderer.camera, recent[max(0, i - f.lag_frames)], f, i, people, faults=True)
            cv2.imwrite(str(folder / f"{i:06d}.png"), mask)
    finally:
        writer.release()


def sensor_frame(world: World, renderer: CameraRenderer, cam_id: str, bodies: list, i: int, *,
                 background: bool = False) -> np.ndarray:
    """Frame ``i`` of a mixed rig's thermal or depth camera (``renderer`` its
    :class:`CameraRenderer`), or of its clip of the empty room before the scenario
    (``background``): (H, W) uint16 centi-kelvin or millimetres."""
    modality = world.modality(cam_id)
    n_bg = int(round(BACKGROUND_S * WORLD_FPS))
    t_s = (i - n_bg if background else i) / WORLD_FPS
    key = (1 if background else 0, int(i))
    image, _ = frame_for(renderer, modality, [] if background else bodies, key,
                         ambient_c=ambient_c(world.seed, t_s), range_model=RangeModel(max_range_m=DEPTH_RANGE_M))
    return image


def _mixed_sensors(rng: np.random.Generator, room: Room, cameras: dict[str, Camera]) -> tuple[dict, dict]:
    """Which camera becomes the depth camera and which the thermal one, and why."""
    walls = [c for c, cam in cameras.items() if cam.model != "fisheye"]
    (x0, y0), (x1, y1) = room.volume_rect_m
    middle = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 1.0])
    dist = {c: float(np.linalg.norm(cameras[c].center - middle)) for c in walls}
    nearest = min(dist.values())
    # cameras within 0.25 m of the nearest are as good: the draw decides
    close = [c for c in walls if dist[c] <= nearest + 0.25]
    depth = close[int(rng.integers(len(close)))]
    rest = [c for c in walls if c != depth]
    thermal = rest[int(rng.integers(len(rest)))]
    far = _floor_beyond(cameras[depth], room, DEPTH_RANGE_M)
    notes = {
        depth: (f"depth: the wall camera nearest the middle of the monitored floor ({dist[depth]:.1f} m from it); "
                f"{100 * far:.0f}% of that floor (at 1 m height) lies beyond its {DEPTH_RANGE_M:g} m range"),
        thermal: f"thermal: drawn among the other {len(rest)} wall cameras",
    }
    return {depth: "depth", thermal: "thermal"}, notes


def _floor_beyond(camera: Camera, room: Room, range_m: float) -> float:
    """Share of the monitored floor, sampled at 1 m height every 0.25 m, farther than ``range_m``."""
    (x0, y0), (x1, y1) = room.volume_rect_m
    xs, ys = np.meshgrid(np.arange(x0, x1 + 1e-9, 0.25), np.arange(y0, y1 + 1e-9, 0.25))
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], axis=1)
    return float(np.mean(np.linalg.norm(pts - camera.center, axis=1) > range_m))


def _write_sensor(world: World, cam_id: str, modality: str, folder: Path, bodies: list) -> None:
    """A thermal or depth camera's 16-bit frames and its clip of the empty room, as PNG folders."""
    frames_dir = folder / SENSOR_FOLDERS[modality]
    back_dir = folder / "background"
    for d in (frames_dir, back_dir):
        d.mkdir(parents=True, exist_ok=True)
        for old in d.glob("*.png"):
            old.unlink()
    renderer = CameraRenderer(world.cameras[cam_id], world.room, seed=world.seed, colour=False)
    for i in range(int(round(BACKGROUND_S * WORLD_FPS))):
        cv2.imwrite(str(back_dir / f"{i:06d}.png"), sensor_frame(world, renderer, cam_id, [], i, background=True))
    for i, people in enumerate(bodies):
        cv2.imwrite(str(frames_dir / f"{i:06d}.png"), sensor_frame(world, renderer, cam_id, people, i))


def _write_video(world: World, cam_id: str, cam: Camera, folder: Path, n: int) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    source = SyntheticCamera(world.scenario, cam_id, world.seed, camera=cam, background_s=BACKGROUND_S,
                             moved=world.faults.get(cam_id, MaskFaults()).moved)
    size = (cam.width, cam.height)
    writer = open_video_writer(folder / "background.avi", "MJPG", WORLD_FPS, size)
    try:
        for i in range(source.n_background_frames):
            writer.write(source.background_frame(i))
    finally:
        writer.release()
    writer = open_video_writer(folder / "video.avi", "MJPG", WORLD_FPS, size)
    try:
        for i in range(n):
            writer.write(source.frame(i)[0])
    finally:
        writer.release()
