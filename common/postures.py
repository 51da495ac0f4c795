"""The posture vocabulary: the names a person's posture takes everywhere.

One tuple, in one order, for the wire (``TrackState.posture``), the track
files, the ground truth and the posture estimator.
:data:`BODY_POSTURES` are the shapes a body takes; :data:`UNKNOWN` is what
a track reports before its posture has been read.
"""

from __future__ import annotations

UNKNOWN = "unknown"
"""A track whose posture has not been read yet."""

POSTURES: tuple[str, ...] = ("standing", "sitting", "lying", "bending", UNKNOWN)
"""Every posture name: the wire's and the track files' vocabulary."""

BODY_POSTURES: tuple[str, ...] = tuple(p for p in POSTURES if p != UNKNOWN)
"""The postures a body takes (all but :data:`UNKNOWN`), in :data:`POSTURES` order:
what the synthetic people are labelled with and what the estimator reports."""
