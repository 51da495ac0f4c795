"""Entering and leaving (``enter``, ``exit``) through door zones and open edges.

A track first seen inside a door zone (or, when ``bounds_xy_m`` is given,
within ``edge_margin_m`` [0.4 m] of the monitored area's border) enters when
it is established; people already there during the first ``startup_s``
[1 s] do not enter. A present track whose last confirmed position is in
such a place exits when the tracker stops confirming it or stops reporting
it, whichever comes first (the tracker coasts a departed person unconfirmed
for a couple of seconds before deleting them). A track that has exited and
is established again in a door zone or at the edge enters again. Tracks
that appear, lose confirmation (occlusion) or vanish mid-room are neither.

When a track is established, loses confirmation or vanishes is the
reasoner's presence bookkeeping (:class:`~fusion_server.events.EventReasoner`),
which dwelling and visits share; this detector says where those moments are
entries and exits, and so keeps no state of its own per track.
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

from pydantic import Field

from common.settings import Settings, group_of
from fusion_server.events._common import NUMBER, ns
from fusion_server.events.records import Emitter
from fusion_server.hotspots import Hotspot, hotspot_at


class EntryParams(Settings):
    """Settings of :class:`EntryDetector`: ``edge_margin_m`` (metres) and
    ``startup_s`` (seconds), as the module text describes them."""

    edge_margin_m: float = Field(0.4, ge=0.0, **NUMBER)
    startup_s: float = Field(1.0, ge=0.0, **NUMBER)


class EntryDetector:
    """``enter`` and ``exit`` at door zones and open edges.

    doors: door zones (Hotspot objects; kind is not used).
    bounds_xy_m: ``(x_min, y_min, x_max, y_max)`` of the monitored floor,
        metres, for entering and leaving at the edge; None: doors only.
    """

    def __init__(
        self,
        params: EntryParams = EntryParams(),
        *,
        doors: Iterable[Hotspot] = (),
        bounds_xy_m: Sequence[float] | None = None,
    ) -> None:
        group_of(params, EntryParams)
        self.params = params
        self.doors = tuple(doors)
        for h in self.doors:
            if not isinstance(h, Hotspot):
                raise ValueError(f"doors must hold Hotspot instances, got {type(h).__name__}")
        if bounds_xy_m is not None:
            b = tuple(float(v) for v in bounds_xy_m)
            if len(b) != 4 or not all(math.isfinite(v) for v in b) or not (b[0] < b[2] and b[1] < b[3]):
                raise ValueError(f"bounds_xy_m must be (x_min, y_min, x_max, y_max) with min < max, got {bounds_xy_m}")
            bounds_xy_m = b
        self.bounds_xy_m: tuple[float, float, float, float] | None = bounds_xy_m
        self._startup_ns = ns(params.startup_s)

    def place(self, x: float, y: float) -> str | None:
        """Name of the door zone containing the floor point, ``"edge"`` near the border, else None."""
        door = hotspot_at(self.doors, x, y)
        if door is not None:
            return door.name
        if self.bounds_xy_m is not None:
            x0, y0, x1, y1 = self.bounds_xy_m
            if min(x - x0, y - y0, x1 - x, y1 - y) <= self.params.edge_margin_m:
                return "edge"
        return None

    def first_arrival(
        self, track: int, x: float, y: float, *, first_xy: tuple[float, float], first_ns: int, start_ns: int,
        emit: Emitter,
    ) -> None:
        """A new track is established at ``(x, y)``: an ``enter`` if it was first seen
        (at ``first_xy``, ``first_ns``) in a door zone or at the edge, after monitoring
        started (``start_ns``) and settled."""
        place = self.place(*first_xy)
        # People already in the room when monitoring starts did not enter.
        if place is not None and first_ns - start_ns > self._startup_ns:
            emit("enter", track, x, y, door=place, first_seen_ns=first_ns)

    def return_arrival(self, track: int, x: float, y: float, *, since_ns: int, emit: Emitter) -> None:
        """A track that exited is established again at ``(x, y)``, confirmed since
        ``since_ns``: an ``enter`` if that is a door zone or the edge (confirmed
        again mid-room, they never left)."""
        place = self.place(x, y)
        if place is not None:
            emit("enter", track, x, y, door=place, first_seen_ns=since_ns)

    def exit(self, track: int, place: str, xy: tuple[float, float], last_seen_ns: int, emit: Emitter) -> None:
        """The track left through ``place`` (from :meth:`place`), last confirmed at ``xy``, ``last_seen_ns``."""
        emit("exit", track, xy[0], xy[1], door=place, last_seen_ns=last_seen_ns)
