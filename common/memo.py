"""A per-process memo of large read-only results, bounded in bytes.

:class:`BytesMemo` keeps values under hashable keys, the least recently used going first once
the values together take more than its bound (the newest is always kept). Thread-safe. The
camera's pixel rays and the renderer's view of the empty room use it: both are computed again and
again for the same camera by every renderer of a run.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Callable, Hashable


class BytesMemo:
    """``get(key, make, size)``: the kept value of ``key``, or ``make()`` kept under it (``size(value)``
    its bytes); at most ``max_bytes`` kept."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self._values: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: Hashable, make: Callable[[], Any], size: Callable[[Any], int]) -> Any:
        with self._lock:
            hit = self._values.get(key)
            if hit is not None:
                self._values.move_to_end(key)
                return hit[0]
        value = make()   # outside the lock: two threads may both make it, and keep one
        n = int(size(value))
        with self._lock:
            if key not in self._values:
                self._values[key] = (value, n)
                self._bytes += n
            while self._bytes > self.max_bytes and len(self._values) > 1:
                _, (_, dropped) = self._values.popitem(last=False)
                self._bytes -= dropped
            return self._values[key][0]   # the newest is never the one dropped
