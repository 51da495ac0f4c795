"""Groups of people for the randomised worlds: scripts composed at random from behaviours.

:func:`random_people` fills a world of ``duration_s`` seconds with ``count``
people (children 1.0-1.4 m among adults 1.5-2.0 m), each taking part in one
main behaviour and walking about, pausing or leaving around it:

===================  =====  ====================================================
behaviour            people what happens
===================  =====  ====================================================
walk                 1      walks between random points with pauses
enter / leave        1      comes in by a door / goes out by one
sit                  1      walks to a seat, sits, stands up again
kneel / bend         1      kneels, or bends to the floor, and straightens
dwell                1      stands at a hot spot (counter, sofa, table, bed)
fall                 1      falls forward, backward or sideways; lies or gets up
slow_fall            1      slides down slowly to the floor (3 s) beside a wall
group_walk           2-3    walks side by side, 0.3-0.7 m apart
hold_hands           2      walks hand in hand, 0.4 m apart
cross                2      walk towards each other and pass 0.3-0.8 m apart
talk_cluster         3-5    stand in a circle talking
hug                  2      meet, stand 0.35 m apart facing each other, part
sit_side_by_side     2      sit on neighbouring seats
help_fallen          2      one falls, the other kneels beside them, both get up
===================  =====  ====================================================

On top of that, ``step_outs`` people (drawn from a generator of their own, so
that a world without them is the same as before) *step out* after their main
behaviour: they walk out through the nearest door (or, with ``open_edges``,
over the nearest edge of the monitored volume), stay away 3-20 s, come back in
through a door (or an edge) and go on as the others do.

Group members are kept in step with :class:`~synth.behaviour.WaitUntil`
on arrival times estimated generously from the planned paths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from synth.behaviour import (
    Bend, Dwell, Enter, Face, Fall, Kneel, Leave, PersonScript, Return, Sit, Stand, WaitUntil, Walk,
)
from synth.rooms import FloorPlan
from synth.scene import Room

SOLO = ("walk", "enter", "leave", "sit", "kneel", "bend", "dwell", "fall", "slow_fall")
GROUP = ("group_walk", "hold_hands", "cross", "talk_cluster", "hug", "sit_side_by_side", "help_fallen")
BEHAVIOURS = SOLO + GROUP
FALL_BEHAVIOURS = ("fall", "slow_fall", "help_fallen")
_WEIGHTS = {"walk": 3.0, "enter": 1.2, "leave": 1.2, "sit": 2.0, "kneel": 0.7, "bend": 0.8, "dwell": 1.5,
            "fall": 0.9, "slow_fall": 0.4, "group_walk": 1.5, "hold_hands": 0.8, "cross": 1.0, "talk_cluster": 1.2,
            "hug": 0.7, "sit_side_by_side": 1.0, "help_fallen": 0.6}
STEP_OUT_AWAY_S = (3.0, 20.0)
"""How long a person who steps out stays away, seconds."""
_EDGE_OUT_M = 1.0  # how far beyond an open edge people aim when they step out over it
_SIZES = {"group_walk": (2, 3), "hold_hands": (2, 2), "cross": (2, 2), "talk_cluster": (3, 5), "hug": (2, 2),
          "sit_side_by_side": (2, 2), "help_fallen": (2, 2)}


@dataclass
class _Person:
    """A script under construction: steps, where the person is, and when (estimated)."""

    pid: int
    height_m: float
    resident: bool
    xy: tuple[float, float] | None = None
    t: float = 0.0
    steps: list = field(default_factory=list)
    start: object = None
    start_s: float = 0.0
    speed: float = 1.0
    jitter: bool = True
    gone: bool = False
    group: int = 0
    heading: float = 0.0  # radians, direction of the last walking leg

    def script(self) -> PersonScript:
        return PersonScript(self.pid, tuple(self.steps), start=self.start, start_s=self.start_s,
                            resident=self.resident, height_m=self.height_m, speed_jitter=self.jitter)


@dataclass(frozen=True)
class Cast:
    """The people of a world: their scripts, each person's behaviour and group (0: alone), and the
    ids of the people who step out and come back."""

    scripts: tuple[PersonScript, ...]
    behaviours: tuple[str, ...]
    groups: tuple[int, ...]
    step_outs: tuple[int, ...] = ()


def random_people(rng: np.random.Generator, room: Room, plan: FloorPlan, count: int, duration_s: float, *,
                  residents: int = 1, falls: bool = True, step_outs: int = 0,
                  step_rng: np.random.Generator | None = None, open_edges: bool = False) -> Cast:
    """``count`` people (1..12) in ``room`` for ``duration_s`` seconds; ``falls``: fall behaviours allowed.
    ``step_outs``: how many people to try to make step out and come back (drawn with ``step_rng``;
    fewer when nobody else has the time left); ``open_edges``: people may leave and come back over
    the edges of the monitored volume (rooms without doors)."""
    if not 1 <= count <= 12:
        raise ValueError(f"count must lie in 1..12, got {count}")
    if step_outs < 0 or (step_outs and step_rng is None):
        raise ValueError(f"step_outs must be >= 0 and come with step_rng, got {step_outs}")
    people = [_Person(k + 1, _height(rng), k < residents, speed=float(rng.uniform(0.7, 1.3))) for k in range(count)]
    comp = _Composer(rng, room, plan, duration_s)
    behaviours = [""] * count
    groups = [0] * count
    free = list(range(count))
    n_falls = 0
    group_id = 0
    while free:
        names = [b for b in BEHAVIOURS if _SIZES.get(b, (1, 1))[0] <= len(free) and comp.possible(b)]
        if not falls or n_falls >= 2:
            names = [b for b in names if b not in FALL_BEHAVIOURS]
        w = np.array([_WEIGHTS[b] for b in names])
        b = names[int(rng.choice(len(names), p=w / w.sum()))]
        lo, hi = _SIZES.get(b, (1, 1))
        size = int(rng.integers(lo, min(hi, len(free)) + 1))
        members = [people[free.pop(0)] for _ in range(size)]
        if size > 1:
            group_id += 1
        for m in members:
            behaviours[m.pid - 1] = b
            groups[m.pid - 1] = group_id if size > 1 else 0
            m.group = group_id if size > 1 else 0
        comp.do(b, members)
        n_falls += b in FALL_BEHAVIOURS
    stepped: list[int] = []
    if step_outs:
        for k in step_rng.permutation(count):
            if len(stepped) == step_outs:
                break
            if comp.step_out(people[int(k)], step_rng, open_edges=open_edges):
                stepped.append(people[int(k)].pid)
    for p in people:
        comp.fill(p)
    return Cast(tuple(p.script() for p in people), tuple(behaviours), tuple(groups), tuple(sorted(stepped)))


class _Composer:
    def __init__(self, rng, room: Room, plan: FloorPlan, duration_s: float) -> None:
        self.rng = rng
        self.room = room
        self.plan = plan
        self.duration_s = float(duration_s)
        self.used_seats: set[str] = set()
        self.spots: list[tuple[float, float]] = []  # where people were placed, to spread them

    # -- what a room allows

    def possible(self, b: str) -> bool:
        if b in ("enter", "leave"):
            return bool(self.room.doors)
        if b == "sit":
            return bool(self._free_seats())
        if b == "sit_side_by_side":
            return self._seat_pair() is not None
        if b == "dwell":
            return bool(self.room.hotspots)
        return True

    # -- behaviours

    def do(self, b: str, m: list[_Person]) -> None:
        rng = self.rng
        if b in ("walk", "kneel", "bend", "fall", "slow_fall", "sit", "dwell", "leave"):
            p = m[0]
            self.appear(p, late=b != "leave" and rng.random() < 0.25 and bool(self.room.doors))
            self.wander(p, int(rng.integers(0, 2)))
            if b == "walk":
                self.wander(p, 3)
            elif b == "kneel":
                p.steps.append(Kneel(hold_s=float(rng.uniform(2, 6))))
                p.t += 3.3 + 4
            elif b == "bend":
                p.steps.append(Bend(hold_s=float(rng.uniform(1, 3))))
                p.t += 4.0
            elif b == "fall":
                self.fall(p, float(rng.uniform(0.0, 0.5)))
            elif b == "slow_fall":
                self.walk_to(p, self._near_wall())
                self.fall(p, 0.0, duration_s=float(rng.uniform(2.5, 3.5)))
            elif b == "sit":
                self.sit(p, self._free_seats()[int(rng.integers(len(self._free_seats())))])
            elif b == "dwell":
                spot = self.room.hotspots[int(rng.integers(len(self.room.hotspots)))]
                target = self.plan.nearest_free(spot.spot_xy_m) if not self.plan.is_free(spot.spot_xy_m) else spot.spot_xy_m
                via = tuple(self.plan.path(p.xy, target)[:-1])
                hold = float(rng.uniform(12, 25))
                p.steps.append(Dwell(spot.name, hold, via=via, speed_mps=p.speed))
                p.t += self._walk_time(p.xy, list(via) + [spot.spot_xy_m], p.speed) + 1.0 + hold
                p.xy = spot.spot_xy_m
            elif b == "leave":
                self.leave(p)
        elif b == "enter":
            p = m[0]
            self.appear(p, late=True)
            self.wander(p, 2)
        elif b in ("group_walk", "hold_hands"):
            gap = 0.4 if b == "hold_hands" else float(self.rng.uniform(0.3, 0.7))
            self.side_by_side(m, gap)
        elif b == "cross":
            self.cross(m)
        elif b == "talk_cluster":
            self.cluster(m, radius=float(self.rng.uniform(0.45, 0.7)), hold=float(self.rng.uniform(8, 18)))
        elif b == "hug":
            self.cluster(m, radius=0.175, hold=float(self.rng.uniform(3, 6)))
        elif b == "sit_side_by_side":
            pair = self._seat_pair()
            for p, seat in zip(m, pair):
                self.appear(p)
            t_sit = max(p.t for p in m)
            for p, seat in zip(m, pair):
                self.sit(p, seat, after=t_sit, hold=float(self.rng.uniform(12, 25)))
        elif b == "help_fallen":
            self.help_fallen(m)
        else:  # pragma: no cover - BEHAVIOURS is closed
            raise ValueError(f"unknown behaviour {b!r}")

    def appear(self, p: _Person, *, late: bool = False) -> None:
        rng = self.rng
        if late:
            door = self.room.doors[int(rng.integers(len(self.room.doors)))]
            p.start = None
            p.start_s = float(rng.uniform(0, max(1.0, self.duration_s * 0.4)))
            target = self.plan.random_point(rng, away_from=self.spots, min_gap_m=1.0)
            to = tuple(self.plan.path(door.inside_xy_m, target))
            p.steps.append(Enter(door.name, to=to, speed_mps=p.speed))
            p.t = p.start_s + self._walk_time(door.outside_xy_m, [door.inside_xy_m, *to], p.speed)
            p.xy = target
        else:
            xy = self.plan.random_point(rng, away_from=self.spots, min_gap_m=1.2)
            p.start = (xy[0], xy[1], float(rng.uniform(-180, 180)))
            p.xy = xy
            p.t = 0.0
        self.spots.append(p.xy)

    def wander(self, p: _Person, legs: int) -> None:
        for _ in range(legs):
            if p.gone or p.t > self.duration_s:
                return
            target = self.plan.random_point(self.rng, near=p.xy, within_m=4.0)
            self.walk_to(p, target)
            pause = float(self.rng.uniform(0.5, 3.0))
            p.steps.append(Stand(pause))
            p.t += pause

    def fill(self, p: _Person) -> None:
        """Walk about or stand until the end; some leave by a door near the end."""
        while not p.gone and p.t < self.duration_s:
            if self.rng.random() < 0.15 and self.room.doors and p.t < self.duration_s - 12:
                self.leave(p)
                return
            if self.rng.random() < 0.3:
                pause = float(self.rng.uniform(2.0, 8.0))
                p.steps.append(Stand(pause))
                p.t += pause
            else:
                self.wander(p, 1)

    def step_out(self, p: _Person, rng: np.random.Generator, *, open_edges: bool = False) -> bool:
        """Leave by the nearest door (or open edge), stay away 3-20 s, come back by a door (or edge)
        drawn with ``rng``, when that fits before the end with 4 s to spare; False (nothing added)
        otherwise."""
        if p.gone or not math.isfinite(p.t) or not (self.room.doors or open_edges):
            return False
        if self.room.doors:
            door = min(self.room.doors, key=lambda d: math.dist(d.inside_xy_m, p.xy))
            via_out = tuple(self.plan.path(p.xy, door.inside_xy_m)[:-1])
            t_out = self._walk_time(p.xy, [*via_out, door.inside_xy_m, door.outside_xy_m], p.speed)
            back = self.room.doors[int(rng.integers(len(self.room.doors)))]
            target = self.plan.random_point(rng, near=back.inside_xy_m, within_m=4.0)
            to = tuple(self.plan.path(back.inside_xy_m, target))
            t_in = self._walk_time(back.outside_xy_m, [back.inside_xy_m, *to], p.speed)
            leave = Leave(door.name, via=via_out, speed_mps=p.speed)
            come = lambda away: Return(away, back.name, to=to, speed_mps=p.speed)  # noqa: E731
        else:
            out = self._beyond_edge(p.xy)
            via_out = tuple(self.plan.path(p.xy, out))
            t_out = self._walk_time(p.xy, via_out, p.speed)
            (x0, y0), (x1, y1) = self.room.volume_rect_m
            edge_at = (float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)))
            start = self._beyond_edge(edge_at)
            if self.room.inside_volume(np.array([out, start])).any():
                return False  # no free floor beyond the edges
            target = self.plan.random_point(rng, near=edge_at, within_m=3.0)
            to = (start, *self.plan.path(start, target))
            t_in = self._walk_time(start, to[1:], p.speed)
            leave = Leave(None, via=via_out, speed_mps=p.speed)
            come = lambda away: Return(away, None, to=to, speed_mps=p.speed)  # noqa: E731
        spare = self.duration_s - 4.0 - (p.t + t_out + t_in)
        away = min(float(rng.uniform(*STEP_OUT_AWAY_S)), spare)
        if away < STEP_OUT_AWAY_S[0]:
            return False
        p.steps += [leave, come(away)]
        p.t += t_out + away + t_in
        p.xy = tuple(to[-1])
        return True

    def walk_to(self, p: _Person, target, *, speed: float | None = None) -> None:
        speed = p.speed if speed is None else speed
        legs = self.plan.path(p.xy, target)
        prev = legs[-2] if len(legs) > 1 else p.xy
        if math.dist(prev, legs[-1]) > 1e-6:
            p.heading = math.atan2(legs[-1][1] - prev[1], legs[-1][0] - prev[0])
        p.steps.append(Walk(tuple(legs), speed))
        p.t += self._walk_time(p.xy, legs, speed)
        p.xy = tuple(target)

    def leave(self, p: _Person) -> None:
        door = min(self.room.doors, key=lambda d: math.dist(d.inside_xy_m, p.xy))
        via = tuple(self.plan.path(p.xy, door.inside_xy_m)[:-1])
        p.steps.append(Leave(door.name, via=via, speed_mps=p.speed))
        p.t += self._walk_time(p.xy, [*via, door.inside_xy_m, door.outside_xy_m], p.speed)
        p.gone = True

    def sit(self, p: _Person, seat, *, after: float | None = None, hold: float | None = None) -> None:
        self.used_seats.add(seat.name)
        hold = float(self.rng.uniform(8, 25)) if hold is None else hold
        via = tuple(self.plan.path(p.xy, seat.approach_xy_m)[:-1])
        if after is not None and after > p.t:
            p.steps.append(WaitUntil(after))
            p.t = after
        p.steps.append(Sit(seat.name, hold, via=via, speed_mps=p.speed))
        p.t += self._walk_time(p.xy, [*via, seat.approach_xy_m], p.speed) + 1.0 + 1.5 + hold + 1.8
        p.xy = seat.approach_xy_m

    def fall(self, p: _Person, wait_s: float, *, duration_s: float | None = None, lie_s: float | None = None,
             get_up: bool | None = None) -> str:
        rng = self.rng
        direction = ("forward", "backward", "left", "right")[int(rng.integers(4))]
        if get_up is None:
            get_up = rng.random() < 0.5
        if lie_s is None and get_up:
            lie_s = float(rng.uniform(4, 12))
        kw = {} if duration_s is None else {"duration_s": duration_s}
        if wait_s > 0:
            p.steps.append(Stand(wait_s))
        p.steps.append(Fall(direction, lie_s=lie_s if get_up else None, get_up=bool(get_up), **kw))
        p.t += wait_s + (duration_s or 0.9) + (lie_s + 5.2 if get_up else math.inf)
        return direction

    def side_by_side(self, m: list[_Person], gap: float) -> None:
        """Walk together along a leader's path, abreast at ``gap`` metres."""
        rng = self.rng
        for p in m:
            self.appear(p)
            p.jitter = False
        speed = float(rng.uniform(0.7, 1.1))
        width = gap * (len(m) - 1)
        start = self.plan.random_point(rng, margin_m=width / 2 + 0.1, away_from=self.spots, min_gap_m=1.0)
        end = self.plan.random_point(rng, margin_m=width / 2 + 0.1, near=start, within_m=6.0)
        route = [start] + self.plan.path(start, end)
        heading = math.atan2(route[1][1] - route[0][1], route[1][0] - route[0][0]) if len(route) > 1 else 0.0
        offsets = (np.arange(len(m)) - (len(m) - 1) / 2) * gap
        lanes = [_offset_polyline(route, off) for off in offsets]
        # gather abreast at the start, then walk in step
        for p, lane in zip(m, lanes):
            self.walk_to(p, lane[0])
            p.steps.append(Face(facing_deg=math.degrees(heading)))
        t0 = max(p.t for p in m) + 1.5
        for p, lane in zip(m, lanes):
            p.steps.append(WaitUntil(t0))
            p.steps.append(Walk(tuple(lane[1:]), speed))
            p.t = t0 + self._walk_time(lane[0], lane[1:], speed)
            p.xy = lane[-1]

    def cross(self, m: list[_Person]) -> None:
        rng = self.rng
        for p in m:
            self.appear(p)
            p.jitter = False
        centre = self.plan.random_point(rng, margin_m=0.8, away_from=self.spots, min_gap_m=0.8)
        a = float(rng.uniform(0, 2 * math.pi))
        half = float(rng.uniform(1.5, 3.0))
        side = float(rng.uniform(0.15, 0.4))
        u = np.array([math.cos(a), math.sin(a)])
        n = np.array([-u[1], u[0]])
        c = np.asarray(centre)
        ends = [(c - half * u + side * n, c + half * u + side * n), (c + half * u - side * n, c - half * u - side * n)]
        ends = [(self._free_or_near(s), self._free_or_near(e)) for s, e in ends]
        speed = float(rng.uniform(0.8, 1.2))
        for p, (s, _) in zip(m, ends):
            self.walk_to(p, s)
        t0 = max(p.t for p in m) + 1.5
        for p, (s, e) in zip(m, ends):
            p.steps.append(WaitUntil(t0))
            p.steps.append(Walk((e,), speed))
            p.t = t0 + self._walk_time(s, [e], speed)
            p.xy = e

    def cluster(self, m: list[_Person], *, radius: float, hold: float) -> None:
        """Meet on a circle of ``radius`` around a point, face its centre, stand ``hold`` s."""
        rng = self.rng
        for p in m:
            self.appear(p)
        centre = self.plan.random_point(rng, margin_m=radius, away_from=self.spots, min_gap_m=1.0)
        a0 = float(rng.uniform(0, 2 * math.pi))
        slots = [(centre[0] + radius * math.cos(a0 + 2 * math.pi * k / len(m)),
                  centre[1] + radius * math.sin(a0 + 2 * math.pi * k / len(m))) for k in range(len(m))]
        for p, slot in zip(m, slots):
            self.walk_to(p, slot)
            p.steps.append(Face(toward=centre))
        t0 = max(p.t for p in m) + 2.0
        for p in m:
            p.steps.append(WaitUntil(t0))
            p.steps.append(Stand(hold, "rest"))
            p.t = t0 + hold

    def help_fallen(self, m: list[_Person]) -> None:
        rng = self.rng
        faller, helper = m
        self.appear(faller)
        self.appear(helper)
        target = self.plan.random_point(rng, margin_m=1.0, away_from=self.spots, min_gap_m=1.0)
        self.walk_to(faller, target)
        lie = float(rng.uniform(8, 14))
        t_fall = faller.t
        direction = self.fall(faller, 0.0, lie_s=lie, get_up=True)
        # the helper kneels beside the middle of the lying body
        heading = faller.heading
        turn = {"forward": 0.0, "backward": math.pi, "left": math.pi / 2, "right": -math.pi / 2}[direction]
        u = np.array([math.cos(heading + turn), math.sin(heading + turn)])
        n = np.array([-u[1], u[0]])
        mid = np.asarray(target) + u * faller.height_m * 0.5
        beside = None
        for side in (1.0, -1.0):
            q = tuple(mid + side * n * 0.75)
            if self.plan.is_free(q):
                beside = q
                break
        if beside is None:
            beside = self.plan.nearest_free(tuple(mid + n * 0.75))
        arrive = t_fall + 1.5
        self.walk_to(helper, beside)
        if helper.t < arrive:
            helper.steps.append(WaitUntil(arrive))
            helper.t = arrive
        helper.steps.append(Face(toward=tuple(mid)))
        helper.steps.append(Kneel(hold_s=float(max(2.0, t_fall + 0.9 + lie - helper.t - 1.5))))
        helper.t = max(helper.t + 5.0, t_fall + lie + 2.0)

    # -- helpers

    def _free_seats(self) -> list:
        return [s for s in self.room.seats if s.name not in self.used_seats and self.plan.is_free(s.approach_xy_m)]

    def _seat_pair(self):
        free = self._free_seats()
        best = None
        for i, a in enumerate(free):
            for b in free[i + 1:]:
                if a.hotspot == b.hotspot and math.dist(a.xy_m, b.xy_m) < 1.0:
                    best = (a, b)
        return best

    def _near_wall(self) -> tuple[float, float]:
        w, d, _ = self.room.size_m
        for _ in range(30):
            p = self.plan.random_point(self.rng)
            if min(p[0], p[1], w - p[0], d - p[1]) < 0.7:
                return p
        return self.plan.random_point(self.rng)

    def _beyond_edge(self, xy) -> tuple[float, float]:
        """The free floor nearest to a point :data:`_EDGE_OUT_M` beyond the monitored volume's edge
        nearest to ``xy`` (a room without doors whose people may leave over its edges)."""
        (x0, y0), (x1, y1) = self.room.volume_rect_m
        x, y = float(xy[0]), float(xy[1])
        gaps = {"x0": x - x0, "x1": x1 - x, "y0": y - y0, "y1": y1 - y}
        edge = min(gaps, key=gaps.get)
        x, y = min(max(x, x0), x1), min(max(y, y0), y1)
        aim = {"x0": (x0 - _EDGE_OUT_M, y), "x1": (x1 + _EDGE_OUT_M, y), "y0": (x, y0 - _EDGE_OUT_M),
               "y1": (x, y1 + _EDGE_OUT_M)}[edge]
        return self.plan.nearest_free(aim)

    def _free_or_near(self, xy) -> tuple[float, float]:
        xy = (float(xy[0]), float(xy[1]))
        return xy if self.plan.is_free(xy) else self.plan.nearest_free(xy)

    @staticmethod
    def _walk_time(start, legs, speed: float) -> float:
        """A generous estimate of walking ``start`` -> legs: distance at speed, plus turning and ramps."""
        pts = [start, *legs]
        dist = sum(math.dist(a, b) for a, b in zip(pts, pts[1:]))
        return dist / (speed * 0.95) + 1.2 + 0.6 * len(legs)


def _height(rng) -> float:
    if rng.random() < 0.15:
        return float(np.round(rng.uniform(1.0, 1.4), 2))
    return float(np.round(rng.uniform(1.5, 2.0), 2))


def _offset_polyline(route: list, offset: float) -> list[tuple[float, float]]:
    """``route`` shifted sideways by ``offset`` metres (left of the direction of travel positive)."""
    pts = np.asarray(route, dtype=np.float64)
    if len(pts) < 2 or offset == 0:
        return [tuple(map(float, p)) for p in pts]
    out = []
    for k in range(len(pts)):
        a = pts[max(k - 1, 0)]
        b = pts[min(k + 1, len(pts) - 1)]
        d = b - a
        d /= max(np.linalg.norm(d), 1e-9)
        out.append(tuple(map(float, pts[k] + offset * np.array([-d[1], d[0]]))))
    return out
