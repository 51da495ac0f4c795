"""From tracked people and their postures to the events a carer acts on.

:class:`EventReasoner` takes one fused frame at a time -- its stamp, number,
the tracker's estimates and the posture readings -- and returns the
:class:`~common.messages.Event` s that frame decides. Same inputs, same events, same ids.

One detector per family of kinds, each with a frozen parameter group checked
once (defaults and meanings in each module's text):

* :mod:`~fusion_server.events.falls`: ``fall``, ``long_lie``
  (:class:`FallDetector`, :class:`FallParams`);
* :mod:`~fusion_server.events.sit_stand`: ``sit_down``, ``stand_up``
  (:class:`SitStandDetector`, :class:`SitStandParams`);
* :mod:`~fusion_server.events.entries`: ``enter``, ``exit`` at doors and edges
  (:class:`EntryDetector`, :class:`EntryParams`);
* :mod:`~fusion_server.events.visits`: ``dwell_start``, ``dwell_end``, ``visit``
  (:class:`VisitDetector`, :class:`VisitParams`);
* :mod:`~fusion_server.events.inactivity`: ``inactivity``
  (:class:`InactivityDetector`, :class:`InactivityParams`).

:mod:`~fusion_server.events.reasoner` composes them and keeps what they share
(which tracks are people and present, their recent tops, local time; its own
:class:`PresenceParams`). Camera events (``camera_lost``, ``camera_back``,
``clock_skew``) are made by the fusion pipeline, not here.

Pure logic: no clock, no I/O. Frames whose stamp goes backwards and tracks
with non-finite positions are dropped and counted, never raised.
"""

from fusion_server.events.entries import EntryDetector, EntryParams
from fusion_server.events.falls import FallDetector, FallParams, crossing_time, detect_fast_drop, drop_is_physical
from fusion_server.events.inactivity import InactivityDetector, InactivityParams
from fusion_server.events.local_time import DEFAULT_MEALS, local_hour, time_of_day_label
from fusion_server.events.reasoner import EventReasoner, PresenceParams
from fusion_server.events.records import EVENT_KINDS, Emitter
from fusion_server.events.sit_stand import SitStandDetector, SitStandParams, height_change_m
from fusion_server.events.track import TrackSnapshot, TrackLike
from fusion_server.events.visits import VisitDetector, VisitParams

__all__ = [
    "DEFAULT_MEALS",
    "EVENT_KINDS",
    "Emitter",
    "EntryDetector",
    "EntryParams",
    "EventReasoner",
    "FallDetector",
    "FallParams",
    "InactivityDetector",
    "InactivityParams",
    "PresenceParams",
    "SitStandDetector",
    "SitStandParams",
    "TrackSnapshot",
    "TrackLike",
    "VisitDetector",
    "VisitParams",
    "crossing_time",
    "detect_fast_drop",
    "drop_is_physical",
    "height_change_m",
    "local_hour",
    "time_of_day_label",
]
