"""The events every detector emits (:class:`common.messages.Event`, the system's one
event type, with its deterministic :func:`~common.messages.event_id`), and the
:class:`Emitter` that builds one frame's events in call order."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from common import messages
from common.messages import Event, event_id

EVENT_KINDS: tuple[str, ...] = messages.PERSON_EVENT_KINDS
"""Kinds :class:`~fusion_server.events.EventReasoner` emits (a subset of the wire's event kinds)."""


class Emitter:
    """Builds the events of one frame, in call order, into ``out``.

    ``emit(kind, track, x, y, **details)`` appends one :class:`~common.messages.Event`
    stamped with this frame; detail values are made scalars the wire carries
    (numpy scalars to Python numbers, non-finite floats to None, anything else
    to str).
    """

    def __init__(self, out: list[Event], stamp_ns: int, frame: int) -> None:
        self.out, self.stamp_ns, self.frame = out, stamp_ns, frame

    def __call__(self, kind: str, track: int, x: float, y: float, **details: Any) -> None:
        clean = {k: _detail_value(v) for k, v in details.items()}
        self.out.append(
            Event(
                id=event_id(self.stamp_ns, kind, track),
                kind=kind,
                track=int(track),
                stamp_ns=self.stamp_ns,
                frame=self.frame,
                x=float(x),
                y=float(y),
                details=clean,
            )
        )


def _detail_value(v: Any) -> Any:
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    return str(v)
