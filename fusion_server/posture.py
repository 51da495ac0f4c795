"""Body posture from a tracked person's voxel height profile.

A person's blob is summarised by its height profile: the number of
foreground voxels in each horizontal layer (layer ``k`` covers
``[k * voxel_m, (k + 1) * voxel_m)`` above the floor). Posture is read from
the *shape* of that profile, never from the top height alone: a seated
person wearing a tall hat or a horse mask reaches 1.6-1.8 m but still has
their mass centre low and their widest layers at the lap, and someone
bending over to pick something up has a wide torso layer at hip height
above two thin legs.

Pipeline per track (:class:`PostureEstimator`):

1. :func:`profile_features` turns one profile into :class:`PostureFeatures`:
   top, bottom (where the body really ends, across small carving gaps),
   mass centre, the fractions of voxels below 0.5 m and in 0.5-1.0 m, the
   horizontal extent (for vertical vs horizontal: lying is wide and low),
   the height of the widest layers, and how wide the body is at the floor.
2. The features are smoothed by a short FIR filter (the seed paper's FIR on
   the posture measurement), :func:`fir_smooth`.
3. :func:`feature_matrix` divides heights by each candidate standing
   height (and scales the low and middle bands to it), and
   :func:`posture_log_likelihoods` scores each internal state (:data:`STATES`: the postures plus shapes
   such as kneeling or a seated person whose lower legs the carving lost)
   with a robust diagonal Gaussian model (:class:`PostureModel`).
4. An HMM forward filter over the states (the online form of the seed's
   Viterbi recursion over standing/fallen states), each frame's
   likelihoods summed under a belief over the person's standing height
   that is learnt beside it, summed per reported posture, and a minimum
   duration for any change keep the reported posture from flickering.
   Or, with ``decisions="viterbi"``, the seed's Viterbi recursion itself
   (:mod:`fusion_server.viterbi`): the same per-frame likelihoods, plus an
   ``outside`` state for frames without a body, decoded by a fixed-lag
   decoder under the transition rates of :data:`VITERBI_RATES_HZ`; the
   reported posture is the best path's state ``viterbi_lag_s`` back, final
   once reported (:func:`viterbi_log_transitions`).

Postures: ``standing``, ``sitting``, ``bending`` and ``lying``. Kneeling
reads ``bending`` (the project's ground truth labels it so; the seed paper:
a person who kneels or bows may read sitting but never fallen); squatting
reads ``sitting`` or ``bending``. Whether a lying person has *fallen* is
decided by :mod:`fusion_server.events` from how fast they got there.

Pure math: time comes in as ``stamp_ns``; no I/O, no clock.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Iterable, Literal, Mapping, Protocol, Sequence

import numpy as np
import scipy.linalg
from pydantic import Field, model_validator

from common.postures import BODY_POSTURES
from common.settings import Settings, declared
from common.site import EventSettings
from fusion_server.detection import body_top_layers
from fusion_server.hotspots import Hotspot
from fusion_server.viterbi import FixedLagViterbi

POSTURES: tuple[str, ...] = BODY_POSTURES
"""Reported posture labels (every posture but ``unknown``), in the order of :attr:`PostureReading.probabilities`."""

STATES: tuple[str, ...] = (
    "standing",
    "sitting",
    "bending",
    "lying",
    "kneeling",
    "sitting_raised",
    "lying_raised",
    "standing_raised",
    "standing_spread",
)
"""Internal states of the posture model (rows of :class:`PostureModel`).

Some postures come in shapes too different for one Gaussian: kneeling
(reported as ``bending``: lowered to do something near the floor);
``sitting_raised``, a seated person whose lower legs the carving lost below
the seat (chair or sofa fronts and table tops hide them from some cameras),
so that the body floats at seat height; ``lying_raised``, lying on a bed or
sofa; ``standing_raised``, a standing person whose legs furniture hides;
``standing_spread``, a standing person whose hull spreads at the floor (the
feet's shadows carved with them, a stride seen by level cameras, a
neighbour's feet): full height, but the mass centre and the widest layers
low and the floor layer nearly the widest (or the widest of all: a standing
person beside furniture that hides their feet from some cameras carves as a
cone widening to the floor), the shape the model otherwise knows only as
kneeling. A lying state rarely enters it (:data:`_NOT_FROM_LYING`)."""

STATE_POSTURE: tuple[int, ...] = tuple(
    POSTURES.index(p)
    for p in ("standing", "sitting", "bending", "lying", "bending", "sitting", "lying", "standing", "standing")
)
"""Index into :data:`POSTURES` of each state in :data:`STATES`."""

_UPRIGHT = np.array([POSTURES[p] == "standing" for p in STATE_POSTURE])
"""(len(STATES),) bool: the states of someone standing (how a walking person's body is)."""

_NOT_FROM_LYING = np.array([s == "standing_spread" for s in STATES])
"""(len(STATES),) bool: states a lying body rarely enters. A body lying on the floor with someone
standing over it (a helper, a neighbour merged into its blob) has that shape too: a person who was
lying gets up through other shapes (sitting, kneeling, plain standing) first. From the others it is
entered as any change is: a person kneeling or bending stands up, and a standing body read kneeling
for a moment must not stay there while its shape says standing spread."""

_LYING = np.array([POSTURES[p] == "lying" for p in STATE_POSTURE])
"""(len(STATES),) bool: the lying states, on the floor or raised."""

_ENTER_RARELY = 1e-3
"""How much rarer than any other change entering :data:`_NOT_FROM_LYING` from a lying state is."""

_RARE_CHANGES = np.outer(_LYING, _NOT_FROM_LYING)
"""(len(STATES), len(STATES)) bool, ``[from, to]``: the changes :data:`_ENTER_RARELY` makes rare."""

_TELLS_HEIGHT = np.array([POSTURES[p] in ("standing", "sitting") for p in STATE_POSTURE]) & ~_NOT_FROM_LYING
"""(len(STATES),) bool: the standing and seated states, whose shapes tell a standing height; not
a standing body spread at the floor, which a seated one read against a smaller height mimics."""

WALK_TELLS_HEIGHT_NS = 1_000_000_000
"""After this long at walking speed (ns), a body's top tells its standing height fully."""

_ON_SEAT = np.array([s in ("sitting", "sitting_raised") for s in STATES])
"""(len(STATES),) bool: the states of a seated body (on a chair, a sofa, a bed's edge)."""

_ON_BED = np.array([s == "lying_raised" for s in STATES])
"""(len(STATES),) bool: the state of a body lying above the floor (on a bed or a sofa)."""

_ON_FLOOR = np.array([s == "lying" for s in STATES])
"""(len(STATES),) bool: the state of a body lying on the floor (see ``lying_min_span``)."""

_BENT = np.array([s in ("bending", "kneeling") for s in STATES])
"""(len(STATES),) bool: the states of a body bent over or kneeling (see ``seated_bend_log_odds``)."""

BACK_BAND_M = (0.5, 0.8)
"""A solid spanning these heights is a back: a seated body's hips and trunk (a seat is 0.4-0.5 m
high) would have to pass through it. A sofa's or a chair's back and a wall are; a chair's seat
(under 0.5 m) and a table top (a slab above the knees) are not."""
BACK_TOUCH_M = 0.02
"""A point this close to a back's polygon is on it."""


def backs_of(occluders: Iterable) -> list[Hotspot]:
    """The backs (:data:`BACK_BAND_M`) among ``occluders`` (``name``, ``polygon_m``, ``z_min_m``,
    ``z_max_m``, as the carver keeps them), as floor polygons for :class:`PostureBank`."""
    lo, hi = BACK_BAND_M
    return [Hotspot(name=o.name, polygon_m=np.asarray(o.polygon_m), kind="back")
            for o in occluders if o.z_min_m <= lo and o.z_max_m >= hi]


def own_spans(tracks: Sequence[object]) -> list[float | None]:
    """Per track, the diagonal of the floor box of the blob it matched this frame (``blob.bbox_m``),
    metres; None for a track without a blob of its own (none matched, or one that another track
    matched too: a blob two people share tells neither's span)."""
    blobs = [getattr(t, "blob", None) for t in tracks]
    shared = Counter(id(b) for b in blobs if b is not None)
    out: list[float | None] = []
    for b in blobs:
        if b is None or shared[id(b)] > 1:
            out.append(None)
        else:
            lo, hi = np.asarray(b.bbox_m, dtype=np.float64)[:, :2]
            out.append(float(np.hypot(*(hi - lo))))
    return out


def company_of(tracks: Sequence[object]) -> np.ndarray:
    """(len(tracks),) float: per track, the floor distance to the nearest other track the tracker
    confirms (``confirmed``, true where missing), metres; infinite when there is none. A track
    without a position (``x``, ``y``) has no company and keeps no one company."""
    xy = np.array([[getattr(t, "x", np.nan), getattr(t, "y", np.nan)] for t in tracks], dtype=np.float64).reshape(-1, 2)
    sure = np.array([bool(getattr(t, "confirmed", True)) for t in tracks], dtype=bool)
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    d[np.isnan(d) | ~sure[None, :]] = np.inf
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1, initial=np.inf)


DECISIONS: tuple[str, ...] = ("frame", "viterbi")
"""How :class:`PostureEstimator` decides the reported posture: ``frame``, the
forward filter's most probable posture held for a minimum duration, decided
on each frame as it comes; ``viterbi``, the best state path of a fixed-lag
Viterbi decoder, decided a bounded delay later and never taken back."""

DECODED_STATES: tuple[str, ...] = STATES + ("outside",)
"""States of the Viterbi decoder: :data:`STATES` and ``outside`` (no body seen:
the track's person is not, or no longer, in view)."""

OUTSIDE = len(STATES)
"""Index of ``outside`` in :data:`DECODED_STATES`."""

VITERBI_RATES_HZ: dict[tuple[str, str], float] = {
    ("standing", "sitting"): 0.1,
    ("standing", "bending"): 0.1,
    ("standing", "lying"): 0.05,
    ("standing", "outside"): 0.1,
    ("sitting", "standing"): 0.1,
    ("sitting", "bending"): 0.05,
    ("sitting", "lying"): 0.05,
    ("sitting", "outside"): 0.02,
    ("bending", "standing"): 0.5,
    ("bending", "sitting"): 0.2,
    ("bending", "lying"): 0.1,
    ("bending", "outside"): 0.02,
    ("lying", "standing"): 0.02,
    ("lying", "sitting"): 0.05,
    ("lying", "bending"): 0.05,
    ("lying", "outside"): 0.02,
    ("outside", "standing"): 0.5,
    ("outside", "sitting"): 0.02,
    ("outside", "bending"): 0.02,
    ("outside", "lying"): 0.02,
}
"""Rates of posture changes for the Viterbi decoder, per second, ``(from, to)``.

They follow the spells people keep: standing and sitting last tens of
seconds to hours (about 0.3 changes a second out of standing, well under
that out of sitting); bending and kneeling are brief (2 s or so), so most
often back to standing; lying on the floor or a bed lasts long, and one gets
up from it mostly through sitting or kneeling; someone who appears comes in
walking (standing) far more often than in any other posture, and someone
who vanishes from view mostly walked out. Falls and lying down are rare but
must never be priced out: at 15 fps a change of 0.05/s costs
``-log(0.05 / 15) = 5.7`` nats, which a body on the floor repays in one or
two frames. Changes between the shapes of one posture (sitting and sitting
with the legs not carved, standing with and without hidden legs, kneeling
and bending, lying on the floor or raised) cost :data:`VITERBI_SHAPE_RATE_HZ`:
they follow what the cameras see, not what the person does."""

VITERBI_SHAPE_RATE_HZ = 1.0
"""Rate of changes between the shapes (states) of one posture, per second."""

VITERBI_AGES = 6
"""Age steps of a posture before it may change (see
:func:`viterbi_aged_log_transitions`): at 15 fps and the default minimum
duration of 0.4 s, one a frame."""

FEATURE_NAMES: tuple[str, ...] = (
    "centre_rel",
    "top_rel",
    "frac_low",
    "frac_mid",
    "log_flatness",
    "widest_rel",
    "floor_frac",
    "bottom_rel",
)
"""Entries of :func:`feature_vector`, in order."""

REFERENCE_HEIGHT_M = 1.70
"""Standing height the low and middle bands are given for: below
:data:`LOW_BAND_M` and below :data:`MID_BAND_M` for a person this tall,
scaled in proportion for anyone else."""
LOW_BAND_M = 0.5
MID_BAND_M = 1.0


class ProfiledTrack(Protocol):
    """What posture needs of a track estimate (any object with these attributes). Optional too:
    ``x``, ``y`` (the seats and beds it is at), ``vx``, ``vy`` (walking), ``confirmed`` (company)
    and ``blob``, the blob matched this frame (None when none): a blob of its own tells the body's
    span (:func:`own_spans`)."""

    id: int
    z_top_m: float
    height_profile: np.ndarray


@dataclass(frozen=True)
class PostureFeatures:
    """Shape of one body's height profile. Heights in metres above the floor.

    top_m: top face of the highest occupied layer.
    bottom_m: bottom face of the body: the lowest layer reached going down
        from the mass centre through occupied layers, across gaps of at most
        ``max_gap_m`` (the floor for anyone standing, even on thinly carved
        legs; the seat for a seated person whose lower legs were not carved;
        the mattress for someone lying on a bed). Floor noise separated from
        the body by a larger gap does not count.
    centre_m: height of the voxel mass centre.
    frac_low: fraction of the voxels below 0.5 m.
    frac_mid: fraction of the voxels in [0.5, 1.0) m.
    horizontal_m: horizontal extent, ``sqrt`` of the largest layer area
        (3-layer running mean), metres.
    widest_m: height of the body's widest part: area-weighted mean height of
        the layers whose (3-layer running mean) area is within ``wide_frac``
        of the largest. A seated person's lap puts it near seat height, a
        standing or bending person's torso near hip height or above.
    floor_frac: largest layer area below ``floor_band_m`` over the largest
        (running-mean) layer area: about 1 for shins lying on the floor
        (kneeling) and for lying, 0.2-0.6 for feet and upright shins, 0 for a
        body that does not reach the floor.
    volume_m3: total voxel volume.
    body_top_m: top face of the body's highest layer that is at least a
        quarter as wide as its widest (:data:`~fusion_server.detection.BODY_WIDTH_FRAC`):
        the top less the thin tent of hull that the cameras' cones leave over
        a body lying on the floor. What falls read as the body's height.
    body_centre_m: mass centre of the voxels below ``body_top_m`` (what
        falls read as the body's centre).
    cumulative: (nz + 1,) float64, fraction of the voxels below each layer
        edge ``k * voxel_m``; the model reads its low and middle bands from
        it at heights scaled to the person (:func:`feature_matrix`), so that
        a child's legs count as legs. ``frac_low`` and ``frac_mid`` are the
        same bands for a person of :data:`REFERENCE_HEIGHT_M`.
    voxel_m: layer thickness of ``cumulative``.
    """

    top_m: float
    bottom_m: float
    centre_m: float
    frac_low: float
    frac_mid: float
    horizontal_m: float
    widest_m: float
    floor_frac: float
    volume_m3: float
    body_top_m: float
    body_centre_m: float
    cumulative: np.ndarray = field(default_factory=lambda: np.zeros(1), compare=False, repr=False)
    voxel_m: float = 0.05

    @property
    def vertical_m(self) -> float:
        """Vertical extent of the body, metres."""
        return self.top_m - self.bottom_m


@dataclass(frozen=True)
class PostureModel:
    """Per-posture robust Gaussian over :data:`FEATURE_NAMES`.

    mean, sigma: (8, 8) float64, rows in :data:`STATES` order, columns in
        :data:`FEATURE_NAMES` order.
    weight: (8,) float64, how much each feature counts (top height is kept
        weak on purpose: hats, masks and raised arms move it).
    clip: the most one feature may cost, in units of ``0.5 * z**2``, so one
        odd feature cannot veto a posture on its own.
    """

    mean: np.ndarray
    sigma: np.ndarray
    weight: np.ndarray
    clip: float = 8.0

    def __post_init__(self) -> None:
        shape = (len(STATES), len(FEATURE_NAMES))
        for name in ("mean", "sigma"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != shape or not np.all(np.isfinite(arr)):
                raise ValueError(f"PostureModel.{name} must be a finite {shape} array")
            object.__setattr__(self, name, arr)
        if np.any(self.sigma <= 0):
            raise ValueError("PostureModel.sigma must be positive")
        weight = np.asarray(self.weight, dtype=np.float64)
        if weight.shape != (len(FEATURE_NAMES),) or np.any(weight < 0) or not np.all(np.isfinite(weight)):
            raise ValueError(f"PostureModel.weight must be {len(FEATURE_NAMES)} finite non-negative values")
        object.__setattr__(self, "weight", weight)
        if not self.clip > 0:
            raise ValueError(f"PostureModel.clip must be positive, got {self.clip}")


def default_model() -> PostureModel:
    """Class parameters measured on three kinds of bodies with known posture:
    the synthetic house's people carved by the full pipeline from rendered
    video (legs thinly carved or hidden by furniture, torsos fattened by the
    visual hull), the same people voxelised directly with and without
    fattening, and the articulated box bodies of tests/test_posture.py
    (hats, masks, 1.5-1.95 m). Medians rounded; spreads widened to at least
    the between-source differences."""
    #   centre  top  f_low f_mid lflat widest floor bottom     (heights / standing height)
    mean = [
        [0.54, 1.01, 0.17, 0.35, 1.30, 0.62, 0.40, 0.00],  # standing
        [0.40, 0.79, 0.27, 0.60, 1.00, 0.38, 0.31, 0.00],  # sitting
        [0.43, 0.69, 0.20, 0.57, 0.62, 0.55, 0.20, 0.00],  # bending
        [0.10, 0.30, 1.00, 0.00, -0.40, 0.08, 1.05, 0.00],  # lying
        [0.38, 0.81, 0.33, 0.45, 1.05, 0.40, 0.96, 0.00],  # kneeling
        [0.48, 0.75, 0.02, 0.72, 0.55, 0.45, 0.00, 0.28],  # sitting_raised
        [0.35, 0.45, 0.16, 0.84, -1.00, 0.35, 0.00, 0.25],  # lying_raised
        [0.59, 1.02, 0.02, 0.36, 0.90, 0.60, 0.00, 0.21],  # standing_raised
        [0.46, 1.01, 0.28, 0.38, 1.00, 0.45, 0.86, 0.00],  # standing_spread
    ]
    sigma = [
        [0.035, 0.05, 0.08, 0.06, 0.25, 0.06, 0.18, 0.06],
        [0.04, 0.15, 0.08, 0.08, 0.25, 0.05, 0.10, 0.05],
        [0.04, 0.06, 0.08, 0.10, 0.25, 0.06, 0.10, 0.06],
        [0.04, 0.10, 0.05, 0.05, 0.45, 0.05, 0.12, 0.05],
        [0.04, 0.06, 0.08, 0.10, 0.25, 0.15, 0.12, 0.05],
        [0.04, 0.15, 0.05, 0.08, 0.25, 0.05, 0.08, 0.05],
        [0.05, 0.06, 0.12, 0.12, 0.35, 0.06, 0.08, 0.05],
        [0.035, 0.05, 0.05, 0.06, 0.25, 0.05, 0.08, 0.06],
        [0.035, 0.05, 0.06, 0.06, 0.25, 0.20, 0.08, 0.05],  # widest anywhere from the floor to the hips
    ]
    # Top height counts least (hats, masks, raised arms move it).
    weight = [1.0, 0.5, 0.5, 0.5, 0.8, 1.0, 1.0, 1.0]
    return PostureModel(mean=np.array(mean), sigma=np.array(sigma), weight=np.array(weight))


def profile_features(
    height_profile: np.ndarray,
    voxel_m: float,
    *,
    max_gap_m: float = 0.1,
    wide_frac: float = 0.8,
    floor_band_m: float = 0.25,
) -> PostureFeatures | None:
    """Shape features of one height profile; None when the profile is empty.

    height_profile: (nz,) integer counts of foreground voxels per layer,
        layer ``k`` covering ``[k * voxel_m, (k + 1) * voxel_m)`` above the floor.
    max_gap_m: see :attr:`PostureFeatures.bottom_m`.
    wide_frac: see :attr:`PostureFeatures.widest_m`.
    floor_band_m: see :attr:`PostureFeatures.floor_frac`.
    """
    counts = np.asarray(height_profile)
    if counts.ndim != 1:
        raise ValueError(f"height_profile must be 1-D (nz,), got shape {counts.shape}")
    if not voxel_m > 0:
        raise ValueError(f"voxel_m must be positive, got {voxel_m}")
    counts = np.clip(np.nan_to_num(counts.astype(np.float64), nan=0.0, posinf=0.0), 0.0, None)
    total = float(counts.sum())
    if total <= 0:
        return None
    nz = counts.shape[0]
    occupied = np.flatnonzero(counts > 0)
    top_m = float((occupied[-1] + 1) * voxel_m)
    centres = (np.arange(nz) + 0.5) * voxel_m
    centre_m = float((counts * centres).sum() / total)
    bottom_m = float(_bottom_layer(occupied, centre_m, voxel_m, max_gap_m) * voxel_m)
    body_layers = body_top_layers(counts)
    body = counts[:body_layers]
    body_centre_m = float((body * centres[:body_layers]).sum() / body.sum())
    frac_low = float(counts[centres < 0.5].sum() / total)
    frac_mid = float(counts[(centres >= 0.5) & (centres < 1.0)].sum() / total)
    area = counts * voxel_m * voxel_m
    smooth = np.convolve(area, np.ones(3) / 3.0, mode="same") if nz >= 3 else area
    largest = max(float(smooth.max()), float(area.max()) / 3.0)
    horizontal_m = math.sqrt(largest)
    low = centres < floor_band_m
    floor_frac = float(area[low].max()) / largest if low.any() else 0.0
    wide = smooth >= wide_frac * smooth.max()
    widest_m = float((smooth[wide] * centres[wide]).sum() / smooth[wide].sum())
    return PostureFeatures(
        top_m=top_m,
        bottom_m=bottom_m,
        centre_m=centre_m,
        frac_low=frac_low,
        frac_mid=frac_mid,
        horizontal_m=horizontal_m,
        widest_m=widest_m,
        floor_frac=floor_frac,
        volume_m3=total * voxel_m**3,
        body_top_m=float(body_layers * voxel_m),
        body_centre_m=body_centre_m,
        cumulative=np.concatenate(([0.0], np.cumsum(counts) / total)),
        voxel_m=float(voxel_m),
    )


def feature_matrix(features: PostureFeatures, standing_heights_m: Sequence[float] | np.ndarray) -> np.ndarray:
    """(len(standing_heights_m), 8) float64, one :func:`feature_vector` per
    candidate standing height."""
    h = np.asarray(standing_heights_m, dtype=np.float64).reshape(-1)
    if len(h) == 0 or not np.all(h > 0):
        raise ValueError(f"standing_height_m must be positive, got {standing_heights_m}")
    vertical = max(features.vertical_m, 1e-3)
    horizontal = max(features.horizontal_m, 1e-3)
    cum = np.asarray(features.cumulative, dtype=np.float64)
    if len(cum) >= 2:
        edges = np.arange(len(cum)) * features.voxel_m
        scale = h / REFERENCE_HEIGHT_M
        low = np.interp(LOW_BAND_M * scale, edges, cum)
        mid = np.interp(MID_BAND_M * scale, edges, cum) - low
    else:  # features built by hand, without a profile: the bands as measured
        low = np.full(len(h), features.frac_low)
        mid = np.full(len(h), features.frac_mid)
    out = np.empty((len(h), len(FEATURE_NAMES)), dtype=np.float64)
    out[:, 0] = features.centre_m / h
    out[:, 1] = features.top_m / h
    out[:, 2] = low
    out[:, 3] = mid
    out[:, 4] = math.log(vertical / horizontal)
    out[:, 5] = features.widest_m / h
    out[:, 6] = features.floor_frac
    out[:, 7] = features.bottom_m / h
    return out


def feature_vector(features: PostureFeatures, standing_height_m: float) -> np.ndarray:
    """(8,) float64 in :data:`FEATURE_NAMES` order: heights divided by the
    person's standing height, the low and middle bands scaled to it."""
    if not standing_height_m > 0:
        raise ValueError(f"standing_height_m must be positive, got {standing_height_m}")
    return feature_matrix(features, [standing_height_m])[0]


def posture_log_likelihoods(vector: np.ndarray, model: PostureModel | None = None) -> np.ndarray:
    """Log-likelihood of each state (:data:`STATES` order), up to a shared
    constant: (8,) for one (8,) feature vector, (n, 8) for (n, 8) vectors."""
    model = model or default_model()
    v = np.asarray(vector, dtype=np.float64)
    if v.shape[-1:] != (len(FEATURE_NAMES),) or v.ndim > 2:
        raise ValueError(f"feature vector must have shape ({len(FEATURE_NAMES)},) or (n, {len(FEATURE_NAMES)}), got {v.shape}")
    cost = 0.5 * ((v[..., None, :] - model.mean) / model.sigma) ** 2
    cost = np.minimum(cost, model.clip)
    return -(cost * model.weight).sum(axis=-1)


def viterbi_log_transitions(dt_s: float) -> np.ndarray:
    """(S, S) float64 log transition matrix over :data:`DECODED_STATES` for one
    step of ``dt_s`` seconds, ``[from, to]``.

    The changes of :data:`VITERBI_RATES_HZ` (each split evenly over the
    destination posture's shapes) and :data:`VITERBI_SHAPE_RATE_HZ` form a
    continuous-time chain; a step is its matrix exponential, so a frame set
    that comes late (a dropped frame) allows proportionally more change.
    """
    if not (math.isfinite(dt_s) and dt_s >= 0):
        raise ValueError(f"dt_s must be a finite number >= 0, got {dt_s}")
    return _log_transitions_ms(int(round(dt_s * 1000.0))).copy()


def viterbi_aged_log_transitions(dt_s: float, min_duration_s: float) -> np.ndarray:
    """(S * A, S * A) float64 log transition matrix over the decoder's aged
    states, ``[from, to]``: state ``s`` of :data:`DECODED_STATES` at age ``a``
    is index ``s * A + a``, with ``A =`` :data:`VITERBI_AGES` (1 when
    ``min_duration_s`` is 0).

    A posture lasts at least ``min_duration_s``: on entering a posture its
    age is 0, and each step of ``dt_s`` ages it by ``A * dt_s /
    min_duration_s`` on average (the whole part always, one more with the
    fraction's probability) up to ``A - 1``, settled; only a settled posture
    may change into another (changes between the shapes of one posture keep
    its age). The changes a young posture may not make stay in it. ``outside``
    is always settled: the frames without a body say when it begins and ends.
    Between postures and shapes, :func:`viterbi_log_transitions`.
    """
    if not (math.isfinite(min_duration_s) and min_duration_s >= 0):
        raise ValueError(f"min_duration_s must be a finite number >= 0, got {min_duration_s}")
    if not (math.isfinite(dt_s) and dt_s >= 0):
        raise ValueError(f"dt_s must be a finite number >= 0, got {dt_s}")
    return _aged_log_transitions(dt_s, min_duration_s).copy()


def classify(features: PostureFeatures, standing_height_m: float, model: PostureModel | None = None) -> str:
    """Single-frame posture, no smoothing: the most likely of :data:`POSTURES`."""
    ll = posture_log_likelihoods(feature_vector(features, standing_height_m), model)
    return POSTURES[STATE_POSTURE[int(np.argmax(ll))]]


def fir_smooth(history: np.ndarray, taps: np.ndarray | None = None) -> np.ndarray:
    """FIR-filter the newest sample of a multichannel history.

    history: (N, F) float64, oldest first. taps: (M,) weights for the newest
    M samples, newest last; default uniform over all N. Fewer than M samples
    use the newest taps, renormalised. Returns (F,) float64.
    """
    h = np.asarray(history, dtype=np.float64)
    if h.ndim != 2 or len(h) == 0:
        raise ValueError(f"history must be a non-empty (N, F) array, got shape {h.shape}")
    w = np.ones(len(h)) if taps is None else np.asarray(taps, dtype=np.float64)
    if w.ndim != 1 or len(w) == 0 or np.any(w < 0) or not w.sum() > 0:
        raise ValueError("taps must be a non-empty 1-D array of non-negative weights")
    n = min(len(h), len(w))
    w = w[-n:]
    if not w.sum() > 0:
        w = np.ones(n)
    return (h[-n:] * w[:, None]).sum(axis=0) / w.sum()


@dataclass(frozen=True)
class PostureReading:
    """One track's posture at one frame.

    posture: the reported (smoothed, debounced) posture, one of :data:`POSTURES`.
    since_ns: when the reported posture began (first frame it led).
    probabilities: per-posture filtered probability, :data:`POSTURES` order.
    raw: this frame's features; smoothed: FIR-smoothed features.
    standing_height_m: the person's long-term standing height estimate.
    stamp_ns: frame time.
    state: the most probable internal state (:data:`STATES`) this frame,
        e.g. ``sitting_raised`` when the reading rests on a body floating at
        seat height.
    """

    posture: str
    since_ns: int
    probabilities: tuple[float, ...]
    raw: PostureFeatures
    smoothed: PostureFeatures
    standing_height_m: float
    stamp_ns: int
    state: str = ""

    @property
    def confidence(self) -> float:
        """Filtered probability of the reported posture."""
        return self.probabilities[POSTURES.index(self.posture)]


_FINITE = {"allow_inf_nan": False}


class PostureParams(Settings):
    """The bounds of :class:`PostureEstimator`'s keyword settings (described there), declared once;
    ``decisions`` and ``viterbi_lag_s`` are the site file's ``[events]`` declarations."""

    voxel_m: float = Field(gt=0.0, **_FINITE)
    standing_height_m: float = Field(1.70, **_FINITE)
    height_sigma_m: float = Field(0.10, gt=0.0, **_FINITE)
    anyone_weight: float = Field(0.15, ge=0.0, le=1.0)
    height_limits_m: tuple[float, float] = (0.9, 2.2)
    height_step_m: float = Field(0.05, gt=0.0, **_FINITE)
    height_evidence_weight: float = Field(0.3, gt=0.0, le=1.0)
    height_evidence_cap: float = Field(3.0, gt=0.0, **_FINITE)
    relearn_time_s: float = Field(60.0, gt=0.0, **_FINITE)
    walked_height_weight: float = Field(0.03, ge=0.0, le=1.0, **_FINITE)
    crowded_height_weight: float = Field(0.0, ge=0.0, le=1.0, **_FINITE)
    fir_taps: tuple[float, ...] | None = None
    switch_rate_hz: float = Field(0.5, gt=0.0, **_FINITE)
    evidence_weight: float = Field(0.5, gt=0.0, **_FINITE)
    min_duration_s: float = Field(0.4, ge=0.0, **_FINITE)
    walking_speed_mps: float = Field(0.5, gt=0.0, **_FINITE)
    walking_log_odds: float = Field(4.0, ge=0.0, **_FINITE)
    seatless_log_odds: float = Field(3.0, ge=0.0, **_FINITE)
    bedless_log_odds: float = Field(8.0, ge=0.0, **_FINITE)
    seated_bend_log_odds: float = Field(1.0, ge=0.0, **_FINITE)
    lying_min_span: float = Field(0.5, ge=0.0, **_FINITE)
    decisions: Literal["frame", "viterbi"] = declared(EventSettings, "decisions")
    viterbi_lag_s: float = declared(EventSettings, "viterbi_lag_s")

    @model_validator(mode="after")
    def _consistent(self) -> "PostureParams":
        lo, hi = self.height_limits_m
        if not 0 < lo < hi:
            raise ValueError(f"height_limits_m must be 0 < low < high, got {self.height_limits_m}")
        if not lo <= self.standing_height_m <= hi:
            raise ValueError(f"standing_height_m {self.standing_height_m} must lie in height_limits_m "
                             f"{self.height_limits_m}")
        if self.height_step_m > hi - lo:
            raise ValueError(f"height_step_m must be at most the limits' span, got {self.height_step_m}")
        taps = self.fir_taps
        if taps is not None and (not taps or any(t < 0 for t in taps) or not sum(taps) > 0):
            raise ValueError("fir_taps must be a non-empty list of non-negative weights with a positive sum")
        return self


class PostureEstimator:
    """Posture of one tracked person over time.

    The person's standing height is not known in advance (an adult seen
    seated first, a child among adults), and every height feature is read
    relative to it. So the estimator keeps a belief over a grid of standing
    heights, every ``height_step_m`` over ``height_limits_m``, beside the
    HMM over :data:`STATES`. The heights start from a population prior (most
    people an adult near ``standing_height_m``, anyone in the limits
    possible). Each frame the states are scored at every height and summed
    under the height belief, and the heights are scored by how well a
    standing or seated state explains the frame at that height (summed over
    those states with equal weight: the posture belief would argue in a
    circle). Only those shapes tell a height (the top of a standing body is
    its height, a seated one's is seat plus trunk); a lying or bending body
    does not, and read relative to a larger height it only looks flatter,
    so a frame counts for the heights in proportion to the filter's belief
    that the person stands or sits. A frame counts for the heights at most
    ``height_evidence_weight`` as much as for the posture, and by at most
    ``height_evidence_cap`` nats between any two heights, because a body's
    height is the same frame after frame while shapes the model does not
    know (getting up through the knees, two people touching) would
    otherwise throw it around in a single frame. So a still child reads
    standing at their own height within two seconds, a seated adult's lap and
    mass centre tell their height too, and walking (upright) pins it from
    the top. The reported standing height is the belief's mean.

    Keyword arguments (:class:`PostureParams`'s fields, declared there with their defaults and bounds;
    ValueError names the bad one):

    voxel_m: layer thickness of the height profiles, metres.
    standing_height_m, height_sigma_m: the adult part of the height prior,
        a normal of this mean and spread, metres.
    anyone_weight: the part of the prior spread evenly over
        ``height_limits_m`` (children, very tall or short adults).
    height_limits_m, height_step_m: the grid of candidate standing heights.
    height_evidence_weight, height_evidence_cap: see above.
    relearn_time_s: time constant with which the height belief drifts back
        towards the prior (a track that changes person, a bad first
        impression); the evidence of each frame holds it where it is.
    walked_height_weight: once the person has walked for a second (their
        top then is their standing height), a still frame counts this much
        of what it counted before for the height: the shapes of a still
        body tell a height less surely than a walk (a child by a table whose
        legs the table hides reads as a seated adult a head taller, and
        within a second the belief would follow).
    crowded_height_weight: a frame in which someone else stands close by
        (``crowded=True`` given to :meth:`update`) counts this much of what it
        would count for the height, walking or still. Two people that close
        are carved as one body or share its columns: the top, the lap and the
        widest layers may be the other's (a short person walking beside a tall
        one would learn the tall one's height, then read seated the moment
        they stand apart). Their posture is read all the same.
    fir_taps: FIR weights over the newest samples, newest last (default 5
        uniform taps: a third of a second at 15 fps).
    switch_rate_hz: prior rate of posture changes for the HMM transition
        model; lower means stickier.
    evidence_weight: scale on the per-frame log-likelihoods (the features are
        correlated, so their naive sum is over-confident).
    min_duration_s: a new posture must lead the filter this long before it is
        reported; with ``decisions="viterbi"``, the shortest spell of a posture
        on the decoded path.
    walking_speed_mps, walking_log_odds: a person whose floor speed is at
        least this walks, and walking is done upright: the upright states
        (standing, and standing with the legs hidden) gain this much
        log-likelihood over the others. 0.5 m/s is well under a walk
        (0.8-1.4 m/s, children too) and well over the jitter of a still
        person's estimate. A walking body's top is its standing height, so
        after a second of walking only the upright states tell the height,
        and fully.
    seatless_log_odds: where the site marks its seats and the person is at
        none of them (``on_seat=False`` given to :meth:`update`), the seated
        states lose this much log-likelihood. A child standing reads like a
        seated adult in a single frame (the same top, lap and mass centre
        relative to an adult's height); where nobody can sit, standing at the
        child's own height explains the body better, and the height belief
        follows.
        Sitting on the floor or on a seat the site does not mark stays
        possible, on stronger evidence.
    bedless_log_odds: likewise, where the site marks its beds and sofas and
        the person is on none of them (``on_bed=False``), lying above the
        floor loses this much: a seated person whose lower body a table
        hides carves as a slab floating at table height, the shape of
        someone lying on a bed, and must not read lying at the table.
    seated_bend_log_odds: at a seat (``on_seat=True``) and not walking, the
        bent-over states (bending, kneeling) lose this much: someone still
        at a table or on a sofa is far more often seated than bent over,
        and a seated body whose lap the table hides carves half-way between
        the two shapes (a short person most of all, their head nearer the
        table). A body clearly bent over still reads bending there.
    lying_min_span: a body whose shape reads lying on the floor but that
        reaches across the floor less than this share of the person's
        standing height (the diagonal of its floor box, ``span_m`` given
        to :meth:`update`) is a piece of the person, not the person, and
        tells nothing of their posture: the frame is passed over as one
        without a body (the reading holds). Someone lying, even curled up,
        spans more than half their height; the shins and thighs of a
        seated person whose upper body the carving lost (a table and a
        faulty camera) span half a metre and carve as flat and low as a
        body lying down, and nothing else in the model looks like them.
    model: the :class:`PostureModel` (default :func:`default_model`).
    decisions: one of :data:`DECISIONS`. ``frame`` reports the forward
        filter's posture after ``min_duration_s``; ``viterbi`` reports the
        fixed-lag Viterbi path's posture ``viterbi_lag_s`` back (the reading
        of a frame then tells the posture of the frame ``viterbi_lag_s``
        older, and nothing before the first one is committed: no reading).
    viterbi_lag_s: how far back the Viterbi decision is taken, seconds, in
        [0, 1]; frames older than this are final.
    """

    def __init__(self, *, model: PostureModel | None = None, **settings) -> None:
        p = PostureParams(**settings)
        lo, hi = p.height_limits_m
        taps = np.ones(5) if p.fir_taps is None else np.asarray(p.fir_taps, dtype=np.float64)
        self.voxel_m = p.voxel_m
        self.height_limits_m = (lo, hi)
        self.heights_m = np.arange(lo, hi + 0.5 * p.height_step_m, p.height_step_m)
        adult = np.exp(-0.5 * ((self.heights_m - p.standing_height_m) / p.height_sigma_m) ** 2)
        self.height_prior = (1.0 - p.anyone_weight) * adult / adult.sum() + p.anyone_weight / len(self.heights_m)
        self.height_evidence_weight = p.height_evidence_weight
        self.height_evidence_cap = p.height_evidence_cap
        self.relearn_time_s = p.relearn_time_s
        self.walked_height_weight = p.walked_height_weight
        self.crowded_height_weight = p.crowded_height_weight
        self.taps = taps
        self.switch_rate_hz = p.switch_rate_hz
        self.evidence_weight = p.evidence_weight
        self.min_duration_ns = int(round(p.min_duration_s * 1e9))
        self.walking_speed_mps = p.walking_speed_mps
        self.walking_log_odds = p.walking_log_odds
        self.seatless_log_odds = p.seatless_log_odds
        self.seated_bend_log_odds = p.seated_bend_log_odds
        self.lying_min_span = p.lying_min_span
        self.bedless_log_odds = p.bedless_log_odds
        self.model = model or default_model()
        self.height_posterior = self.height_prior.copy()
        self._history: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=len(taps))
        self._log_alpha: np.ndarray | None = None
        self._last_stamp_ns: int | None = None
        self._reported: int | None = None
        self._since_ns = 0
        self._candidate: int | None = None
        self._candidate_ns = 0
        self._last: PostureReading | None = None
        self._walking_since_ns: int | None = None  # start of the current spell of walking speed
        self._walked = False
        self.decisions = p.decisions
        self.viterbi_lag_ns = int(round(p.viterbi_lag_s * 1e9))
        self._decoder: FixedLagViterbi | None = None
        # per frame not yet committed: (stamp_ns, per-posture filtered probabilities)
        self._pending: deque[tuple[int, np.ndarray]] = deque()
        self._pending_last_ns: int | None = None
        self._committed: tuple[int, np.ndarray] | None = None  # newest committed body state, its probabilities

    @property
    def standing_height_m(self) -> float:
        """The person's standing height: the posterior mean over the candidate heights."""
        return float(self.height_posterior @ self.heights_m)

    @property
    def last(self) -> PostureReading | None:
        """The most recent reading, None before the first non-empty profile."""
        return self._last

    def update(self, stamp_ns: int, height_profile: np.ndarray, speed_mps: float = 0.0,
               on_seat: bool | None = None, on_bed: bool | None = None, crowded: bool = False,
               span_m: float | None = None) -> PostureReading | None:
        """Feed one frame's (nz,) height profile; returns the current reading.

        speed_mps: the person's floor speed (the tracker's smoothed estimate);
        at ``walking_speed_mps`` and above they walk, upright.
        on_seat: whether the person is at one of the site's seats; None where
        the site marks none (see ``seatless_log_odds``).
        on_bed: whether the person is on one of the site's beds or sofas; None
        where the site marks none (see ``bedless_log_odds``).
        crowded: whether someone else stands close by (see ``crowded_height_weight``).
        span_m: how far the body reaches across the floor (the diagonal of its floor box), metres;
        None where it is not known (see ``lying_min_span``).

        An empty profile changes nothing and returns the previous reading
        (None if there is none yet). Frames must come in time order; a frame
        older than the previous one raises ValueError.
        """
        stamp_ns = int(stamp_ns)
        if self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
            raise ValueError(f"stamp_ns {stamp_ns} is older than the previous frame {self._last_stamp_ns}")
        raw = profile_features(height_profile, self.voxel_m)
        if raw is None:
            if self.decisions == "viterbi" and self._decoder is not None:
                # no body seen: the person is outside for the decoder
                lik = np.full(len(DECODED_STATES), -np.inf)
                lik[OUTSIDE] = 0.0
                self._decode(stamp_ns, lik, None)
            return self._last
        if span_m is not None and self._a_piece(raw, float(span_m)):
            return self._last
        dt_s = 0.0 if self._last_stamp_ns is None else (stamp_ns - self._last_stamp_ns) * 1e-9
        self._last_stamp_ns = stamp_ns
        if self._history and len(self._history[-1][1]) != len(raw.cumulative):
            self._history.clear()
        self._history.append((_as_array(raw), raw.cumulative))
        smoothed = _from_array(
            fir_smooth(np.stack([h[0] for h in self._history]), self.taps),
            fir_smooth(np.stack([h[1] for h in self._history]), self.taps),
            self.voxel_m,
        )
        ll = self.evidence_weight * posture_log_likelihoods(feature_matrix(smoothed, self.heights_m), self.model)
        walking = float(speed_mps) >= self.walking_speed_mps
        if walking:
            if self._walking_since_ns is None:
                self._walking_since_ns = stamp_ns
            ll = ll + np.where(_UPRIGHT, self.walking_log_odds, 0.0)
        else:
            self._walking_since_ns = None
        if on_seat is False:
            ll = ll - np.where(_ON_SEAT, self.seatless_log_odds, 0.0)
        elif on_seat and not walking:
            ll = ll - np.where(_BENT, self.seated_bend_log_odds, 0.0)
        if on_bed is False:
            ll = ll - np.where(_ON_BED, self.bedless_log_odds, 0.0)
        top = ll.max()
        like = np.exp(ll - top)  # (H, S)
        self._log_alpha = _forward_step(
            self._log_alpha, np.log(np.maximum(self.height_posterior @ like, 1e-300)) + top, self.switch_rate_hz, dt_s
        )
        state_prob = np.exp(self._log_alpha)
        # Walking is done upright: the top of a body that has walked for a while is its standing
        # height (a body that comes down in a fall moves as fast, but for under a second).
        if walking and stamp_ns - self._walking_since_ns >= WALK_TELLS_HEIGHT_NS:
            tells, telling = _UPRIGHT, 1.0
            self._walked = self._walked or not crowded
        else:
            tells, telling = _TELLS_HEIGHT, float(state_prob[_TELLS_HEIGHT].sum())
            if self._walked:
                telling *= self.walked_height_weight
        if crowded:
            telling *= self.crowded_height_weight
        self._learn_height(np.log(np.maximum(like[:, tells].sum(axis=1), 1e-300)), telling, dt_s)
        prob = np.bincount(STATE_POSTURE, weights=state_prob, minlength=len(POSTURES))
        if self.decisions == "viterbi":
            # a body is seen: not outside
            lik = np.append(np.log(np.maximum(self.height_posterior @ like, 1e-300)) + top, -np.inf)
            decided = self._decode(stamp_ns, lik, prob)
            if decided is None:
                return self._last  # nothing committed yet
            state, prob = decided
        else:
            self._debounce(int(np.argmax(prob)), stamp_ns)
            state = int(np.argmax(state_prob))
        self._last = PostureReading(
            posture=POSTURES[self._reported],
            since_ns=self._since_ns,
            probabilities=tuple(float(p) for p in prob),
            raw=raw,
            smoothed=smoothed,
            standing_height_m=self.standing_height_m,
            stamp_ns=stamp_ns,
            state=STATES[state],
        )
        return self._last

    def _a_piece(self, raw: PostureFeatures, span_m: float) -> bool:
        """Whether a body of ``span_m`` across the floor whose shape ``raw`` reads lying on the floor
        is a piece of the person (see ``lying_min_span``), at the standing height believed now."""
        height = self.standing_height_m
        if span_m >= self.lying_min_span * height:
            return False
        return bool(_ON_FLOOR[int(np.argmax(posture_log_likelihoods(feature_vector(raw, height), self.model)))])

    def _decode(self, stamp_ns: int, lik: np.ndarray, prob: np.ndarray | None) -> tuple[int, np.ndarray] | None:
        """Push one frame's (S,) log-likelihoods over :data:`DECODED_STATES` into
        the fixed-lag decoder and commit every frame older than the lag. Returns
        the newest committed body state and that frame's filtered posture
        probabilities, or None while nothing with a body has been committed."""
        ages = VITERBI_AGES if self.min_duration_ns > 0 else 1
        lik = np.repeat(lik, ages)
        if self._decoder is None:
            self._decoder = FixedLagViterbi(_log_viterbi_prior(ages))
            self._decoder.push(lik)
        else:
            dt_s = max(stamp_ns - self._pending_last_ns, 0) * 1e-9
            self._decoder.push(lik, _aged_log_transitions(dt_s, self.min_duration_ns * 1e-9))
        self._pending_last_ns = stamp_ns
        self._pending.append((stamp_ns, prob))
        keep = sum(1 for t, _ in self._pending if t > stamp_ns - self.viterbi_lag_ns)
        for aged in self._decoder.commit(keep):
            state = aged // ages
            t, p = self._pending.popleft()
            if state == OUTSIDE or p is None:
                continue  # keeps the posture last committed with a body
            posture = STATE_POSTURE[state]
            if self._reported != posture:
                self._reported, self._since_ns = posture, t
            self._committed = (state, p)
        return self._committed

    def _learn_height(self, evidence: np.ndarray, weight: float, dt_s: float) -> None:
        """Update the height belief with one frame's (H,) log evidence, counted
        ``weight`` (0-1) of a full frame (see the class docstring)."""
        evidence = np.maximum(evidence - evidence.max(), -self.height_evidence_cap)
        post = self.height_posterior * np.exp(weight * self.height_evidence_weight * evidence)
        post /= post.sum()
        drift = 1.0 - math.exp(-max(dt_s, 0.0) / self.relearn_time_s)
        self.height_posterior = (1.0 - drift) * post + drift * self.height_prior

    def _debounce(self, best: int, stamp_ns: int) -> None:
        if self._reported is None:
            self._reported, self._since_ns = best, stamp_ns
            self._candidate = None
            return
        if best == self._reported:
            self._candidate = None
            return
        if best != self._candidate:
            self._candidate, self._candidate_ns = best, stamp_ns
        if stamp_ns - self._candidate_ns >= self.min_duration_ns:
            self._reported, self._since_ns = best, self._candidate_ns
            self._candidate = None


class PostureBank:
    """One :class:`PostureEstimator` per track id, created on first sight and
    forgotten when the track is no longer reported; the fusion pipeline's own.

    estimator_kwargs: passed to every :class:`PostureEstimator`. A track with a
    velocity (``vx``, ``vy`` in m/s, as the tracker's estimates carry) tells its
    estimator its speed; one without is taken as still.
    seats: the site's seats (hot spots where people sit, :data:`SEAT_KINDS`);
        a track with a position (``x``, ``y``) within ``seat_margin_m`` of
        one is on a seat, further from all of them it is not (its estimator
        is told so); without seats, nothing is said. 0.4 m covers a track's
        position error and a chair pulled out beyond a table's hot spot.
    beds: the site's beds and sofas (:data:`BED_KINDS`), the same way.
    backs: solids a seated body cannot sit beyond (floor polygons: a sofa's or a chair's back, a
        wall; :data:`BACK_BAND_M`). A track outside a seat or bed whose nearest point of it lies on
        a back is behind that back, not on the seat, however near: someone bending behind a sofa
        stands within the margin of its seat, with the backrest between them and it.
    crowd_m: a track with another confirmed track (``confirmed``, true where
        the track does not say) within this floor distance is crowded (its
        estimator is told so: see ``crowded_height_weight``). 0.8 m is the
        distance within which the tracker cannot tell two people's voxels
        apart (:class:`~fusion_server.tracker.PopulationParams` ``apart_m``).
    """

    def __init__(self, *, seats: Sequence[Hotspot] = (), beds: Sequence[Hotspot] = (), seat_margin_m: float = 0.4,
                 crowd_m: float = 0.8, backs: Sequence[Hotspot] = (), **estimator_kwargs) -> None:
        PostureEstimator(**estimator_kwargs)  # validate once, up front
        if not (math.isfinite(seat_margin_m) and seat_margin_m >= 0):
            raise ValueError(f"seat_margin_m must be a finite number >= 0, got {seat_margin_m}")
        if not (math.isfinite(crowd_m) and crowd_m >= 0):
            raise ValueError(f"crowd_m must be a finite number >= 0, got {crowd_m}")
        self.crowd_m = float(crowd_m)
        self._kwargs = dict(estimator_kwargs)
        self._estimators: dict[int, PostureEstimator] = {}
        self.seats = tuple(seats)
        self.beds = tuple(beds)
        self.seat_margin_m = float(seat_margin_m)
        self.backs = tuple(backs)

    def update(self, stamp_ns: int, tracks: Iterable[ProfiledTrack]) -> dict[int, PostureReading]:
        """Readings of every reported track that has had a non-empty profile."""
        out: dict[int, PostureReading] = {}
        seen: set[int] = set()
        tracks = list(tracks)
        crowded = self.crowded(tracks)
        spans = own_spans(tracks)
        for n, track in enumerate(tracks):
            tid = int(track.id)
            seen.add(tid)
            est = self._estimators.get(tid)
            if est is None:
                est = self._estimators[tid] = PostureEstimator(**self._kwargs)
            vx, vy = getattr(track, "vx", 0.0), getattr(track, "vy", 0.0)
            reading = est.update(stamp_ns, track.height_profile, speed_mps=float(np.hypot(vx, vy)),
                                 on_seat=self.on_seat(track), on_bed=self.on_bed(track), crowded=bool(crowded[n]),
                                 span_m=spans[n])
            if reading is not None:
                out[tid] = reading
        for tid in [t for t in self._estimators if t not in seen]:
            del self._estimators[tid]
        return out

    def crowded(self, tracks: Sequence[object]) -> np.ndarray:
        """(len(tracks),) bool: whether each track has another confirmed track within ``crowd_m``
        on the floor (a track without a position is never crowded nor crowds another)."""
        return company_of(tracks) <= self.crowd_m

    def on_seat(self, track: object) -> bool | None:
        """Whether ``track`` (x, y) is at one of the seats; None without seats or a position."""
        return self._near(track, self.seats)

    def on_bed(self, track: object) -> bool | None:
        """Whether ``track`` (x, y) is on one of the beds and sofas; None without them or a position."""
        return self._near(track, self.beds)

    def _near(self, track: object, places: Sequence[Hotspot]) -> bool | None:
        """Whether ``track`` (x, y) is within ``seat_margin_m`` of one of ``places``; None without
        places or a position."""
        x, y = getattr(track, "x", None), getattr(track, "y", None)
        if not places or x is None or y is None:
            return None
        return any(self._reaches(h, float(x), float(y)) for h in places)

    def _reaches(self, place: Hotspot, x: float, y: float) -> bool:
        """Whether (x, y) is within ``seat_margin_m`` of ``place`` with no back between: inside it, or
        outside with its nearest point of ``place`` on none of the backs that (x, y) is not on."""
        px, py = place.nearest_m(x, y)
        if math.hypot(px - x, py - y) > self.seat_margin_m:
            return False
        if (px, py) == (x, y):
            return True
        return not any(b.distance_m(px, py) <= BACK_TOUCH_M and b.distance_m(x, y) > BACK_TOUCH_M for b in self.backs)

    @property
    def settings(self) -> dict:
        """The keyword arguments every estimator is made with."""
        return dict(self._kwargs)

    def rename(self, renames: Mapping[int, int]) -> None:
        """Carry estimators over to the tracks' new ids at once (a swap is two renames)."""
        self._estimators = {renames.get(k, k): v for k, v in self._estimators.items()}

    def estimator(self, track_id: int) -> PostureEstimator | None:
        return self._estimators.get(int(track_id))


# --------------------------------------------------------------------------- helpers


@lru_cache(maxsize=256)
def _log_transitions_ms(dt_ms: int) -> np.ndarray:
    names = [POSTURES[p] for p in STATE_POSTURE] + ["outside"]
    n = len(names)
    rate = np.zeros((n, n))
    for i, a in enumerate(names):
        for j, b in enumerate(names):
            if i == j:
                continue
            if a == b:
                rate[i, j] = VITERBI_SHAPE_RATE_HZ
            else:
                rate[i, j] = VITERBI_RATES_HZ.get((a, b), 0.0) / names.count(b)
            if i < len(STATES) and j < len(STATES) and _RARE_CHANGES[i, j]:
                rate[i, j] *= _ENTER_RARELY
    np.fill_diagonal(rate, -rate.sum(axis=1))
    step = scipy.linalg.expm(rate * (dt_ms * 1e-3))
    return np.log(np.clip(step, 1e-300, 1.0))


def _log_viterbi_prior(ages: int) -> np.ndarray:
    """(S * ages,) log prior of a track's first frame: any state alike (a track
    may begin with someone already seated, or lying), settled."""
    prior = np.full((len(DECODED_STATES), ages), -np.inf)
    prior[:, ages - 1] = -math.log(len(DECODED_STATES))
    return prior.reshape(-1)


def _aged_log_transitions(dt_s: float, min_duration_s: float) -> np.ndarray:
    """The cached (read-only) matrix of :func:`viterbi_aged_log_transitions`."""
    dt_ms = int(round(dt_s * 1000.0))
    min_ms = int(round(min_duration_s * 1000.0))
    return _log_transitions_ms(dt_ms) if min_ms == 0 else _aged_ms(dt_ms, min_ms)


@lru_cache(maxsize=256)
def _aged_ms(dt_ms: int, min_ms: int) -> np.ndarray:
    n, m = len(DECODED_STATES), VITERBI_AGES
    step = np.exp(_log_transitions_ms(dt_ms))
    group = [STATE_POSTURE[i] for i in range(len(STATES))] + [-1]  # -1: outside
    x = m * dt_ms / min_ms
    whole, frac = int(math.floor(x)), x - math.floor(x)
    trans = np.zeros((n, m, n, m))
    for d in range(n):
        for a in range(m):
            settled = a == m - 1 or group[d] == -1
            for e in range(n):
                if group[e] == group[d]:
                    for k, w in ((whole, 1.0 - frac), (whole + 1, frac)):
                        if w > 0:
                            trans[d, a, e, m - 1 if group[e] == -1 else min(a + k, m - 1)] += step[d, e] * w
                elif settled:
                    trans[d, a, e, m - 1 if group[e] == -1 else 0] += step[d, e]
    trans = trans.reshape(n * m, n * m)
    trans /= trans.sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore"):
        return np.log(trans)


_FIELDS = (
    "top_m",
    "bottom_m",
    "centre_m",
    "frac_low",
    "frac_mid",
    "horizontal_m",
    "widest_m",
    "floor_frac",
    "volume_m3",
    "body_top_m",
    "body_centre_m",
)


def _as_array(f: PostureFeatures) -> np.ndarray:
    return np.array([getattr(f, n) for n in _FIELDS], dtype=np.float64)


def _from_array(a: np.ndarray, cumulative: np.ndarray, voxel_m: float) -> PostureFeatures:
    return PostureFeatures(**{n: float(v) for n, v in zip(_FIELDS, a)}, cumulative=cumulative, voxel_m=voxel_m)


def _bottom_layer(occupied: np.ndarray, centre_m: float, voxel_m: float, max_gap_m: float) -> int:
    """Lowest occupied layer connected to the mass centre's layer through gaps of at most ``max_gap_m``."""
    below = occupied[occupied <= int(centre_m / voxel_m)]
    if len(below) == 0:
        return int(occupied[0])
    max_step = int(round(max_gap_m / voxel_m)) + 1
    k = len(below) - 1
    while k > 0 and below[k] - below[k - 1] <= max_step:
        k -= 1
    return int(below[k])


def _forward_step(log_alpha: np.ndarray | None, log_lik: np.ndarray, rate_hz: float, dt_s: float) -> np.ndarray:
    """One normalised HMM forward step in the log domain; (S,) -> (S,)."""
    n = len(log_lik)
    if log_alpha is None:
        post = log_lik
    else:
        switch = 1.0 - math.exp(-rate_hz * max(dt_s, 0.0))
        switch = min(max(switch, 1e-6), 1.0 - 1.0 / n)
        trans = np.full((n, n), switch / (n - 1))
        np.fill_diagonal(trans, 1.0 - switch)
        if n == len(STATES):
            moved = np.where(_RARE_CHANGES, trans * (1.0 - _ENTER_RARELY), 0.0)   # stays put instead
            trans = trans - moved + np.diag(moved.sum(axis=1))
        post = np.log(np.maximum(np.exp(log_alpha) @ trans, 1e-300)) + log_lik
    m = post.max()
    return post - (m + math.log(np.exp(post - m).sum()))
