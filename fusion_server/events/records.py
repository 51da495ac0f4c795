"""Event records: the :class:`EventRecord` every detector emits, its deterministic
id, and the :class:`Emitter` that builds one frame's records in call order."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from common import messages

EVENT_KINDS: tuple[str, ...] = messages.PERSON_EVENT_KINDS
"""Kinds :class:`~fusion_server.events.EventReasoner` emits (a subset of the wire's event kinds)."""


@dataclass(frozen=True)
class EventRecord:
    """One event. Field names match the wire ``Event`` message.

    id: ``f"{stamp_ns}-{kind}-{track}"``, unique and deterministic.
    kind: one of :data:`EVENT_KINDS`.
    track: track id, -1 when the event concerns no single track (visits).
    stamp_ns: the frame that decided the event. frame: its number.
    x, y: world floor position, metres.
    details: flat map of str -> str | int | float | bool | None.
    """

    id: str
    kind: str
    track: int
    stamp_ns: int
    frame: int
    x: float
    y: float
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (a copy)."""
        return {
            "id": self.id,
            "kind": self.kind,
            "track": self.track,
            "stamp_ns": self.stamp_ns,
            "frame": self.frame,
            "x": self.x,
            "y": self.y,
            "details": dict(self.details),
        }

    @classmethod
    def from_dict(cls, obj: Mapping[str, Any]) -> "EventRecord":
        """Inverse of :meth:`to_dict`; ValueError naming the bad field."""
        if not isinstance(obj, Mapping):
            raise ValueError(f"event must be a mapping, got {type(obj).__name__}")
        out: dict[str, Any] = {}
        for name, typ in (("id", str), ("kind", str), ("track", int), ("stamp_ns", int), ("frame", int)):
            if name not in obj:
                raise ValueError(f"event field {name!r} is missing")
            val = obj[name]
            if isinstance(val, bool) or not isinstance(val, typ):
                raise ValueError(f"event field {name!r} must be {typ.__name__}, got {type(val).__name__}")
            out[name] = val
        if not out["id"]:
            raise ValueError("event field 'id' must not be empty")
        for name in ("x", "y"):
            val = obj.get(name, 0.0)
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
                raise ValueError(f"event field {name!r} must be a finite number, got {val!r}")
            out[name] = float(val)
        details = obj.get("details") or {}
        if not isinstance(details, Mapping):
            raise ValueError(f"event field 'details' must be a mapping, got {type(details).__name__}")
        out["details"] = dict(details)
        return cls(**out)


def event_id(stamp_ns: int, kind: str, track: int) -> str:
    """The deterministic event id ``f"{stamp_ns}-{kind}-{track}"``."""
    return f"{int(stamp_ns)}-{kind}-{int(track)}"


class Emitter:
    """Builds the records of one frame, in call order, into ``out``.

    ``emit(kind, track, x, y, **details)`` appends one :class:`EventRecord`
    stamped with this frame; detail values are made JSON-plain (numpy scalars
    to Python numbers, non-finite floats to None, anything else to str).
    """

    def __init__(self, out: list[EventRecord], stamp_ns: int, frame: int) -> None:
        self.out, self.stamp_ns, self.frame = out, stamp_ns, frame

    def __call__(self, kind: str, track: int, x: float, y: float, **details: Any) -> None:
        clean = {k: _plain(v) for k, v in details.items()}
        self.out.append(
            EventRecord(
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


def _plain(v: Any) -> Any:
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    return str(v)
