"""The shared start of workers replaying recordings in step: one stamp in a file.

Workers replaying several cameras of one recording (the demo, a soak, a
replay over processes) must stamp frame ``i`` of every camera alike, so they
are given one start stamp. A stamp fixed at launch is a guess at how long the
slowest worker takes to get ready (opening its source, learning the
background); one that guessed short makes the late workers join after the
recording's first frames. Instead the launcher starts the workers with a
start file (``--start-file``); each gets ready, says so (its liveliness
token), then waits for the file; the launcher writes the stamp once every
worker is ready. A worker started when the file is already there (restarted
after a crash) reads it at once and joins the shared clock at the frame for
now.

The file holds one integer, nanoseconds since the Unix epoch, and is written
whole (a temporary file renamed over it), so a reader never sees half of it.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

__all__ = ["read_start", "wait_start", "write_start"]


def write_start(path: str | Path, start_ns: int) -> None:
    """Write the shared start ``start_ns`` to ``path`` in one step."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(f"{int(start_ns)}\n")
    os.replace(tmp, path)


def read_start(path: str | Path) -> int | None:
    """The stamp in ``path``; None while there is no file. Raises ValueError naming the file when
    it cannot be read or holds anything but one non-negative integer."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:   # a folder, no permission, not text
        raise ValueError(f"start file {path}: cannot be read ({exc.__class__.__name__}: {exc})") from None
    try:
        value = int(text.strip())
    except ValueError:
        raise ValueError(f"start file {path}: expected one integer (ns since the epoch), got {text.strip()[:40]!r}") from None
    if value < 0:
        raise ValueError(f"start file {path}: the start must not be negative, got {value}")
    return value


def wait_start(path: str | Path, stop: threading.Event, poll_s: float = 0.02) -> int | None:
    """Wait until ``path`` holds the shared start and return it; None when ``stop`` is set first."""
    while not stop.is_set():
        value = read_start(path)
        if value is not None:
            return value
        stop.wait(poll_s)
    return None
