"""Random rooms for the randomised worlds: shape, furniture, seats, hot spots, doors, and where people can walk.

:func:`random_room` draws a rectangular or L-shaped room (3 x 3 m to 12 x 10 m,
ceiling 2.3-3.0 m) for a random generator: one or two doors in the outer
walls, each onto a short corridor; furniture against the walls (sofa, bed,
kitchen counter, cupboards) and a dinner table with chairs standing free;
seats on the sofa, the chairs and the bed's edge; a hot spot at each piece.
The missing corner of an L-shaped room is a full-height block, so it
occludes like a wall.

:class:`FloorPlan` is the walkable floor of a room at 10 cm: free of walls,
furniture and the L's block with a body's clearance, with shortest paths
between two points (Dijkstra on the 8-connected grid, then cut to the
fewest straight legs that stay on free floor) and random free points.

World frame: metres, Z up, the room's floor rectangle from (0, 0) to
``size_m[:2]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from synth.scene import Box, Door, HotSpot, Room, Seat, WallDecal

SIZE_RANGE_M = ((3.0, 12.0), (3.0, 10.0))
CEILING_RANGE_M = (2.3, 3.0)
DOOR_WIDTH_M = 0.95
DOOR_HEIGHT_M = 2.1
BLOCK = "wall block"

_SOFA = ((92, 74, 58), (70, 70, 120), (60, 100, 70), (120, 120, 125), (40, 60, 140))
_WOOD = ((86, 132, 170), (60, 90, 120), (140, 170, 200), (50, 70, 90))
_WHITE = ((205, 205, 200), (228, 228, 226), (190, 200, 210))
_BED = ((200, 180, 160), (150, 170, 200), (170, 150, 190))


def random_room(rng: np.random.Generator, *, min_area_m2: float = 9.0, shape: str | None = None,
                size_m: tuple[float, float] | None = None) -> Room:
    """A random room with at least ``min_area_m2`` of floor (before furniture).

    shape: 'rect' or 'L' (default: L-shaped one time in three when both sides reach 4 m).
    size_m: the floor rectangle (default: drawn from :data:`SIZE_RANGE_M`).
    """
    if shape not in (None, "rect", "L"):
        raise ValueError(f"shape must be 'rect' or 'L', got {shape!r}")
    for _ in range(200):
        if size_m is None:
            w = float(np.round(rng.uniform(*SIZE_RANGE_M[0]), 1))
            d = float(np.round(rng.uniform(*SIZE_RANGE_M[1]), 1))
        else:
            w, d = (float(v) for v in size_m)
        kind = shape or ("L" if min(w, d) >= 4.0 and rng.random() < 1 / 3 else "rect")
        block = _l_block(rng, w, d) if kind == "L" else None
        area = w * d - (0.0 if block is None else (block[2] - block[0]) * (block[3] - block[1]))
        if area >= min_area_m2 or size_m is not None:
            break
    else:  # pragma: no cover - the largest rooms always qualify
        raise ValueError(f"no room of {min_area_m2} m2 within {SIZE_RANGE_M}")
    h = float(np.round(rng.uniform(*CEILING_RANGE_M), 2))
    return _furnish(rng, (w, d, h), block)


@dataclass(frozen=True)
class RoomSummary:
    """What a room holds, for reports: shape 'rect' | 'L', floor size and area, furniture kinds."""

    shape: str
    size_m: tuple[float, float, float]
    floor_area_m2: float
    furniture: tuple[str, ...]
    doors: int


def summarise_room(room: Room) -> RoomSummary:
    block = [b for b in room.boxes if b.kind == "wall"]
    area = room.size_m[0] * room.size_m[1] - sum((b.max_m[0] - b.min_m[0]) * (b.max_m[1] - b.min_m[1]) for b in block)
    kinds = tuple(dict.fromkeys(b.kind for b in room.boxes if b.kind != "wall"))
    return RoomSummary("L" if block else "rect", tuple(room.size_m), round(area, 2), kinds, len(room.doors))


class FloorPlan:
    """Where a person's pelvis can be in ``room``: a 2-D grid of free cells.

    cell_m: grid step. clearance_m: distance kept from walls, furniture (anything
    below 1.2 m high counts: a table top blocks legs too) and the L's block.
    region: optional ((x0, y0), (x1, y1)) to confine people to (a real rig's
    monitored area and its surroundings).
    """

    def __init__(self, room: Room, *, cell_m: float = 0.1, clearance_m: float = 0.3,
                 region: tuple[tuple[float, float], tuple[float, float]] | None = None) -> None:
        self.room = room
        self.cell_m = float(cell_m)
        nx = int(math.ceil(room.size_m[0] / cell_m))
        ny = int(math.ceil(room.size_m[1] / cell_m))
        self.shape = (ny, nx)
        occupied = np.zeros((ny, nx), dtype=bool)
        occupied[0, :] = occupied[-1, :] = occupied[:, 0] = occupied[:, -1] = True
        for box in room.boxes:
            if box.min_m[2] >= 1.2:
                continue
            i0, j0 = self._cell(box.min_m[0], box.min_m[1], floor=True)
            i1, j1 = self._cell(box.max_m[0], box.max_m[1], floor=False)
            occupied[max(j0, 0):min(j1 + 1, ny), max(i0, 0):min(i1 + 1, nx)] = True
        clear = ndimage.distance_transform_edt(~occupied) * cell_m
        self.free = clear >= clearance_m
        if region is not None:
            (x0, y0), (x1, y1) = region
            xs, ys = self.cell_centres()
            self.free &= (xs[None, :] >= x0) & (xs[None, :] <= x1) & (ys[:, None] >= y0) & (ys[:, None] <= y1)
        # keep the largest connected free area: every free cell reaches every other
        labels, n = ndimage.label(self.free, structure=np.ones((3, 3)))
        if n > 1:
            sizes = ndimage.sum(self.free, labels, index=np.arange(1, n + 1))
            self.free = labels == 1 + int(np.argmax(sizes))
        if not self.free.any():
            raise ValueError("the room has no free floor")
        self._graph = _grid_graph(self.free, cell_m)
        self._index = np.full(self.free.shape, -1, dtype=np.int64)
        self._index[self.free] = np.arange(int(self.free.sum()))
        self._cells = np.argwhere(self.free)  # (N, 2) rows (j, i)

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(nx,) x and (ny,) y of the cell centres, metres."""
        return ((np.arange(self.shape[1]) + 0.5) * self.cell_m, (np.arange(self.shape[0]) + 0.5) * self.cell_m)

    @property
    def free_area_m2(self) -> float:
        return float(self.free.sum()) * self.cell_m ** 2

    def is_free(self, xy) -> bool:
        i, j = self._cell(*xy, floor=True)
        return 0 <= j < self.shape[0] and 0 <= i < self.shape[1] and bool(self.free[j, i])

    def nearest_free(self, xy) -> tuple[float, float]:
        """The centre of the free cell nearest to ``xy``."""
        c = (np.asarray(xy, dtype=np.float64) / self.cell_m)[::-1] - 0.5
        k = int(np.argmin(np.sum((self._cells - c) ** 2, axis=1)))
        j, i = self._cells[k]
        return (float((i + 0.5) * self.cell_m), float((j + 0.5) * self.cell_m))

    def random_point(self, rng: np.random.Generator, *, near=None, within_m: float | None = None,
                     away_from=(), min_gap_m: float = 0.0, margin_m: float = 0.0) -> tuple[float, float]:
        """A random free point; ``near``/``within_m`` keep it close to a point; ``away_from``/
        ``min_gap_m`` keep it from others (kept as far as possible when the floor is crowded);
        ``margin_m`` keeps it this much further from obstacles."""
        cells = self._cells
        if margin_m > 0:
            deep = ndimage.binary_erosion(self.free, iterations=max(1, int(round(margin_m / self.cell_m))))
            if deep.any():
                cells = np.argwhere(deep)
        xy = (cells[:, ::-1] + 0.5) * self.cell_m
        ok = np.ones(len(xy), dtype=bool)
        if near is not None and within_m is not None:
            ok &= np.hypot(*(xy - np.asarray(near)).T) <= within_m
            if not ok.any():
                ok[:] = True
        if len(away_from) and min_gap_m > 0:
            gaps = np.min(np.linalg.norm(xy[:, None, :] - np.asarray(away_from, dtype=np.float64)[None], axis=2), axis=1)
            far = ok & (gaps >= min_gap_m)
            if far.any():
                ok = far
            else:
                ok &= gaps >= np.max(gaps[ok]) * 0.8
        k = int(rng.choice(np.nonzero(ok)[0]))
        jitter = rng.uniform(-0.3, 0.3, size=2) * self.cell_m
        return (float(xy[k, 0] + jitter[0]), float(xy[k, 1] + jitter[1]))

    def path(self, a, b) -> list[tuple[float, float]]:
        """Waypoints from ``a`` to ``b`` (``a`` left out, ``b`` last) that keep to free floor
        between them; straight when the line is free."""
        a = tuple(float(v) for v in a)
        b = tuple(float(v) for v in b)
        if self.line_free(a, b):
            return [b]
        sa, sb = self.nearest_free(a), self.nearest_free(b)
        ia = self._index[self._cell(*sa, floor=True)[::-1]]
        ib = self._index[self._cell(*sb, floor=True)[::-1]]
        _, pred = csgraph.dijkstra(self._graph, indices=int(ia), return_predecessors=True)
        chain = [int(ib)]
        while chain[-1] != ia and pred[chain[-1]] >= 0:
            chain.append(int(pred[chain[-1]]))
        cells = self._cells[chain[::-1]]
        pts = [a] + [(float((i + 0.5) * self.cell_m), float((j + 0.5) * self.cell_m)) for j, i in cells] + [b]
        out: list[tuple[float, float]] = []
        k = 0
        while k < len(pts) - 1:
            nxt = len(pts) - 1
            while nxt > k + 1 and not self.line_free(pts[k], pts[nxt]):
                nxt -= 1
            out.append(pts[nxt])
            k = nxt
        return out

    def line_free(self, a, b) -> bool:
        """Whether the straight floor segment a -> b stays on free cells (its ends may not)."""
        n = max(2, int(math.hypot(b[0] - a[0], b[1] - a[1]) / (self.cell_m * 0.5)) + 1)
        s = np.linspace(0.0, 1.0, n)[1:-1]
        if s.size == 0:
            return True
        xs = a[0] + s * (b[0] - a[0])
        ys = a[1] + s * (b[1] - a[1])
        i = np.floor(xs / self.cell_m).astype(int)
        j = np.floor(ys / self.cell_m).astype(int)
        inside = (i >= 0) & (i < self.shape[1]) & (j >= 0) & (j < self.shape[0])
        if not inside.all():
            return False
        # a leg may start or end just off the free floor (a seat's approach, a doorway)
        hit = ~self.free[j, i]
        core = slice(int(0.15 * s.size), int(math.ceil(0.85 * s.size)))
        return not hit[core].any() and hit.sum() <= max(2, int(0.3 * s.size))

    def _cell(self, x: float, y: float, *, floor: bool) -> tuple[int, int]:
        f = math.floor if floor else math.ceil
        return int(f(x / self.cell_m)), int(f(y / self.cell_m))


# ---------------------------------------------------------------------- helpers


def _grid_graph(free: np.ndarray, cell_m: float) -> sparse.csr_matrix:
    idx = np.full(free.shape, -1, dtype=np.int64)
    idx[free] = np.arange(int(free.sum()))
    rows, cols, w = [], [], []
    ny, nx = free.shape
    for dj, di, cost in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, math.sqrt(2)), (1, -1, math.sqrt(2))):
        a = free[max(0, -dj):ny - max(0, dj), max(0, -di):nx - max(0, di)]
        b = free[max(0, dj):ny - max(0, -dj) or None, max(0, di):nx - max(0, -di) or None]
        ia = idx[max(0, -dj):ny - max(0, dj), max(0, -di):nx - max(0, di)]
        ib = idx[max(0, dj):ny - max(0, -dj) or None, max(0, di):nx - max(0, -di) or None]
        both = a & b
        rows.append(ia[both])
        cols.append(ib[both])
        w.append(np.full(int(both.sum()), cost * cell_m))
    r, c, ww = np.concatenate(rows), np.concatenate(cols), np.concatenate(w)
    n = int(free.sum())
    return sparse.csr_matrix((np.concatenate([ww, ww]), (np.concatenate([r, c]), np.concatenate([c, r]))), shape=(n, n))


def _l_block(rng, w: float, d: float) -> tuple[float, float, float, float]:
    bw = float(np.round(rng.uniform(0.3, 0.5) * w, 1))
    bd = float(np.round(rng.uniform(0.3, 0.5) * d, 1))
    corner = int(rng.integers(4))
    x0 = 0.0 if corner in (0, 3) else w - bw
    y0 = 0.0 if corner in (0, 1) else d - bd
    return (x0, y0, x0 + bw, y0 + bd)


class _Layout:
    """Free-floor bookkeeping while furnishing: footprints that must not overlap."""

    def __init__(self, size_m, block) -> None:
        self.w, self.d, self.h = size_m
        self.taken: list[tuple[float, float, float, float]] = []
        if block is not None:
            self.taken.append(block)

    def fits(self, rect, gap: float) -> bool:
        x0, y0, x1, y1 = rect
        if x0 < -1e-9 or y0 < -1e-9 or x1 > self.w + 1e-9 or y1 > self.d + 1e-9:
            return False
        return all(x0 >= b[2] + gap or x1 <= b[0] - gap or y0 >= b[3] + gap or y1 <= b[1] - gap for b in self.taken)


def _wall_frame(wall: str, w: float, d: float, offset: float):
    """A map from a wall's local frame (u along the wall from ``offset``, v into the room)
    to world (x, y), and the facing (degrees) that looks away from the wall."""
    if wall == "y0":
        return (lambda u, v: (offset + u, v)), 90.0
    if wall == "y1":
        return (lambda u, v: (offset + u, d - v)), -90.0
    if wall == "x0":
        return (lambda u, v: (v, offset + u)), 0.0
    return (lambda u, v: (w - v, offset + u)), 180.0


def _rect(to_world, u0, v0, u1, v1) -> tuple[float, float, float, float]:
    (ax, ay), (bx, by) = to_world(u0, v0), to_world(u1, v1)
    return (min(ax, bx), min(ay, by), max(ax, bx), max(ay, by))


def _box(name, kind, rect, z0, z1, colour) -> Box:
    x0, y0, x1, y1 = rect
    return Box(name, kind, (round(x0, 3), round(y0, 3), z0), (round(x1, 3), round(y1, 3), z1), colour)


def _pick(rng, table):
    return tuple(int(c) for c in table[int(rng.integers(len(table)))])


def _furnish(rng: np.random.Generator, size_m, block) -> Room:
    w, d, h = size_m
    lay = _Layout(size_m, block)
    boxes: list[Box] = []
    seats: list[Seat] = []
    hotspots: list[HotSpot] = []
    doors = _doors(rng, lay, 1 if rng.random() < 0.6 or w * d < 14 else 2)
    if block is not None:
        boxes.append(_box(BLOCK, "wall", block, 0.0, h, (200, 205, 210)))
    area = w * d
    wants = ["sofa", "table"]
    extra = ["counter", "bed", "cupboard", "cupboard", "counter"]
    rng.shuffle(extra)
    wants += extra[: int(np.clip(area // 12, 0, 4))]
    for item in wants:
        placed = _place(rng, item, lay, boxes, seats, hotspots)
        if not placed and item == "sofa":
            _place(rng, "cupboard", lay, boxes, seats, hotspots)
    decals = _decals(rng, size_m)
    light = (w / 2, d / 2, h - 0.05)
    if block is not None:  # the lamp hangs over the free floor of an L
        bx = (block[0] + block[2]) / 2
        by = (block[1] + block[3]) / 2
        light = (w - bx if abs(w - 2 * bx) > 0.1 else w / 2, d - by if abs(d - 2 * by) > 0.1 else d / 2, h - 0.05)
    return Room(size_m=(w, d, h), boxes=tuple(boxes), seats=tuple(seats), hotspots=tuple(hotspots), doors=tuple(doors),
                decals=decals, light_m=light)


def _doors(rng, lay: _Layout, count: int) -> list[Door]:
    doors: list[Door] = []
    walls = ["x0", "x1", "y0", "y1"]
    rng.shuffle(walls)
    for wall in walls:
        if len(doors) >= count:
            break
        length = lay.d if wall in ("x0", "x1") else lay.w
        for _ in range(20):
            a = float(np.round(rng.uniform(0.4, length - DOOR_WIDTH_M - 0.4), 2))
            to_world, facing = _wall_frame(wall, lay.w, lay.d, a)
            zone = _rect(to_world, -0.3, 0.0, DOOR_WIDTH_M + 0.3, 1.3)
            if lay.fits(zone, 0.0):
                lay.taken.append(zone)
                doors.append(_door(f"door {len(doors) + 1}", wall, a, lay.w, lay.d, to_world))
                break
    return doors


def _door(name, wall, a, w, d, to_world) -> Door:
    b = a + DOOR_WIDTH_M
    mid = DOOR_WIDTH_M / 2
    zone = _rect(to_world, 0.0, 0.0, DOOR_WIDTH_M, 0.5)
    polygon = ((zone[0], zone[1]), (zone[2], zone[1]), (zone[2], zone[3]), (zone[0], zone[3]))
    inside = to_world(mid, 0.6)
    outside = to_world(mid, -1.8)
    c = _rect(to_world, -0.3, -2.4, DOOR_WIDTH_M + 0.3, 0.0)
    return Door(name, tuple((round(x, 3), round(y, 3)) for x, y in polygon), (a, b), DOOR_HEIGHT_M,
                tuple(round(v, 3) for v in inside), tuple(round(v, 3) for v in outside),
                (c[0], c[1], 0.0), (c[2], c[3], 2.3), wall=wall)


def _place(rng, item: str, lay: _Layout, boxes, seats, hotspots) -> bool:
    for _ in range(40):
        if item == "table":
            if _place_table(rng, lay, boxes, seats, hotspots):
                return True
            continue
        wall = ("x0", "x1", "y0", "y1")[int(rng.integers(4))]
        length = {"sofa": rng.uniform(1.6, 2.4), "bed": 2.0, "counter": rng.uniform(1.5, 3.0),
                  "cupboard": rng.uniform(0.8, 1.5)}[item]
        depth = {"sofa": 0.9, "bed": rng.uniform(1.4, 1.6) if rng.random() < 0.6 else 0.95, "counter": 0.6,
                 "cupboard": 0.5}[item]
        if item == "bed":
            length, depth = depth, 2.0  # the bed's head is against the wall
        wall_len = lay.d if wall in ("x0", "x1") else lay.w
        if wall_len < length + 0.2:
            continue
        a = float(np.round(rng.uniform(0.05, wall_len - length - 0.05), 2))
        to_world, facing = _wall_frame(wall, lay.w, lay.d, a)
        clear_front = 0.9 if item != "cupboard" else 0.5
        footprint = _rect(to_world, 0.0, 0.0, length, depth)
        if not lay.fits(_rect(to_world, 0.0, 0.0, length, depth + clear_front), 0.1):
            continue
        lay.taken.append(footprint)
        name = _unique_name(item, {h.name for h in hotspots} | {b.name for b in boxes})
        if item == "sofa":
            _sofa(rng, name, length, to_world, facing, boxes, seats, hotspots)
        elif item == "bed":
            _bed(rng, name, length, to_world, facing, boxes, seats, hotspots)
        elif item == "counter":
            colour = _pick(rng, _WHITE)
            boxes.append(_box(name, "kitchen", footprint, 0.0, 0.9, colour))
            spot = to_world(length / 2, depth + 0.35)
            zone = _rect(to_world, 0.0, depth, length, depth + 0.75)
            hotspots.append(_hotspot(name, "kitchen", zone, spot, facing + 180.0))
        else:
            boxes.append(_box(name, "cupboard", footprint, 0.0, float(np.round(rng.uniform(1.8, 2.1), 2)),
                              _pick(rng, _WOOD)))
        return True
    return False


def _sofa(rng, name, length, to_world, facing, boxes, seats, hotspots) -> None:
    colour = _pick(rng, _SOFA)
    dark = tuple(int(c * 0.9) for c in colour)
    boxes += [
        _box(f"{name} back", "sofa", _rect(to_world, 0.0, 0.0, length, 0.25), 0.0, 0.9, dark),
        _box(f"{name} seat", "sofa", _rect(to_world, 0.0, 0.25, length, 0.9), 0.0, 0.42, colour),
        _box(f"{name} arm left", "sofa", _rect(to_world, 0.0, 0.25, 0.2, 0.9), 0.42, 0.62, dark),
        _box(f"{name} arm right", "sofa", _rect(to_world, length - 0.2, 0.25, length, 0.9), 0.42, 0.62, dark),
    ]
    n = max(1, int((length - 0.4) // 0.6))
    for k in range(n):
        u = 0.2 + (length - 0.4) * (k + 0.5) / n
        seats.append(Seat(f"{name} seat {k + 1}", name, _r2(to_world(u, 0.45)), 0.42, facing, _r2(to_world(u, 1.2))))
    hotspots.append(_hotspot(name, "sofa", _rect(to_world, 0.0, 0.0, length, 1.35), _r2(to_world(length / 2, 1.2)),
                             facing))


def _bed(rng, name, width, to_world, facing, boxes, seats, hotspots) -> None:
    colour = _pick(rng, _BED)
    boxes += [
        _box(f"{name} headboard", "bed", _rect(to_world, 0.0, 0.0, width, 0.08), 0.0, 0.95, _pick(rng, _WOOD)),
        _box(f"{name} mattress", "bed", _rect(to_world, 0.0, 0.08, width, 2.0), 0.0, 0.5, colour),
    ]
    # sitting on the edge of the bed, on its free long side (the side facing the room's centre is not
    # known here: use the side at u = width, the other may be against a cupboard)
    for k, v in enumerate((0.8, 1.4)):
        seats.append(Seat(f"{name} edge {k + 1}", name, _r2(to_world(width - 0.25, v)), 0.5, facing - 90.0,
                          _r2(to_world(width + 0.5, v))))
    hotspots.append(_hotspot(name, "bed", _rect(to_world, 0.0, 0.0, width + 0.7, 2.0), _r2(to_world(width + 0.45, 1.0)),
                             facing - 90.0 + 180.0))


def _place_table(rng, lay: _Layout, boxes, seats, hotspots) -> bool:
    tw = float(np.round(rng.uniform(1.2, 1.8), 2))
    td = float(np.round(rng.uniform(0.8, 1.0), 2))
    if lay.w < tw + 2.2 or lay.d < td + 2.2:
        return False
    x0 = float(np.round(rng.uniform(1.1, lay.w - tw - 1.1), 2))
    y0 = float(np.round(rng.uniform(1.1, lay.d - td - 1.1), 2))
    outer = (x0 - 0.75, y0 - 0.75, x0 + tw + 0.75, y0 + td + 0.75)
    if not lay.fits(outer, 0.2):
        return False
    lay.taken.append(outer)
    name = _unique_name("dinner table", {h.name for h in hotspots})
    wood = _pick(rng, _WOOD)
    boxes.append(_box(f"{name} top", "table", (x0, y0, x0 + tw, y0 + td), 0.71, 0.76, wood))
    for lx, ly in ((x0 + 0.05, y0 + 0.05), (x0 + tw - 0.11, y0 + 0.05), (x0 + 0.05, y0 + td - 0.11),
                   (x0 + tw - 0.11, y0 + td - 0.11)):
        boxes.append(_box(f"{name} leg", "table", (lx, ly, lx + 0.06, ly + 0.06), 0.0, 0.71, wood))
    chair = _pick(rng, _WOOD)
    per_side = 2 if tw >= 1.4 else 1
    k = 0
    for side, cy, facing in ((0, y0 - 0.3, 90.0), (1, y0 + td + 0.3, -90.0)):
        for m in range(per_side):
            cx = x0 + tw * (m + 0.5) / per_side
            k += 1
            cname = f"{name} chair {k}"
            sgn = 1.0 if facing > 0 else -1.0
            boxes.append(_box(f"{cname} seat", "chair", (cx - 0.22, cy - 0.22, cx + 0.22, cy + 0.22), 0.42, 0.46, chair))
            back_y = cy - sgn * 0.22
            boxes.append(_box(f"{cname} back", "chair", (cx - 0.22, min(back_y, back_y - sgn * 0.04), cx + 0.22,
                                                         max(back_y, back_y - sgn * 0.04)), 0.46, 0.92, chair))
            for lx in (cx - 0.21, cx + 0.17):
                for ly in (cy - 0.21, cy + 0.17):
                    boxes.append(_box(f"{cname} leg", "chair", (lx, ly, lx + 0.04, ly + 0.04), 0.0, 0.42, chair))
            seats.append(Seat(cname, name, (round(cx, 3), round(cy - sgn * 0.05, 3)), 0.46, facing,
                              (round(cx, 3), round(cy - sgn * 0.62, 3))))
    hotspots.append(_hotspot(name, "table", outer, (round(x0 - 0.45, 3), round(y0 + td / 2, 3)), 0.0))
    return True


def _unique_name(base: str, taken: set[str]) -> str:
    name, k = base, 1
    while name in taken:
        k += 1
        name = f"{base} {k}"
    return name


def _hotspot(name, kind, rect, spot, facing) -> HotSpot:
    x0, y0, x1, y1 = (round(v, 3) for v in rect)
    return HotSpot(name, kind, ((x0, y0), (x1, y0), (x1, y1), (x0, y1)), _r2(spot), float(facing % 360.0))


def _r2(p) -> tuple[float, float]:
    return (round(float(p[0]), 3), round(float(p[1]), 3))


def _decals(rng, size_m) -> tuple[WallDecal, ...]:
    w, d, h = size_m
    out = []
    for _ in range(int(rng.integers(2, 6))):
        wall = ("x0", "x1", "y0", "y1")[int(rng.integers(4))]
        length = d if wall in ("x0", "x1") else w
        a = float(rng.uniform(0.2, max(0.3, length - 1.5)))
        b = min(length - 0.1, a + float(rng.uniform(0.5, 1.4)))
        z0 = float(rng.uniform(0.9, 1.3))
        out.append(WallDecal(wall, (a, z0, b, min(h - 0.2, z0 + rng.uniform(0.4, 0.9))),
                             tuple(int(c) for c in rng.integers(30, 220, size=3)),
                             ("frame", "window", "plain")[int(rng.integers(3))]))
    if rng.random() < 0.6:
        x0, y0 = float(rng.uniform(0.5, w - 2.0)), float(rng.uniform(0.5, d - 1.6))
        out.append(WallDecal("floor", (x0, y0, x0 + 1.5, y0 + 1.0), tuple(int(c) for c in rng.integers(40, 160, size=3)),
                             "stripes"))
    return tuple(out)
