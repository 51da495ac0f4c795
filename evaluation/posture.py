"""Posture accuracy over matched truth/run pairs, with a confusion matrix.

Every frame in which the tracking association matched a truth person to a
run track (CLEAR-MOT pairs, 0.5 m) gives one posture pair. Pairs whose truth
posture is ``unknown`` are left out of the accuracies (there is nothing to be
right about) but stay in the confusion matrix; a run that says ``unknown``
about a known truth posture is wrong.

* strict: the run posture equals the truth posture;
* lenient: ``bending`` and ``standing`` count as one posture on both sides,
  for pipelines that cannot tell a bent-over person from a standing one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from evaluation.io import POSTURES, TrackTable
from evaluation.tracking import Matches, ratio

LENIENT_SAME: dict[str, str] = {"bending": "standing"}


@dataclass(frozen=True)
class PostureResult:
    """Posture counts; ``confusion`` (P, P) int64, rows truth, columns run, in ``labels`` order."""

    labels: tuple[str, ...]
    confusion: np.ndarray
    scored: int
    strict_correct: int
    lenient_correct: int

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
        }


def posture_scores(truth: TrackTable, run: TrackTable, matches: Matches) -> PostureResult:
    """Accuracies and confusion of the run's postures over the matched pairs."""
    t_post = truth.posture[matches.truth_row] if len(matches) else np.zeros(0, dtype=str)
    r_post = run.posture[matches.run_row] if len(matches) else np.zeros(0, dtype=str)
    return posture_from_labels(t_post, r_post)


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
