"""Target management and tracking: blobs of one frame set -> people with ids.

Seed paper 000, sections 2.2.2 and 2.3. Every frame:

1. each target's 2.5D particle filter moves to the new time and refines the
   target's floor position on the frame's floor count map (never beyond the
   volume's floor: there is no evidence there; never onto the place of
   someone known to be another person whose head the cameras see beside its
   own: see ``PopulationParams.apart_m``);
2. targets are matched to the detected blobs by the Hungarian method on a
   cost (by default the floor distance between the target and the blob's
   centroid), with a gate;
   a target left out that stands on a matched blob shares it (two people
   touching above tau1 make one blob) once it is old enough to be a person
   rather than a ghost; a target alone on a low blob (a body lying on the
   floor) is placed at the blob's centroid;
3. each target's reliability follows the IIR filter ``r = r + l (M - r)``
   with ``M`` = 1 when matched and 0 when not, and the age-dependent learning
   rate ``l = min(l_max, 1 / age + l_min)``: a young target becomes trusted
   within a few frames, an old one survives a few seconds of misses (but not
   at the border of the volume, where a miss means the person walked out);
4. a target is *confirmed* (trusted as a person) while ``r`` is at least
   ``confirm_reliability`` and destroyed when ``r`` drops below
   ``delete_reliability``;
   a confirmed target that stands still and is left without a blob, on hull
   the explanation refused (``hidden``: an upright blob no camera could vouch for, its
   top within :data:`HELD_UP_TOP_M` of the top read at the target on the
   frame before), counts as matched: a person seated or standing still
   where others hide them from the cameras that could vouch for them is
   still carved there;
5. blobs no target matched start new targets, if large enough;
6. two targets closer than ``merge_distance_m`` for ``merge_frames``
   consecutive frames follow the same person: the older one is kept.

Time comes from ``stamp_ns`` only, randomness from the injected generator,
track ids from the injected id source.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from pydantic import Field, model_validator

from fusion_server.association import associate, floor_distance_cost
from fusion_server.detection import Blob
from fusion_server.grid import CarveResult
from fusion_server.particle_filter import FloorEvidence, ParticleFilter, floor_evidence
from common.settings import NON_NEGATIVE, Settings

__all__ = [
    "AssociationParams",
    "ConfirmationParams",
    "CostFunction",
    "FilterFactory",
    "MotionParams",
    "PopulationParams",
    "TrackEstimate",
    "Tracker",
]

HELD_UP_M = 0.4
"""A refused blob holds up a still target whose floor position is at most this far from its centroid ..."""
HELD_UP_TOP_M = 0.3
"""... and whose top is within this of the top read at the target on the frame set before."""

CostFunction = Callable[[np.ndarray, Sequence[Blob]], np.ndarray]
"""``(target_xy, blobs) -> cost``: target_xy (T, 2) float64 floor positions, world
frame, metres; blobs the frame's D blobs; cost (T, D), NaN or +inf where a pair
must not match."""


class FilterFactory(Protocol):
    """Makes the particle filter of a target starting at floor ``(x_m, y_m)``, world
    metres, with box half-size ``alpha_m``; every draw comes from ``rng``."""

    def __call__(self, x_m: float, y_m: float, alpha_m: float, *, rng: np.random.Generator) -> ParticleFilter: ...


class AssociationParams(Settings):
    """How targets take this frame's blobs.

    gate_m: largest cost of a target-blob pair that can match, in the unit of
        the tracker's cost function (metres of floor distance by default)
        [0.6 m; a walker moves 0.1 m per frame at 15 fps and a blob's centroid
        can sit 0.2-0.3 m off the person when it includes furniture or an arm].
    share_blobs: a target left unmatched whose filter still sees evidence and
        whose position lies on a blob's footprint counts as matched to that
        blob [True]. Two people touching above tau1 form one blob; the
        paper's one-to-one assignment would starve one of them. With False
        the tracker follows the paper strictly.
    share_known_only: only targets known to be other people share [False]:
        two confirmed while ``apart_m`` apart (with their tops, or each on a
        blob of its own), or whose heads the cameras saw apart
        (:class:`PopulationParams`). A target never seen apart from the
        blob's target is a piece of hull beside that person, not a second
        person: the older of the two keeps the blob, and the other misses.
        With False any target at least ``share_min_age_frames`` old shares
        the blob it stands on. Off: it cuts second tracks on one person on
        colour and mixed-rig tuning worlds alike (MOTA +1.2 and +0.5), but
        seated people are read lying twice as often with it (0.42 -> 0.98 %
        of seated frames on the colour tuning worlds).
    share_min_age_frames: only targets at least this old share a blob [15
        frames, 1 s at 15 fps]. People who come to touch were tracked apart
        before; a target a few frames old that has lost its own blob is a
        ghost (hull voxels where two people's silhouettes cross, a fragment
        of a body lying half hidden) and must not live on a person's blob.
    low_top_m: a target matched on its own to a blob no higher than this
        [0.8 m] stands on a body lying on the floor, and is placed at the
        blob's centroid. The filter's square box settles on part of an
        elongated body (the box fits anywhere along it, so the estimate
        also drifts with the velocity fed back into the motion model),
        while the centroid of a lying body lies within about 0.1 m of the
        pelvis. Standing, sitting and kneeling bodies reach higher.
    """

    gate_m: float = Field(0.6, **NON_NEGATIVE)
    share_blobs: bool = True
    share_known_only: bool = False
    share_min_age_frames: int = Field(15, ge=0)
    low_top_m: float = Field(0.8, **NON_NEGATIVE)


class ConfirmationParams(Settings):
    """When a target is trusted as a person and when it is destroyed.

    The reliability follows ``r = r + l (M - r)`` with ``M`` = 1 on a matched
    frame and 0 on a miss, and ``l = min(l_max, 1 / age + l_min)``.

    learning_rate_max, learning_rate_min: l_max and l_min [0.3, 0.05].
    confirm_reliability: r at or above which a target is a person [0.6].
    delete_reliability: r below which a target is destroyed [0.1]. With the
        defaults a new target is confirmed on its 3rd matched frame and a
        one-frame ghost destroyed on its 4th miss; a target seen for 4 s
        (60 frames at 15 fps) is unconfirmed on the 8th missed frame and
        destroyed on the 36th; never later than the 45th.
    leave_margin_m: a target left unmatched this close to the border of the
        volume's floor loses its confirmation at once [0.1 m]. A body cannot
        come that close to a wall, so it is someone who walked out through a
        door (the filter stops a coasting target at the border); they are
        gone, not hidden.
    """

    learning_rate_max: float = Field(0.3, gt=0.0, le=1.0)
    learning_rate_min: float = Field(0.05, ge=0.0, le=1.0)
    confirm_reliability: float = Field(0.6, ge=0.0, le=1.0)
    delete_reliability: float = Field(0.1, ge=0.0, le=1.0)
    leave_margin_m: float = Field(0.1, **NON_NEGATIVE)

    @model_validator(mode="after")
    def _ordered(self) -> "ConfirmationParams":
        if self.learning_rate_min > self.learning_rate_max:
            raise ValueError(f"learning_rate_min must be at most learning_rate_max ({self.learning_rate_max}), "
                             f"got {self.learning_rate_min}")
        if self.confirm_reliability <= self.delete_reliability:
            raise ValueError(f"confirm_reliability must be above delete_reliability ({self.delete_reliability}), "
                             f"got {self.confirm_reliability}")
        return self


class PopulationParams(Settings):
    """Which blobs start new targets and when two targets become one.

    new_target_min_distance_m: an unmatched blob this close to an existing
        target does not start a new one [0.3 m].
    new_target_min_volume_m3: an unmatched blob smaller than this does not
        start a new target [0: every blob the detector keeps]. The fusion
        pipeline asks for a person-sized blob (see
        ``fusion_server.pipeline.NEW_TARGET_MIN_VOLUME_M3``).
    merge_distance_m, merge_frames: duplicate targets closer than this for
        this many consecutive frames merge, the older one kept [0.3 m, 8
        frames]. People do not stand closer than 0.3 m centre to centre for
        half a second.
    apart_m, two_memory_s: two targets both confirmed while this far apart
        or more [0.8 m] are two people. While the cameras saw their two heads
        apart (``Tracker.step``'s ``heads_apart``) within the last
        ``two_memory_s`` [1 s], neither filter takes the place of the other
        (no particle of one within ``merge_distance_m`` of the other's last
        position): two people who come together make one hump on the floor
        map, and two filters free to climb it both settle on its top and
        become one target. The same holds while the two share one blob that
        holds the bodies of all the targets on it: its volume is the sum of
        theirs but ``1 - hold_share`` [0.5] of the smallest one's or more
        (two: the larger body and half the smaller; each body's volume the
        median of its last ``volume_frames`` [30] frames on a blob of its
        own, and each at least ``body_min_m3`` [0.1 m^3], the least a
        standing person carves: a column of hull confirmed beside someone
        is no body; two people in a hug, whose heads the cameras cannot part,
        keep their two bodies' worth of voxels). A target that slid onto someone
        else's body has no head of its own there, and that body's blob no
        room for a second one: it may merge. A target's top is read only from
        the floor cells nearer to it than to the targets known to be other people
        and to those whose heads the cameras ever saw apart from its own while both
        live (never far apart, still someone else: their shoulders are not its top).
    two_min_top_m: both targets of such a pair stand or sit: their tops at
        least this high [1.0 m] when seen apart. A body
        lying on the floor is up to 1.9 m long and can hold two targets
        further apart than ``apart_m``: one of them is a piece of it, not a
        second person.
    """

    new_target_min_distance_m: float = Field(0.3, **NON_NEGATIVE)
    new_target_min_volume_m3: float = Field(0.0, **NON_NEGATIVE)
    merge_distance_m: float = Field(0.3, **NON_NEGATIVE)
    merge_frames: int = Field(8, ge=1)
    apart_m: float = Field(0.8, **NON_NEGATIVE)
    two_min_top_m: float = Field(1.0, **NON_NEGATIVE)
    two_memory_s: float = Field(1.0, **NON_NEGATIVE)
    hold_share: float = Field(0.5, **NON_NEGATIVE)
    body_min_m3: float = Field(0.1, **NON_NEGATIVE)
    volume_frames: int = Field(30, ge=1)


class MotionParams(Settings):
    """The smoothed velocity of a target and when it counts as still.

    velocity_tau_s: time constant of the velocity smoothing [0.3 s].
    still_speed_mps, still_window_s: a target is still when its smoothed
        speed stayed below the speed for the whole window, or when the blobs
        matched to it, or its own estimates, over the window stayed within
        ``still_speed_mps * still_window_s`` [0.15 m/s, 1.0 s].
    """

    velocity_tau_s: float = Field(0.3, gt=0.0, allow_inf_nan=False)
    still_speed_mps: float = Field(0.15, **NON_NEGATIVE)
    still_window_s: float = Field(1.0, **NON_NEGATIVE)


@dataclass(frozen=True, eq=False)
class TrackEstimate:
    """One target after a frame.

    id: track id from the tracker's id source.
    x, y: world metres, floor position (particle filter mean).
    z_top_m: highest foreground voxel top in the target's floor box, metres
        (falls back to the matched blob's top, then to the last value).
    volume_m3: volume of the matched blob (of this target's part of it when
        several targets share it), or of the last one matched.
    reliability: r in [0, 1] from the IIR filter.
    confirmed: r >= the tracker's ``confirmation.confirm_reliability``.
    age_frames: frames since the target was created, counting this one.
    vx, vy: smoothed floor velocity, metres per second.
    height_profile: (nz,) int32 voxels per height layer of the matched blob
        (this target's part when shared; else of the last one matched).
    blob: the blob matched this frame, or None. Several tracks can share one
        blob when people touch above tau1.
    still: the smoothed speed stayed below the tracker's
        ``motion.still_speed_mps`` for the last ``motion.still_window_s``, or
        the blobs matched over that window stayed put (within
        ``still_speed_mps * still_window_s``).
    alpha_m: half-size of the filter's square floor box, metres.
    stamp_ns: the frame time.
    """

    id: int
    x: float
    y: float
    z_top_m: float
    volume_m3: float
    reliability: float
    confirmed: bool
    age_frames: int
    vx: float
    vy: float
    height_profile: np.ndarray
    blob: Blob | None
    still: bool
    alpha_m: float = 0.0
    stamp_ns: int = 0


class Tracker:
    """Multi-person tracker over blobs and floor maps.

    Keyword parameters (defaults in brackets):

    rng: numpy Generator for every particle filter (required).
    id_source: iterator or zero-argument callable giving new track ids
        [a fresh ``itertools.count(1)``].
    association, confirmation, population, motion: the parameter groups
        :class:`AssociationParams`, :class:`ConfirmationParams`,
        :class:`PopulationParams` and :class:`MotionParams` [None: the
        group's defaults].
    cost_function: ``(target_xy (T, 2) float64 world metres, blobs (D,)) ->
        (T, D) cost`` of matching each target to each blob, in the unit of
        ``association.gate_m``; NaN or +inf forbids a pair
        [:func:`~fusion_server.association.floor_distance_cost`].
    filter_factory: ``(x_m, y_m, alpha_m, *, rng) -> ParticleFilter``, the
        filter of a new target (and of one restarted on its blob)
        [:class:`~fusion_server.particle_filter.ParticleFilter` with its
        defaults; ``functools.partial(ParticleFilter, n_particles=100)``
        changes one setting]. It is called once here, so that bad filter
        settings fail at construction.
    """

    def __init__(
        self,
        *,
        rng: np.random.Generator,
        id_source: Iterator[int] | Callable[[], int] | None = None,
        association: AssociationParams | None = None,
        confirmation: ConfirmationParams | None = None,
        population: PopulationParams | None = None,
        motion: MotionParams | None = None,
        cost_function: CostFunction = floor_distance_cost,
        filter_factory: FilterFactory = ParticleFilter,
    ):
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy Generator, got {type(rng).__name__}")
        self.rng = rng
        self.association = association if association is not None else AssociationParams()
        self.confirmation = confirmation if confirmation is not None else ConfirmationParams()
        self.population = population if population is not None else PopulationParams()
        self.motion = motion if motion is not None else MotionParams()
        self.cost_function = cost_function
        self.filter_factory = filter_factory
        # A filter made now makes bad filter settings fail here, not on the first frame, and
        # tells how far the floor evidence must reach. It draws its particles from ``rng``
        # like every target's filter, so it is part of the sequence the tracks depend on.
        probe = self._new_filter(0.0, 0.0, 0.0)
        self._alpha_range_m = probe.alpha_range_m
        self._max_half_m = probe.max_half_m
        if id_source is None:
            id_source = itertools.count(1)
        self._next_id: Callable[[], int] = id_source if callable(id_source) else (lambda it=id_source: next(it))
        self._targets: list[_Target] = []
        self._close_frames: dict[tuple[int, int], int] = {}
        self._two_people: dict[int, set[int]] = {}  # target id -> targets known to be other people
        self._heads_apart_ns: dict[frozenset, int] = {}  # pair of target ids -> when their heads were last seen apart
        self._heads_seen: dict[int, set[int]] = {}  # target id -> targets whose head the cameras saw apart from its own
        self._blobs_apart: dict[int, set[int]] = {}  # target id -> targets both confirmed on blobs of their own, apart
        self._last_stamp_ns: int | None = None

    @property
    def track_ids(self) -> list[int]:
        return [t.id for t in self._targets]

    def learning_rate(self, age_frames: int) -> float:
        """l = min(l_max, 1 / age + l_min), the paper's equation (2)."""
        c = self.confirmation
        return min(c.learning_rate_max, 1.0 / max(age_frames, 1) + c.learning_rate_min)

    def step(self, result: CarveResult, blobs: list[Blob], stamp_ns: int,
             heads_apart: Iterable[tuple[int, int]] = (), hidden: Sequence[Blob] = ()) -> list[TrackEstimate]:
        """Advance all targets to ``stamp_ns`` with this frame's floor maps and blobs.

        heads_apart: pairs of target ids whose two heads the cameras see apart on this frame set
        (:class:`~fusion_server.heads.HeadGaps`, tested where the targets stood on the last one).
        hidden: the blobs of the frame set the explanation did not take for people; they start no
        target and move none, but one under a still confirmed target left without a blob holds it
        up (module text, step 4).

        Returns every live target (confirmed or not), sorted by id.
        Raises ValueError if ``stamp_ns`` is earlier than the previous frame's.
        """
        stamp_ns = int(stamp_ns)
        if self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
            raise ValueError(f"stamp_ns {stamp_ns} is before the previous frame's {self._last_stamp_ns}")
        dt_s = 0.0 if self._last_stamp_ns is None else (stamp_ns - self._last_stamp_ns) * 1e-9
        self._last_stamp_ns = stamp_ns
        evidence = floor_evidence(result.floor, result.grid, max_half_m=self._max_half_m)

        grid = result.grid
        floor_lo = grid.origin_m[:2]
        floor_hi = floor_lo + np.asarray(grid.shape[:2], dtype=np.float64) * grid.voxel_m
        tau_s = self.motion.velocity_tau_s
        for pair in heads_apart:
            self._heads_apart_ns[frozenset(pair)] = stamp_ns
            _add_pair(self._heads_seen, *pair)
        memory_ns = int(round(self.population.two_memory_s * 1e9))
        self._heads_apart_ns = {k: v for k, v in self._heads_apart_ns.items() if stamp_ns - v <= memory_ns}
        last = {t.id: (t.x, t.y) for t in self._targets}
        held = self._blobs_holding_all()
        by_id = {t.id: t for t in self._targets}
        for t in self._targets:
            others = [last[o] for o in self._two_people.get(t.id, ())
                      if o in last and (frozenset((t.id, o)) in self._heads_apart_ns
                                        or (t.blob is not None and t.blob is by_id[o].blob and id(t.blob) in held))]
            t.track(evidence, stamp_ns, dt_s, tau_s, (floor_lo, floor_hi),
                    exclude_xy=np.array(others).reshape(-1, 2), exclude_radius_m=self.population.merge_distance_m)

        positions = np.array([[t.x, t.y] for t in self._targets]).reshape(-1, 2)
        cost = np.asarray(self.cost_function(positions, blobs))
        if cost.shape != (len(self._targets), len(blobs)):
            raise ValueError(f"cost_function gave shape {cost.shape}, need {(len(self._targets), len(blobs))}")
        matches, unmatched_targets, unmatched_blobs = associate(cost, self.association.gate_m)
        blob_of = {int(ti): int(bi) for ti, bi in matches}
        if self.association.share_blobs and len(unmatched_targets) and blobs:
            self._share(blob_of, unmatched_targets, blobs, result)
            unmatched_blobs = [bi for bi in unmatched_blobs if int(bi) not in blob_of.values()]
        parts = self._split_shared(blob_of, blobs, result)
        held_up = self._held_up(blob_of, hidden)

        for n, t in enumerate(self._targets):
            bi = blob_of.get(n)
            blob = None if bi is None else blobs[bi]
            t.age += 1
            hit = 1.0 if blob is not None or n in held_up else 0.0
            t.reliability += self.learning_rate(t.age) * (hit - t.reliability)
            if hit == 0.0 and _border_distance(t.x, t.y, floor_lo, floor_hi) <= self.confirmation.leave_margin_m:
                t.reliability = min(t.reliability, np.nextafter(self.confirmation.confirm_reliability, 0.0))
            profile, volume_m3 = parts.get(n, (None, None)) if blob is not None else (None, None)
            if blob is not None and profile is None:
                profile, volume_m3 = blob.height_profile, blob.volume_m3
            apart = self._two_people.get(t.id, set()) | self._heads_seen.get(t.id, set())
            others = np.array([[o.x, o.y] for o in self._targets if o.id in apart]).reshape(-1, 2)
            t.observe(blob, profile, volume_m3, result, self._new_filter, others)
            if blob is not None and n not in parts and blob.z_top_m <= self.association.low_top_m:
                t.centre_on(blob, dt_s, tau_s, result, others)
        users = Counter(blob_of.values())
        alone = [n for n, bi in blob_of.items() if users[bi] == 1]  # targets on a blob of their own
        for n in alone:
            self._targets[n].note_alone_volume(blobs[blob_of[n]].volume_m3, self.population.volume_frames)
        if self.association.share_known_only:
            self._note_blobs_apart(alone)

        pop = self.population
        for bi in unmatched_blobs:
            blob = blobs[int(bi)]
            if blob.volume_m3 < pop.new_target_min_volume_m3:
                continue
            if any(math.hypot(t.x - blob.x, t.y - blob.y) < pop.new_target_min_distance_m for t in self._targets):
                continue
            self._targets.append(self._create(blob, evidence, result, stamp_ns))

        self._merge_duplicates()
        self._targets = [t for t in self._targets if t.reliability >= self.confirmation.delete_reliability]
        live = {t.id for t in self._targets}
        self._close_frames = {k: v for k, v in self._close_frames.items() if k[0] in live and k[1] in live}
        self._note_two_people(live)

        nz = result.grid.shape[2]
        for t in self._targets:
            t.update_stillness(stamp_ns, self.motion.still_window_s, self.motion.still_speed_mps)
        confirm = self.confirmation.confirm_reliability
        return [t.estimate(stamp_ns, confirm, nz) for t in sorted(self._targets, key=lambda t: t.id)]

    def _held_up(self, blob_of: dict[int, int], hidden: Sequence[Blob]) -> set[int]:
        """Indices of the still confirmed targets left without a blob that a ``hidden`` blob holds up
        (:data:`HELD_UP_M`, :data:`HELD_UP_TOP_M`); each blob holds up one target, the first in order."""
        if not hidden:
            return set()
        held, used = set(), set()
        confirm = self.confirmation.confirm_reliability
        for n, t in enumerate(self._targets):
            if n in blob_of or t.reliability < confirm or not t.still:
                continue
            d = [math.hypot(b.x - t.x, b.y - t.y) if abs(b.z_top_m - t.z_top_m) <= HELD_UP_TOP_M else math.inf
                 for b in hidden]
            k = int(np.argmin(d))
            if d[k] <= HELD_UP_M and k not in used:
                used.add(k)
                held.add(n)
        return held

    def _blobs_holding_all(self) -> set[int]:
        """``id()`` of the blobs of the last frame shared by targets and holding all their bodies: the
        blob's volume is their bodies' sum but ``1 - hold_share`` of the smallest or more
        (:class:`PopulationParams`; each body's volume the median of its blobs of its own)."""
        users: dict[int, list[_Target]] = {}
        for t in self._targets:
            if t.blob is not None:
                users.setdefault(id(t.blob), []).append(t)
        held = set()
        for key, ts in users.items():
            if len(ts) < 2:
                continue
            volumes = [t.alone_volume_m3 for t in ts]
            if None in volumes or min(volumes) < self.population.body_min_m3:
                continue
            if ts[0].blob.volume_m3 >= sum(volumes) - (1.0 - self.population.hold_share) * min(volumes):
                held.add(key)
        return held

    def _new_filter(self, x_m: float, y_m: float, alpha_m: float) -> ParticleFilter:
        return self.filter_factory(x_m, y_m, alpha_m, rng=self.rng)

    def _create(self, blob: Blob, evidence: FloorEvidence, result: CarveResult, stamp_ns: int) -> "_Target":
        lo, hi = self._alpha_range_m
        alpha_m = float(np.clip(0.5 * math.sqrt(blob.footprint_area_m2), lo, hi))
        pf = self._new_filter(blob.x, blob.y, alpha_m)
        t = _Target(id=int(self._next_id()), pf=pf, x=blob.x, y=blob.y, alpha_m=alpha_m)
        t.track(evidence, stamp_ns, 0.0, self.motion.velocity_tau_s)
        t.age = 1
        t.reliability = self.learning_rate(1)
        t.observe(blob, blob.height_profile, blob.volume_m3, result, self._new_filter)
        return t

    def _share(self, blob_of: dict[int, int], unmatched: np.ndarray, blobs: list[Blob], result: CarveResult) -> None:
        """Let a target the assignment left out share the blob it stands on.

        Two people who touch above ``tau1`` make one blob, and the one-to-one
        assignment gives it to one of them; the other's filter still sees its
        person, so its target counts as matched to the same blob (with
        ``share_known_only``, only when the two are known to be two people).
        """
        grid = result.grid
        owner = np.full(result.floor.count.shape, -1, dtype=np.int32)
        for bi, b in enumerate(blobs):
            owner[b.footprint[:, 0], b.footprint[:, 1]] = bi
        for ti in unmatched:
            t = self._targets[int(ti)]
            if not t.pf.supported or t.age < self.association.share_min_age_frames:
                continue
            i = int(math.floor((t.x - grid.origin_m[0]) / grid.voxel_m))
            j = int(math.floor((t.y - grid.origin_m[1]) / grid.voxel_m))
            if not (0 <= j < owner.shape[0] and 0 <= i < owner.shape[1] and owner[j, i] >= 0):
                continue
            bi = int(owner[j, i])
            if not self.association.share_known_only:
                blob_of[int(ti)] = bi
                continue
            apart = (self._two_people.get(t.id, set()) | self._heads_seen.get(t.id, set())
                     | self._blobs_apart.get(t.id, set()))
            strangers = [u for u, b in blob_of.items() if b == bi and self._targets[u].id not in apart]
            if not strangers:
                blob_of[int(ti)] = bi
            elif all((t.age, -t.id) > (self._targets[u].age, -self._targets[u].id) for u in strangers):
                # the blob is one person's, never seen as two: the older target keeps it
                for u in strangers:
                    del blob_of[u]
                blob_of[int(ti)] = bi

    def _split_shared(self, blob_of: dict[int, int], blobs: list[Blob], result: CarveResult) -> dict[int, tuple[np.ndarray, float]]:
        """Height profile and volume of each target's part of a shared blob.

        Each voxel of a blob matched to several targets goes to the target
        nearest on the floor. Returns {target index: (profile (nz,) int32, volume_m3)}.
        """
        users: dict[int, list[int]] = {}
        for ti, bi in blob_of.items():
            users.setdefault(bi, []).append(ti)
        parts: dict[int, tuple[np.ndarray, float]] = {}
        nz = result.grid.shape[2]
        for bi, tis in users.items():
            if len(tis) < 2:
                continue
            b = blobs[bi]
            xy = result.grid.centres(b.ijk)[:, :2]
            pos = np.array([[self._targets[ti].x, self._targets[ti].y] for ti in tis])
            nearest = np.argmin(((xy[:, None, :] - pos[None, :, :]) ** 2).sum(-1), axis=1)
            for n, ti in enumerate(tis):
                k = b.ijk[nearest == n, 2]
                parts[ti] = (np.bincount(k, minlength=nz).astype(np.int32), len(k) * b.voxel_m**3)
        return parts

    def _note_two_people(self, live: set[int]) -> None:
        """Keep, per live target, the live targets known to be other people: both confirmed
        while at least ``apart_m`` apart (:class:`PopulationParams`)."""
        known = _live_pairs(self._two_people, live)
        confirm = self.confirmation.confirm_reliability
        sure = [t for t in self._targets if t.reliability >= confirm and t.z_top_m >= self.population.two_min_top_m]
        for a, b in itertools.combinations(sure, 2):
            if math.hypot(a.x - b.x, a.y - b.y) >= self.population.apart_m:
                _add_pair(known, a.id, b.id)
        self._two_people = known
        self._heads_seen = _live_pairs(self._heads_seen, live)
        self._blobs_apart = _live_pairs(self._blobs_apart, live)

    def _note_blobs_apart(self, alone: list[int]) -> None:
        """Note the pairs of confirmed targets each matched to a blob of its own (``alone``: their
        indices) at least ``apart_m`` apart: whatever their height, the cameras saw them as two bodies."""
        confirm = self.confirmation.confirm_reliability
        sure = [self._targets[n] for n in alone if self._targets[n].reliability >= confirm]
        for a, b in itertools.combinations(sure, 2):
            if math.hypot(a.x - b.x, a.y - b.y) >= self.population.apart_m:
                _add_pair(self._blobs_apart, a.id, b.id)

    def _merge_duplicates(self) -> None:
        targets = self._targets
        close_now: dict[tuple[int, int], int] = {}
        doomed: set[int] = set()
        for a, b in itertools.combinations(targets, 2):
            key = (min(a.id, b.id), max(a.id, b.id))
            if math.hypot(a.x - b.x, a.y - b.y) >= self.population.merge_distance_m:
                continue
            close_now[key] = self._close_frames.get(key, 0) + 1
            if close_now[key] >= self.population.merge_frames and a.id not in doomed and b.id not in doomed:
                keep, drop = (a, b) if (a.age, -a.id) >= (b.age, -b.id) else (b, a)
                keep.reliability = max(keep.reliability, drop.reliability)
                doomed.add(drop.id)
        self._close_frames = close_now
        if doomed:
            self._targets = [t for t in targets if t.id not in doomed]


class _Target:
    """Mutable state of one target."""

    def __init__(self, *, id: int, pf: ParticleFilter, x: float, y: float, alpha_m: float):
        self.id = id
        self.pf = pf
        self.x = x
        self.y = y
        self.alpha_m = alpha_m
        self.vx = 0.0
        self.vy = 0.0
        self.age = 0
        self.reliability = 0.0
        self.z_top_m = 0.0
        self.volume_m3 = 0.0
        self.height_profile: np.ndarray | None = None
        self.blob: Blob | None = None
        self.speeds: deque[tuple[int, float]] = deque()
        self.blob_xy: deque[tuple[int, float, float]] = deque()  # (stamp, x, y) of the blobs matched
        self.alone_volumes: deque[float] = deque()  # volumes of the last blobs it had to itself
        self.xy: deque[tuple[int, float, float]] = deque()  # (stamp, x, y) of the target's own estimates
        self.still = False
        self._before = (x, y, 0.0, 0.0)  # position and velocity before this frame's filter step

    @property
    def alone_volume_m3(self) -> float | None:
        """The body's volume: the median of the blobs it had to itself lately (None before any)."""
        return float(np.median(self.alone_volumes)) if self.alone_volumes else None

    def note_alone_volume(self, volume_m3: float, frames: int) -> None:
        self.alone_volumes.append(float(volume_m3))
        while len(self.alone_volumes) > frames:
            self.alone_volumes.popleft()

    def track(self, evidence: FloorEvidence, stamp_ns: int, dt_s: float, tau_s: float, bounds=None, *,
              exclude_xy: np.ndarray | None = None, exclude_radius_m: float = 0.0) -> None:
        """Particle filter step; velocity from the change of position. ``exclude_xy``,
        ``exclude_radius_m``: where other people stand, and how near them this one cannot
        (:meth:`ParticleFilter.step`).

        bounds: ((2,), (2,)) floor rectangle of the volume, world metres. The
        floor maps hold no evidence outside it, so a target coasting on its
        velocity (someone who walked out through a door) stops at its edge,
        where they were last seen, instead of gliding on beyond it.
        """
        est = self.pf.step(evidence, stamp_ns, velocity_mps=(self.vx, self.vy),
                           exclude_xy=exclude_xy, exclude_radius_m=exclude_radius_m)
        if bounds is not None:
            lo, hi = bounds
            self.pf.particles[:, :2] = np.clip(self.pf.particles[:, :2], lo, hi)
            est = est.copy()
            est[:2] = np.clip(est[:2], lo, hi)
        self._before = (self.x, self.y, self.vx, self.vy)
        if dt_s > 0:
            beta = 1.0 - math.exp(-dt_s / tau_s)
            self.vx += beta * (float(est[0] - self.x) / dt_s - self.vx)
            self.vy += beta * (float(est[1] - self.y) / dt_s - self.vy)
        self.x, self.y, self.alpha_m = float(est[0]), float(est[1]), float(est[2])

    def observe(
        self,
        blob: Blob | None,
        profile: np.ndarray | None,
        volume_m3: float | None,
        result: CarveResult,
        new_filter: Callable[[float, float, float], ParticleFilter],
        others_xy: np.ndarray | None = None,
    ) -> None:
        """Take this frame's measurements of the target (its part of ``blob``);
        ``new_filter(x_m, y_m, alpha_m)`` makes a filter should it need a fresh one.
        ``others_xy`` (K, 2): where the other targets stand; the top is read only from
        the floor cells nearer to this target than to any of them (:func:`_box_top`)."""
        self.blob = blob
        if blob is not None:
            self.volume_m3 = float(volume_m3)
            self.height_profile = profile
            if not self.pf.supported:
                # The particles lost the person while a blob still matched: restart them on it.
                self.pf = _restart(self.pf, blob, self.alpha_m, new_filter)
                self.x, self.y = blob.x, blob.y
        top = _box_top(result, self.x, self.y, self.alpha_m, others_xy)
        if top > 0:
            self.z_top_m = top
        elif blob is not None:
            self.z_top_m = blob.z_top_m

    def centre_on(self, blob: Blob, dt_s: float, tau_s: float, result: CarveResult,
                  others_xy: np.ndarray | None = None) -> None:
        """Place the target at ``blob``'s centroid: the particles move by the same offset,
        the velocity follows the change of position since the last frame, the top is
        read around the new position."""
        dx, dy = blob.x - self.x, blob.y - self.y
        self.pf.particles[:, 0] += dx
        self.pf.particles[:, 1] += dy
        x0, y0, vx0, vy0 = self._before
        self.x, self.y = float(blob.x), float(blob.y)
        if dt_s > 0:
            beta = 1.0 - math.exp(-dt_s / tau_s)
            self.vx = vx0 + beta * ((self.x - x0) / dt_s - vx0)
            self.vy = vy0 + beta * ((self.y - y0) / dt_s - vy0)
        top = _box_top(result, self.x, self.y, self.alpha_m, others_xy)
        if top > 0:
            self.z_top_m = top

    def update_stillness(self, stamp_ns: int, window_s: float, still_speed_mps: float) -> None:
        """Still when, over the whole window, the smoothed speed stayed below the threshold; or a
        blob matched the target on every frame and their centres stayed within ``still_speed_mps *
        window_s`` of each other along both axes (the filter's estimate can jitter where the hull
        around a still person is wide: behind furniture, beside a phantom); or the target's own
        estimates stayed that close (the blob's centre jumps where the hull splits or merges for a
        frame, and a single quick step of the estimate lifts the smoothed speed over the threshold,
        though the person stands where they stood: such a person must not lose their hold and
        fade into the cameras' background)."""
        window_ns = int(round(window_s * 1e9))
        _keep_window(self.speeds, (stamp_ns, math.hypot(self.vx, self.vy)), window_ns)
        _keep_window(self.xy, (stamp_ns, self.x, self.y), window_ns)
        if self.blob is None:
            self.blob_xy.clear()
        else:
            _keep_window(self.blob_xy, (stamp_ns, self.blob.x, self.blob.y), window_ns)
        covered = stamp_ns - self.speeds[0][0] >= window_ns
        slow = max(s for _, s in self.speeds) < still_speed_mps
        reach = still_speed_mps * window_s
        placed = _within(self.blob_xy, stamp_ns, window_ns, reach)
        settled = _within(self.xy, stamp_ns, window_ns, reach)
        self.still = covered and (slow or placed or settled)

    def estimate(self, stamp_ns: int, confirm: float, nz: int) -> TrackEstimate:
        profile = self.height_profile if self.height_profile is not None else np.zeros(nz, dtype=np.int32)
        return TrackEstimate(
            id=self.id,
            x=self.x,
            y=self.y,
            z_top_m=self.z_top_m,
            volume_m3=self.volume_m3,
            reliability=self.reliability,
            confirmed=self.reliability >= confirm,
            age_frames=self.age,
            vx=self.vx,
            vy=self.vy,
            height_profile=profile,
            blob=self.blob,
            still=bool(self.still),
            alpha_m=self.alpha_m,
            stamp_ns=stamp_ns,
        )


def _restart(
    pf: ParticleFilter, blob: Blob, alpha_m: float, new_filter: Callable[[float, float, float], ParticleFilter]
) -> ParticleFilter:
    """A fresh filter on ``blob`` that goes on from ``pf``'s last step."""
    fresh = new_filter(blob.x, blob.y, alpha_m)
    fresh.last_stamp_ns = pf.last_stamp_ns
    return fresh


def _border_distance(x_m: float, y_m: float, lo: np.ndarray, hi: np.ndarray) -> float:
    """Floor distance (metres) from (x, y) to the nearest side of the rectangle ``lo``..``hi``."""
    return float(min(x_m - lo[0], y_m - lo[1], hi[0] - x_m, hi[1] - y_m))


def _box_top(result: CarveResult, x_m: float, y_m: float, alpha_m: float,
             others_xy: np.ndarray | None = None) -> float:
    """Highest column top (metres) in the square floor box around (x, y), over the cells
    nearer to (x, y) than to any of ``others_xy`` (K, 2) world metres: a column belongs to
    the person standing nearest to it, so a neighbour's head inside the box is not this
    person's top (someone fallen beside a helper has the top of a body on the floor)."""
    grid = result.grid
    top = result.floor.top_m
    v = grid.voxel_m
    i = int(math.floor((x_m - grid.origin_m[0]) / v))
    j = int(math.floor((y_m - grid.origin_m[1]) / v))
    a = max(0, int(round(alpha_m / v)))
    j0, j1 = max(j - a, 0), min(j + a + 1, top.shape[0])
    i0, i1 = max(i - a, 0), min(i + a + 1, top.shape[1])
    if j0 >= j1 or i0 >= i1:
        return 0.0
    box = top[j0:j1, i0:i1]
    if others_xy is not None and len(others_xy):
        cx = grid.origin_m[0] + (np.arange(i0, i1) + 0.5) * v
        cy = grid.origin_m[1] + (np.arange(j0, j1) + 0.5) * v
        own = (cy[:, None] - y_m) ** 2 + (cx[None, :] - x_m) ** 2
        near = np.asarray(others_xy, dtype=np.float64).reshape(-1, 2)
        near = near[np.hypot(near[:, 0] - x_m, near[:, 1] - y_m) < 3.0 * (a + 1) * v]  # farther: no cell of the box is nearer to them
        for ox, oy in near:
            box = np.where(own <= (cy[:, None] - oy) ** 2 + (cx[None, :] - ox) ** 2, box, 0.0)
    return float(box.max())


def _within(samples: deque, stamp_ns: int, window_ns: int, reach_m: float) -> bool:
    """Whether ``samples`` (stamp, x, y) span the window up to ``stamp_ns`` and stay within
    ``reach_m`` of each other along both axes."""
    if not samples or stamp_ns - samples[0][0] < window_ns:
        return False
    xy = np.array([(x, y) for _, x, y in samples])
    return bool(np.all(np.ptp(xy, axis=0) < reach_m))


def _keep_window(samples: deque, sample: tuple, window_ns: int) -> None:
    """Append ``sample`` (stamp first) and drop the oldest while the next one still spans ``window_ns``."""
    samples.append(sample)
    while len(samples) > 1 and samples[1][0] <= sample[0] - window_ns:
        samples.popleft()


def _add_pair(pairs: dict[int, set[int]], a: int, b: int) -> None:
    """Note targets ``a`` and ``b`` as two people in ``pairs`` (target id -> the others), both ways."""
    pairs.setdefault(a, set()).add(b)
    pairs.setdefault(b, set()).add(a)


def _live_pairs(pairs: dict[int, set[int]], live: set[int]) -> dict[int, set[int]]:
    """``pairs`` (target id -> the others) kept to the ``live`` targets, those left with no other dropped."""
    kept = {tid: others & live for tid, others in pairs.items() if tid in live}
    return {tid: others for tid, others in kept.items() if others}
