"""Identity across re-entries: does a person who leaves and comes back get their old track id again?

A re-entry is a truth ``exit`` of a person followed by their next ``enter``
within :data:`REENTRY_WITHIN_S` seconds (``track`` of the truth events is the
person's id in the truth tracks). The run track ids the person had on either
side come from the matches of :func:`~evaluation.tracking.clear_mot`
(the same radius as the tracking figures):

* before: the run ids matched to the person in the last :data:`BEFORE_S`
  seconds of frames up to and including their last matched frame before the
  exit; the most frequent one (ties: the latest seen);
* after: the run ids matched to the person in the :data:`AFTER_S` seconds of
  frames from their first matched frame at or after the re-entry (and before
  their next exit); the most frequent one (ties: the first seen).

The re-entry keeps its identity ("same id") when both exist and are equal; a
person never matched on one side counts as a re-entry without it. The rate is
same / re-entries, None without re-entries; totals over recordings sum both
counts.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from evaluation.io import Event, TrackTable
from evaluation.tracking import Matches, ratio

REENTRY_WITHIN_S = 600.0
BEFORE_S = 1.0
AFTER_S = 3.0


@dataclass(frozen=True)
class Reentry:
    """One truth re-entry: ``person`` (truth id), ``exit_frame`` and ``enter_frame``; ``before`` and
    ``after`` the majority run track ids on either side (None: not matched there)."""

    person: str
    exit_frame: int
    enter_frame: int
    before: str | None
    after: str | None

    @property
    def same_id(self) -> bool:
        return self.before is not None and self.before == self.after


@dataclass(frozen=True)
class ReentryResult:
    """The re-entries of one recording and the windows they were judged with."""

    reentries: tuple[Reentry, ...]
    within_s: float = REENTRY_WITHIN_S
    before_s: float = BEFORE_S
    after_s: float = AFTER_S

    @property
    def same_id(self) -> int:
        return sum(r.same_id for r in self.reentries)

    def summary(self) -> dict[str, Any]:
        """Counts, the rate and the windows as plain JSON values."""
        n = len(self.reentries)
        return {"reentries": n, "same_id": self.same_id, "rate": ratio(self.same_id, n),
                "within_s": self.within_s, "before_s": self.before_s, "after_s": self.after_s}


def reentry_identity(truth: TrackTable, run: TrackTable, pairs: Matches, truth_events: Sequence[Event], fps: float,
                     *, within_s: float = REENTRY_WITHIN_S, before_s: float = BEFORE_S,
                     after_s: float = AFTER_S) -> ReentryResult:
    """Judge every re-entry of ``truth_events`` (see the module text). ``pairs``: the matches of
    :func:`~evaluation.tracking.clear_mot` on the same ``truth`` and ``run`` tables, as passed
    in; ``fps`` frames per second (converts the windows to frames)."""
    if not (fps and np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    within = within_s * fps
    n_before = max(1, int(round(before_s * fps)))
    n_after = max(1, int(round(after_s * fps)))
    person = truth.track_id[pairs.truth_row] if len(pairs) else np.zeros(0, dtype=str)
    track = run.track_id[pairs.run_row] if len(pairs) else np.zeros(0, dtype=str)
    order = np.argsort(pairs.frame, kind="stable")
    frames, person, track = pairs.frame[order], person[order], track[order]
    doors: dict[str, list[tuple[int, str]]] = {}
    for e in truth_events:
        if e.kind in ("enter", "exit") and e.track is not None:
            doors.setdefault(str(e.track), []).append((int(e.frame), e.kind))
    out: list[Reentry] = []
    for pid in sorted(doors, key=_id_order):
        seq = sorted(doors[pid])
        mine = person == pid
        f, t = frames[mine], track[mine]
        for k, (fe, kind) in enumerate(seq):
            if kind != "exit":
                continue
            nxt = next(((fr, j) for j, (fr, kd) in enumerate(seq[k + 1:], k + 1) if kd == "enter"), None)
            if nxt is None or nxt[0] - fe > within:
                continue
            fr, j = nxt
            leave_again = next((fx for fx, kd in seq[j + 1:] if kd == "exit"), None)
            before = f < fe
            before_id = None
            if before.any():
                last = f[before][-1]
                win = before & (f > last - n_before)
                before_id = _majority(t[win][::-1])
            after = (f >= fr) & (f < leave_again if leave_again is not None else True)
            after_id = None
            if after.any():
                first = f[after][0]
                win = after & (f < first + n_after)
                after_id = _majority(t[win])
            out.append(Reentry(pid, int(fe), int(fr), before_id, after_id))
    return ReentryResult(tuple(out), within_s=float(within_s), before_s=float(before_s), after_s=float(after_s))


# ---------------------------------------------------------------------- helpers


def _majority(ids: np.ndarray) -> str:
    """The most frequent id; ties go to the one met first in ``ids``."""
    return str(Counter(ids.tolist()).most_common(1)[0][0])


def _id_order(pid: str) -> tuple[int, int | str]:
    return (0, int(pid)) if pid.lstrip("-").isdigit() else (1, pid)
