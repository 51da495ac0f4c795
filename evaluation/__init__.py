"""Scoring a run against ground truth: tracking, events and posture.

Typical use::

    from evaluation import evaluate, format_table, suite_table
    results = evaluate("scenarios/fall_kitchen", "runs/fall_kitchen")
    print(format_table(results))

* :mod:`~evaluation.io`: the tracks CSV and events JSON-lines formats;
* :mod:`~evaluation.tracking`: CLEAR-MOT (MOTA, MOTP, ID switches,
  fragmentations, MT/PT/ML), identity measures (IDF1, IDP, IDR) and the
  per-frame MOTME, MOTV, missed and artifact tracks per frame;
* :mod:`~evaluation.events`: precision, recall, F1 per event kind with a
  +-30-frame window, fall delays, false alarms per hour;
* :mod:`~evaluation.posture`: posture accuracy and confusion matrix;
* :mod:`~evaluation.report`: :func:`evaluate`, console tables, JSON;
* :mod:`~evaluation.plots`: plan view, posture timeline and mask
  overlay pictures (needs the ``plots`` extra for the first two).
"""

from evaluation.events import ALARM_KINDS, WINDOW_FRAMES, EventScores, TrackLinks, score_events
from evaluation.io import (
    POSTURES,
    SCORED_KINDS,
    EvalFormatError,
    Event,
    TrackTable,
    read_events,
    read_tracks,
    write_events,
    write_tracks,
)
from evaluation.posture import PostureResult, posture_scores
from evaluation.report import evaluate, format_table, suite_table, suite_totals, to_json, write_json
from evaluation.tracking import Matches, PerFrameResult, TrackingResult, clear_mot, per_frame_measures

__all__ = [
    "ALARM_KINDS",
    "POSTURES",
    "SCORED_KINDS",
    "WINDOW_FRAMES",
    "EvalFormatError",
    "Event",
    "EventScores",
    "Matches",
    "PostureResult",
    "PerFrameResult",
    "TrackLinks",
    "TrackTable",
    "TrackingResult",
    "clear_mot",
    "evaluate",
    "format_table",
    "posture_scores",
    "read_events",
    "read_tracks",
    "score_events",
    "per_frame_measures",
    "suite_table",
    "suite_totals",
    "to_json",
    "write_events",
    "write_json",
    "write_tracks",
]
