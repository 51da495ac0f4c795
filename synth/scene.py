"""The synthetic house: one living room, its furniture, seats, hot spots, door and cameras.

World frame: metres, right-handed, Z up, floor at Z = 0; the room spans
x 0..8, y 0..6, z 0..2.5. The front door is an opening in the west wall
(x = 0, y 3.8..4.8) onto a short corridor outside the monitored volume, so a
person can appear beyond the door and walk in.

Layout (plan view, y up)::

    y=6 +--------------------------------------------+
        | counter + cabinets   fridge                |
        |   (kitchen)                          shelf |
   door =                                            |
        |   chair3  chair4                           |
        |  [ dinner table ]       [====sofa====]     |
        |   chair1  chair2         (facing TV)       |
        |                          [TV on stand]     |
    y=0 +--------------------------------------------+
       x=0                                         x=8

Cameras (ids cam1..cam5): four pinholes 640x480 high in the corners looking
at the room centre, one OpenCV fisheye in the ceiling centre looking down,
as in the seed paper's setup.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.calibration import save_voxelwatch
from common.camera import Camera, look_at

ROOM_SIZE_M = (8.0, 6.0, 2.5)
CAMERA_IDS = ("cam1", "cam2", "cam3", "cam4", "cam5")
FPS = 15.0
SITE_NAME = "synthetic-house"
MASK_SCALE = 0.5
VOLUME_HEIGHT_M = 3.0
"""The monitored volume ends at the ceiling or at this height, whichever is lower."""


@dataclass(frozen=True)
class Box:
    """An axis-aligned solid box (furniture), world frame, metres.

    name: what it is ("sofa back"). kind: furniture group ("sofa", "table", ...).
    min_m, max_m: (3,) corners. colour_bgr: base colour, 0..255.
    """

    name: str
    kind: str
    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]
    colour_bgr: tuple[int, int, int]

    def __post_init__(self) -> None:
        if any(hi <= lo for lo, hi in zip(self.min_m, self.max_m)):
            raise ValueError(f"box {self.name!r}: max_m {self.max_m} must exceed min_m {self.min_m}")


@dataclass(frozen=True)
class Seat:
    """Where a person sits.

    xy_m: floor position of the pelvis (hip joints) when seated.
    height_m: seat surface height. facing_deg: direction the seated person
    faces (0 = +x, 90 = +y). approach_xy_m: where the person stands just
    before sitting down and just after standing up.
    """

    name: str
    hotspot: str
    xy_m: tuple[float, float]
    height_m: float
    facing_deg: float
    approach_xy_m: tuple[float, float]


@dataclass(frozen=True)
class HotSpot:
    """A named floor polygon (world x, y, metres) where dwelling means something.

    spot_xy_m / facing_deg: where a person stands to use it, and which way they face.
    """

    name: str
    kind: str
    polygon_m: tuple[tuple[float, float], ...]
    spot_xy_m: tuple[float, float]
    facing_deg: float


@dataclass(frozen=True)
class Door:
    """A doorway in one of the room's outer walls.

    polygon_m: the floor zone just inside the door (site file ``[[doors]]``).
    y_range_m: the opening's span along its wall (y on the x walls, x on the y walls),
    metres; height_m its height.
    inside_xy_m: a point just inside; outside_xy_m: where people appear/vanish,
    in the corridor beyond the door (outside the monitored volume).
    corridor_min_m / corridor_max_m: the corridor box behind the opening.
    wall: 'x0' (x = 0, the house's west wall), 'x1' (x = room width), 'y0' or 'y1'.
    """

    name: str
    polygon_m: tuple[tuple[float, float], ...]
    y_range_m: tuple[float, float]
    height_m: float
    inside_xy_m: tuple[float, float]
    outside_xy_m: tuple[float, float]
    corridor_min_m: tuple[float, float, float]
    corridor_max_m: tuple[float, float, float]
    wall: str = "x0"

    def __post_init__(self) -> None:
        if self.wall not in WALLS:
            raise ValueError(f"door {self.name!r}: wall must be one of {WALLS}, got {self.wall!r}")


WALLS = ("x0", "x1", "y0", "y1")


@dataclass(frozen=True)
class WallDecal:
    """A flat coloured rectangle on a wall or the floor (pictures, a rug).

    surface: 'floor' or a wall 'x0' | 'x1' | 'y0' | 'y1'. rect_m: (u0, v0, u1, v1)
    where (u, v) is (x, y) on the floor, (y, z) on x-walls and (x, z) on y-walls.
    """

    surface: str
    rect_m: tuple[float, float, float, float]
    colour_bgr: tuple[int, int, int]
    pattern: str = "plain"


@dataclass(frozen=True)
class Room:
    """Everything static in the synthetic house."""

    size_m: tuple[float, float, float]
    boxes: tuple[Box, ...]
    seats: tuple[Seat, ...]
    hotspots: tuple[HotSpot, ...]
    doors: tuple[Door, ...]
    decals: tuple[WallDecal, ...] = ()
    light_m: tuple[float, float, float] = (4.0, 3.0, 2.45)
    waypoints: dict[str, tuple[float, float]] = field(default_factory=dict)
    volume_xy_m: tuple[tuple[float, float], tuple[float, float]] | None = None
    """The monitored floor rectangle ((x0, y0), (x1, y1)) when it is smaller than the room
    (a real rig whose cameras hang far from the area they all see); None: the whole room."""

    def seat(self, name: str) -> Seat:
        for s in self.seats:
            if s.name == name:
                return s
        raise ValueError(f"no seat {name!r}; seats are {[s.name for s in self.seats]}")

    def hotspot(self, name: str) -> HotSpot:
        for h in self.hotspots:
            if h.name == name:
                return h
        raise ValueError(f"no hot spot {name!r}; hot spots are {[h.name for h in self.hotspots]}")

    def door(self, name: str) -> Door:
        for d in self.doors:
            if d.name == name:
                return d
        raise ValueError(f"no door {name!r}; doors are {[d.name for d in self.doors]}")

    def point(self, name_or_xy) -> tuple[float, float]:
        """A named waypoint (see :func:`default_room`) or an (x, y) pair, metres."""
        if isinstance(name_or_xy, str):
            if name_or_xy not in self.waypoints:
                raise ValueError(f"no waypoint {name_or_xy!r}; waypoints are {sorted(self.waypoints)}")
            return self.waypoints[name_or_xy]
        x, y = name_or_xy
        return float(x), float(y)

    @property
    def box_min_m(self) -> np.ndarray:
        """(B, 3) float64 furniture minimum corners."""
        return np.array([b.min_m for b in self.boxes], dtype=np.float64).reshape(-1, 3)

    @property
    def box_max_m(self) -> np.ndarray:
        """(B, 3) float64 furniture maximum corners."""
        return np.array([b.max_m for b in self.boxes], dtype=np.float64).reshape(-1, 3)

    @property
    def volume_rect_m(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The monitored floor rectangle ((x0, y0), (x1, y1)), metres."""
        if self.volume_xy_m is not None:
            return self.volume_xy_m
        return (0.0, 0.0), (float(self.size_m[0]), float(self.size_m[1]))

    def inside_volume(self, xy_m: np.ndarray) -> np.ndarray:
        """(N, 2) floor points -> (N,) bool inside the monitored floor rectangle."""
        xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
        (x0, y0), (x1, y1) = self.volume_rect_m
        return (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)


def default_room() -> Room:
    """The synthetic living room (see the module docstring for the plan)."""
    boxes: list[Box] = []
    sofa = (92, 74, 58)
    boxes += [
        Box("sofa seat", "sofa", (4.6, 1.6, 0.0), (6.8, 2.3, 0.42), sofa),
        Box("sofa back", "sofa", (4.6, 2.3, 0.0), (6.8, 2.55, 0.9), tuple(int(c * 0.9) for c in sofa)),
        Box("sofa arm left", "sofa", (4.6, 1.6, 0.42), (4.8, 2.3, 0.62), tuple(int(c * 0.95) for c in sofa)),
        Box("sofa arm right", "sofa", (6.6, 1.6, 0.42), (6.8, 2.3, 0.62), tuple(int(c * 0.95) for c in sofa)),
        Box("TV stand", "tv", (5.0, 0.05, 0.0), (6.4, 0.5, 0.5), (40, 62, 88)),
        Box("TV", "tv", (5.15, 0.12, 0.5), (6.25, 0.2, 1.15), (24, 22, 22)),
    ]
    table_top = (86, 132, 170)
    boxes.append(Box("dinner table top", "table", (1.4, 1.8, 0.71), (3.0, 2.6, 0.76), table_top))
    for i, (x, y) in enumerate(((1.45, 1.85), (2.89, 1.85), (1.45, 2.49), (2.89, 2.49))):
        boxes.append(Box(f"dinner table leg {i + 1}", "table", (x, y, 0.0), (x + 0.06, y + 0.06, 0.71), table_top))
    seats: list[Seat] = []
    chair = (70, 104, 140)
    chairs = ((1.85, 1.2, 90.0), (2.55, 1.2, 90.0), (1.85, 3.2, -90.0), (2.55, 3.2, -90.0))
    for i, (cx, cy, facing) in enumerate(chairs):
        name = f"chair {i + 1}"
        sgn = 1.0 if facing > 0 else -1.0
        boxes.append(Box(f"{name} seat", "chair", (cx - 0.22, cy - 0.22, 0.42), (cx + 0.22, cy + 0.22, 0.46), chair))
        back_y = cy - sgn * 0.22
        boxes.append(Box(f"{name} back", "chair", (cx - 0.22, min(back_y, back_y - sgn * 0.04), 0.46),
                         (cx + 0.22, max(back_y, back_y - sgn * 0.04), 0.92), chair))
        for lx in (cx - 0.21, cx + 0.17):
            for ly in (cy - 0.21, cy + 0.17):
                boxes.append(Box(f"{name} leg", "chair", (lx, ly, 0.0), (lx + 0.04, ly + 0.04, 0.42), chair))
        seats.append(Seat(name, "dinner table", (cx, cy - sgn * 0.05), 0.46, facing, (cx, cy + sgn * 0.4)))
    for name, x in (("sofa left", 5.1), ("sofa middle", 5.7), ("sofa right", 6.3)):
        seats.append(Seat(name, "sofa", (x, 2.14), 0.42, -90.0, (x, 1.3)))
    boxes += [
        Box("kitchen counter", "kitchen", (0.8, 5.4, 0.0), (3.4, 6.0, 0.9), (205, 205, 200)),
        Box("fridge", "kitchen", (3.4, 5.3, 0.0), (4.1, 6.0, 1.9), (228, 228, 226)),
        Box("bookshelf", "shelf", (7.6, 3.0, 0.0), (8.0, 4.5, 1.8), (50, 80, 120)),
    ]
    hotspots = (
        HotSpot("sofa", "sofa", ((4.6, 1.15), (6.8, 1.15), (6.8, 2.55), (4.6, 2.55)), (5.7, 1.3), -90.0),
        HotSpot("dinner table", "table", ((1.0, 0.8), (3.5, 0.8), (3.5, 3.6), (1.0, 3.6)), (2.2, 1.6), 90.0),
        HotSpot("kitchen", "kitchen", ((0.8, 4.6), (4.1, 4.6), (4.1, 5.3), (0.8, 5.3)), (2.1, 5.0), 90.0),
        HotSpot("TV", "tv", ((4.9, 0.5), (6.5, 0.5), (6.5, 1.1), (4.9, 1.1)), (5.7, 0.85), -90.0),
    )
    doors = (
        Door(
            "front door",
            ((0.0, 3.8), (0.5, 3.8), (0.5, 4.8), (0.0, 4.8)),
            (3.8, 4.8),
            2.1,
            (0.6, 4.3),
            (-1.8, 4.3),
            (-2.4, 3.5, 0.0),
            (0.0, 5.1, 2.3),
        ),
    )
    decals = (
        WallDecal("floor", (4.8, 0.6, 6.6, 1.5), (60, 50, 130), "stripes"),
        WallDecal("y0", (1.2, 1.0, 2.4, 1.8), (40, 120, 170), "frame"),
        WallDecal("y0", (2.8, 1.2, 3.4, 1.7), (130, 90, 50), "frame"),
        WallDecal("x1", (0.8, 1.0, 2.2, 1.9), (90, 150, 90), "frame"),
        WallDecal("y1", (5.0, 1.1, 6.4, 1.9), (150, 110, 170), "frame"),
        WallDecal("x0", (1.2, 0.9, 2.6, 1.9), (200, 190, 140), "window"),
    )
    waypoints = {
        "door inside": (0.6, 4.3),
        "hall": (1.2, 4.2),
        "hall east": (4.2, 4.2),
        "north east": (7.0, 4.2),
        "kitchen": (2.1, 5.0),
        "fridge": (3.75, 4.85),
        "centre": (4.05, 3.0),
        "south centre": (4.05, 0.7),
        "south west": (0.7, 0.55),
        "south east": (7.3, 0.8),
        "east": (7.3, 2.3),
        "behind sofa west": (4.25, 2.95),
        "behind sofa east": (7.2, 2.95),
        "west": (0.7, 2.2),
        "table west": (0.9, 1.6),
        "table east": (3.5, 1.6),
        "table north west": (0.9, 2.8),
        "table north east": (3.5, 2.8),
        "TV": (5.7, 0.85),
    }
    return Room(size_m=ROOM_SIZE_M, boxes=tuple(boxes), seats=tuple(seats), hotspots=hotspots, doors=doors,
                decals=decals, waypoints=waypoints)


def default_cameras(*, scale: float = 1.0) -> dict[str, Camera]:
    """The five cameras of the synthetic house, ids cam1..cam5.

    cam1..cam4: pinhole 640x480 at 2.4 m in the corners (0.15 m from both
    walls) looking at the room centre (4, 3, 0.8), fx = fy = 300 px (about
    94 degrees horizontal field of view) with mild barrel distortion that
    differs slightly per camera. cam5: OpenCV fisheye 640x480 in the ceiling
    centre looking straight down, f = 150 px (the image circle of the
    180-degree view just fits the image height), image up = world +y.
    ``scale`` resizes every image (0.5 gives 320x240, for fast tests).
    """
    if not (0.05 <= scale <= 4.0):
        raise ValueError(f"scale must lie in 0.05..4, got {scale}")
    cams: dict[str, Camera] = {}
    target = (4.0, 3.0, 0.8)
    corners = ((0.15, 0.15), (7.85, 0.15), (7.85, 5.85), (0.15, 5.85))
    dists = ((-0.060, 0.010, 0.0004, -0.0003, 0.0), (-0.055, 0.008, -0.0002, 0.0003, 0.0),
             (-0.065, 0.012, 0.0003, 0.0002, 0.0), (-0.058, 0.009, -0.0003, -0.0002, 0.0))
    for i, ((x, y), dist) in enumerate(zip(corners, dists)):
        R, t = look_at((x, y, 2.4), target)
        cam = Camera.pinhole(CAMERA_IDS[i], 640, 480, fx=300.0, fy=300.0, cx=319.5 + (i - 1.5),
                             cy=239.5 + (1.5 - i) * 0.7,
                             dist=dist, R=R, t=t)
        cams[cam.id] = cam
    R, t = look_at((4.0, 3.0, 2.47), (4.0, 3.0, 0.0), up=(0.0, 1.0, 0.0))
    cams["cam5"] = Camera.fisheye("cam5", 640, 480, fx=150.0, fy=150.0, dist=(0.012, -0.004, 0.0, 0.0), R=R, t=t)
    if scale != 1.0:
        cams = {k: c.scaled(scale) for k, c in cams.items()}
    return cams


OCCLUDER_MIN_SIDE_M = 0.1
"""Furniture parts narrower than this on the floor (table and chair legs) are not written as occluders."""


def site_dict(
    room: Room,
    cameras: dict[str, Camera],
    *,
    name: str = SITE_NAME,
    fps: float = FPS,
    residents: int = 1,
    sources: dict[str, str] | None = None,
    backgrounds: dict[str, str] | None = None,
) -> dict:
    """The site file content (as a dict for :func:`common.site.site_from_dict`) for ``room`` and ``cameras``;
    calibrations are referenced as ``calib/<id>.toml``."""
    sources = sources or {}
    backgrounds = backgrounds or {}
    return {
        "name": name,
        "residents": residents,
        "utc_offset_hours": 0.0,
        "volume": {"min_m": [*room.volume_rect_m[0], 0.0],
                   "max_m": [*room.volume_rect_m[1], min(float(room.size_m[2]), VOLUME_HEIGHT_M)]},
        # half-size masks: a quarter of the segmentation, distance-transform and
        # bandwidth cost, with the same scores on the scenario suite
        "carving": {"mask_scale": MASK_SCALE},
        "cameras": [
            {
                "id": cam_id,
                "calibration": f"calib/{cam_id}.toml",
                "format": "voxelwatch",
                "resolution": [cam.width, cam.height],
                "fps": fps,
                "source": sources.get(cam_id, ""),
                "background": backgrounds.get(cam_id, ""),
            }
            for cam_id, cam in cameras.items()
        ],
        "hotspots": [{"name": h.name, "kind": h.kind, "polygon_m": [list(p) for p in h.polygon_m]}
                     for h in room.hotspots],
        "doors": [{"name": d.name, "polygon_m": [list(p) for p in d.polygon_m]} for d in room.doors],
        "occluders": occluders(room),
    }


def occluders(room: Room, *, min_side_m: float = OCCLUDER_MIN_SIDE_M) -> list[dict]:
    """The site file's ``[[occluders]]`` of ``room``: its furniture and wall blocks, except the
    parts narrower than ``min_side_m`` on the floor (legs), which hide nobody."""
    out = []
    for b in room.boxes:
        (x0, y0, z0), (x1, y1, z1) = b.min_m, b.max_m
        if min(x1 - x0, y1 - y0) < min_side_m or z1 <= max(z0, 0.0):
            continue
        x0, y0, x1, y1, z0, z1 = (round(float(v), 3) for v in (x0, y0, x1, y1, max(z0, 0.0), z1))
        out.append({"name": b.name, "polygon_m": [[x0, y0], [x1, y0], [x1, y1], [x0, y1]], "z_m": [z0, z1]})
    return out


def default_site(
    out_dir: str | Path,
    *,
    cameras: dict[str, Camera] | None = None,
    room: Room | None = None,
    sources: dict[str, str] | None = None,
    backgrounds: dict[str, str] | None = None,
    fps: float = FPS,
):
    """Write the synthetic house's site file ``OUT/site.toml`` and calibrations ``OUT/calib/<id>.toml``
    (voxelwatch format); return the loaded :class:`common.site.Site`.

    sources / backgrounds: optional per-camera source and background clip paths
    (relative to ``out_dir``) to record in the site file.
    """
    from common.site import load_site, site_from_dict, write_site

    out = Path(out_dir)
    room = room or default_room()
    cameras = cameras or default_cameras()
    (out / "calib").mkdir(parents=True, exist_ok=True)
    for cam_id, cam in cameras.items():
        save_voxelwatch(cam, out / "calib" / f"{cam_id}.toml")
    content = site_dict(room, cameras, sources=sources, backgrounds=backgrounds, fps=fps)
    site = site_from_dict(content, base_dir=out.resolve())
    path = write_site(site, out / "site.toml")
    return load_site(path)


def floor_coverage(cameras: dict[str, Camera], room: Room | None = None, *, step_m: float = 0.25,
                   z_m: float = 1.0) -> np.ndarray:
    """(ny, nx) int number of cameras that see the point at height ``z_m`` over a floor grid
    with ``step_m`` spacing (cell centres); a planning aid for camera placement."""
    room = room or default_room()
    xs = np.arange(step_m / 2, room.size_m[0], step_m)
    ys = np.arange(step_m / 2, room.size_m[1], step_m)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z_m)], axis=1)
    count = np.zeros(gx.size, dtype=int)
    for cam in cameras.values():
        count += cam.project(pts)[1]
    return count.reshape(gx.shape)


def yaw_of(dx: float, dy: float) -> float:
    """Heading (radians, 0 = +x, counter-clockwise) of a floor direction."""
    return math.atan2(dy, dx)
