"""Small helpers the event detectors share: seconds to nanoseconds, a plain
median, and the field options of their parameter groups' numbers."""

from __future__ import annotations

from collections.abc import Mapping


def ns(seconds: float) -> int:
    """Seconds as integer nanoseconds (rounded)."""
    return int(round(float(seconds) * 1e9))


def median(values: list[float]) -> float:
    """Median of a non-empty list (mean of the middle two for an even count)."""
    v = sorted(values)
    n = len(v)
    return float(v[n // 2]) if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


NUMBER = {"strict": True, "allow_inf_nan": False}
"""Field options of a detector's number: a finite int or float (no text, no bool), held as
given (ints of float fields as floats): ``hold_s: float = Field(2.0, ge=0, **NUMBER)``."""


def rekey(states: dict, renames: Mapping[int, int]) -> dict:
    """``states`` (track id -> state) with the ids in ``renames`` ({old: new}) renamed at once."""
    return {renames.get(k, k): v for k, v in states.items()}
