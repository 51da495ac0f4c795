"""What the event detectors read of a track: :class:`TrackLike`, the attributes
the reasoner reads of a tracker estimate, and :class:`TrackSnapshot`, what one
frame tells a detector about one track."""

from __future__ import annotations

import math

from dataclasses import dataclass
from typing import Protocol, Sequence

from fusion_server.posture import PostureReading

TopSample = tuple[int, float, "float | None", "str | None", float]
"""``(stamp_ns, top_m, centre_m | None, posture | None, body_top_m)`` of one frame: heights above the
floor, metres; ``body_top_m`` is the top less any thin hull over the body and ``centre_m`` the mass
centre below it (:attr:`~fusion_server.posture.PostureFeatures.body_top_m`,
:attr:`~fusion_server.posture.PostureFeatures.body_centre_m`; the top itself and no centre without a
posture reading)."""


class TrackLike(Protocol):
    """What the reasoner reads of a track estimate (any object with these attributes)."""

    id: int
    x: float
    y: float
    z_top_m: float
    confirmed: bool


@dataclass(frozen=True)
class TrackSnapshot:
    """One track in one frame, as the detectors see it.

    track: track id. stamp_ns: the frame's time.
    x, y: world floor position, metres.
    posture: the reported posture name, None when the frame has none.
    reading: the full posture reading, None when the posture came as a bare
        name (or not at all).
    top_m, centre_m: heights above the floor, metres, of the highest voxel
        and of the mass centre of the body below
        :attr:`~fusion_server.posture.PostureFeatures.body_top_m` (top NaN
        when unknown; centre None without a reading).
    standing_height_m: the reading's learnt standing height, None without one.
    tops: the track's recent tops, oldest first, this frame's included: the
        history the reasoner keeps from the track's first frame (frames with
        a non-finite top are left out).
    upright_ns: time the track read standing or sitting since its first frame.
    confirmed: the tracker confirms the track this frame (an unconfirmed one
        coasts, or follows what the explanation did not take for a person).
    company_m: floor distance to the nearest other track the tracker confirms
        this frame, metres (infinite when there is none).
    """

    track: int
    stamp_ns: int
    x: float
    y: float
    posture: str | None
    reading: PostureReading | None
    top_m: float
    centre_m: float | None
    standing_height_m: float | None
    tops: Sequence[TopSample]
    upright_ns: int
    confirmed: bool
    company_m: float = math.inf
