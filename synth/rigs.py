"""Camera rigs for the randomised worlds: drawn at random for a room, or the real rigs of the recordings.

Drawn rigs (:func:`random_rig`), 3 to 8 cameras:

* ``high-corners``: cameras 0.1-0.3 m under the ceiling in the corners of the
  free floor (then high on the walls), looking down at the middle of the room;
* ``level-walls``: cameras on the walls at 1.6-2.2 m looking almost level
  (5-15 degrees down) across the room, as in the lab recording;

either with or without a fisheye in the ceiling looking straight down. Lenses
are normal (60-75 degrees across, mild distortion) or wide (95-115 degrees,
strong barrel distortion); images 320x240, 640x480, 800x600 or 1280x720.

Real rigs (:func:`real_rig`), calibrations read as they are from the
recordings' folder: ``lab`` (the four level cameras of ``lab4cam-seated``,
644x486, OpenCV files in millimetres with -Z up) and ``pets`` (seven PETS 2009
views, Tsai files in millimetres; view 4 looks away from the shared area and
is left out). Their room is placed so its floor starts at (0, 0): the site
file says so with each camera's ``origin_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.calibration import WorldTransform, load_calibration
from common.camera import Camera, look_at
from synth.scene import Room

RIG_KINDS = ("high-corners", "level-walls", "real-lab", "real-pets")
RESOLUTIONS = ((320, 240), (640, 480), (800, 600), (1280, 720))


@dataclass(frozen=True)
class CalibrationRef:
    """How the site file names one camera's calibration: a file (relative to the site's folder
    once written), its format, units, up axis and where its origin lies in the room."""

    source: Path | None  # None: written by the world (voxelwatch format)
    format: str = "voxelwatch"
    units: str = "m"
    up: str = "+z"
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class RealRig:
    """A real rig placed in the world frame: cameras, their calibration files, the room's
    floor size and height around them, and the monitored rectangle, metres."""

    name: str
    cameras: dict[str, Camera]
    refs: dict[str, CalibrationRef]
    room_size_m: tuple[float, float, float]
    volume_xy_m: tuple[tuple[float, float], tuple[float, float]]
    chair_xy_m: tuple[float, float] | None


def random_rig(rng: np.random.Generator, room: Room, *, kind: str, fisheye: bool, count: int) -> dict[str, Camera]:
    """``count`` cameras (the fisheye included when ``fisheye``) of a drawn rig ``kind`` in ``room``."""
    if kind not in ("high-corners", "level-walls"):
        raise ValueError(f"kind must be 'high-corners' or 'level-walls', got {kind!r}")
    if not 3 <= count <= 8:
        raise ValueError(f"count must lie in 3..8, got {count}")
    w, d, h = room.size_m
    free = _free_rect(room)
    centre = ((free[0] + free[2]) / 2, (free[1] + free[3]) / 2)
    n_wall = count - (1 if fisheye else 0)
    mounts = _mounts(rng, room, n_wall, kind)
    cams: dict[str, Camera] = {}
    # most rigs are bought as a set; some mix models
    rig_size = RESOLUTIONS[int(rng.choice(len(RESOLUTIONS), p=(0.2, 0.45, 0.15, 0.2)))]
    for k, (x, y) in enumerate(mounts):
        cam_id = f"cam{k + 1}"
        width, height = rig_size if rng.random() < 0.75 else RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
        wide = rng.random() < 0.45
        hfov = rng.uniform(95, 115) if wide else rng.uniform(60, 75)
        if wide:
            dist = (rng.uniform(-0.32, -0.18), rng.uniform(0.04, 0.1), rng.normal(0, 5e-4), rng.normal(0, 5e-4), 0.0)
        else:
            dist = (rng.uniform(-0.06, 0.03), rng.uniform(-0.01, 0.02), rng.normal(0, 3e-4), rng.normal(0, 3e-4), 0.0)
        if kind == "high-corners":
            z = h - rng.uniform(0.1, 0.3)
            target = (centre[0] + rng.normal(0, 0.3), centre[1] + rng.normal(0, 0.3), rng.uniform(0.5, 1.0))
        else:
            z = rng.uniform(1.6, 2.2)
            # look across the room, 5-15 degrees down
            dx, dy = centre[0] - x, centre[1] - y
            yaw = math.atan2(dy, dx) + rng.normal(0, 0.12)
            pitch = math.radians(rng.uniform(5, 15))
            target = (x + math.cos(yaw), y + math.sin(yaw), z - math.tan(pitch))
        fx = (width / 2) / math.tan(math.radians(hfov) / 2)
        R, t = look_at((x, y, z), target)
        cams[cam_id] = Camera.pinhole(cam_id, width, height, fx=fx, fy=fx * rng.uniform(0.995, 1.005),
                                      cx=(width - 1) / 2 + rng.normal(0, 2), cy=(height - 1) / 2 + rng.normal(0, 2),
                                      dist=dist, R=R, t=t)
    if fisheye:
        cam_id = f"cam{len(cams) + 1}"
        width, height = ((640, 480), (800, 600), (1280, 720))[int(rng.integers(3))]
        f = (height / 2) / (math.pi / 2) * 0.98
        R, t = look_at((centre[0], centre[1], h - 0.03), (centre[0], centre[1], 0.0), up=(0.0, 1.0, 0.0))
        cams[cam_id] = Camera.fisheye(cam_id, width, height, fx=f, fy=f,
                                      dist=(rng.uniform(-0.01, 0.02), rng.uniform(-0.006, 0.0), 0.0, 0.0), R=R, t=t)
    return cams


def real_rig(name: str, data_dir: str | Path) -> RealRig:
    """The real rig ``name`` ('lab' or 'pets') from the recordings in ``data_dir``; ValueError naming the
    missing file when the recordings are not there."""
    data = Path(data_dir)
    if name == "lab":
        files = {f"cam{i}": data / "lab4cam-seated" / f"cam{i}" / "config.xml" for i in range(1, 5)}
        fmt, units, up, size = "opencv", "mm", "-z", (644, 486)
        # the room's walls lie just behind the cameras, which hang 4-5 m from the chair;
        # all four see the 3.2 x 2.6 m around it
        room_lo, room_hi, height = (-3.9, -4.9), (3.9, 2.8), 2.6
        volume = ((-1.6, -1.3), (1.6, 1.3))
        chair = (0.3, 0.0)
    elif name == "pets":
        files = {f"view{i}": data / "pets2009-calibration" / f"View_00{i}.xml" for i in (1, 2, 3, 5, 6, 7, 8)}
        fmt, units, up, size = "pets-tsai", "mm", "+z", None
        # the square the views share (4 to 7 of them see every point of it)
        room_lo, room_hi, height = (-35.5, -38.5), (1.0, 0.5), 8.0
        volume = ((-13.0, -12.0), (-1.0, -2.0))
        chair = None
    else:
        raise ValueError(f"unknown real rig {name!r}; real rigs are 'lab' and 'pets'")
    missing = [str(p) for p in files.values() if not p.is_file()]
    if missing:
        raise ValueError(f"real rig {name}: calibration file {missing[0]} not found (set VOXELWATCH_DATA to the "
                         "recordings' folder)")
    origin = (-room_lo[0], -room_lo[1], 0.0)
    cams, refs = {}, {}
    for cam_id, path in files.items():
        ref = CalibrationRef(path, fmt, units, up, origin)
        cams[cam_id] = load_calibration(path, fmt, cam_id, WorldTransform(units=units, up=up, origin_m=origin),
                                        image_size=size)
        refs[cam_id] = ref
    shift = np.asarray(origin[:2])
    vol = (tuple(np.round(np.asarray(volume[0]) + shift, 3)), tuple(np.round(np.asarray(volume[1]) + shift, 3)))
    room_size = (round(room_hi[0] - room_lo[0], 3), round(room_hi[1] - room_lo[1], 3), height)
    chair_xy = None if chair is None else tuple(np.round(np.asarray(chair) + shift, 3))
    return RealRig(name, cams, refs, room_size, vol, chair_xy)


def _free_rect(room: Room) -> tuple[float, float, float, float]:
    """The larger free rectangle of the floor (the whole room, or the wider arm of an L)."""
    w, d, _ = room.size_m
    blocks = [b for b in room.boxes if b.kind == "wall"]
    if not blocks:
        return (0.0, 0.0, w, d)
    b = blocks[0]
    options = [(0.0, 0.0, w, b.min_m[1]), (0.0, b.max_m[1], w, d), (0.0, 0.0, b.min_m[0], d), (b.max_m[0], 0.0, w, d)]
    return max(options, key=lambda r: (r[2] - r[0]) * (r[3] - r[1]))


def _mounts(rng, room: Room, n: int, kind: str) -> list[tuple[float, float]]:
    """Wall mounting points (x, y), 0.15 m from the walls: corners of the free floor first for
    high rigs, spread along the walls otherwise."""
    w, d, _ = room.size_m
    inset = 0.15
    blocks = [b for b in room.boxes if b.kind == "wall"]
    corners = [(inset, inset), (w - inset, inset), (w - inset, d - inset), (inset, d - inset)]
    if blocks:
        b = blocks[0]
        corners = [c for c in corners if not (b.min_m[0] - 0.2 <= c[0] <= b.max_m[0] + 0.2
                                              and b.min_m[1] - 0.2 <= c[1] <= b.max_m[1] + 0.2)]
        # the two corners where the block meets the outer walls
        for x in (b.min_m[0], b.max_m[0]):
            for y in (b.min_m[1], b.max_m[1]):
                on_wall_x = x in (0.0, w)
                on_wall_y = y in (0.0, d)
                if on_wall_x != on_wall_y:
                    sx = inset if x == b.max_m[0] else -inset
                    sy = inset if y == b.max_m[1] else -inset
                    corners.append((float(np.clip(x + sx, inset, w - inset)), float(np.clip(y + sy, inset, d - inset))))
    # points along the walls, every metre or so, away from the block and the doors
    wall_pts = []
    perimeter = np.linspace(0, 2 * (w + d), max(8, int(2 * (w + d))), endpoint=False)
    for s in perimeter + rng.uniform(0, 1.0):
        s %= 2 * (w + d)
        if s < w:
            p = (s, inset)
        elif s < w + d:
            p = (w - inset, s - w)
        elif s < 2 * w + d:
            p = (w - (s - w - d), d - inset)
        else:
            p = (inset, d - (s - 2 * w - d))
        p = (float(np.clip(p[0], inset, w - inset)), float(np.clip(p[1], inset, d - inset)))
        if blocks and (blocks[0].min_m[0] - 0.2 <= p[0] <= blocks[0].max_m[0] + 0.2
                       and blocks[0].min_m[1] - 0.2 <= p[1] <= blocks[0].max_m[1] + 0.2):
            continue
        if any(door.polygon_m[0][0] - 0.3 <= p[0] <= door.polygon_m[2][0] + 0.3
               and door.polygon_m[0][1] - 0.3 <= p[1] <= door.polygon_m[2][1] + 0.3 for door in room.doors):
            continue
        wall_pts.append(p)
    rng.shuffle(corners)
    if kind == "high-corners":
        chosen = corners[:n]
    else:
        chosen = []
    rest = [p for p in wall_pts if all(math.dist(p, c) > 1.0 for c in chosen)]
    # spread: farthest-point picks among the wall points
    while len(chosen) < n and rest:
        if not chosen:
            k = int(rng.integers(len(rest)))
        else:
            gaps = [min(math.dist(p, c) for c in chosen) for p in rest]
            k = int(np.argmax(gaps))
        chosen.append(rest.pop(k))
    while len(chosen) < n:  # a tiny room: stack cameras on the corners again
        chosen.append(corners[len(chosen) % len(corners)])
    return [(round(x, 3), round(y, 3)) for x, y in chosen]
