"""A scenario: scripted people in the synthetic house over time, with lighting.

:class:`ScenarioSpec` is pure data (who does what, when, the start time of
day, light switches). :class:`Scenario` compiles it for one seed into
per-person timelines and answers, for any frame index, the people's bodies,
the scene's illumination gain and the frame's time stamp:

``stamp_ns = start_ns + round(index * 1e9 / fps)`` where ``start_ns`` is the
scenario's start (date and local time of day, converted to UTC with the
site's offset).
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from synth.behaviour import PersonScript, Timeline, compile_person
from synth.body import Body, forward_kinematics, pose_body
from synth.scene import FPS, Room, default_room


@dataclass(frozen=True)
class LightChange:
    """A sudden change of the room's light at ``at_s``: the scene gain is multiplied by
    ``factor`` from then on (1.25 = a lamp switched on), over ``ramp_s`` seconds."""

    at_s: float
    factor: float
    ramp_s: float = 0.1


@dataclass(frozen=True)
class ScenarioSpec:
    """What happens.

    name / description: identification. duration_s: length. people: the scripts.
    start_local: local time of day at frame 0, 'HH:MM:SS'. date: 'YYYY-MM-DD'.
    fps: frame rate. lights: sudden light changes. drift: amplitude (fraction) of the
    slow illumination drift. residents: people who live here.
    """

    name: str
    description: str
    duration_s: float
    people: tuple[PersonScript, ...]
    start_local: str = "10:00:00"
    date: str = "2024-03-05"
    fps: float = FPS
    lights: tuple[LightChange, ...] = ()
    drift: float = 0.03
    residents: int = 1

    def __post_init__(self) -> None:
        if not self.duration_s > 0:
            raise ValueError(f"scenario {self.name}: duration_s must be positive, got {self.duration_s}")
        if not self.fps > 0:
            raise ValueError(f"scenario {self.name}: fps must be positive, got {self.fps}")
        ids = [p.person_id for p in self.people]
        if len(set(ids)) != len(ids):
            raise ValueError(f"scenario {self.name}: person ids must be unique, got {ids}")


class Scenario:
    """A compiled scenario for one seed. Deterministic: same spec, seed and room give the
    same people, poses, lighting and truth.

    people: one :class:`Timeline` per person. n_frames: ``round(duration_s * fps)``.
    """

    def __init__(self, spec: ScenarioSpec, seed: int = 0, *, room: Room | None = None,
                 utc_offset_hours: float = 0.0) -> None:
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {seed!r}")
        self.spec = spec
        self.seed = int(seed)
        self.room = room or default_room()
        self.utc_offset_hours = float(utc_offset_hours)
        self.people: list[Timeline] = [
            compile_person(p, self.room, np.random.default_rng([self.seed, p.person_id]), spec.duration_s)
            for p in spec.people
        ]
        light_rng = np.random.default_rng([self.seed, 7919])
        self._drift_phase = light_rng.uniform(0, 2 * np.pi, size=2)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def fps(self) -> float:
        return self.spec.fps

    @property
    def n_frames(self) -> int:
        return int(round(self.spec.duration_s * self.spec.fps))

    @cached_property
    def start_ns(self) -> int:
        """UTC nanoseconds of frame 0."""
        local = _dt.datetime.fromisoformat(f"{self.spec.date}T{self.spec.start_local}")
        utc = local.replace(tzinfo=_dt.timezone.utc) - _dt.timedelta(hours=self.utc_offset_hours)
        return int(round(utc.timestamp())) * 1_000_000_000

    def time_s(self, index) -> np.ndarray | float:
        """Scenario time of frame ``index`` (int or array), seconds."""
        return np.asarray(index, dtype=np.float64) / self.fps if np.ndim(index) else float(index) / self.fps

    def stamp_ns(self, index: int) -> int:
        return self.start_ns + int(round(index * 1e9 / self.fps))

    def local_hour(self, index: int) -> float:
        """Local time of day of frame ``index``, hours (0..24)."""
        h, m, s = (float(v) for v in self.spec.start_local.split(":"))
        return ((h + m / 60 + s / 3600) + self.time_s(index) / 3600) % 24.0

    def gain(self, index) -> float:
        """Scene illumination gain at frame ``index`` (may be negative: before the start)."""
        return float(self.gain_at(self.time_s(index)))

    def gain_at(self, t_s) -> np.ndarray | float:
        """Scene illumination gain at scenario time(s) ``t_s``: slow drift times light switches."""
        t = np.asarray(t_s, dtype=np.float64)
        p = self._drift_phase
        wave = 0.7 * np.sin(2 * np.pi * t / 97.0 + p[0]) + 0.3 * np.sin(2 * np.pi * t / 31.0 + p[1])
        g = 1.0 + self.spec.drift * wave
        for lc in self.spec.lights:
            f = np.clip((t - lc.at_s) / max(lc.ramp_s, 1e-6), 0.0, 1.0)
            g = g * (1.0 + (lc.factor - 1.0) * f)
        return g

    def bodies(self, index: int) -> list[Body]:
        """The bodies of everyone present (inside the volume or in the corridor) at frame ``index``."""
        t = self.time_s(index)
        out = []
        for person in self.people:
            q, _, _, present = person.evaluate(np.array([t]))
            if present[0]:
                out.append(pose_body(person.shape, q[0], person.person_id))
        return out

    @cached_property
    def states(self) -> list[dict[str, np.ndarray]]:
        """Per person, per frame: ``q`` (F, N_Q), ``label`` (F,) int8, ``moving`` (F,) bool,
        ``present`` (F,) bool, ``z_top`` (F,) float64, ``xy`` (F, 2) float64 (pelvis on the floor)."""
        t = np.arange(self.n_frames) / self.fps
        out = []
        for person in self.people:
            q, label, moving, present = person.evaluate(t)
            centers, axes = forward_kinematics(person.shape, q)
            z_top = np.max(centers[:, :, 2] + np.linalg.norm(axes[:, :, 2, :], axis=2), axis=1)
            out.append({"q": q, "label": label, "moving": moving, "present": present, "z_top": z_top,
                        "xy": q[:, :2].copy()})
        return out

    def frame_of(self, t_s: float) -> int:
        """The first frame whose time is at or after ``t_s``."""
        return int(math.ceil(t_s * self.fps - 1e-9))

    def end_time_s(self) -> float:
        """When the last scripted activity ends (a person lying or sitting to the end counts as
        the scenario's end)."""
        return max((seg.t1 for p in self.people for seg in p.segments), default=0.0)
