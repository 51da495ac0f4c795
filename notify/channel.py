"""Delivery channels and the thread that drains the outbox into each.

A channel (MQTT, one webhook, e-mail) knows how to hand one event to its
receiver and says how it went with an :class:`Outcome`: ``delivered`` (the
receiver confirmed: a PUBACK, a 2xx answer, the SMTP server took the
message), ``retry`` (a passing fault: broker away, 5xx, timeout, connection
refused) or ``give_up`` (the receiver refused it for good: a 4xx answer other
than 408/429, a mail address refused). ``deliver`` never raises for an
expected fault.

A :class:`Dispatcher` (one thread per channel) takes the channel's due
deliveries from the :class:`~notify.outbox.Outbox`, oldest first,
hands them over while the channel is ready, and writes each outcome back;
the outbox does the back-off. Its log says each problem once when it starts
(``webhook http://hub/hook: HTTP 500; retrying ...``), again at most once a
minute while it lasts, and once when deliveries go through again; a refused
event is one line each.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal

from common.messages import Event
from notify.outbox import Outbox

log = logging.getLogger("voxelwatch.notify")

REPEAT_S = 60.0
"""A problem that lasts is logged again at most this often."""


@dataclass(frozen=True)
class Outcome:
    """How one delivery attempt went; ``reason`` in words for the log; ``retry_after_s``: the
    receiver asked for this wait (HTTP Retry-After)."""

    kind: Literal["delivered", "retry", "give_up"]
    reason: str = ""
    retry_after_s: float | None = None


DELIVERED = Outcome("delivered")


class Channel:
    """Base of the delivery channels: ``name`` keys its rows in the outbox, ``label`` names it
    in the log, ``kinds`` are the event kinds it takes."""

    name: str = ""
    label: str = ""
    kinds: frozenset[str] = frozenset()

    def start(self, wake: Callable[[], None]) -> None:
        """Begin connecting (if the channel keeps a connection); call ``wake`` when it becomes ready."""

    def ready(self) -> bool:
        """Whether an attempt could succeed now (an MQTT channel waits for its broker)."""
        return True

    def deliver(self, event: Event, context: Mapping[str, str]) -> Outcome:
        raise NotImplementedError

    def close(self) -> None:
        """Stop connecting and close the connection."""


class Dispatcher:
    """The thread that feeds one channel from the outbox until ``stop`` is set."""

    def __init__(self, channel: Channel, outbox: Outbox, stop: threading.Event, *,
                 clock: Callable[[], int] = time.time_ns) -> None:
        self.channel = channel
        self.outbox = outbox
        self.stop = stop
        self.clock = clock
        self.wake = threading.Event()
        self.attempts_failed = 0
        self.given_up = 0
        self.delivered = 0
        self._streak = 0
        self._warned = -REPEAT_S
        self._thread = threading.Thread(target=self._run, name=f"notify-{channel.label}"[:15], daemon=True)

    def start(self) -> None:
        self.channel.start(self.wake.set)
        self._thread.start()

    def join(self, timeout_s: float = 10.0) -> None:
        self.wake.set()
        self._thread.join(timeout_s)

    def alive(self) -> bool:
        return self._thread.is_alive()

    # ------------------------------------------------------------------ the loop

    def _run(self) -> None:
        while not self.stop.is_set():
            self.wake.clear()
            if not self.channel.ready():
                self.wake.wait(1.0)
                continue
            now = self.clock()
            batch = self.outbox.due(self.channel.name, now)
            for item in batch:
                if self.stop.is_set() or not self.channel.ready():
                    break
                self._attempt(item.event, item.context, item.attempts)
            if batch:
                continue
            nxt = self.outbox.next_due_ns(self.channel.name)
            wait = 1.0 if nxt is None else min(1.0, max(0.02, (nxt - self.clock()) * 1e-9))
            self.wake.wait(wait)

    def _attempt(self, event: Event, context: Mapping[str, str], attempts: int) -> None:
        label = self.channel.label
        try:
            outcome = self.channel.deliver(event, context)
        except Exception as exc:  # noqa: BLE001 - a fault of ours must not stop the channel
            log.exception("%s: delivering %s failed unexpectedly", label, event.id)
            outcome = Outcome("retry", f"{type(exc).__name__}: {exc}")
        now = self.clock()
        if outcome.kind == "delivered":
            self.outbox.delivered(event.id, self.channel.name, now)
            self.delivered += 1
            if self._streak:
                log.info("%s: delivering again after %d failed attempts", label, self._streak)
            self._streak = 0
            log.info("%s: delivered %s %s%s", label, event.kind, event.id,
                     f" ({outcome.reason})" if outcome.reason else "")
        elif outcome.kind == "give_up":
            self.outbox.give_up(event.id, self.channel.name, now, outcome.reason)
            self.given_up += 1
            log.warning("%s: gave up %s %s: %s (not retried)", label, event.kind, event.id, outcome.reason)
        else:
            wait = self.outbox.retry(event.id, self.channel.name, now, outcome.reason, after_s=outcome.retry_after_s)
            self.attempts_failed += 1
            self._streak += 1
            text = (f"{outcome.reason}; {event.kind} {event.id} stays in the outbox, next attempt in {wait:.0f} s "
                    f"(attempt {attempts + 1}; back-off up to {self.outbox.retry_max_s:.0f} s)")
            mono = time.monotonic()
            if self._streak == 1 or mono - self._warned >= REPEAT_S:
                more = f" (still failing: {self._streak} attempts in a row)" if self._streak > 1 else ""
                log.warning("%s: %s%s", label, text, more)
                self._warned = mono
