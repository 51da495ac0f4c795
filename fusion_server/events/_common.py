"""Small helpers the event detectors share: seconds to nanoseconds, a plain
median, and the checks their parameter groups run once, in ``__post_init__``."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Iterable


def ns(seconds: float) -> int:
    """Seconds as integer nanoseconds (rounded)."""
    return int(round(float(seconds) * 1e9))


def median(values: list[float]) -> float:
    """Median of a non-empty list (mean of the middle two for an even count)."""
    v = sorted(values)
    n = len(v)
    return float(v[n // 2]) if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def is_number(value: Any) -> bool:
    """A finite int or float (bools are not numbers here)."""
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


def positive(params: Any, *names: str) -> None:
    """Check that each named field of ``params`` is a finite number above 0, and store it as float."""
    for name in names:
        value = getattr(params, name)
        if not (is_number(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value!r}")
        object.__setattr__(params, name, float(value))


def non_negative(params: Any, *names: str) -> None:
    """Check that each named field of ``params`` is a finite number >= 0, and store it as float."""
    for name in names:
        value = getattr(params, name)
        if not (is_number(value) and value >= 0):
            raise ValueError(f"{name} must be a number >= 0, got {value!r}")
        object.__setattr__(params, name, float(value))


def fraction(params: Any, *names: str) -> None:
    """Check that each named field of ``params`` lies strictly between 0 and 1, and store it as float."""
    for name in names:
        value = getattr(params, name)
        if not (is_number(value) and 0 < value < 1):
            raise ValueError(f"{name} must lie in (0, 1), got {value!r}")
        object.__setattr__(params, name, float(value))


def names(params: Any, name: str, allowed: Iterable[str] | None = None) -> None:
    """Check that the named field of ``params`` is a collection of strings (out of ``allowed``,
    when given), and store it as a frozenset."""
    value = getattr(params, name)
    try:
        items = frozenset(value) if not isinstance(value, str) else None
    except TypeError:
        items = None
    if items is None or not all(isinstance(v, str) for v in items):
        raise ValueError(f"{name} must be a collection of names, got {value!r}")
    value = items
    if allowed is not None and not value <= frozenset(allowed):
        raise ValueError(f"{name} may hold {', '.join(repr(a) for a in allowed)}, got {sorted(value)}")
    object.__setattr__(params, name, value)


def rekey(states: dict, renames: Mapping[int, int]) -> dict:
    """``states`` (track id -> state) with the ids in ``renames`` ({old: new}) renamed at once."""
    return {renames.get(k, k): v for k, v in states.items()}
