"""Enrolled residents: is the name on a track the right person's?

A run names the tracks of an enrolled resident (the ``person`` column of its
tracks file). Against a truth in which the resident is one known person
id, over the CLEAR-MOT matches (:func:`~evaluation.tracking.clear_mot`):

* ``false_named``: matched pairs whose run track carries the resident's name
  while the truth person is someone else: a false resident identity (the
  target is zero: a visitor must never be taken for the resident);
* ``named_unmatched``: run rows carrying the name that match no truth person;
* ``resident_matched``, ``resident_named``: the resident's matched pairs, and
  those whose track carries the name; ``named_ratio`` is their ratio (None
  when the resident was never matched).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from evaluation.io import TrackTable
from evaluation.tracking import Matches, ratio

COUNTS = ("named_rows", "false_named", "named_unmatched", "resident_matched", "resident_named")


def resident_scores(truth: TrackTable, run: TrackTable, pairs: Matches, *, person: str, name: str) -> dict[str, Any]:
    """The counts above for the resident ``name``, truth person id ``person``; ``pairs`` are the
    matches of :func:`~evaluation.tracking.clear_mot` on the same tables."""
    named = run.person == name
    t_rows, r_rows = pairs.truth_row, pairs.run_row
    is_resident = truth.track_id[t_rows] == str(person)
    pair_named = named[r_rows]
    matched = np.zeros(len(run), dtype=bool)
    matched[r_rows] = True
    return summary({
        "person": str(person),
        "name": name,
        "named_rows": int(np.count_nonzero(named)),
        "false_named": int(np.count_nonzero(pair_named & ~is_resident)),
        "named_unmatched": int(np.count_nonzero(named & ~matched)),
        "resident_matched": int(np.count_nonzero(is_resident)),
        "resident_named": int(np.count_nonzero(pair_named & is_resident)),
    })


def summary(counts: dict[str, Any]) -> dict[str, Any]:
    """``counts`` with ``named_ratio`` added."""
    return {**counts, "named_ratio": ratio(counts["resident_named"], counts["resident_matched"])}


def totals(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Summed counts of several recordings' :func:`resident_scores` (one resident)."""
    return summary({"person": results[0]["person"], "name": results[0]["name"],
                    **{k: sum(r[k] for r in results) for k in COUNTS}})
