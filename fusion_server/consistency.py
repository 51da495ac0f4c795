"""Is each camera still where its calibration says? Its masks against the hull the others carve.

A camera bumped by a cleaner, turned by 2 degrees or shifted by 10 cm, keeps
sending clean masks, but they no longer sit where its calibration projects
the people: the carve loses volume, tracks break and postures go wrong, for
weeks, without any error anywhere. :class:`ConsistencyMonitor` watches for it
inside the fusion pipeline, at a low rate, from the masks the pipeline fuses
anyway.

**One measurement** (:func:`measure_person`): for a person tracked
confidently (confirmed, reliability at least ``min_reliability``), the 10 cm
voxels of the octree in a cylinder around them are voted again *without*
camera ``c`` (leave one out): each other camera tests the voxel's centre
against its mask through the carver's own lookup tables (so the site's
occluders count: a voxel a camera sees only through furniture is not seen by
it), under the carver's own rule (``min_cameras``, ``min_ratio``). What the
others carve is projected into ``c`` (each voxel splatted at its projected
half-size) and slid over ``c``'s mask (:func:`shifted_fit`): the fit at each
shift is the intersection over union of the prediction and the foreground in
its box. The **offset** is the shift that fits best: where ``c`` sees the
person relative to where the others put them, in pixels of ``c``'s full
image; the **agreement** is the fit where the prediction stands over the best
fit (1: nothing fits better). Sliding makes both independent of how loose the
hull is (a visual hull is larger than the body) and of the person's pose.
Only clear views count: the person seen by ``c`` (at least ``MIN_SEEN`` of
the voxels in its image and not behind an occluder), their window and search
range inside the image, the window clear of every other tracked body's box, at least two other cameras
carving them, and foreground in the window (a camera showing nobody where the
others carve someone is dark or covered, not moved). A person standing still
is measured again only once they have moved ``remeasure_m`` or after
``remeasure_s``: the same view repeated would weigh one pose (whose hull can
sit a few pixels off in some camera) as many measurements.

**The background as a whole.** A knocked camera's own background model sees
a changed room: its mask floods with foreground until the model learns the
new view. A camera whose mask is more than ``flood_share`` foreground while
the other cameras' median is under a tenth of that counts, on a measured
frame, as one view that does not fit.

**Cheap.** One frame set every ``every_s`` seconds of capture time, at most
``max_people`` people a time (taken in turn): a few milliseconds a second
whatever the crowd.

**The figure, the baseline and the decision rule.** A view *fits* when its
offset lies within ``offset_share`` of the silhouette's height, plus one mask
pixel, of the camera's own baseline offset (2 degrees of turn move a person 3
m away by some 6 % of their height in the image, a 10 cm shift sideways by 6
% at any distance). The baseline is the camera's own: its first
``baseline_count`` views, once they span at least ``baseline_s`` seconds (its
first minutes of people walking), give the baseline offset (their median: a
camera whose masks carry shadows or lag sees people a little off, and that is
its normal) and the baseline figure (the share of them that fit). The running
figure, ``consistency`` in the status (None until the baseline is taken), is
the share of the last ``window`` views that fit. A camera is *down* when its
figure is under ``drop_ratio`` of its baseline; a ``camera_moved`` alarm is
raised when it has been down for ``alarm_count`` views in a row spanning at
least ``alarm_s`` seconds (a few odd views, a camera dark or flooded for a few
seconds, never do) and no other camera's figure has dropped further against its
own baseline (a moved camera spoils the others' carve a little, and its own
fit most: when several drop together, the one that dropped most is blamed),
with the figure, the baseline and the median offset of the
down views against the baseline offset in its details. It is raised once; the
camera is re-armed when its figure is back to ``recover_ratio`` of its
baseline (put back, or recalibrated and the server restarted, which takes a
new baseline). No threshold is fitted to a scene: the tolerance is a share of
the person's own image size, and each camera is judged against itself.

**The view as the camera itself sees it.** Colour and infrared workers
register their live picture against a reference picture of the room and
send how far the view has moved with their masks (``view_shift_px``,
:mod:`camera_worker.viewcheck`); :meth:`ConsistencyMonitor.report_view` turns
it into degrees through the camera's focal length. This needs no people at
all, so it decides in a crowd, in an empty room, and for a shift along the
camera's axis, which people barely show. A camera whose view has turned by
``view_deg`` or more (0.3 degree: the tolerance a calibration is held to;
an untouched camera reads under 0.1) for ``view_s`` seconds of its reports
raises ``camera_moved`` (details: ``view_deg``), once until its view is back
within half of that. One alarm per move, whichever evidence comes first:
either latch silences the other (the view's alarm latches the people's rule
until the view is back). The camera's own picture outranks the people: a
people's alarm for a camera whose latest view reads under half of
``view_deg`` is not raised (counted in ``vetoed``): the masks disagree for
another reason (lag, a part of a person missed), and the camera has not
moved. The people decide alone for cameras that send no view (thermal,
depth). A camera judged moved, by either evidence, no longer
votes in the carve the others are measured against (it is still measured
itself): its own changed view would otherwise make them look moved in turn.

Pure: no clock (time is the frame sets' capture stamps), no I/O.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from pydantic import Field, model_validator

from common.camera import Camera
from common.settings import NON_NEGATIVE, Settings
from fusion_server.carving import Carver
from fusion_server.carving.distance import FOREGROUND_THRESHOLD, mask_pixels, needed_votes
from fusion_server.carving.lut import RADIUS_UNITS_PER_PX
from fusion_server.tracker import TrackEstimate

__all__ = ["AlarmRule", "CameraMoved", "ConsistencyMonitor", "ConsistencyParams", "Measurement", "measure_person",
           "shifted_fit"]

VOXEL_M = 0.1
"""The octree level nearest this voxel edge is re-voted (a body is some 400 such voxels)."""
BODY_RADIUS_M = 0.45
"""Voxels within this floor distance of a person's position are theirs."""
MIN_SEEN = 0.95
"""A camera is measured on a person only when it sees this share of the others' voxels clearly."""
BLIND_SHARE = 0.1
"""A camera whose window holds less foreground than this share of the predicted silhouette is not
measured: it shows nobody where the others carve someone (dark, covered, a person it has learnt into
its background), which says nothing about where it points."""
OTHER_HALF_M = 0.45
"""Half-width of the floor box of another body whose image box must stay clear of the window."""


_COUNT = dict(ge=1, strict=True)
_SHARE = dict(gt=0.0, le=1.0)   # (0, 1]


class ConsistencyParams(Settings):
    """Settings of :class:`ConsistencyMonitor` (module text), each declared with its range."""

    every_s: float = Field(0.25, **NON_NEGATIVE)
    max_people: int = Field(2, **_COUNT)
    min_reliability: float = Field(0.8, **_SHARE)
    min_voxels: int = Field(40, **_COUNT)
    window: int = Field(15, **_COUNT)
    baseline_count: int = Field(20, **_COUNT)
    baseline_s: float = Field(40.0, **NON_NEGATIVE)
    remeasure_m: float = Field(0.2, **NON_NEGATIVE)
    remeasure_s: float = Field(10.0, **NON_NEGATIVE)
    offset_share: float = Field(0.04, **_SHARE)
    drop_ratio: float = Field(0.6, **_SHARE)
    recover_ratio: float = Field(0.85, **_SHARE)
    alarm_count: int = Field(10, **_COUNT)
    alarm_s: float = Field(10.0, **NON_NEGATIVE)
    flood_share: float = Field(0.5, **_SHARE)
    view_deg: float = Field(0.3, gt=0.0, le=45.0)
    view_s: float = Field(10.0, **NON_NEGATIVE)

    @model_validator(mode="after")
    def _recover_above_drop(self) -> ConsistencyParams:
        if self.recover_ratio < self.drop_ratio:
            raise ValueError(f"recover_ratio ({self.recover_ratio}) must not be under drop_ratio ({self.drop_ratio})")
        return self


@dataclass(frozen=True)
class Measurement:
    """One view of one person by one camera against the others' carve.

    agreement: the fit of the predicted silhouette where it stands over its best fit nearby
    (:func:`shifted_fit`; 0..1, 0 for a flooded mask). offset_px: (dx, dy) the best fit's shift,
    where the camera sees the person relative to where the others put them, pixels of the camera's
    full image (None when the mask was flooded). height_px: the predicted silhouette's height, same
    pixels. pixel_px: one mask pixel, same pixels (the offset's resolution).
    """

    cam: str
    stamp_ns: int
    agreement: float
    offset_px: tuple[float, float] | None = None
    height_px: float = 0.0
    pixel_px: float = 1.0


@dataclass(frozen=True)
class CameraMoved:
    """A camera judged moved at ``stamp_ns``. From the people (``evidence`` 'people'): its running
    ``figure`` against its ``baseline``, the median ``offset_px`` (dx, dy, full-image pixels; None
    when unknown) of its down measurements, and how many measurements and seconds it has been down.
    From its own picture (``evidence`` 'view'): ``view_deg``, how far its view has turned, held for
    ``down_s`` seconds."""

    cam: str
    stamp_ns: int
    figure: float | None
    baseline: float | None
    offset_px: tuple[float, float] | None
    down_measurements: int
    down_s: float
    view_deg: float | None = None

    @property
    def evidence(self) -> str:
        return "view" if self.view_deg is not None else "people"

    def describe(self) -> str:
        """One line for the log."""
        if self.view_deg is not None:
            return (f"its view has moved by {self.view_deg:.2f} degrees for {self.down_s:.0f} s against its "
                    f"reference picture: moved or bumped?")
        return (f"its masks no longer agree with the other cameras' carve ({self.figure:.2f} against its "
                f"baseline {self.baseline:.2f}): moved or bumped?")

    def details(self) -> dict:
        """The event's details (the camera id is added by the event itself)."""
        if self.view_deg is not None:
            return {"evidence": "view", "view_deg": round(self.view_deg, 2), "down_s": round(self.down_s, 1)}
        out = {"evidence": "people", "consistency": round(self.figure, 3), "baseline": round(self.baseline, 3),
               "down_measurements": self.down_measurements, "down_s": round(self.down_s, 1)}
        if self.offset_px is not None:
            out["offset_dx_px"] = round(self.offset_px[0], 1)
            out["offset_dy_px"] = round(self.offset_px[1], 1)
            out["offset_norm_px"] = round(float(np.hypot(*self.offset_px)), 1)
        return out


@dataclass
class _ViewRecord:
    deg: float | None = None  # the latest reported turn
    stamp_ns: int = 0
    above_since_ns: int | None = None
    alarmed: bool = False
    latched_rule: bool = False  # this view's alarm latched the people's rule


@dataclass
class _CameraRecord:
    recent: deque  # whether each of the last ``window`` measurements fit
    down: deque  # the last ``window`` measurements of the current down streak
    baseline_values: list = field(default_factory=list)
    baseline_start_ns: int | None = None
    baseline: float | None = None
    baseline_offset: tuple[float, float] = (0.0, 0.0)
    down_count: int = 0
    down_since_ns: int | None = None
    alarmed: bool = False


class ConsistencyMonitor:
    """Per camera, how well its masks agree with the people the other cameras carve, and the
    ``camera_moved`` decision (module text).

    carver: the pipeline's carver (its lookup tables, grid and vote). cameras: camera id ->
    full-resolution camera (offsets are given in its pixels). params: :class:`ConsistencyParams`.
    """

    def __init__(self, carver: Carver, cameras: Mapping[str, Camera],
                 params: ConsistencyParams = ConsistencyParams()) -> None:
        self.carver = carver
        self.params = params
        self.cameras = dict(cameras)
        self.full_width = {c: int(cam.width) for c, cam in cameras.items()}
        self._sized_cache: dict[tuple[str, int, int], Camera] = {}
        sizes = carver.voxel_sizes_m
        self.level = min(range(len(sizes)), key=lambda L: abs(sizes[L] - VOXEL_M))
        self.voxel_m = float(sizes[self.level])
        self.rule = AlarmRule(carver.camera_ids, params)
        self._views = {c: _ViewRecord() for c in cameras}
        self._vetoed: set[str] = set()   # people's alarms the camera's own view contradicted
        self.vetoed = 0
        """People's alarms not raised because the camera's own view said it had not moved."""
        self._next_ns: int | None = None
        self._last_seen: dict[int, tuple[float, float, int]] = {}  # body id -> where and when last measured
        self.history: list[Measurement] | None = None
        """Set to a list to keep every measurement (offline checks); None keeps none."""
        self._turn = 0

    # ------------------------------------------------------------------ public

    def figure(self, cam: str) -> float | None:
        """The camera's running figure (median of its recent measurements), None until measured."""
        return self.rule.figure(cam)

    def baseline(self, cam: str) -> float | None:
        """The camera's own baseline figure, None until its first minutes are measured."""
        return self.rule.baseline(cam)

    def moved_cameras(self) -> set[str]:
        """The cameras judged moved and not yet re-armed, by either evidence."""
        return {c for c, rec in self._views.items() if rec.alarmed} | (self.rule.alarmed() - self._vetoed)

    def view_deg(self, cam: str) -> float | None:
        """How far the camera's view has turned by its own latest report (degrees), None before one."""
        rec = self._views.get(cam)
        return None if rec is None else rec.deg

    def report_view(self, cam: str, shift_px: float, stamp_ns: int, src_width: int) -> None:
        """Camera ``cam``'s worker measured its view moved by ``shift_px`` pixels of its ``src_width``
        wide capture on its frame stamped ``stamp_ns`` (module text); decided on in :meth:`step`."""
        rec = self._views.get(cam)
        if rec is None or not (math.isfinite(shift_px) and src_width > 0):
            return
        cam_obj = self.cameras[cam]
        focal_px = float(cam_obj.K[0, 0]) * src_width / cam_obj.width
        rec.deg, rec.stamp_ns = math.degrees(float(shift_px) / focal_px), max(rec.stamp_ns, int(stamp_ns))

    def step(self, masks: Mapping[str, np.ndarray], bodies: Sequence[TrackEstimate],
             stamp_ns: int) -> tuple[list[Measurement], list[CameraMoved]]:
        """Decide on the views reported, and measure on this frame set if one is due; returns the
        measurements taken and the alarms raised. masks: camera id -> (H, W) uint8 masks of the frame
        set (absent cameras are not measured). bodies: the tracker's estimates this frame."""
        stamp_ns = int(stamp_ns)
        alarms = self._view_alarms()
        if self._next_ns is not None and stamp_ns < self._next_ns:
            return [], alarms
        self._next_ns = stamp_ns + int(self.params.every_s * 1e9)
        masks = {c: m for c, m in masks.items() if c in self.full_width}
        measurements = self.measure(masks, bodies, stamp_ns)
        if self.history is not None:
            self.history.extend(measurements)
        self._vetoed &= self.rule.alarmed()   # re-armed: a later alarm is judged afresh
        for m in measurements:
            alarm = self.rule.add(m)
            if alarm is None:
                continue
            view = self._views[m.cam]
            if view.deg is not None and view.deg < 0.5 * self.params.view_deg:
                self._vetoed.add(m.cam)   # its own picture says it has not moved: the people misled
                self.vetoed += 1
                continue
            if not view.alarmed:   # the view has not said so already
                alarms.append(alarm)
            view.alarmed = True
        return measurements, alarms

    def _view_alarms(self) -> list[CameraMoved]:
        """The cameras whose own view has stayed turned by ``view_deg`` for ``view_s`` (module text)."""
        p = self.params
        out = []
        for cam, rec in self._views.items():
            if rec.deg is None:
                continue
            if rec.deg < p.view_deg:
                rec.above_since_ns = None
                if rec.deg < 0.5 * p.view_deg and rec.alarmed:   # back where it was: re-armed
                    rec.alarmed = False
                    if rec.latched_rule:
                        self.rule.unlatch(cam)
                        rec.latched_rule = False
                continue
            if rec.above_since_ns is None:
                rec.above_since_ns = rec.stamp_ns
            held_s = (rec.stamp_ns - rec.above_since_ns) / 1e9
            if rec.alarmed or held_s < p.view_s:
                continue
            rec.alarmed = True
            said = self.rule.latch(cam) and cam not in self._vetoed
            rec.latched_rule = not said
            self._vetoed.discard(cam)
            if said:   # the people said so already
                continue
            out.append(CameraMoved(cam=cam, stamp_ns=rec.stamp_ns, figure=self.rule.figure(cam),
                                   baseline=self.rule.baseline(cam), offset_px=None, down_measurements=0,
                                   down_s=held_s, view_deg=rec.deg))
        return out

    def measure(self, masks: Mapping[str, np.ndarray], bodies: Sequence[TrackEstimate],
                stamp_ns: int) -> list[Measurement]:
        """The measurements of one frame set (no decision): flooded cameras, then the people due."""
        if len(masks) < 3:
            return []
        out = []
        shares = {c: cv2.countNonZero((np.asarray(m) > FOREGROUND_THRESHOLD).view(np.uint8)) / m.size
                  for c, m in masks.items()}
        flooded = set()
        for c, share in shares.items():
            others = statistics.median(v for k, v in shares.items() if k != c)
            if share > self.params.flood_share and others < 0.1 * self.params.flood_share:
                flooded.add(c)
                out.append(Measurement(cam=c, stamp_ns=stamp_ns, agreement=0.0))
        live = {b.id for b in bodies}
        self._last_seen = {k: v for k, v in self._last_seen.items() if k in live}
        confident = [b for b in bodies if b.confirmed and b.reliability >= self.params.min_reliability
                     and self._due(b, stamp_ns)]
        if not confident:
            return out
        k = min(self.params.max_people, len(confident))
        start = self._turn % len(confident)
        self._turn += k
        chosen = [confident[(start + i) % len(confident)] for i in range(k)]
        for body in chosen:
            self._last_seen[body.id] = (body.x, body.y, stamp_ns)
            others = [b for b in bodies if b is not body]
            for m in measure_person(self.carver, self.level, masks, self._sized(masks), body, others, stamp_ns,
                                    min_voxels=self.params.min_voxels, full_width=self.full_width,
                                    distrusted=self.moved_cameras()):
                if m.cam not in flooded:
                    out.append(m)
        return out

    def _due(self, body: TrackEstimate, stamp_ns: int) -> bool:
        """A body is measured again once it has moved ``remeasure_m`` or ``remeasure_s`` have passed:
        the same view of someone standing still says nothing new, and would weigh their pose (whose
        hull may sit a few pixels off in some camera) as many measurements."""
        last = self._last_seen.get(body.id)
        if last is None:
            return True
        x, y, then = last
        return (math.hypot(body.x - x, body.y - y) >= self.params.remeasure_m
                or stamp_ns - then >= self.params.remeasure_s * 1e9)

    def _sized(self, masks: Mapping[str, np.ndarray]) -> dict[str, Camera]:
        """Camera id -> the camera resized to its mask (built once per size)."""
        out = {}
        for c, m in masks.items():
            h, w = np.shape(m)
            key = (c, w, h)
            if key not in self._sized_cache:
                cam = self.cameras[c]
                self._sized_cache[key] = cam if (cam.width, cam.height) == (w, h) else cam.resized(w, h)
            out[c] = self._sized_cache[key]
        return out

class AlarmRule:
    """The decision of the module text over measurements: per camera its running figure, its own
    baseline, and when it is judged moved. ``camera_ids``: the cameras; ``params``: the settings."""

    def __init__(self, camera_ids: Sequence[str], params: ConsistencyParams = ConsistencyParams()) -> None:
        self.params = params
        self._records = {c: _CameraRecord(recent=deque(maxlen=params.window), down=deque(maxlen=params.window))
                         for c in camera_ids}

    def figure(self, cam: str) -> float | None:
        """The camera's running figure: the share of its recent views that fit (0..1), None until
        its baseline is taken."""
        rec = self._records.get(cam)
        if rec is None or rec.baseline is None or len(rec.recent) < max(1, self.params.window // 2):
            return None
        return sum(rec.recent) / len(rec.recent)

    def baseline(self, cam: str) -> float | None:
        """The camera's own baseline figure, None until its first minutes are measured."""
        rec = self._records.get(cam)
        return None if rec is None else rec.baseline

    def alarmed(self) -> set[str]:
        """The cameras judged moved and not yet re-armed."""
        return {c for c, rec in self._records.items() if rec.alarmed}

    def latch(self, cam: str) -> bool:
        """Mark the camera judged moved (by other evidence); returns whether it already was."""
        rec = self._records.get(cam)
        if rec is None:
            return False
        was, rec.alarmed = rec.alarmed, True
        return was

    def unlatch(self, cam: str) -> None:
        """Re-arm the camera (the other evidence that latched it is clear)."""
        rec = self._records.get(cam)
        if rec is not None:
            rec.alarmed = False

    def _ratios(self) -> dict[str, float]:
        """Camera id -> its figure over its baseline, for the cameras with both (and a baseline above 0)."""
        out = {}
        for cam, rec in self._records.items():
            figure = self.figure(cam)
            if figure is not None and rec.baseline:
                out[cam] = figure / rec.baseline
        return out

    def fits(self, m: Measurement, reference_px: tuple[float, float]) -> bool:
        """Whether the camera sees the person where the others put them: its offset within
        ``offset_share`` of the silhouette's height (plus one mask pixel) of ``reference_px``."""
        if m.offset_px is None:
            return False
        off = float(np.hypot(m.offset_px[0] - reference_px[0], m.offset_px[1] - reference_px[1]))
        return off <= self.params.offset_share * m.height_px + m.pixel_px

    def add(self, m: Measurement) -> CameraMoved | None:
        """Take one measurement; the alarm it raises, if any (module text)."""
        p = self.params
        rec = self._records[m.cam]
        if rec.baseline is None:
            if rec.baseline_start_ns is None:
                rec.baseline_start_ns = m.stamp_ns
            rec.baseline_values.append(m)
            if len(rec.baseline_values) >= p.baseline_count and \
                    m.stamp_ns - rec.baseline_start_ns >= p.baseline_s * 1e9:
                rec.baseline_offset = _median_offset(rec.baseline_values) or (0.0, 0.0)
                fits = [self.fits(b, rec.baseline_offset) for b in rec.baseline_values]
                rec.baseline = sum(fits) / len(fits)
                rec.recent.extend(fits)
                rec.baseline_values = []
            return None
        rec.recent.append(self.fits(m, rec.baseline_offset))
        figure = self.figure(m.cam)
        if figure >= p.recover_ratio * rec.baseline:
            rec.alarmed = False
        if figure >= p.drop_ratio * rec.baseline:
            rec.down_count, rec.down_since_ns = 0, None  # a streak must be unbroken
            rec.down.clear()
            return None
        rec.down.append(m)
        rec.down_count += 1
        if rec.down_since_ns is None:
            rec.down_since_ns = m.stamp_ns
        down_s = (m.stamp_ns - rec.down_since_ns) / 1e9
        if rec.alarmed or rec.down_count < p.alarm_count or down_s < p.alarm_s:
            return None
        if figure / rec.baseline > min(self._ratios().values()):
            return None  # another camera dropped further: it is the one moved, and spoils this one's carve
        rec.alarmed = True
        offset = _median_offset(rec.down)
        if offset is not None:
            offset = (offset[0] - rec.baseline_offset[0], offset[1] - rec.baseline_offset[1])
        return CameraMoved(cam=m.cam, stamp_ns=m.stamp_ns, figure=figure, baseline=rec.baseline, offset_px=offset,
                           down_measurements=rec.down_count, down_s=down_s)


def measure_person(carver: Carver, level: int, masks: Mapping[str, np.ndarray], cameras: Mapping[str, Camera],
                   body: TrackEstimate, others: Sequence[TrackEstimate], stamp_ns: int, *, min_voxels: int = 40,
                   full_width: Mapping[str, int] | None = None, distrusted: Collection[str] = ()) -> list[Measurement]:
    """Per camera in ``masks`` with a clear view of ``body``, its agreement with the voxels the other
    cameras carve around it (module text). ``level``: the octree level re-voted; ``cameras``: camera
    id -> camera at its mask's size; ``others``: every other body, whose image boxes must stay clear
    of the measured window; ``full_width``: camera id -> full image width, to give offsets in
    full-image pixels (default: mask pixels); ``distrusted``: cameras already judged moved, measured
    but left out of the others' carve (a moved camera would make the others look moved)."""
    present = [c for c in carver.camera_ids if c in masks]
    voters = [c for c in present if c not in distrusted]
    if len(present) < 3 or len(voters) < 2:
        return []
    linear, centres = _cylinder(carver, level, body)
    if linear.size == 0:
        return []
    pixel, radius = carver.tables(level, linear)
    fg, px, seen, hit = {}, {}, {}, {}
    for c in present:
        col = carver.camera_ids.index(c)
        m = np.asarray(masks[c])
        h, w = m.shape
        fg[c] = m > FOREGROUND_THRESHOLD
        px[c] = mask_pixels(pixel[:, col], carver.lut_sizes[c], (w, h))
        seen[c] = px[c] >= 0
        hit[c] = seen[c] & fg[c].ravel()[np.maximum(px[c], 0)]
    found = np.sum([hit[c] for c in voters], axis=0)
    seeing = np.sum([seen[c] for c in voters], axis=0)
    out = []
    for c in present:
        voting = c in voters
        n_others = len(voters) - voting
        if n_others < 2:
            continue
        need = needed_votes(n_others, min(carver.min_cameras, n_others), carver.min_ratio)
        found_o = found - hit[c] if voting else found
        seeing_o = seeing - seen[c] if voting else seeing
        loo = (seeing_o >= 2) & (found_o >= need[seeing_o])
        if np.count_nonzero(loo) < min_voxels or np.count_nonzero(seen[c][loo]) < MIN_SEEN * np.count_nonzero(loo):
            continue
        loo &= seen[c]  # a few voxels behind furniture or off the image are left out of the prediction
        col = carver.camera_ids.index(c)
        h, w = fg[c].shape
        lut_w, lut_h = carver.lut_sizes[c]
        scale = max(w / lut_w, h / lut_h)
        r = max(1, int(round(0.6 * float(np.median(radius[loo, col])) * scale / RADIUS_UNITS_PER_PX)))
        v, u = np.divmod(px[c][loo], w)
        bx0, bx1, by0, by1 = int(u.min()) - r, int(u.max()) + r + 1, int(v.min()) - r, int(v.max()) + r + 1
        sx, sy = max(3, (bx1 - bx0) // 2), max(3, (by1 - by0) // 4)
        x0, x1, y0, y1 = bx0 - sx, bx1 + sx, by0 - sy, by1 + sy
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            continue  # the person (or a moved view of them) may run off the image
        if any(_overlaps(_image_box(cameras[c], o), (x0, y0, x1, y1)) for o in others):
            continue
        pred = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
        pred[v - y0, u - x0] = 1
        pred = cv2.dilate(pred, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        n_pred = int(np.count_nonzero(pred))
        if np.count_nonzero(fg[c][y0:y1, x0:x1]) < BLIND_SHARE * n_pred:
            continue  # the camera shows nobody there at all: dark or covered, not moved
        agreement, (dx, dy) = shifted_fit(fg[c], pred, (x0, y0), (sx, sy))
        k = (full_width or {}).get(c, w) / w
        out.append(Measurement(cam=c, stamp_ns=int(stamp_ns), agreement=agreement, offset_px=(k * dx, k * dy),
                               height_px=k * float(by1 - by0), pixel_px=k))
    return out


def shifted_fit(fg: np.ndarray, pred: np.ndarray, corner: tuple[int, int],
                search: tuple[int, int]) -> tuple[float, tuple[int, int]]:
    """How well a predicted silhouette fits a mask where it is, against how well it fits anywhere near.

    fg: (H, W) bool mask. pred: (h, w) uint8 0/1 predicted silhouette whose top-left pixel lies at
    ``corner`` (x, y) of the mask. search: (sx, sy) largest shifts tried, pixels. For each shift the
    fit is the intersection over union of the shifted prediction and the mask's foreground in the
    prediction's shifted box. Returns the fit without shift over the best fit (1: nothing fits better;
    0 when nothing fits at all) and the best shift (dx, dy), mask pixels: where the camera sees the
    person relative to where the others put them.
    """
    (x0, y0), (sx, sy) = corner, search
    h, w = pred.shape
    region = np.zeros((h + 2 * sy, w + 2 * sx), dtype=np.float32)
    H, W = fg.shape
    ax0, ay0, ax1, ay1 = max(0, x0 - sx), max(0, y0 - sy), min(W, x0 + w + sx), min(H, y0 + h + sy)
    region[ay0 - (y0 - sy):ay1 - (y0 - sy), ax0 - (x0 - sx):ax1 - (x0 - sx)] = fg[ay0:ay1, ax0:ax1]
    template = pred.astype(np.float32)
    both = cv2.matchTemplate(region, template, cv2.TM_CCORR)
    seen = cv2.matchTemplate(region, np.ones_like(template), cv2.TM_CCORR)
    iou = both / np.maximum(float(template.sum()) + seen - both, 1.0)
    best = float(iou.max())
    if best <= 0.0:
        return 0.0, (0, 0)
    j, i = np.unravel_index(int(np.argmax(iou)), iou.shape)
    return float(iou[sy, sx]) / best, (int(i) - sx, int(j) - sy)


# ---------------------------------------------------------------------- helpers


def _median_offset(measurements) -> tuple[float, float] | None:
    """The per-axis median of the measurements' offsets (None when none has one)."""
    offsets = [m.offset_px for m in measurements if m.offset_px is not None]
    if not offsets:
        return None
    return float(np.median([o[0] for o in offsets])), float(np.median([o[1] for o in offsets]))


def _cylinder(carver: Carver, level: int, body: TrackEstimate) -> tuple[np.ndarray, np.ndarray]:
    """(M,) int64 linear indices on ``level`` of the voxels whose centres lie within BODY_RADIUS_M on
    the floor of the body's position, from the floor to 0.15 m over its top; and their (M, 3) centres."""
    grid = carver.grid
    size = carver.voxel_sizes_m[level]
    nx, ny, nz = carver.layout.dims[level]
    o = grid.origin_m
    lo = np.floor((np.array([body.x, body.y]) - BODY_RADIUS_M - o[:2]) / size).astype(int)
    hi = np.floor((np.array([body.x, body.y]) + BODY_RADIUS_M - o[:2]) / size).astype(int)
    i = np.arange(max(lo[0], 0), min(hi[0], nx - 1) + 1)
    j = np.arange(max(lo[1], 0), min(hi[1], ny - 1) + 1)
    k = np.arange(0, min(int(np.floor((body.z_top_m + 0.15 - o[2]) / size)), nz - 1) + 1)
    if not (i.size and j.size and k.size):
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    ii, jj, kk = np.meshgrid(i, j, k, indexing="ij")
    ijk = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1)
    centres = o + (ijk + 0.5) * size
    near = np.hypot(centres[:, 0] - body.x, centres[:, 1] - body.y) <= BODY_RADIUS_M
    ijk, centres = ijk[near], centres[near]
    return (ijk[:, 0].astype(np.int64) * ny + ijk[:, 1]) * nz + ijk[:, 2], centres


def _image_box(cam: Camera, body: TrackEstimate) -> tuple[int, int, int, int] | None:
    """The box (x0, y0, x1, y1) in ``cam``'s image of a body's floor square (OTHER_HALF_M) from the
    floor to its top, or None when it projects nowhere."""
    top = max(float(body.z_top_m), 0.5) + 0.1
    pts = np.array([(body.x + sx * OTHER_HALF_M, body.y + sy * OTHER_HALF_M, z)
                    for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, top)])
    uv, _ = cam.project(pts)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if not len(uv):
        return None
    return int(uv[:, 0].min()), int(uv[:, 1].min()), int(uv[:, 0].max()) + 1, int(uv[:, 1].max()) + 1


def _overlaps(a: tuple[int, int, int, int] | None, b: tuple[int, int, int, int]) -> bool:
    return a is not None and a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]
