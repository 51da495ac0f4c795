"""Frame-set synchronisation: masks from free-running cameras -> sets of one instant.

Cameras are not genlocked: each stamps its frames with its own capture time,
at the same nominal frame rate but with its own phase. Frame sets sit on a
lattice of reference stamps one frame period apart, anchored at the first
frame pushed: ``ref_n = anchor + n * period``. A frame belongs to the set of
its nearest reference when it lies within ``tolerance_ns`` of it (default:
half a period, so every frame has a set and consecutive frames of one camera
never share one). A lattice rather than "the first frame opens a window"
keeps the sets from drifting when the cameras' phases spread over more than
the tolerance.

Release rules (time comes only from the stamps pushed, never from a clock):

* a set holding every camera is released at once;
* a set is released with the cameras it has once the newest stamp seen from
  any camera is more than ``max_wait_ns`` past its reference stamp, so a late
  or silent camera never holds the others back;
* sets leave in reference order: releasing a set first releases every older
  pending set.

Dropped and counted per camera (``counters[cam][...]``):

* ``duplicate``: same stamp as a recent frame of that camera, or same sequence
  number within one frame period of it (a restarted worker numbers its frames
  from 0 again, with new stamps: those are new frames);
* ``out_of_order``: its set is not newer than the last released set;
* ``stale``: its set is new but already more than ``max_wait_ns`` behind the
  newest stamp seen (it would leave at once, without the others);
* ``unmatched``: farther than ``tolerance_ns`` from its nearest reference (only
  with a tolerance below half a period);
* ``superseded``: a second frame of the camera for one set; the frame nearer to
  the reference stays;
* ``dropped_overflow``: the camera already had ``max_buffer`` frames pending;
  its oldest pending frame is dropped to make room.

``received`` counts every push of a known camera and ``released`` the frames that
left in sets. Pushes from unknown cameras are counted in ``unknown`` and dropped.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

__all__ = ["FrameSet", "FrameSynchroniser", "COUNTER_NAMES"]

COUNTER_NAMES = (
    "received", "duplicate", "out_of_order", "stale", "unmatched", "superseded", "released", "dropped_overflow",
)


@dataclass(frozen=True)
class FrameSet:
    """Frames of one instant.

    stamp_ns: the set's reference stamp on the lattice (anchor + n * period).
    payloads: camera id -> payload, for the cameras present.
    stamps_ns: camera id -> that frame's own stamp.
    seqs: camera id -> that frame's sequence number.
    missing: ids of the configured cameras absent from the set.
    """

    stamp_ns: int
    payloads: dict[str, Any]
    stamps_ns: dict[str, int]
    seqs: dict[str, int]
    missing: tuple[str, ...] = ()

    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(self.payloads)

    @property
    def complete(self) -> bool:
        return not self.missing


@dataclass
class _Pending:
    slot: int
    stamp_ns: int
    frames: dict[str, tuple[int, int, Any]] = field(default_factory=dict)  # cam -> (seq, stamp_ns, payload)


class FrameSynchroniser:
    """Groups masks of several cameras into frame sets. Pure: no clock, no I/O.

    Keyword arguments:
      camera_ids: the cameras expected in a complete set.
      fps: nominal frame rate: the lattice period and the defaults below.
      tolerance_ns: largest |stamp - reference| in a set; default half a frame period.
      max_wait_ns: how far the newest stamp may run ahead of a set before it is released
        without its missing cameras; default one frame period.
      max_buffer: most frames pending per camera.
    """

    def __init__(self, *, camera_ids: Iterable[str], fps: float = 15.0, tolerance_ns: int | None = None,
                 max_wait_ns: int | None = None, max_buffer: int = 8) -> None:
        ids = tuple(camera_ids) if not isinstance(camera_ids, str) else ()
        if not ids or any(not isinstance(c, str) or not c for c in ids):
            raise ValueError(f"camera_ids must be non-empty strings, got {camera_ids!r}")
        if len(set(ids)) != len(ids):
            raise ValueError(f"camera_ids must be unique, got {list(ids)}")
        if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps!r}")
        self.period_ns: float = 1e9 / fps
        tolerance_ns = int(round(self.period_ns / 2)) if tolerance_ns is None else tolerance_ns
        max_wait_ns = int(round(self.period_ns)) if max_wait_ns is None else max_wait_ns
        for name, value in (("tolerance_ns", tolerance_ns), ("max_wait_ns", max_wait_ns)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name} must be a non-negative int, got {value!r}")
        if isinstance(max_buffer, bool) or not isinstance(max_buffer, int) or max_buffer < 1:
            raise ValueError(f"max_buffer must be an int >= 1, got {max_buffer!r}")
        self.camera_ids: tuple[str, ...] = ids
        self.tolerance_ns = tolerance_ns
        self.max_wait_ns = max_wait_ns
        self.max_buffer = max_buffer
        self.counters: dict[str, dict[str, int]] = {c: dict.fromkeys(COUNTER_NAMES, 0) for c in ids}
        self.unknown = 0
        self.sets_released = 0
        self.sets_partial = 0
        self._pending: dict[int, _Pending] = {}  # lattice slot -> open set
        self._recent: dict[str, deque[tuple[int, int]]] = {c: deque(maxlen=2 * max_buffer + 2) for c in ids}
        self._anchor_ns: int | None = None
        self._newest_ns: int | None = None
        self._released_slot: int | None = None
        self._released_ns: int | None = None

    @property
    def pending(self) -> int:
        """Number of frames waiting in open sets."""
        return sum(len(p.frames) for p in self._pending.values())

    @property
    def last_released_ns(self) -> int | None:
        """Reference stamp of the last released set, None before the first."""
        return self._released_ns

    def reference_ns(self, stamp_ns: int) -> int:
        """The lattice reference nearest to ``stamp_ns`` (the anchor is the first frame pushed)."""
        if self._anchor_ns is None:
            return int(stamp_ns)
        return self._slot_stamp(self._slot(int(stamp_ns)))

    def push(self, cam: str, seq: int, stamp_ns: int, payload: Any) -> list[FrameSet]:
        """Offer one frame; returns the frame sets ready for fusion, oldest first (often empty)."""
        if cam not in self.counters:
            self.unknown += 1
            return []
        count = self.counters[cam]
        count["received"] += 1
        seq, stamp_ns = int(seq), int(stamp_ns)
        # a worker restarted counts from 0 again with new stamps: a repeated number alone is no copy
        if any(t == stamp_ns or (s == seq and abs(stamp_ns - t) < self.period_ns) for s, t in self._recent[cam]):
            count["duplicate"] += 1
            return []
        if self._anchor_ns is None:
            self._anchor_ns = stamp_ns
        slot = self._slot(stamp_ns)
        ref_ns = self._slot_stamp(slot)
        if abs(stamp_ns - ref_ns) > self.tolerance_ns:
            count["unmatched"] += 1
            return []
        if self._released_slot is not None and slot <= self._released_slot:
            count["out_of_order"] += 1
            return []
        target = self._pending.get(slot)
        if target is None and self._newest_ns is not None and self._newest_ns - ref_ns > self.max_wait_ns:
            count["stale"] += 1
            return []
        self._recent[cam].append((seq, stamp_ns))
        if target is None:
            target = self._pending[slot] = _Pending(slot, ref_ns)
        if cam in target.frames:
            count["superseded"] += 1
            if abs(target.frames[cam][1] - ref_ns) <= abs(stamp_ns - ref_ns):
                return []
        else:
            self._make_room(cam)
        target.frames[cam] = (seq, stamp_ns, payload)
        self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        out: list[FrameSet] = []
        if len(target.frames) == len(self.camera_ids):
            out.extend(self._release_through(slot))
        due = [s for s, p in self._pending.items() if self._newest_ns - p.stamp_ns > self.max_wait_ns]
        if due:
            out.extend(self._release_through(max(due)))
        return out

    def flush(self) -> list[FrameSet]:
        """Release every pending set as it is (end of a recording), oldest first."""
        return self._release_through(max(self._pending)) if self._pending else []

    # ------------------------------------------------------------------ helpers

    def _slot(self, stamp_ns: int) -> int:
        return math.floor((stamp_ns - self._anchor_ns) / self.period_ns + 0.5)

    def _slot_stamp(self, slot: int) -> int:
        return self._anchor_ns + int(round(slot * self.period_ns))

    def _make_room(self, cam: str) -> None:
        """Keep at most max_buffer - 1 frames of ``cam`` pending before adding one."""
        held = sorted(s for s, p in self._pending.items() if cam in p.frames)
        while len(held) >= self.max_buffer:
            oldest = self._pending[held.pop(0)]
            del oldest.frames[cam]
            self.counters[cam]["dropped_overflow"] += 1
            if not oldest.frames:
                del self._pending[oldest.slot]

    def _release_through(self, last_slot: int) -> list[FrameSet]:
        """Release the set of ``last_slot`` and every pending set older than it, oldest first."""
        slots = sorted(s for s in self._pending if s <= last_slot)
        sets = []
        for s in slots:
            p = self._pending.pop(s)
            cams = [c for c in self.camera_ids if c in p.frames]
            for c in cams:
                self.counters[c]["released"] += 1
            missing = tuple(c for c in self.camera_ids if c not in p.frames)
            self.sets_released += 1
            self.sets_partial += bool(missing)
            sets.append(FrameSet(
                stamp_ns=p.stamp_ns,
                payloads={c: p.frames[c][2] for c in cams},
                stamps_ns={c: p.frames[c][1] for c in cams},
                seqs={c: p.frames[c][0] for c in cams},
                missing=missing,
            ))
        if slots:
            self._released_slot = slots[-1]
            self._released_ns = sets[-1].stamp_ns
        return sets
