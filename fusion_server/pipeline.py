"""One fused frame: masks of a frame set -> voxels -> people -> postures -> events.

The whole algorithmic chain of the fusion server, shared line for line by the
live server and offline replay through :class:`fusion_server.node.FusionNode`. Pure: no zenoh, no clock, no files (the carving
lookup-table cache aside, which the carver owns).

Each stage is built in one place: the carver, the event reasoner and the
identity keeper of a site by :func:`build_carver`, :func:`build_reasoner` and
:func:`build_identity` (which reads the enrolled residents' model files, as
``from_site`` reads the calibrations), the tracker by :func:`build_tracker`. ``FusionPipeline.from_site`` and the benchmark
(``evaluation.benchmark``) both build through them.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.appearance import AppearanceModel
from common.camera import Camera
from common.messages import Appearance, Event, PersonRegion
from common.site import Site
from fusion_server.carving import Carver
from fusion_server.carving.occlusion import Occluder
from fusion_server.consistency import CameraMoved, ConsistencyMonitor, ConsistencyParams
from fusion_server.detection import Blob, detect_blobs
from fusion_server.explain import BlobExplainer, upright
from fusion_server.events import EventReasoner, FallParams, InactivityParams
from fusion_server.grid import CarveResult
from fusion_server.heads import HeadGaps
from fusion_server.hotspots import BED_KINDS, SEAT_KINDS, Hotspot
from fusion_server.identity import IdentityKeeper, IdentityParams, Resident
from fusion_server.posture import PostureBank, PostureReading, backs_of
from fusion_server.snapshot import Snapshot, Watched
from fusion_server.tracker import PopulationParams, TrackEstimate, Tracker

log = logging.getLogger("voxelwatch.fusion")


RESTORE_WINDOW_S = 10.0
"""After a restart, how long a restored person waits to be found again where they were (seconds)."""
HELD_REACH_M = 1.0
"""A held person's hold keeps what their body covered since it was first held, up to this far from
their floor position (a body lying on the floor reaches about 1 m from its pelvis either way)."""
NEW_TARGET_MIN_VOLUME_M3 = 0.05
"""Smallest blob that starts a new track. A person carves 0.1-0.5 m^3 standing (a
body lying half hidden by furniture about 0.05-0.1 m^3, but that person was tracked
before falling); hull voxels where two people's silhouettes cross, or behind a
person near a wall that few cameras see, form blobs of 0.02-0.045 m^3 that last a
few frames, long enough to be confirmed as people."""


@dataclass(frozen=True)
class TrackOutput:
    """A confirmed track as users see it. World frame, metres, m/s."""

    id: int
    x: float
    y: float
    z_top: float
    volume_m3: float
    posture: str
    reliability: float
    vx: float
    vy: float
    still: bool
    person: str | None = None


@dataclass(frozen=True)
class FusedFrame:
    """Everything one frame set produced.

    holds: camera id -> full-resolution pixel boxes ``(x0, y0, x1, y1)``
        (exclusive ends) around each still person, which that camera must not
        learn into its background.
    looks: camera id -> the people whose colours that camera should describe
        on its next frame (sent as a :class:`~common.messages.LookRequest`).
    """

    frame: int
    stamp_ns: int
    cameras: tuple[str, ...]
    tracks: list[TrackOutput]
    events: list[Event]
    holds: dict[str, list[tuple[int, int, int, int]]]
    carve: CarveResult
    looks: dict[str, list[PersonRegion]] = field(default_factory=dict)
    moved: list[CameraMoved] = field(default_factory=list)
    """Cameras judged moved on this frame set (:mod:`fusion_server.consistency`)."""


class FusionPipeline:
    """Carve, detect, track, judge posture and reason about events, frame by frame.

    Keyword arguments:
      carver: the voxel carver of the site's cameras and volume.
      cameras: camera id -> full-resolution camera (for hold regions).
      reasoner: the event reasoner (hot spots, doors, residents).
      rng: generator for the particle filters of the tracker (:func:`build_tracker`).
      identity: who is who (:class:`~fusion_server.identity.IdentityKeeper`)
        [None: one over ``cameras`` with default settings and no residents].
      hold_radius_m: half-width of the floor square around a still person
        whose projection a camera must not learn.
      min_cameras: fewest cameras a frame set needs to be fused.
      decisions, viterbi_lag_s: how each track's posture is decided, frame by
        frame or by fixed-lag Viterbi decoding
        (:class:`~fusion_server.posture.PostureEstimator`).
      consistency: the settings of the moved-camera check
        (:class:`~fusion_server.consistency.ConsistencyMonitor`, attribute ``consistency``).

    posture_settings: the keyword arguments every track's posture estimator is made with.
    """

    def __init__(
        self,
        *,
        carver: Carver,
        cameras: Mapping[str, Camera],
        reasoner: EventReasoner,
        rng: np.random.Generator,
        hold_radius_m: float = 0.45,
        min_cameras: int | None = None,
        identity: IdentityKeeper | None = None,
        decisions: str = "frame",
        viterbi_lag_s: float = 0.6,
        consistency: ConsistencyParams = ConsistencyParams(),
        monitored_xy_m: tuple[float, float, float, float] | None = None,
    ) -> None:
        if hold_radius_m <= 0:
            raise ValueError(f"hold_radius_m must be positive, got {hold_radius_m}")
        self.carver = carver
        grid = carver.grid
        lo = grid.origin_m
        hi = grid.origin_m + np.asarray(grid.shape) * grid.voxel_m
        self.monitored_xy_m = tuple(float(v) for v in (
            monitored_xy_m if monitored_xy_m is not None else (lo[0], lo[1], hi[0], hi[1])))
        """The floor rectangle (x0, y0, x1, y1) whose people are reported; the carver's volume may
        reach beyond it, where people are followed but not reported."""
        self._inside: set[int] = set()  # labels reported on the last frame set
        x0, y0, x1, y1 = self.monitored_xy_m
        self._carved_beyond_m = max(0.0, float(x0 - lo[0]), float(y0 - lo[1]), float(hi[0] - x1), float(hi[1] - y1))
        self.cameras = dict(cameras)
        self.reasoner = reasoner
        self.tracker = build_tracker(rng)
        self.hold_radius_m = float(hold_radius_m)
        self._held_extent: dict[int, tuple[float, float, float, float, float]] = {}  # held person -> floor box and top so far
        self.min_cameras = int(min_cameras if min_cameras is not None else carver.min_cameras)
        self.camera_ids: tuple[str, ...] = carver.camera_ids
        self.explainer = BlobExplainer(self.cameras)
        self.refused_blobs: list[Blob] = []  # the last frame set's upright blobs the explanation did not take for people
        self.head_gaps = HeadGaps(self.cameras)
        self._bodies: list[TrackEstimate] = []  # the tracker's estimates of the last frame set
        self.consistency = ConsistencyMonitor(carver, self.cameras, consistency)
        self.consistency_errors = 0
        """Frame sets on which the moved-camera check failed (they are fused all the same)."""
        self.identity = identity if identity is not None else IdentityKeeper(self.cameras)
        self.postures = PostureBank(voxel_m=carver.grid.voxel_m, decisions=decisions, viterbi_lag_s=viterbi_lag_s,
                                    seats=[h for h in reasoner.hotspots if h.kind in SEAT_KINDS],
                                    beds=[h for h in reasoner.hotspots if h.kind in BED_KINDS],
                                    backs=backs_of(carver.occluders),
                                    crowd_m=self.tracker.population.apart_m)
        self._labels: dict[int, int] = {}  # target id -> label, as of the last frame
        self._watched: tuple[int, list[TrackOutput], dict] | None = None   # (stamp, tracks, holds) of the last step
        self._restore: Snapshot | None = None   # a snapshot to go on from, taken at the next step
        self._restoring: dict[int, dict | None] = {}   # restored labels not taken back yet -> fall state
        self._restoring_until_ns = 0
        self._restored: dict[int, Watched] = {}   # the restored people, as the snapshot had them

    @classmethod
    def from_site(
        cls,
        site: Site,
        *,
        cameras: Mapping[str, Camera] | None = None,
        cache_dir: str | Path | None = None,
        seed: int = 0,
        min_cameras: int | None = None,
        residents: Sequence[Resident] | None = None,
    ) -> "FusionPipeline":
        """The pipeline a site file describes (calibrations loaded unless given;
        event timing from its ``[events]`` section; who is who from its
        ``[identity]`` section and the residents it enrols, unless ``residents``
        is given: ``()`` recognises nobody, as an enrolment must; posture
        decisions from ``[events]``)."""
        cameras = dict(cameras) if cameras is not None else site.load_cameras()
        return cls(
            carver=build_carver(site, cameras, cache_dir=cache_dir),
            cameras=cameras,
            reasoner=build_reasoner(site),
            rng=np.random.default_rng(seed),
            min_cameras=min_cameras,
            identity=build_identity(site, cameras, residents=residents),
            decisions=site.events.decisions,
            viterbi_lag_s=site.events.viterbi_lag_s,
            monitored_xy_m=(*site.volume.min_m[:2], *site.volume.max_m[:2]),
        )

    def step(self, masks: Mapping[str, np.ndarray], stamp_ns: int, frame: int,
             looks: Mapping[str, Iterable[Appearance]] | None = None,
             depths: Mapping[str, np.ndarray] | None = None) -> FusedFrame:
        """Fuse one frame set.

        masks: camera id -> (H, W) uint8 mask, 0 background, 255 foreground,
            at full or downscaled resolution; absent cameras do not vote.
        stamp_ns: the frame set's capture time. frame: its frame number.
        looks: camera id -> the colour descriptors that came with its mask.
        depths: camera id -> (H, W) uint16 range image, millimetres, at its mask's size,
            from depth cameras (0 = no measurement): carves free space in front of people.
        """
        if self._restore is not None:
            self._take_restore(self._restore, stamp_ns)
            self._restore = None
        carve = self.carver.carve(masks, stamp_ns, depths=depths)
        blobs = self.detect_people(carve, masks)
        bodies = self.tracker.step(carve, blobs, stamp_ns, heads_apart=self._heads_apart(masks), hidden=self.refused_blobs)
        self._bodies = bodies
        try:
            _, moved = self.consistency.step(masks, bodies, stamp_ns)
        except Exception as exc:  # noqa: BLE001 - the check must never cost a frame set its tracks
            self.consistency_errors += 1
            moved = []
            if self.consistency_errors == 1 or self.consistency_errors % 1000 == 0:
                log.warning("moved-camera check failed %d time(s), last on the frame set at %d: %s: %s",
                            self.consistency_errors, stamp_ns, type(exc).__name__, exc)
        estimates = self.label(bodies, looks or {}, stamp_ns)
        readings = self.update_postures(estimates, stamp_ns)
        standing = {b.id: float(e.z_top_m) for b, e in zip(bodies, estimates)
                    if readings.get(e.id) is not None and readings[e.id].posture == "standing"}
        self.identity.learn(bodies, standing, stamp_ns)
        # people followed beyond the monitored volume's sides are nobody's business here
        monitored = [e for e in estimates if self.monitors(e.x, e.y, self._leave_margin_m(e, readings.get(e.id)))]
        self._inside = {e.id for e in monitored}
        # the reasoner follows them too: their tops and upright time count (someone who stood
        # outside and fell in fell from their height), but they are nobody present (no entry,
        # no event) until they are inside
        outside = [e.id for e in estimates if e.id not in self._inside]
        events = [self._named(ev) for ev in self.reasoner.step(stamp_ns, frame, estimates, readings, outside=outside)]
        confirmed = [e for e in estimates if e.confirmed]
        tracks = [_output(e, readings.get(e.id), self.identity.name_of(e.id)) for e in monitored if e.confirmed]
        # A seated or lying person is held even when the tracker's estimate jitters
        # (late masks, a camera rejoining): losing the hold would let the cameras
        # learn exactly the people who must never fade, those on the floor.
        held = [e for e in confirmed if e.still or (e.id in readings and readings[e.id].posture in ("sitting", "lying"))]
        holds = self.hold_regions(held)
        self._watched = (int(stamp_ns), tracks, holds)
        if self._restoring and stamp_ns > self._restoring_until_ns:
            log.info("restart: %s not found again within %.0f s; they are lost people now",
                     ", ".join(f"person {label}" for label in sorted(self._restoring)), RESTORE_WINDOW_S)
            self._restoring.clear()
        return FusedFrame(
            frame=int(frame),
            stamp_ns=int(stamp_ns),
            cameras=tuple(sorted(masks)),
            tracks=tracks,
            events=events,
            holds=holds,
            carve=carve,
            looks=self.identity.regions(bodies, stamp_ns),
            moved=moved,
        )

    def _leave_margin_m(self, est: TrackEstimate, reading: PostureReading | None) -> float:
        """How far beyond the monitored sides the person ``est`` is still inside: 0 for someone
        outside; :data:`LEAVE_MARGIN_M` for someone inside; for someone inside who is low (their
        top this frame, or the fall reasoner's reading of their last frames, at most the fall
        rule's low fraction of their standing height), as far as the carve reaches: a body falling
        or lying across a side is half out and its estimate drifts outward as it spreads, and
        neither the fall nor a long lie may end because the centre crossed the line."""
        if est.id not in self._inside:
            return 0.0
        if self.reasoner.falls.low(est.id, est.z_top_m, reading.standing_height_m if reading is not None else None):
            return max(LEAVE_MARGIN_M, self._carved_beyond_m)
        return LEAVE_MARGIN_M

    def monitors(self, x: float, y: float, margin_m: float = 0.0) -> bool:
        """Whether floor point (x, y) lies in the monitored volume (:attr:`monitored_xy_m`), or
        within ``margin_m`` beyond its sides."""
        x0, y0, x1, y1 = self.monitored_xy_m
        return x0 - margin_m <= x <= x1 + margin_m and y0 - margin_m <= y <= y1 + margin_m

    def label(self, bodies: list[TrackEstimate], looks: Mapping[str, Iterable[Appearance]],
              stamp_ns: int) -> list[TrackEstimate]:
        """The tracker's estimates under the labels of the people they are (ids users
        see; negative for a target not yet confirmed). What the posture estimators
        and the event reasoner keep of a body follows it when its label changes."""
        labels = self.identity.assign(bodies, looks, stamp_ns)
        # A body whose identity opened again (label back to negative) leaves its person's
        # state behind: that person is gone from here, as far as events go.
        renames = {self._labels.get(tid, -tid): label for tid, label in labels.items()
                   if self._labels.get(tid, -tid) != label and label > 0}
        if renames:
            self.postures.rename(renames)
            self.reasoner.rename(renames)
            for label in renames.values():
                if label in self._restoring:
                    self.reasoner.restore(label, self._restoring.pop(label))
                    log.info("restart: person %d found again", label)
        self._labels = labels
        # a body waiting for its identity is not reported (nor taken for a person) yet
        return [dataclasses.replace(b, id=labels[b.id], confirmed=b.confirmed and labels[b.id] > 0) for b in bodies]

    def snapshot(self) -> Snapshot | None:
        """What a restarted server needs to go on from the last step (None before the first):
        the confirmed people with their models and fall state, and the holds."""
        if self._watched is None:
            return None
        stamp_ns, tracks, holds = self._watched
        people = []
        for t in tracks:
            model = self.identity.model_of(t.id)
            people.append(Watched(label=int(t.id), x=round(float(t.x), 3), y=round(float(t.y), 3), posture=t.posture,
                                  name=t.person, model=model.to_dict() if model is not None else None,
                                  fall=self.reasoner.state_of(t.id)))
        # restored people not found again yet stay in the next snapshot as they were
        people += [p for label, p in self._restored.items() if label in self._restoring]
        return Snapshot(stamp_ns=stamp_ns, people=tuple(people), holds={c: list(b) for c, b in holds.items()})

    def restore(self, snapshot: Snapshot) -> None:
        """Go on from ``snapshot`` (a restarted server): at the next step its people are lost
        right where they were, and the first body confirmed at each place within
        :data:`RESTORE_WINDOW_S` takes their label, name and fall state back."""
        self._restore = snapshot

    @property
    def restoring(self) -> tuple[int, ...]:
        """Labels of a restored snapshot not taken back yet."""
        return tuple(sorted(set(self._restoring) | ({p.label for p in self._restore.people} if self._restore else set())))

    def _take_restore(self, snap: Snapshot, stamp_ns: int) -> None:
        people = []
        for p in snap.people:
            model = None
            if p.model is not None:
                try:
                    model = AppearanceModel.from_dict(p.model, where=f"snapshot person {p.label}")
                except ValueError as exc:
                    log.warning("restart: %s; their appearance is learnt afresh", exc)
            people.append((p.label, p.name, (p.x, p.y), model))
            self._restoring[p.label] = p.fall
        self._restored = {p.label: p for p in snap.people}
        self.identity.restore(people, stamp_ns)
        self._restoring_until_ns = int(stamp_ns) + int(RESTORE_WINDOW_S * 1e9)

    def _named(self, event: Event) -> Event:
        """``event`` with the enrolled resident's name in its details, when it is about one."""
        name = self.identity.name_of(event.track) if event.track > 0 else None
        if name is None:
            return event
        return event.model_copy(update={"details": {**event.details, "person": name}})

    def hold_regions(self, still: list[TrackEstimate]) -> dict[str, list[tuple[int, int, int, int]]]:
        """Per camera, the image boxes of the given people: a floor rectangle
        covering the square of ``hold_radius_m`` around each and the floor
        extent of their matched blob, from the floor to their top.

        The blob matters for anyone whose body reaches beyond the square
        around their floor position: a seated person's lower legs and feet,
        a person lying down. Left out of the hold, those parts would be
        learned into the background while the rest of the body is held.
        While a person stays held, what their blob covered since stays in
        their hold, up to :data:`HELD_REACH_M` from their place: a body
        still on the floor does not shrink, and a part that fades from one
        camera's mask for a while (its blob shrinking with it) must not be
        learned into that camera's background and lost for good.
        """
        holds: dict[str, list[tuple[int, int, int, int]]] = {cam: [] for cam in self.cameras}
        if not still:
            self._held_extent = {}
            return holds
        r = self.hold_radius_m
        corners = []
        extents = {}
        for est in still:
            x0, x1, y0, y1 = est.x - r, est.x + r, est.y - r, est.y + r
            top = float(est.z_top_m)
            if est.blob is not None:
                (bx0, by0, _), (bx1, by1, bz1) = est.blob.bbox_m
                x0, x1, y0, y1 = min(x0, bx0), max(x1, bx1), min(y0, by0), max(y1, by1)
                top = max(top, float(bz1))
            before = self._held_extent.get(est.id)
            if before is not None:  # what the body covered since it settled stays held, near it
                reach = HELD_REACH_M
                x0, x1 = min(x0, max(before[0], est.x - reach)), max(x1, min(before[1], est.x + reach))
                y0, y1 = min(y0, max(before[2], est.y - reach)), max(y1, min(before[3], est.y + reach))
                top = max(top, before[4])
            extents[est.id] = (x0, x1, y0, y1, top)
            top = max(top, 0.5) + 0.1
            for x, y, z in itertools.product((x0, x1), (y0, y1), (0.0, top)):
                corners.append((x, y, z))
        self._held_extent = extents
        pts = np.asarray(corners, dtype=np.float64).reshape(len(still), 8, 3)
        for cam_id, cam in self.cameras.items():
            uv, valid = cam.project(pts.reshape(-1, 3))
            uv = uv.reshape(len(still), 8, 2)
            valid = valid.reshape(len(still), 8)
            for person_uv, person_valid in zip(uv, valid):
                if not person_valid.any():
                    continue
                seen = person_uv[person_valid]
                x0, y0 = np.floor(seen.min(axis=0)).astype(int)
                x1, y1 = np.ceil(seen.max(axis=0)).astype(int) + 1
                if not person_valid.all():  # part of the box is off-image: extend to the border it leaves by
                    x0, y0, x1, y1 = _extend_to_border(person_uv, person_valid, (x0, y0, x1, y1), cam)
                box = (max(0, x0), max(0, y0), min(cam.width, x1), min(cam.height, y1))
                if box[2] > box[0] and box[3] > box[1]:
                    holds[cam_id].append(tuple(int(v) for v in box))
        return holds

    def _heads_apart(self, masks: Mapping[str, np.ndarray]) -> list[tuple[int, int]]:
        """Pairs of the last frame set's targets, standing or sitting (their tops as high as the
        tracker's ``two_min_top_m``) within :data:`HEADS_NEAR_M` of each other, whose two heads the
        cameras see apart in ``masks``."""
        upright = [b for b in self._bodies if b.z_top_m >= self.tracker.population.two_min_top_m]
        pairs = [(a, b) for a, b in itertools.combinations(upright, 2)
                 if (a.x - b.x) ** 2 + (a.y - b.y) ** 2 < HEADS_NEAR_M**2]
        seen = self.head_gaps.seen_apart((((a.x, a.y, a.z_top_m), (b.x, b.y, b.z_top_m)) for a, b in pairs), masks)
        return [(a.id, b.id) for (a, b), s in zip(pairs, seen) if s]

    def detect_people(self, carve: CarveResult, masks: Mapping[str, np.ndarray]) -> list[Blob]:
        """The blobs of ``carve`` that are people, given the frame set's ``masks``."""
        # only the blobs that explain foreground of their own are people: the rest are phantoms
        # where other people's cones cross, duplicates of someone already accepted, or people the
        # others hide; the upright ones are kept for the tracker (they hold up a still person it
        # follows; a low one is as often a piece of someone's legs beside them)
        verdict = self.explainer.explain(detect_blobs(carve), masks, carve.grid)
        self.refused_blobs = [b for b in verdict.phantoms if upright(b)]
        return verdict.people

    def update_postures(self, estimates: list[TrackEstimate], stamp_ns: int) -> dict[int, PostureReading]:
        """Feed each track's posture estimator this frame's estimate (a new track gets a new
        estimator, a gone one loses its own). Returns track id -> reading, for the tracks
        whose posture is known."""
        return self.postures.update(stamp_ns, estimates)

    @property
    def posture_settings(self) -> dict:
        """The keyword arguments every track's posture estimator is made with."""
        return self.postures.settings


def build_carver(site: Site, cameras: Mapping[str, Camera], *, cache_dir: str | Path | None = None) -> Carver:
    """The carver of the site's volume, carving settings and occluders over ``cameras``
    (camera id -> full-resolution camera); lookup tables cached in ``cache_dir`` [None:
    the carver's default cache]."""
    carving = site.carving
    kwargs = {} if cache_dir is None else {"cache_dir": cache_dir}
    margin = carve_margin_m(site)
    lo, hi = site.volume.min_m, site.volume.max_m
    return Carver(
        cameras=cameras,
        volume_min_m=(lo[0] - margin, lo[1] - margin, lo[2]),
        volume_max_m=(hi[0] + margin, hi[1] + margin, hi[2]),
        voxel_sizes_m=carving.voxel_sizes_m,
        min_cameras=carving.min_cameras,
        min_ratio=carving.min_ratio,
        mask_scale=carving.mask_scale,
        fusion=carving.fusion,
        smoothing=carving.smoothing,
        free_space=carving.free_space,
        occluders=[Occluder(name=o.name, polygon_m=tuple(o.polygon_m), z_min_m=o.z_m[0], z_max_m=o.z_m[1])
                   for o in site.occluders],
        **kwargs,
    )


def build_reasoner(site: Site) -> EventReasoner:
    """The event reasoner of the site's hot spots, doors, residents and ``[events]`` timing."""
    return EventReasoner(
        hotspots=[Hotspot(name=h.name, polygon_m=np.asarray(h.polygon_m), kind=h.kind) for h in site.hotspots],
        doors=[Hotspot(name=d.name, polygon_m=np.asarray(d.polygon_m), kind="door") for d in site.doors],
        bounds_xy_m=_entry_edges(site),
        residents=site.residents,
        utc_offset_h=site.utc_offset_hours,
        falls=FallParams(long_lie_s=site.events.long_lie_s),
        inactivity=InactivityParams(inactivity_s=site.events.inactivity_s),
    )


def build_identity(site: Site, cameras: Mapping[str, Camera], *,
                   residents: Sequence[Resident] | None = None) -> IdentityKeeper:
    """The identity keeper of the site's ``[identity]`` settings over ``cameras`` (camera
    id -> full-resolution camera), recognising ``residents`` [None: the site's enrolled
    residents, their model files read now (:class:`~common.site.SiteError` on a bad one)]."""
    params = IdentityParams(reid_window_s=site.identity.reid_window_s, rate_hz=site.identity.rate_hz)
    people = site.load_residents() if residents is None else list(residents)
    return IdentityKeeper(cameras, params, residents=people)


def build_tracker(rng: np.random.Generator) -> Tracker:
    """The pipeline's tracker: track ids from 1, new tracks only on person-sized blobs."""
    return Tracker(
        rng=rng,
        id_source=itertools.count(1),
        population=PopulationParams(new_target_min_volume_m3=NEW_TARGET_MIN_VOLUME_M3),
    )


HEADS_NEAR_M = 1.2
"""Two people this close on the floor (or closer) are tested for two heads on every frame set."""
LEAVE_MARGIN_M = 0.1
"""Someone in the monitored volume is in it until their floor position lies this far beyond its side;
someone outside is in once their position is. The margin is the estimate's own jitter, not a body's
width: a person is in the room while their pelvis is (as the ground truth counts them), and the
margin only keeps someone standing on the side from flickering in and out. The floor position of a
track standing still strays from its mean over a second by 0.007 m (median), 0.024 m (90th
percentile) and 0.074 m (99th) on the 38 tuning worlds; at 0.2 m, a body's half-width, people
who had stopped 0.05-0.2 m outside were still reported."""
OPEN_EDGE_MARGIN_M = 0.6
"""How far beyond open edges the cameras follow people unless the site says (``[volume] margin_m``):
a person's carved hull reaches about half a metre from their centre."""


def carve_margin_m(site: Site) -> float:
    """How far beyond the monitored volume's sides the site's people are carved and followed."""
    if site.volume.margin_m is not None:
        return float(site.volume.margin_m)
    return OPEN_EDGE_MARGIN_M if _entry_edges(site) is not None else 0.0


def _entry_edges(site: Site) -> tuple[float, float, float, float] | None:
    """The floor rectangle whose edges people cross to enter and leave, or None
    when they come and go only through the site's doors."""
    open_edges = site.volume.open_edges if site.volume.open_edges is not None else not site.doors
    if not open_edges:
        return None
    lo, hi = site.volume.min_m, site.volume.max_m
    return (lo[0], lo[1], hi[0], hi[1])


def _output(est: TrackEstimate, reading: PostureReading | None, person: str | None = None) -> TrackOutput:
    return TrackOutput(
        id=int(est.id),
        x=float(est.x),
        y=float(est.y),
        z_top=float(est.z_top_m),
        volume_m3=float(est.volume_m3),
        posture=reading.posture if reading is not None else "unknown",
        reliability=float(est.reliability),
        vx=float(est.vx),
        vy=float(est.vy),
        still=bool(est.still),
        person=person,
    )


def _extend_to_border(
    uv: np.ndarray, valid: np.ndarray, box: tuple[int, int, int, int], cam: Camera
) -> tuple[int, int, int, int]:
    """``box`` (pixels, exclusive ends) of the corners inside ``cam``'s image, grown
    over the corners that project outside it.

    uv: (8, 2) float64 pixel projections of a hold box's corners; valid: (8,) bool,
    inside the image. A corner that projects off the image lies beyond a border, so
    the box reaches past that border (the caller clips it to the image). A corner
    that projects nowhere (behind the camera, beyond ``max_radius``; NaN) gives no
    direction and is left out.
    """
    x0, y0, x1, y1 = box
    off = uv[~valid & np.all(np.isfinite(uv), axis=1)]
    if len(off):
        x0 = min(x0, int(np.floor(off[:, 0].min())))
        y0 = min(y0, int(np.floor(off[:, 1].min())))
        x1 = max(x1, int(np.ceil(off[:, 0].max())) + 1)
        y1 = max(y1, int(np.ceil(off[:, 1].max())) + 1)
    return x0, y0, x1, y1
