"""Event scoring: precision, recall and F1 per kind, fall delays, false alarms per hour.

Matching rule (the +-30-frame protocol of the multi-sensor fusion paper in
DESIGN.md, made one-to-one): a run event can match a
truth event of the same kind when their frames differ by at most
``window_frames`` (30 frames = 2 s at 15 fps; inclusive). Per kind, the
gated Hungarian assignment first maximises the number of matched pairs and
then minimises the summed frame difference (ties broken by floor distance),
so one run event never explains two truth events and a duplicated alarm
counts as a false positive.

Extra conditions, both optional:

* ``position_gate_m``: per kind, the floor distance between the two events
  must be at most this many metres when both events have a position.
  Default: 1 m for ``enter`` and ``exit`` (several people may come through
  different doors within the window), no gate for the other kinds.
* ``track_links``: the run event's track must be a run track that the
  CLEAR-MOT association matched to the truth event's track in some frame of
  the window. Off by default: the paper matches events by time alone, and
  identity mistakes are already scored by IDF1 and ID switches. Events
  without a track on either side pass this test.

Kinds outside ``kinds`` (``camera_lost`` and other health events) are not
scored. An undefined ratio (nothing to divide by) is None.
"""

from __future__ import annotations

import bisect
import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from evaluation.io import SCORED_KINDS, Event, TrackTable
from evaluation.tracking import Matches, gated_assignment, ratio

WINDOW_FRAMES = 30
POSITION_GATE_M: Mapping[str, float] = {"enter": 1.0, "exit": 1.0}
ALARM_KINDS: tuple[str, ...] = ("fall", "long_lie", "inactivity")


@dataclass(frozen=True)
class EventPair:
    """A truth event and the run event matched to it."""

    truth: Event
    run: Event

    @property
    def kind(self) -> str:
        return self.truth.kind

    @property
    def delay_s(self) -> float:
        """Run stamp minus truth stamp, seconds (negative when the run was early)."""
        return (self.run.stamp_ns - self.truth.stamp_ns) / 1e9

    @property
    def frame_offset(self) -> int:
        return self.run.frame - self.truth.frame


@dataclass(frozen=True)
class KindScore:
    """Counts for one event kind."""

    kind: str
    truth: int
    run: int
    tp: int

    @property
    def fp(self) -> int:
        return self.run - self.tp

    @property
    def fn(self) -> int:
        return self.truth - self.tp

    @property
    def precision(self) -> float | None:
        return ratio(self.tp, self.run)

    @property
    def recall(self) -> float | None:
        return ratio(self.tp, self.truth)

    @property
    def f1(self) -> float | None:
        return f1_score(self.tp, self.fp, self.fn)

    def summary(self) -> dict[str, Any]:
        return {
            "truth": self.truth,
            "run": self.run,
            "tp": self.tp,
            "fp": self.fp,
            "fn": self.fn,
            "precision": self.precision,
            "recall": self.recall,
            "f1": self.f1,
        }


@dataclass(frozen=True)
class EventScores:
    """Everything event scoring found for one recording."""

    window_frames: int
    position_gate_m: Mapping[str, float]
    track_required: bool
    per_kind: Mapping[str, KindScore]
    pairs: Sequence[EventPair]
    unmatched_truth: Sequence[Event]
    unmatched_run: Sequence[Event]
    unscored_run: int

    @property
    def overall(self) -> KindScore:
        """Counts summed over every scored kind (micro average)."""
        return KindScore(
            kind="all",
            truth=sum(s.truth for s in self.per_kind.values()),
            run=sum(s.run for s in self.per_kind.values()),
            tp=sum(s.tp for s in self.per_kind.values()),
        )

    def delays_s(self, kind: str = "fall") -> list[float]:
        """Signed delay of every detected event of ``kind``, seconds, in truth order."""
        return [p.delay_s for p in self.pairs if p.kind == kind]

    def false_alarms(self, alarm_kinds: Iterable[str] = ALARM_KINDS) -> int:
        """Run events of the alarm kinds that match no truth event."""
        kinds = set(alarm_kinds)
        return sum(1 for e in self.unmatched_run if e.kind in kinds)

    def summary(self, *, duration_s: float | None, alarm_kinds: Sequence[str] = ALARM_KINDS) -> dict[str, Any]:
        """Plain JSON values; ``duration_s`` of the recording turns false alarms into a rate."""
        delays = self.delays_s("fall")
        n_false = self.false_alarms(alarm_kinds)
        hours = None if not duration_s else duration_s / 3600.0
        return {
            "window_frames": self.window_frames,
            "position_gate_m": dict(self.position_gate_m),
            "track_required": self.track_required,
            "per_kind": {kind: s.summary() for kind, s in self.per_kind.items()},
            "overall": self.overall.summary(),
            "fall_delays_s": delays,
            "fall_delay_mean_s": statistics.fmean(delays) if delays else None,
            "fall_delay_median_s": statistics.median(delays) if delays else None,
            "fall_delay_max_s": max(delays) if delays else None,
            "alarm_kinds": list(alarm_kinds),
            "false_alarms": n_false,
            "duration_s": duration_s,
            "false_alarms_per_hour": None if hours is None else n_false / hours,
            "unscored_run_events": self.unscored_run,
            "matched": [
                {"kind": p.kind, "truth_frame": p.truth.frame, "run_frame": p.run.frame,
                 "truth_track": p.truth.track, "run_track": p.run.track, "delay_s": p.delay_s}
                for p in self.pairs
            ],
            "missed": [_brief(e) for e in self.unmatched_truth],
            "spurious": [_brief(e) for e in self.unmatched_run],
        }


class TrackLinks:
    """Which run track the tracking association matched to which truth track, and when.

    Built from the CLEAR-MOT :class:`~evaluation.tracking.Matches`;
    answers whether a truth track and a run track were matched in any frame of
    an inclusive frame interval.
    """

    def __init__(self, frames_by_pair: Mapping[tuple[str, str], Sequence[int]]) -> None:
        self._frames = {pair: sorted(int(f) for f in frames) for pair, frames in frames_by_pair.items()}

    @classmethod
    def from_matches(cls, truth: TrackTable, run: TrackTable, matches: Matches) -> "TrackLinks":
        by_pair: dict[tuple[str, str], list[int]] = {}
        t_ids = truth.track_id[matches.truth_row]
        r_ids = run.track_id[matches.run_row]
        for f, t, r in zip(matches.frame.tolist(), t_ids.tolist(), r_ids.tolist()):
            by_pair.setdefault((t, r), []).append(f)
        return cls(by_pair)

    def linked(self, truth_track: str, run_track: str, first_frame: int, last_frame: int) -> bool:
        frames = self._frames.get((truth_track, run_track))
        if not frames:
            return False
        k = bisect.bisect_left(frames, first_frame)
        return k < len(frames) and frames[k] <= last_frame


def score_events(
    truth: Iterable[Event],
    run: Iterable[Event],
    *,
    window_frames: int = WINDOW_FRAMES,
    kinds: Sequence[str] = SCORED_KINDS,
    position_gate_m: Mapping[str, float] | None = None,
    track_links: TrackLinks | None = None,
) -> EventScores:
    """Match run events to truth events one-to-one per kind (see the module text)."""
    if isinstance(window_frames, bool) or not isinstance(window_frames, (int, np.integer)) or window_frames < 0:
        raise ValueError(f"window_frames must be a non-negative integer, got {window_frames!r}")
    gates = dict(POSITION_GATE_M if position_gate_m is None else position_gate_m)
    for kind, gate in gates.items():
        if not (isinstance(gate, (int, float)) and gate > 0):
            raise ValueError(f"position_gate_m[{kind!r}] must be a positive number of metres, got {gate!r}")
    kinds = list(dict.fromkeys(kinds))
    truth = sorted(truth, key=lambda e: (e.frame, e.stamp_ns))
    run = sorted(run, key=lambda e: (e.frame, e.stamp_ns))
    scored = set(kinds)
    per_kind: dict[str, KindScore] = {}
    pairs: list[EventPair] = []
    unmatched_truth: list[Event] = []
    unmatched_run: list[Event] = []
    for kind in kinds:
        t_k = [e for e in truth if e.kind == kind]
        r_k = [e for e in run if e.kind == kind]
        matched = _match_kind(t_k, r_k, window_frames, gates.get(kind), track_links)
        per_kind[kind] = KindScore(kind=kind, truth=len(t_k), run=len(r_k), tp=len(matched))
        used_t = {i for i, _ in matched}
        used_r = {j for _, j in matched}
        pairs.extend(EventPair(truth=t_k[i], run=r_k[j]) for i, j in matched)
        unmatched_truth.extend(e for i, e in enumerate(t_k) if i not in used_t)
        unmatched_run.extend(e for j, e in enumerate(r_k) if j not in used_r)
    order = lambda e: (e.frame, e.stamp_ns)  # noqa: E731
    pairs.sort(key=lambda p: order(p.truth))
    unmatched_truth.sort(key=order)
    unmatched_run.sort(key=order)
    return EventScores(
        window_frames=int(window_frames),
        position_gate_m=gates,
        track_required=track_links is not None,
        per_kind=per_kind,
        pairs=pairs,
        unmatched_truth=unmatched_truth,
        unmatched_run=unmatched_run,
        unscored_run=sum(1 for e in run if e.kind not in scored),
    )


def f1_score(tp: int, fp: int, fn: int) -> float | None:
    """2 TP / (2 TP + FP + FN); None when there was nothing to find and nothing found."""
    return ratio(2 * tp, 2 * tp + fp + fn)


# ---------------------------------------------------------------- helpers


def _match_kind(
    truth: Sequence[Event],
    run: Sequence[Event],
    window_frames: int,
    gate_m: float | None,
    links: TrackLinks | None,
) -> list[tuple[int, int]]:
    """Index pairs (truth i, run j); both lists sorted by frame."""
    matched: list[tuple[int, int]] = []
    for t_idx, r_idx in _clusters(truth, run, window_frames):
        cost = np.full((len(t_idx), len(r_idx)), np.inf)
        for a, i in enumerate(t_idx):
            t = truth[i]
            for b, j in enumerate(r_idx):
                r = run[j]
                df = abs(r.frame - t.frame)
                if df > window_frames:
                    continue
                dist_m = _distance_m(t, r)
                if gate_m is not None and dist_m > gate_m:
                    continue
                if links is not None and t.track >= 0 and r.track >= 0:
                    if not links.linked(str(t.track), str(r.track), t.frame - window_frames, t.frame + window_frames):
                        continue
                # the distance only breaks ties between equal frame differences
                cost[a, b] = df + 1e-3 * min(dist_m, 100.0)
        rows, cols = gated_assignment(cost, window_frames + 1.0)
        matched.extend((t_idx[a], r_idx[b]) for a, b in zip(rows.tolist(), cols.tolist()))
    return matched


def _clusters(truth: Sequence[Event], run: Sequence[Event], window_frames: int):
    """Yield (truth indices, run indices) of groups no pair can cross.

    Walking all events in frame order, a gap of more than ``window_frames``
    between neighbours separates events that can never match, so each group
    is solved on its own and the cost matrices stay small on long recordings.
    """
    merged = sorted([(e.frame, 0, i) for i, e in enumerate(truth)] + [(e.frame, 1, j) for j, e in enumerate(run)])
    group: tuple[list[int], list[int]] = ([], [])
    last_frame = None
    for frame, side, k in merged:
        if last_frame is not None and frame - last_frame > window_frames:
            if group[0] and group[1]:
                yield group
            group = ([], [])
        group[side].append(k)
        last_frame = frame
    if group[0] and group[1]:
        yield group


def _distance_m(a: Event, b: Event) -> float:
    return math.hypot(a.x - b.x, a.y - b.y)


def _brief(e: Event) -> dict[str, Any]:
    return {"kind": e.kind, "frame": e.frame, "stamp_ns": e.stamp_ns, "track": e.track, "x": e.x, "y": e.y}
