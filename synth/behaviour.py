"""Scripted behaviours: steps as data, compiled into per-frame poses.

A person's script is a :class:`PersonScript`: where they start (or an
:class:`Enter` step: they appear in the corridor beyond the door and walk
in) and a list of steps: :class:`Walk`, :class:`Face`, :class:`Stand`,
:class:`Dwell`, :class:`Sit`, :class:`Fall`, :class:`Bend`, :class:`Kneel`,
:class:`Wait`, :class:`WaitUntil`, :class:`Leave` (then, to come back
after a while, :class:`Return`). :func:`compile_person`
turns it into a :class:`Timeline` of segments (key-framed transitions,
holds and walks) that evaluates any batch of times into poses, posture
labels, a moving flag and presence, deterministically for a seed.

Transition timing: sitting down 1.5 s, standing up 1.8 s, falling 0.9 s
(accelerating drop), bending 1.0 s down / 1.0 s up, kneeling 1.5 s / 1.8 s,
getting up from the floor 4 s (5 s from the side, 5.2 s from the back),
turning in place about 2 rad/s; walking speed as scripted (0.6..1.4 m/s)
with +-5 % per-seed variation (unless ``speed_jitter`` is off) and a
1.5 m/s^2 start/stop ramp.

Posture labels and the events they imply switch at documented instants:
``sit_down`` / ``stand_up`` at the middle of the transition (half-way
down / up), ``fall`` when the body reaches the floor (the end of the
drop), bending/kneeling ('bending') half-way down and back to 'standing'
half-way up, getting up: 'bending' once on hands and knees, ``stand_up``
half-way from kneeling to standing.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Union

import numpy as np

from common.postures import BODY_POSTURES
from synth.body import (
    N_Q, Q_ELBOW, Q_HIP_ABD, Q_HIP_FLEX, Q_KNEE, Q_NECK, Q_PITCH, Q_ROLL, Q_SHOULDER_ABD, Q_SHOULDER_FLEX,
    Q_SPINE, Q_TWIST, Q_YAW, TRUNK_PARTS, BodyShape, lowest_point_m, standing_pose,
)
from synth.scene import Room

STANDING, SITTING, LYING, BENDING = (BODY_POSTURES.index(p) for p in ("standing", "sitting", "lying", "bending"))
"""Posture labels: indices into :data:`common.postures.BODY_POSTURES`."""
FALL_DIRECTIONS = ("forward", "backward", "left", "right")

Point = Union[str, tuple[float, float]]

SIT_DOWN_S = 1.5
STAND_UP_S = 1.8
FALL_S = 0.9
TURN_RATE = 2.0  # rad/s
WALK_ACCEL = 1.5  # m/s^2
SPEED_RANGE = (0.3, 2.0)


# ---------------------------------------------------------------------- steps (data)


@dataclass(frozen=True)
class Walk:
    """Walk through waypoints (names from the room or (x, y) metres) at ``speed_mps``."""

    to: tuple[Point, ...]
    speed_mps: float = 1.0


@dataclass(frozen=True)
class Face:
    """Turn in place toward a point or to ``facing_deg`` (0 = +x, 90 = +y)."""

    toward: Point | None = None
    facing_deg: float | None = None


@dataclass(frozen=True)
class Stand:
    """Stand still for ``duration_s``; ``activity`` 'rest' (arms down) or 'work' (hands busy in front)."""

    duration_s: float
    activity: str = "rest"


@dataclass(frozen=True)
class Dwell:
    """Walk (via waypoints) to a hot spot's spot, face it and stand there for ``duration_s``."""

    hotspot: str
    duration_s: float
    via: tuple[Point, ...] = ()
    activity: str = "work"
    speed_mps: float = 1.0


@dataclass(frozen=True)
class Sit:
    """Walk (via waypoints) to a seat, sit down, stay ``duration_s`` (None: to the end), stand up."""

    seat: str
    duration_s: float | None
    via: tuple[Point, ...] = ()
    speed_mps: float = 1.0


@dataclass(frozen=True)
class Fall:
    """Fall ``direction`` ('forward', 'backward', 'left', 'right') in ``duration_s``, lie still
    ``lie_s`` (None: to the end), then get up when ``get_up``."""

    direction: str = "forward"
    lie_s: float | None = None
    get_up: bool = False
    duration_s: float = FALL_S


@dataclass(frozen=True)
class Bend:
    """Bend forward to pick something up from the floor, hold ``hold_s``, straighten."""

    hold_s: float = 2.0
    down_s: float = 1.0
    up_s: float = 1.0


@dataclass(frozen=True)
class Kneel:
    """Kneel on both knees, hold ``hold_s``, stand up."""

    hold_s: float = 5.0
    down_s: float = 1.5
    up_s: float = 1.8


@dataclass(frozen=True)
class Wait:
    """Keep the current posture for ``duration_s``."""

    duration_s: float


@dataclass(frozen=True)
class WaitUntil:
    """Keep the current posture until scenario time ``t_s`` (synchronises people)."""

    t_s: float


@dataclass(frozen=True)
class Enter:
    """Appear in the corridor beyond ``door`` and walk in, then through ``to`` waypoints."""

    door: str = "front door"
    to: tuple[Point, ...] = ()
    speed_mps: float = 1.0


@dataclass(frozen=True)
class Leave:
    """Walk (via waypoints) out through ``door`` into the corridor and vanish; with ``door`` None,
    vanish at the last waypoint (out over an open edge of the monitored volume)."""

    door: str | None = "front door"
    via: tuple[Point, ...] = ()
    speed_mps: float = 1.0


@dataclass(frozen=True)
class Return:
    """After a :class:`Leave`: stay away ``away_s`` seconds, then come back as :class:`Enter` does
    (appear beyond ``door``, walk in and through ``to``); with ``door`` None, appear at the first
    waypoint of ``to`` (beyond an open edge) and walk through the rest."""

    away_s: float
    door: str | None = "front door"
    to: tuple[Point, ...] = ()
    speed_mps: float = 1.0


Step = Union[Walk, Face, Stand, Dwell, Sit, Fall, Bend, Kneel, Wait, WaitUntil, Enter, Leave, Return]


@dataclass(frozen=True)
class PersonScript:
    """One person's script.

    person_id: positive int (the ground-truth track id).
    steps: what they do, in order.
    start: (x, y, facing_deg) or a waypoint name where they stand at ``start_s``; None when the
        first step is :class:`Enter`; ``'seat:<name>'`` to start seated.
    start_s: when they appear (scenario seconds).
    resident: lives here (more people present than residents makes a visit).
    height_m: fixed height, or None for a random one (1.5..1.95 m) from the seed.
    speed_jitter: vary the walking speed by +-5 % with the seed (off to keep people in step).
    clothes: ``(shirt_bgr, trousers_bgr, long_sleeves)`` worn instead of the drawn ones (the
        rest of the body is drawn from the seed as without it), or None.
    """

    person_id: int
    steps: tuple
    start: tuple[float, float, float] | str | None = None
    start_s: float = 0.0
    resident: bool = True
    height_m: float | None = None
    speed_jitter: bool = True
    clothes: tuple[tuple[int, int, int], tuple[int, int, int], bool] | None = None


# ---------------------------------------------------------------------- timeline


@dataclass(frozen=True)
class Switch:
    """A posture change inside a segment at time ``t_s``; ``event`` kind or '' (none)."""

    t_s: float
    label: int
    event: str = ""
    details: dict = field(default_factory=dict)


@dataclass
class Segment:
    """A span ``[t0, t1)`` of one person's timeline.

    Key-framed when ``path`` is None: ``key_t`` (K,) absolute times and ``key_q`` (K, N_Q),
    interpolated with smoothstep easing (``ease``) or linearly. A walk otherwise.
    """

    t0: float
    t1: float
    label: int
    moving: bool
    key_t: np.ndarray | None = None
    key_q: np.ndarray | None = None
    ease: bool = True
    switches: tuple[Switch, ...] = ()
    walk: "_WalkPlan | None" = None

    def evaluate(self, t: np.ndarray) -> np.ndarray:
        """(n,) times -> (n, N_Q) poses."""
        if self.walk is not None:
            return self.walk.evaluate(t)
        kt, kq = self.key_t, self.key_q
        if len(kt) == 1:
            return np.repeat(kq[:1], t.shape[0], axis=0)
        i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, len(kt) - 2)
        f = np.clip((t - kt[i]) / (kt[i + 1] - kt[i]), 0.0, 1.0)
        if self.ease:
            f = f * f * (3.0 - 2.0 * f)
        return kq[i] + f[:, None] * (kq[i + 1] - kq[i])

    def labels(self, t: np.ndarray) -> np.ndarray:
        out = np.full(t.shape[0], self.label, dtype=np.int8)
        for sw in self.switches:
            out[t >= sw.t_s] = sw.label
        return out


@dataclass
class Timeline:
    """One person's compiled behaviour.

    shape: the body. segments: contiguous spans while present. present: list of
    (t_start, t_end) intervals. events: list of (t_s, kind, details) from switches and steps.
    """

    person_id: int
    shape: BodyShape
    resident: bool
    segments: list[Segment]
    present: list[tuple[float, float]]
    events: list[tuple[float, str, dict]]

    def evaluate(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Poses at times ``t`` (n,) seconds.

        Returns q (n, N_Q) float64, label (n,) int8 (index into :data:`common.postures.BODY_POSTURES`),
        moving (n,) bool (walking), present (n,) bool. Rows where absent hold the last pose.
        """
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        q = np.zeros((t.shape[0], N_Q))
        label = np.zeros(t.shape[0], dtype=np.int8)
        moving = np.zeros(t.shape[0], dtype=bool)
        present = np.zeros(t.shape[0], dtype=bool)
        for a, b in self.present:
            present |= (t >= a) & (t < b)
        starts = np.array([s.t0 for s in self.segments])
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(self.segments) - 1)
        for k in np.unique(idx):
            sel = idx == k
            seg = self.segments[k]
            tt = np.clip(t[sel], seg.t0, seg.t1)
            q[sel] = seg.evaluate(tt)
            label[sel] = seg.labels(t[sel])
            moving[sel] = seg.moving & (t[sel] < seg.t1)
        return q, label, moving, present


def compile_person(script: PersonScript, room: Room, rng: np.random.Generator, duration_s: float) -> Timeline:
    """Compile ``script`` into a :class:`Timeline` lasting until ``duration_s`` (or until they leave).

    ``rng`` draws the body shape and small variations (speed, gait phase); the same
    generator state gives the same timeline.
    """
    if not isinstance(script.person_id, int) or not (1 <= script.person_id <= 255):
        raise ValueError(f"person_id must be an int in 1..255, got {script.person_id!r}")
    shape = BodyShape.random(rng, height_m=script.height_m)
    if script.clothes is not None:
        shirt, trousers, sleeves = script.clothes
        shape = dataclasses.replace(shape, shirt_bgr=tuple(int(c) for c in shirt),
                                    trousers_bgr=tuple(int(c) for c in trousers), long_sleeves=bool(sleeves))
    b = _Builder(room, shape, rng, script.person_id)
    if not script.speed_jitter:
        b.speed_factor = 1.0
    steps = list(script.steps)
    if script.start is None:
        if not steps or not isinstance(steps[0], Enter):
            raise ValueError(f"person {script.person_id}: start is None, so the first step must be Enter")
        b.appear_outside(room.door(steps[0].door), script.start_s)
    elif isinstance(script.start, str) and script.start.startswith("seat:"):
        b.appear_seated(room.seat(script.start[5:]), script.start_s)
    else:
        if isinstance(script.start, str):
            x, y = room.point(script.start)
            facing = 0.0
        else:
            x, y, facing = script.start
        b.appear_standing(float(x), float(y), math.radians(facing), script.start_s)
    for step in steps:
        if b.gone and not isinstance(step, Return):
            break
        b.step(step)
    if not b.gone:
        b.hold_until(max(duration_s, b.t))
    return b.timeline(script.resident)


# ---------------------------------------------------------------------- builder


class _Builder:
    def __init__(self, room: Room, shape: BodyShape, rng: np.random.Generator, person_id: int) -> None:
        self.room = room
        self.shape = shape
        self.rng = rng
        self.person_id = person_id
        self.speed_factor = float(rng.uniform(0.95, 1.05))
        self.phase = float(rng.uniform(0, 2 * np.pi))
        self.segments: list[Segment] = []
        self.events: list[tuple[float, str, dict]] = []
        self.present: list[tuple[float, float]] = []
        self.t = 0.0
        self.t_appear = 0.0
        self.q = np.zeros(N_Q)
        self.label = STANDING
        self.gone = False

    # -- appearance

    def appear_standing(self, x: float, y: float, yaw: float, t: float) -> None:
        self.t = self.t_appear = t
        self.q = self._grounded(standing_pose(self.shape, x, y, yaw))
        self.label = STANDING

    def appear_outside(self, door, t: float) -> None:
        x, y = door.outside_xy_m
        self.appear_standing(x, y, math.atan2(door.inside_xy_m[1] - y, door.inside_xy_m[0] - x), t)

    def appear_seated(self, seat, t: float) -> None:
        self.t = self.t_appear = t
        self.q = self._seated_pose(seat)
        self.label = SITTING

    def timeline(self, resident: bool) -> Timeline:
        if not self.gone:
            self.present.append((self.t_appear, self.t))
        if not self.segments:
            self._hold(1e-3)
        return Timeline(self.person_id, self.shape, resident, self.segments, self.present, self.events)

    # -- steps

    def step(self, step) -> None:
        if isinstance(step, Walk):
            self.walk([self.room.point(p) for p in step.to], step.speed_mps)
        elif isinstance(step, Face):
            self.face(step)
        elif isinstance(step, Stand):
            self.stand(step.duration_s, step.activity)
        elif isinstance(step, Dwell):
            spot = self.room.hotspot(step.hotspot)
            self.walk([self.room.point(p) for p in step.via] + [spot.spot_xy_m], step.speed_mps)
            self.turn_to(math.radians(spot.facing_deg))
            self.stand(step.duration_s, step.activity)
        elif isinstance(step, Sit):
            seat = self.room.seat(step.seat)
            self.walk([self.room.point(p) for p in step.via] + [seat.approach_xy_m], step.speed_mps)
            self.turn_to(math.radians(seat.facing_deg))
            self.sit_down(seat)
            if step.duration_s is None:
                return
            self._hold(step.duration_s)
            self.stand_up(seat)
        elif isinstance(step, Fall):
            if step.direction not in FALL_DIRECTIONS:
                raise ValueError(f"Fall.direction must be one of {FALL_DIRECTIONS}, got {step.direction!r}")
            self.fall(step.direction, step.duration_s)
            if step.lie_s is None:
                return
            self._hold(step.lie_s)
            if step.get_up:
                self.get_up()
        elif isinstance(step, Bend):
            self.bend(step)
        elif isinstance(step, Kneel):
            self.kneel(step)
        elif isinstance(step, Wait):
            self._hold(step.duration_s)
        elif isinstance(step, WaitUntil):
            if step.t_s > self.t:
                self._hold(step.t_s - self.t)
        elif isinstance(step, Enter):
            door = self.room.door(step.door)
            self.walk([door.inside_xy_m] + [self.room.point(p) for p in step.to], step.speed_mps)
        elif isinstance(step, Leave):
            via = [self.room.point(p) for p in step.via]
            if step.door is None:
                if not via:
                    raise ValueError("Leave without a door needs waypoints: where to vanish")
                self.walk(via, step.speed_mps)
            else:
                door = self.room.door(step.door)
                self.walk(via + [door.inside_xy_m, door.outside_xy_m], step.speed_mps)
            self.present.append((self.t_appear, self.t))
            self.gone = True
        elif isinstance(step, Return):
            self.come_back(step)
        else:
            raise ValueError(f"unknown step {step!r}")

    def come_back(self, step: Return) -> None:
        if not self.gone:
            raise ValueError(f"person {self.person_id}: Return must follow a Leave")
        if not step.away_s >= 0:
            raise ValueError(f"Return.away_s must be >= 0, got {step.away_s}")
        to = [self.room.point(p) for p in step.to]
        t = self.t + float(step.away_s)
        if step.door is None:
            if not to:
                raise ValueError("Return without a door needs waypoints: where to appear")
            (x, y), rest = to[0], to[1:]
            yaw = math.atan2(rest[0][1] - y, rest[0][0] - x) if rest else float(self.q[Q_YAW])
            self.appear_standing(x, y, yaw, t)
        else:
            door = self.room.door(step.door)
            self.appear_outside(door, t)
            rest = [door.inside_xy_m] + to
        self.gone = False
        self.walk(rest, step.speed_mps)

    def hold_until(self, t_end: float) -> None:
        if t_end > self.t:
            self._hold(t_end - self.t)

    # -- primitives

    def _hold(self, duration: float) -> None:
        if duration < 0:
            raise ValueError(f"durations must be >= 0, got {duration}")
        if duration == 0:
            return
        self._keys([0.0, duration], [self.q, self.q], ease=False, moving=False)

    def _keys(self, rel_t, qs, *, ease=True, moving=False, switches=()) -> None:
        """Append a key-framed segment starting now; ``rel_t`` relative times, ``qs`` poses."""
        rel_t = np.asarray(rel_t, dtype=np.float64)
        key_q = np.array(qs, dtype=np.float64)
        t0 = self.t
        sw = tuple(Switch(t0 + dt, lab, ev, det) for dt, lab, ev, det in switches)
        self.segments.append(Segment(t0=t0, t1=t0 + rel_t[-1], label=self.label, moving=moving, key_t=t0 + rel_t,
                                     key_q=key_q, ease=ease, switches=sw))
        for s in sw:
            if s.event:
                self.events.append((s.t_s, s.event, dict(s.details)))
            self.label = s.label
        self.t = t0 + rel_t[-1]
        self.q = key_q[-1].copy()

    def turn_to(self, yaw: float) -> None:
        cur = self.q[Q_YAW]
        target = cur + _wrap(yaw - cur)
        delta = abs(target - cur)
        if delta < 1e-3:
            return
        q1 = self.q.copy()
        q1[Q_YAW] = target
        self._keys([0.0, 0.3 + delta / TURN_RATE], [self.q, q1])

    def face(self, step: Face) -> None:
        if step.facing_deg is not None:
            self.turn_to(math.radians(step.facing_deg))
        elif step.toward is not None:
            x, y = self.room.point(step.toward)
            self.turn_to(math.atan2(y - self.q[1], x - self.q[0]))
        else:
            raise ValueError("Face needs toward or facing_deg")

    def stand(self, duration: float, activity: str) -> None:
        if activity == "rest":
            self._hold(duration)
            return
        if activity != "work":
            raise ValueError(f"activity must be 'rest' or 'work', got {activity!r}")
        base = self.q.copy()
        a = base.copy()
        b = base.copy()
        for side, (fa, fb) in enumerate(((0.75, 0.55), (0.55, 0.8))):
            a[Q_SHOULDER_FLEX[side]], b[Q_SHOULDER_FLEX[side]] = fa, fb
            a[Q_ELBOW[side]], b[Q_ELBOW[side]] = 1.1, 0.9
        a[Q_SPINE] = b[Q_SPINE] = 0.12
        ramp = min(0.6, duration / 3)
        times = [0.0, ramp]
        poses = [base, a]
        t = ramp
        period = 1.6
        flip = True
        while t + period < duration - ramp:
            t += period
            times.append(t)
            poses.append(b if flip else a)
            flip = not flip
        times.append(duration)
        poses.append(base)
        self._keys(times, poses)

    def walk(self, points: list[tuple[float, float]], speed: float) -> None:
        if not (SPEED_RANGE[0] <= speed <= SPEED_RANGE[1]):
            raise ValueError(f"speed_mps must lie in {SPEED_RANGE}, got {speed}")
        pts = [tuple(self.q[:2])] + [tuple(p) for p in points]
        path = [pts[0]]
        for p in pts[1:]:
            if math.dist(p, path[-1]) > 1e-3:
                path.append(p)
        if len(path) < 2:
            return
        path = np.array(path, dtype=np.float64)
        heading0 = math.atan2(path[1, 1] - path[0, 1], path[1, 0] - path[0, 0])
        if abs(_wrap(heading0 - self.q[Q_YAW])) > 0.35:
            self.turn_to(heading0)
        plan = _WalkPlan(self.shape, path, speed * self.speed_factor, self.t, self.q.copy(), self.phase)
        self.segments.append(Segment(t0=self.t, t1=self.t + plan.duration_s, label=STANDING, moving=True, walk=plan))
        self.phase = plan.end_phase
        self.t += plan.duration_s
        self.q = plan.evaluate(np.array([self.t]))[0]
        self.label = STANDING

    def sit_down(self, seat) -> None:
        q0 = self.q.copy()
        q2 = self._seated_pose(seat)
        q2[Q_YAW] = q0[Q_YAW] + _wrap(q2[Q_YAW] - q0[Q_YAW])
        q1 = q0 + 0.4 * (q2 - q0)
        q1[Q_PITCH], q1[Q_SPINE] = 0.35, 0.2
        for side in (0, 1):
            q1[Q_HIP_FLEX[side]], q1[Q_KNEE[side]] = 1.0, 1.0
            q1[Q_SHOULDER_FLEX[side]] = 0.5
        q1 = self._on_floor(q1)
        d = SIT_DOWN_S
        self._keys([0.0, 0.45 * d, d], [q0, q1, q2],
                   switches=[(0.5 * d, SITTING, "sit_down", {"seat": seat.name})])

    def stand_up(self, seat) -> None:
        q0 = self.q.copy()
        q3 = self._grounded(standing_pose(self.shape, *seat.approach_xy_m, q0[Q_YAW]))
        q1 = q0.copy()
        q1[Q_PITCH], q1[Q_SPINE] = 0.45, 0.15
        q1[:2] = q0[:2] + 0.1 * (q3[:2] - q0[:2])
        q1[2] = q0[2] + 0.02
        for side in (0, 1):
            q1[Q_HIP_FLEX[side]] = 1.75
            q1[Q_SHOULDER_FLEX[side]] = 0.6
        q2 = q0 + 0.7 * (q3 - q0)
        q2[Q_PITCH], q2[Q_SPINE] = 0.3, 0.1
        for side in (0, 1):
            q2[Q_HIP_FLEX[side]], q2[Q_KNEE[side]] = 0.75, 0.55
        q2 = self._on_floor(q2)
        d = STAND_UP_S
        self._keys([0.0, 0.4 * d, 0.7 * d, d], [q0, q1, q2, q3],
                   switches=[(0.55 * d, STANDING, "stand_up", {"from": "sitting", "seat": seat.name})])

    def fall(self, direction: str, duration: float) -> None:
        q0 = self.q.copy()
        yaw = q0[Q_YAW]
        fwd = np.array([math.cos(yaw), math.sin(yaw)])
        right = np.array([math.sin(yaw), -math.cos(yaw)])
        dirs = {"forward": (fwd, Q_PITCH, 1.0), "backward": (-fwd, Q_PITCH, -1.0),
                "right": (right, Q_ROLL, 1.0), "left": (-right, Q_ROLL, -1.0)}
        vec, axis, sgn = dirs[direction]
        lying = self._lying_pose(q0, direction)
        z_lie = lying[2]
        r = self.shape.hip_height_m
        feet = q0[:2].copy()
        lying[:2] = feet + vec * r * 0.92
        s = np.linspace(0.0, 1.0, 8)
        keys = []
        for sj in s:
            theta = 0.5 * np.pi * sj**2
            qj = q0 + sj * (lying - q0)
            qj[axis] = sgn * theta
            qj[:2] = feet + vec * r * math.sin(theta) * 0.92
            qj[2] = z_lie + (r - z_lie) * math.cos(theta)
            for side in (0, 1):
                qj[Q_KNEE[side]] += 0.5 * math.sin(np.pi * sj)
            keys.append(self._lifted(qj))
        keys[-1] = lying
        self._keys(duration * s, keys, ease=False,
                   switches=[(duration, LYING, "fall", {"direction": direction})])
        if axis == Q_ROLL:
            # The same orientation as a prone body turned about its long axis, so that
            # getting up interpolates a roll onto the front rather than a swing through upright.
            q = self.q.copy()
            q[Q_YAW] -= sgn * 0.5 * np.pi
            q[Q_PITCH], q[Q_ROLL], q[Q_TWIST] = 0.5 * np.pi, 0.0, sgn * 0.5 * np.pi
            self.q = q

    def get_up(self) -> None:
        """From lying: (sit up if on the back,) onto hands and knees, kneel, stand."""
        q0 = self.q.copy()
        yaw = q0[Q_YAW]
        sh = self.shape
        keys, times = [q0], [0.0]
        if q0[Q_PITCH] < -0.5:
            sit = standing_pose(sh, q0[0], q0[1], yaw)
            sit[Q_SPINE] = 0.3
            for side in (0, 1):
                sit[Q_HIP_FLEX[side]], sit[Q_KNEE[side]] = 1.5, 0.4
            keys.append(self._grounded(sit))
            times.append(1.2)
        if abs(q0[Q_TWIST]) > 0.1:
            front = q0.copy()
            front[Q_TWIST] = 0.0
            for side in (0, 1):
                front[Q_SHOULDER_FLEX[side]], front[Q_HIP_FLEX[side]], front[Q_KNEE[side]] = 2.4, 0.2, 0.3
            keys.append(self._lifted(front))
            times.append(1.0)
        fours = standing_pose(sh, q0[0], q0[1], yaw)
        fours[Q_PITCH] = 1.25
        for side in (0, 1):
            fours[Q_HIP_FLEX[side]], fours[Q_KNEE[side]] = 1.25, 0.5 * np.pi
            fours[Q_SHOULDER_FLEX[side]], fours[Q_ELBOW[side]] = 1.35, 0.1
        keys.append(self._grounded(fours))
        times.append(times[-1] + 1.4)
        t_fours = times[-1]
        keys.append(self._kneel_pose(q0[0], q0[1], yaw))
        times.append(times[-1] + 1.0)
        keys.append(self._grounded(standing_pose(sh, keys[-1][0], keys[-1][1], yaw)))
        times.append(times[-1] + 1.6)
        self._keys(times, keys, switches=[(t_fours, BENDING, "", {}),
                                          (times[-2] + 0.5 * (times[-1] - times[-2]), STANDING, "stand_up",
                                           {"from": "lying"})])

    def bend(self, step: Bend) -> None:
        q0 = self.q.copy()
        q1 = q0.copy()
        q1[Q_PITCH], q1[Q_SPINE], q1[Q_NECK] = 0.45, 1.0, 0.15
        for side in (0, 1):
            q1[Q_HIP_FLEX[side]], q1[Q_KNEE[side]] = 0.7, 0.6
            q1[Q_SHOULDER_FLEX[side]], q1[Q_ELBOW[side]] = 1.5, 0.2
        q1 = self._grounded(q1)
        d0, h, d1 = step.down_s, step.hold_s, step.up_s
        self._keys([0.0, d0, d0 + h, d0 + h + d1], [q0, q1, q1, q0],
                   switches=[(0.5 * d0, BENDING, "", {}), (d0 + h + 0.5 * d1, STANDING, "", {})])

    def kneel(self, step: Kneel) -> None:
        q0 = self.q.copy()
        q2 = self._kneel_pose(q0[0], q0[1], q0[Q_YAW])
        q1 = q0 + 0.5 * (q2 - q0)
        q1[Q_PITCH] = 0.25
        for side in (0, 1):
            q1[Q_HIP_FLEX[side]], q1[Q_KNEE[side]] = 0.9, 1.2
        q1 = self._grounded(q1)
        d0, h, d1 = step.down_s, step.hold_s, step.up_s
        self._keys([0.0, 0.5 * d0, d0, d0 + h, d0 + h + 0.5 * d1, d0 + h + d1], [q0, q1, q2, q2, q1, q0],
                   switches=[(0.5 * d0, BENDING, "", {}), (d0 + h + 0.5 * d1, STANDING, "", {})])

    # -- poses

    def _seated_pose(self, seat) -> np.ndarray:
        sh = self.shape
        q = standing_pose(sh, seat.xy_m[0], seat.xy_m[1], math.radians(seat.facing_deg))
        q[2] = seat.height_m + sh.seat_offset_m
        q[Q_PITCH] = -0.08
        q[Q_SPINE] = 0.05
        alpha = 1.5
        knee_z = q[2] - sh.thigh_m * math.cos(alpha)
        beta = math.acos(float(np.clip((knee_z - sh.ankle_m) / sh.shank_m, -1.0, 1.0)))
        for side in (0, 1):
            q[Q_HIP_FLEX[side]] = alpha + q[Q_PITCH]
            q[Q_KNEE[side]] = alpha - beta
            q[Q_SHOULDER_FLEX[side]], q[Q_ELBOW[side]] = 0.45, 0.9
            q[Q_HIP_ABD[side]] = 0.08
        return q

    def _lying_pose(self, q0: np.ndarray, direction: str) -> np.ndarray:
        q = standing_pose(self.shape, 0.0, 0.0, q0[Q_YAW])
        if direction == "forward":
            q[Q_PITCH] = 0.5 * np.pi
            q[Q_SHOULDER_FLEX[0]], q[Q_SHOULDER_FLEX[1]] = 3.0, 2.9
        elif direction == "backward":
            q[Q_PITCH] = -0.5 * np.pi
            q[Q_SHOULDER_ABD[0]], q[Q_SHOULDER_ABD[1]] = 0.6, 0.5
        else:
            bottom = 1 if direction == "right" else 0
            q[Q_ROLL] = 0.5 * np.pi if direction == "right" else -0.5 * np.pi
            q[Q_SHOULDER_FLEX[bottom]] = 2.8
            q[Q_HIP_FLEX[1 - bottom]], q[Q_KNEE[1 - bottom]] = 0.5, 0.6
        for side in (0, 1):
            q[Q_KNEE[side]] = max(q[Q_KNEE[side]], 0.05)
        q[2] = 0.0
        # The trunk rests on the floor; a limb under it sinks in rather than lifting the body.
        q[2] -= float(lowest_point_m(self.shape, q, TRUNK_PARTS)[0])
        return q

    def _kneel_pose(self, x: float, y: float, yaw: float) -> np.ndarray:
        q = standing_pose(self.shape, x + 0.1 * math.cos(yaw), y + 0.1 * math.sin(yaw), yaw)
        q[Q_SPINE] = 0.35
        for side in (0, 1):
            q[Q_HIP_FLEX[side]] = 0.1
            q[Q_KNEE[side]] = 0.5 * np.pi + 0.1
            q[Q_SHOULDER_FLEX[side]], q[Q_ELBOW[side]] = 0.8, 0.4
        return self._grounded(q)

    def _grounded(self, q: np.ndarray) -> np.ndarray:
        """The pose moved vertically so that its lowest point touches the floor."""
        q = q.copy()
        q[2] -= float(lowest_point_m(self.shape, q)[0])
        return q

    def _lifted(self, q: np.ndarray) -> np.ndarray:
        """The pose lifted, if needed, so that nothing is below the floor."""
        low = float(lowest_point_m(self.shape, q)[0])
        q = q.copy()
        if low < 0:
            q[2] -= low
        return q

    def _on_floor(self, q: np.ndarray) -> np.ndarray:
        """For crouching transitions: feet on the floor (but not below)."""
        return self._grounded(q)


# ---------------------------------------------------------------------- walking


class _WalkPlan:
    """Walking along a polyline with a trapezoidal speed profile and a sinusoidal gait."""

    BLEND_M = 0.3

    def __init__(self, shape: BodyShape, path: np.ndarray, speed: float, t0: float, q_start: np.ndarray,
                 phase0: float) -> None:
        self.shape = shape
        self.path = path
        self.speed = speed
        self.t0 = t0
        self.phase0 = phase0
        seg = np.diff(path, axis=0)
        self.seg_len = np.linalg.norm(seg, axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        self.length = float(self.cum[-1])
        h = np.arctan2(seg[:, 1], seg[:, 0])
        h[0] = q_start[Q_YAW] + _wrap(h[0] - q_start[Q_YAW])
        for i in range(1, len(h)):
            h[i] = h[i - 1] + _wrap(h[i] - h[i - 1])
        self.headings = h
        self.yaw_start = float(q_start[Q_YAW])
        self.base = standing_pose(shape, 0.0, 0.0, 0.0)
        a = WALK_ACCEL
        if self.length >= speed * speed / a:
            self.t_ramp = speed / a
            self.v_peak = speed
            self.duration_s = self.length / speed + speed / a
        else:
            self.v_peak = math.sqrt(self.length * a)
            self.t_ramp = self.v_peak / a
            self.duration_s = 2 * self.t_ramp
        self.cycle_m = 1.45 * (shape.height_m / 1.75) * (max(speed, 0.3) / 1.2) ** 0.6
        self.end_phase = phase0 + 2 * np.pi * self.length / self.cycle_m

    def distance(self, t: np.ndarray) -> np.ndarray:
        tau = np.clip(t - self.t0, 0.0, self.duration_s)
        a, tr, v, T = WALK_ACCEL, self.t_ramp, self.v_peak, self.duration_s
        s_acc = 0.5 * a * np.minimum(tau, tr) ** 2
        s_cruise = v * np.clip(tau - tr, 0.0, max(T - 2 * tr, 0.0))
        tail = np.clip(tau - (T - tr), 0.0, tr)
        s_dec = v * tail - 0.5 * a * tail**2
        return np.minimum(s_acc + s_cruise + s_dec, self.length)

    def evaluate(self, t: np.ndarray) -> np.ndarray:
        s = self.distance(np.asarray(t, dtype=np.float64))
        x = np.interp(s, self.cum, self.path[:, 0])
        y = np.interp(s, self.cum, self.path[:, 1])
        yaw = self._heading(s)
        n = s.shape[0]
        q = np.repeat(self.base[None, :], n, axis=0)
        phi = self.phase0 + 2 * np.pi * s / self.cycle_m
        env = np.clip(np.minimum(s, self.length - s) / 0.5, 0.0, 1.0) * min(1.0, self.length / 0.8)
        amp = 0.3 + 0.12 * (self.speed - 1.0)
        sin_l = np.sin(phi)
        for side, sgn in ((0, 1.0), (1, -1.0)):
            hip = sgn * amp * sin_l
            swing = np.maximum(0.0, np.cos(phi + (0.0 if side == 0 else np.pi))) ** 2
            q[:, Q_HIP_FLEX[side]] = self.base[Q_HIP_FLEX[side]] + env * hip
            q[:, Q_KNEE[side]] = self.base[Q_KNEE[side]] + env * (0.05 + 0.95 * swing)
            q[:, Q_SHOULDER_FLEX[side]] = self.base[Q_SHOULDER_FLEX[side]] - env * 0.8 * hip
            q[:, Q_ELBOW[side]] = self.base[Q_ELBOW[side]] + env * (0.15 + 0.15 * np.maximum(0.0, -sgn * sin_l))
        sh = self.shape
        hip = q[:, Q_HIP_FLEX[0]], q[:, Q_HIP_FLEX[1]]
        knee = q[:, Q_KNEE[0]], q[:, Q_KNEE[1]]
        ext = np.maximum(*(sh.thigh_m * np.cos(h) + sh.shank_m * np.cos(h - k) for h, k in zip(hip, knee)))
        q[:, 0], q[:, 1], q[:, 2] = x, y, sh.ankle_m + ext
        q[:, Q_YAW] = yaw
        q[:, Q_SPINE] = self.base[Q_SPINE] + env * 0.05
        return q

    def _heading(self, s: np.ndarray) -> np.ndarray:
        h, cum = self.headings, self.cum
        i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(h) - 1)
        yaw = h[i].copy()
        B = np.minimum(self.BLEND_M, 0.5 * self.seg_len)
        into = s - cum[i]
        left = cum[i + 1] - s
        has_prev = i > 0
        prev = np.where(has_prev, h[np.maximum(i - 1, 0)], h[i])
        b_prev = B[np.maximum(i - 1, 0)]
        bi = np.minimum(B[i], np.where(has_prev, b_prev, B[i]))
        m = has_prev & (into < bi)
        f = np.where(m, 0.5 + 0.5 * into / np.where(bi > 0, bi, 1.0), 1.0)
        yaw = np.where(m, prev + (h[i] - prev) * f, yaw)
        has_next = i < len(h) - 1
        nxt = np.where(has_next, h[np.minimum(i + 1, len(h) - 1)], h[i])
        bn = np.minimum(B[i], B[np.minimum(i + 1, len(h) - 1)])
        m2 = has_next & (left < bn)
        g = np.where(m2, 0.5 * (1.0 - left / np.where(bn > 0, bn, 1.0)), 0.0)
        yaw = np.where(m2, h[i] + (nxt - h[i]) * g, yaw)
        # The first metre blends from the starting yaw (small turns happen while walking).
        start = np.clip(s / 0.4, 0.0, 1.0)
        first = i == 0
        yaw = np.where(first & (s < 0.4), self.yaw_start + (yaw - self.yaw_start) * start, yaw)
        return yaw


def _wrap(a: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return (a + np.pi) % (2 * np.pi) - np.pi
