"""A log that repeats itself at most once per period, counting what it held back.

A flood of broken messages must not turn into a flood of log lines, and the
line that does go out says how many like it were held back since the last.
Time is passed in (monotonic seconds), so the behaviour can be driven by a
test's own clock.
"""

from __future__ import annotations

import logging
import math

__all__ = ["RateLimitedLog"]


class RateLimitedLog:
    """At most one warning per ``(subject, reason)`` every ``period_s`` seconds.

    logger: where the lines go. period_s: the shortest time between two lines
    of one subject and reason.
    """

    def __init__(self, logger: logging.Logger, period_s: float) -> None:
        if not (isinstance(period_s, (int, float)) and math.isfinite(period_s) and period_s > 0):
            raise ValueError(f"period_s must be a positive number of seconds, got {period_s!r}")
        self.logger = logger
        self.period_s = float(period_s)
        self._last: dict[tuple[str, str], tuple[float, int]] = {}

    def warn(self, subject: str, reason: str, text: str, mono: float) -> bool:
        """Log ``"<subject>: <text>"`` unless a line of this subject and reason went out
        less than ``period_s`` before ``mono``; returns whether it was logged."""
        last, held = self._last.get((subject, reason), (-math.inf, 0))
        if mono - last < self.period_s:
            self._last[(subject, reason)] = (last, held + 1)
            return False
        more = f" ({held} more since the last report)" if held else ""
        self.logger.warning("%s: %s%s", subject, text, more)
        self._last[(subject, reason)] = (mono, 0)
        return True
