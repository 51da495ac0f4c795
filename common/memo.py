"""Memos of large read-only results: per process, bounded in bytes, and optionally shared on disk.

:class:`BytesMemo` keeps values under hashable keys, the least recently used going first once
the values together take more than its bound (the newest is always kept). Thread-safe. The
camera's pixel rays and the renderer's view of the empty room use it: both are computed again and
again for the same camera by every renderer of a run.

:func:`kept_on_disk` shares such a result between processes: with :data:`MEMO_DIR_ENV` set to a
folder, the first process to need it computes it and writes it there (a temporary file, then a
rename, so a reader never sees half a file), and the others read it back bit for bit. The demo's
camera workers, or the processes of a test run, each render the same room through the same
camera; without the variable every process computes its own.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import threading
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Hashable

import numpy as np

MEMO_DIR_ENV = "VOXELWATCH_MEMO_DIR"
"""The environment variable naming the folder of :func:`kept_on_disk` (unset or empty: none)."""


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


def kept_on_disk(name: str, key: Hashable, make: Callable[[], Any], pack: Callable[[Any], dict[str, np.ndarray]],
                 unpack: Callable[[dict[str, np.ndarray]], Any]) -> Any:
    """``make()``, or what an earlier ``make()`` of the same ``name`` and ``key`` left in the folder named
    by :data:`MEMO_DIR_ENV` (file ``<folder>/<name>/<digest of repr(key)>.npz``; ``pack`` turns the value
    into named arrays, ``unpack`` back; the arrays come back read-only). ``repr(key)`` must say everything
    the value depends on. A file that cannot be read is made again and replaced."""
    folder = os.environ.get(MEMO_DIR_ENV, "")
    if not folder:
        return make()
    digest = hashlib.blake2b(repr(key).encode("utf-8"), digest_size=20).hexdigest()
    path = Path(folder) / name / f"{digest}.npz"
    try:
        with np.load(path, allow_pickle=False) as stored:
            arrays = {k: stored[k] for k in stored.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        pass   # none yet, or one that cannot be read (another version, a full disk): made again below
    else:
        for array in arrays.values():
            array.setflags(write=False)
        return unpack(arrays)
    value = make()
    part = path.with_name(f"{path.stem}.{os.getpid()}.{threading.get_ident()}.part")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(part, "wb") as f:
            np.savez(f, **pack(value))
        os.replace(part, path)
    except OSError:   # a full or read-only disk costs only the time to make it again
        with contextlib.suppress(OSError):
            part.unlink()
    return value
