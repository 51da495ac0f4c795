"""Local time of day from Unix-epoch stamps, and the words a visit's reason uses for it."""

from __future__ import annotations

from typing import Sequence

DEFAULT_MEALS: tuple[tuple[str, float, float], ...] = (
    ("for breakfast", 6.0, 10.0),
    ("for lunch", 11.5, 14.0),
    ("for tea", 15.0, 17.5),
    ("for dinner", 17.5, 21.5),
)
"""(label, first local hour, end local hour) of each meal window."""


def local_hour(stamp_ns: int, utc_offset_h: float = 0.0) -> float:
    """Local time of day in hours [0, 24) of a Unix-epoch ``stamp_ns``."""
    seconds = stamp_ns / 1e9 + utc_offset_h * 3600.0
    return (seconds % 86400.0) / 3600.0


def time_of_day_label(hour: float, meals: Sequence[tuple[str, float, float]] = DEFAULT_MEALS) -> str:
    """Meal label for a local hour, or a part of the day outside the meal windows."""
    h = float(hour) % 24.0
    for label, start, end in meals:
        if start <= h < end:
            return label
    if 5.0 <= h < 12.0:
        return "in the morning"
    if 12.0 <= h < 17.0:
        return "in the afternoon"
    if 17.0 <= h < 22.0:
        return "in the evening"
    return "at night"
