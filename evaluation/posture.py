"""Posture accuracy over matched truth/run pairs, with a confusion matrix.

Every frame in which the tracking association matched a truth person to a
run track (CLEAR-MOT pairs, 0.5 m) gives one posture pair. Pairs whose truth
posture is ``unknown`` are left out of the accuracies (there is nothing to be
right about) but stay in the confusion matrix; a run that says ``unknown``
about a known truth posture is wrong.

* strict: the run posture equals the truth posture;
* lenient: ``bending`` and ``standing`` count as one posture on both sides,
  for pipelines that cannot tell a bent-over person from a standing one.

And the false lying markers a carer would see: spells in which a run track
reads ``lying`` on every frame while matched to a truth person who is not
lying (standing, sitting or bending), longer than :data:`FALSE_LYING_MIN_S`
from the spell's first frame to its last (a frame the track is not matched,
or reads another posture, ends the spell).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from evaluation.io import POSTURES, TrackTable
from evaluation.tracking import Matches, ratio

LENIENT_SAME: dict[str, str] = {"bending": "standing"}
FALSE_LYING_MIN_S = 2.0
"""A lying marker shown this long, seconds, for someone who is not lying, counts as a false one."""


@dataclass(frozen=True)
class PostureResult:
    """Posture counts; ``confusion`` (P, P) int64, rows truth, columns run, in ``labels`` order."""

    labels: tuple[str, ...]
    confusion: np.ndarray
    scored: int
    strict_correct: int
    lenient_correct: int
    false_lying_spells: int = 0
    false_lying_s: float = 0.0

    @property
    def pairs(self) -> int:
        return int(self.confusion.sum())

    @property
    def strict_accuracy(self) -> float | None:
        return ratio(self.strict_correct, self.scored)

    @property
    def lenient_accuracy(self) -> float | None:
        return ratio(self.lenient_correct, self.scored)

    def recall_by_truth(self) -> dict[str, float | None]:
        """Strict share of each known truth posture that the run got right."""
        out = {}
        for k, label in enumerate(self.labels):
            if label != "unknown":
                out[label] = ratio(int(self.confusion[k, k]), int(self.confusion[k].sum()))
        return out

    def summary(self) -> dict[str, Any]:
        return {
            "pairs": self.pairs,
            "scored": self.scored,
            "strict_correct": self.strict_correct,
            "lenient_correct": self.lenient_correct,
            "strict_accuracy": self.strict_accuracy,
            "lenient_accuracy": self.lenient_accuracy,
            "recall_by_truth": self.recall_by_truth(),
            "labels": list(self.labels),
            "confusion": self.confusion.astype(int).tolist(),
            "false_lying_spells": self.false_lying_spells,
            "false_lying_s": self.false_lying_s,
        }


def posture_scores(truth: TrackTable, run: TrackTable, matches: Matches) -> PostureResult:
    """Accuracies and confusion of the run's postures over the matched pairs."""
    t_post = truth.posture[matches.truth_row] if len(matches) else np.zeros(0, dtype=str)
    r_post = run.posture[matches.run_row] if len(matches) else np.zeros(0, dtype=str)
    spells, seconds = false_lying(truth, run, matches)
    return dataclasses.replace(posture_from_labels(t_post, r_post), false_lying_spells=spells,
                               false_lying_s=seconds)


def false_lying(truth: TrackTable, run: TrackTable, matches: Matches,
                min_s: float = FALSE_LYING_MIN_S) -> tuple[int, float]:
    """(spells, their seconds in all): the run's ``lying`` spells longer than ``min_s`` on people who
    were not lying (see the module text). Durations from the run's own stamps."""
    if not len(matches):
        return 0, 0.0
    false_row = np.zeros(len(run), dtype=bool)
    wrong = (run.posture[matches.run_row] == "lying") & np.isin(
        truth.posture[matches.truth_row], ("standing", "sitting", "bending"))
    false_row[matches.run_row[wrong]] = True
    spells, seconds = 0, 0.0
    for tid in np.unique(run.track_id[false_row]):
        rows = np.flatnonzero(run.track_id == tid)
        rows = rows[np.argsort(run.frame[rows], kind="stable")]
        flags = false_row[rows]
        # spells: runs of flagged rows over consecutive frames of the track
        breaks = np.flatnonzero(~flags[1:] | ~flags[:-1] | (np.diff(run.frame[rows]) != 1)) + 1
        for part in np.split(np.arange(len(rows)), breaks):
            if not len(part) or not flags[part[0]]:
                continue
            span_s = (run.stamp_ns[rows[part[-1]]] - run.stamp_ns[rows[part[0]]]) * 1e-9
            if span_s > min_s:
                spells += 1
                seconds += float(span_s)
    return spells, round(seconds, 3)


def posture_from_labels(truth_postures: np.ndarray, run_postures: np.ndarray) -> PostureResult:
    """Same as :func:`posture_scores` from two (M,) str arrays of paired postures."""
    t = np.asarray(truth_postures, dtype=str)
    r = np.asarray(run_postures, dtype=str)
    if t.shape != r.shape:
        raise ValueError(f"truth_postures and run_postures differ in shape: {t.shape} vs {r.shape}")
    index = {label: k for k, label in enumerate(POSTURES)}
    for name, arr in (("truth_postures", t), ("run_postures", r)):
        bad = sorted(set(arr.tolist()) - set(POSTURES))
        if bad:
            raise ValueError(f"{name} holds unknown postures {bad}; expected {list(POSTURES)}")
    confusion = np.zeros((len(POSTURES), len(POSTURES)), dtype=np.int64)
    if t.size:
        np.add.at(confusion, (np.array([index[v] for v in t]), np.array([index[v] for v in r])), 1)
    known = t != "unknown"
    lenient_t = np.array([LENIENT_SAME.get(v, v) for v in t], dtype=str)
    lenient_r = np.array([LENIENT_SAME.get(v, v) for v in r], dtype=str)
    return PostureResult(
        labels=POSTURES,
        confusion=confusion,
        scored=int(known.sum()),
        strict_correct=int((known & (t == r)).sum()),
        lenient_correct=int((known & (lenient_t == lenient_r)).sum()),
    )
