"""The notifier process: zenoh in, the outbox in the middle, channels out.

* Subscribes, as a reader, to ``<p>/events/**``, ``<p>/tracks`` and
  ``<p>/status``. The callbacks only enqueue: events into a bounded inbox
  (drop-oldest, counted: the history query brings a dropped alarm back),
  tracks and status as the newest one only.
* On start, and then every :data:`HISTORY_EVERY_S`, it queries
  ``<p>/history/events/**`` for the chosen kinds since the newest event it
  had before the previous query (:data:`FIRST_LOOKBACK_S` back on the very
  first start), so alarms published while it was down, or while its zenoh
  link was, are delivered too. The outbox's key on the event id makes an
  event heard both ways one delivery per channel.
* :class:`Notifier` (the logic, fed with messages and the time) writes each
  event of a channel's kinds into the outbox once per channel, with the
  person's name and the place as heard, and turns tracks and camera status
  into MQTT states. One :class:`~notify.channel.Dispatcher` thread per
  channel drains the outbox.
* Every :data:`STATUS_EVERY_S` one log line per channel: delivered, pending
  and failed.

:func:`build_channels` reads the site's ``[notify]`` section (secrets from
their files) and stops start-up with one line naming the field on a problem.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common import keys, messages
from common.messages import Event
from notify.channel import Channel, Dispatcher
from notify.mail import EmailChannel
from notify.mqtt import MqttChannel
from notify.outbox import Outbox
from notify.people import CameraStates, PeopleState, place_at, zones_of
from notify.webhook import WebhookChannel
from common.ratelog import RateLimitedLog
from common.site import Site, SiteError

log = logging.getLogger("voxelwatch.notify")

STATUS_EVERY_S = 60.0
HISTORY_EVERY_S = 60.0
FIRST_LOOKBACK_S = 600.0
"""On its very first start (an empty outbox) the notifier asks the history this far back."""
HISTORY_TIMEOUT_S = 10.0
INBOX_EVENTS = 10_000
PRUNE_EVERY_S = 3600.0
STOP_WAIT_S = 3.0
"""On SIGTERM, how long the channels may finish an attempt under way."""


def build_channels(site: Site) -> list[Channel]:
    """The channels of the site's ``[notify]`` section; SiteError naming the field on a problem
    (a secret file missing or empty, a TLS authority missing, no channel at all)."""
    n = site.notify
    where = f"site file {site.source}"
    default = frozenset(n.kinds)
    channels: list[Channel] = []
    if n.mqtt is not None:
        m = n.mqtt
        password = site.secret(m.password, m.password_file, "notify.mqtt.password_file")
        tls_ca = ""
        if m.tls_ca:
            tls_ca = str(site.resolve(m.tls_ca))
            if not Path(tls_ca).is_file():
                raise SiteError(f"{where}: field notify.mqtt.tls_ca: file {tls_ca} not found")
        channels.append(MqttChannel(
            host=m.host, port=m.port, username=m.username, password=password, tls_ca=tls_ca,
            topic_prefix=m.topic_prefix or keys.default_prefix(site.name), discovery=m.discovery,
            discovery_prefix=m.discovery_prefix, kinds=frozenset(m.kinds) if m.kinds is not None else default,
            site=site.name, utc_offset_hours=site.utc_offset_hours, retry_max_s=n.retry_max_s))
    urls = [w.url for w in n.webhooks]
    for i, w in enumerate(n.webhooks):
        if urls.index(w.url) != i:
            raise SiteError(f"{where}: field notify.webhooks[{i}].url: {w.url} is listed twice")
        channels.append(WebhookChannel(w.url, kinds=frozenset(w.kinds) if w.kinds is not None else default,
                                       headers=w.headers, timeout_s=w.timeout_s))
    if n.email is not None:
        e = n.email
        password = site.secret(e.password, e.password_file, "notify.email.password_file")
        if e.username and not password:
            raise SiteError(f"{where}: field notify.email.password: a username is set but no password "
                            "(password or password_file)")
        channels.append(EmailChannel(
            host=e.host, port=e.port, security=e.security, username=e.username, password=password, sender=e.sender,
            to=e.to, kinds=frozenset(e.kinds) if e.kinds is not None else default, site=site.name,
            utc_offset_hours=site.utc_offset_hours))
    if not channels:
        raise SiteError(f"{where}: field notify: no channel to deliver to: add [notify.mqtt], "
                        "[[notify.webhooks]] or [notify.email]")
    return channels


def open_outbox(site: Site, path: Path) -> Outbox:
    """The outbox file at ``path`` with the back-off of the site's ``[notify]`` section (ValueError
    naming the file when it cannot be opened)."""
    return Outbox(path, retry_max_s=site.notify.retry_max_s)


class Notifier:
    """What the notifier does with each message, given the time; no zenoh, no threads."""

    def __init__(self, site: Site, outbox: Outbox, channels: Sequence[Channel],
                 wake: Callable[[str], None] = lambda name: None) -> None:
        self.site = site
        self.outbox = outbox
        self.channels = list(channels)
        self.wake = wake
        self.zones = zones_of(site)
        self.people = PeopleState(self.zones, forget_s=site.identity.reid_window_s)
        self.cameras = CameraStates()
        self.mqtt = next((c for c in self.channels if isinstance(c, MqttChannel)), None)
        self.kinds = sorted(set().union(*(c.kinds for c in self.channels)))
        self.heard = 0
        self.kept = 0

    def on_event(self, event: Event, now_ns: int) -> list[str]:
        """Keep ``event`` for each channel that takes its kind; the channels it is new for."""
        self.heard += 1
        names = [c.name for c in self.channels if event.kind in c.kinds]
        if not names:
            return []
        person = self.people.name_of(event.track) if event.track >= 0 else None
        context = {"person": person or "",
                   "place": place_at(event.x, event.y, self.zones) if event.track >= 0 else ""}
        new = self.outbox.add(event, names, now_ns, context)
        if new:
            self.kept += 1
            labels = {c.name: c.label for c in self.channels}
            log.info("alarm %s %s kept for %s", event.kind, event.id, ", ".join(labels[n] for n in new))
        for name in new:
            self.wake(name)
        return new

    def on_tracks(self, frame: messages.TrackFrame, now_ns: int) -> None:
        changed = self.people.update(frame, now_ns)
        if self.mqtt is not None:
            for state in changed:
                self.mqtt.publish_person(state)
            for pid in self.people.forgotten:
                self.mqtt.forget_person(pid)

    def on_status(self, status: messages.Status) -> None:
        changed = self.cameras.update(status)
        if self.mqtt is not None:
            for cam, state in changed.items():
                self.mqtt.publish_camera(cam, state)

    def status_line(self) -> str:
        """``notify: <channel> delivered n, pending n, failed n; ...; events heard n, kept n``."""
        counts = self.outbox.counts([c.name for c in self.channels])
        parts = []
        for c in self.channels:
            k = counts[c.name]
            ready = "" if c.ready() else " (not ready)"
            parts.append(f"{c.label}{ready}: delivered {k['delivered']}, pending {k['pending']}, failed {k['failed']}")
        return f"notify: {'; '.join(parts)}; events heard {self.heard}, kept {self.kept}"


@dataclass
class _Latest:
    """The newest payload of one key (tracks, status): older ones are of no use."""

    payload: bytes | None = None


def run(session: Any, notifier: Notifier, stop: threading.Event, *, status_every_s: float = STATUS_EVERY_S,
        history_every_s: float = HISTORY_EVERY_S, clock: Callable[[], int] = time.time_ns) -> int:
    """Serve on an open zenoh session until ``stop`` is set (the caller closes the session)."""
    p = notifier.site.prefix
    wake = threading.Event()
    lock = threading.Lock()
    inbox: deque[bytes] = deque()
    dropped = [0]
    tracks, status = _Latest(), _Latest()
    bad = RateLimitedLog(log, 60.0)

    def on_event(sample) -> None:
        with lock:
            if len(inbox) >= INBOX_EVENTS:
                inbox.popleft()
                dropped[0] += 1
            inbox.append(sample.payload.to_bytes())
        wake.set()

    def keep(latest: _Latest) -> Callable:
        def callback(sample) -> None:
            with lock:
                latest.payload = sample.payload.to_bytes()
            wake.set()
        return callback

    subs = [session.declare_subscriber(keys.events_wildcard(p), on_event),
            session.declare_subscriber(keys.tracks_key(p), keep(tracks)),
            session.declare_subscriber(keys.status_key(p), keep(status))]
    newest = notifier.outbox.newest_stamp_ns()
    since = newest if newest is not None else clock() - int(FIRST_LOOKBACK_S * 1e9)
    next_history = 0.0
    next_status = time.monotonic() + status_every_s
    next_prune = 0.0
    log.info("notify: listening on %s for %s; delivering through %s", p, ", ".join(notifier.kinds),
             ", ".join(c.label for c in notifier.channels))
    try:
        while not stop.is_set():
            mono = time.monotonic()
            if mono >= next_history:
                since = _catch_up(session, notifier, since, clock, bad)
                next_history = time.monotonic() + history_every_s
            wake.wait(0.5)
            wake.clear()
            with lock:
                events = list(inbox)
                inbox.clear()
                frame, report = tracks.payload, status.payload
                tracks.payload = status.payload = None
            for payload in events:
                try:
                    event = messages.decode_event(payload)
                except messages.WireError as exc:
                    bad.warn("notify", "event", f"unreadable event: {exc}", time.monotonic())
                    continue
                notifier.on_event(event, clock())
            if frame is not None:
                try:
                    notifier.on_tracks(messages.decode(frame, messages.TrackFrame), clock())
                except messages.WireError as exc:
                    bad.warn("notify", "tracks", f"unreadable tracks: {exc}", time.monotonic())
            if report is not None:
                try:
                    notifier.on_status(messages.decode(report, messages.Status))
                except messages.WireError as exc:
                    bad.warn("notify", "status", f"unreadable status: {exc}", time.monotonic())
            if dropped[0]:
                log.warning("notify: %d events dropped from a full inbox (the history query brings alarms back)",
                            dropped[0])
                dropped[0] = 0
            mono = time.monotonic()
            if mono >= next_status:
                log.info("%s", notifier.status_line())
                next_status = mono + status_every_s
            if mono >= next_prune:
                notifier.outbox.prune(clock())
                next_prune = mono + PRUNE_EVERY_S
    finally:
        for sub in subs:
            sub.undeclare()
    return 0


def _catch_up(session: Any, notifier: Notifier, since_ns: int, clock: Callable[[], int],
              bad: RateLimitedLog) -> int:
    """Ask the history for the chosen kinds since ``since_ns``; keep what comes back. The next
    query's start: the newest event kept when this one began (so nothing missed in between)."""
    start = notifier.outbox.newest_stamp_ns()
    selector = (f"{keys.history_key(notifier.site.prefix)}/**?since={max(0, since_ns)};"
                f"kind={','.join(notifier.kinds)};limit=1000")
    got = failed = 0
    try:
        replies = list(session.get(selector, timeout=HISTORY_TIMEOUT_S))
    except Exception as exc:  # noqa: BLE001 - zenoh reports every failure as ZError
        bad.warn("notify", "history", f"history query failed: {exc}", time.monotonic())
        return since_ns
    for reply in replies:
        if reply.ok is None:
            failed += 1
            bad.warn("notify", "history", f"history query refused: {reply.err.payload.to_string()[:200]}",
                     time.monotonic())
            continue
        try:
            event = messages.decode_event(reply.ok.payload.to_bytes())
        except messages.WireError as exc:
            bad.warn("notify", "history", f"unreadable history reply: {exc}", time.monotonic())
            continue
        got += 1
        notifier.on_event(event, clock())
    if got:
        log.info("notify: the history query since %d returned %d events", since_ns, got)
    if failed:
        return since_ns
    return max(since_ns, start) if start is not None else since_ns


def run_forever(site: Site, *, outbox_path: Path, make_config: Callable[[], Any], endpoints: Sequence[str],
                channels: Sequence[Channel], status_every_s: float = STATUS_EVERY_S) -> int:
    """Open the outbox and the zenoh session, start the channels, :func:`run` until SIGINT/SIGTERM.

    Returns 0 after a stop, 1 when the zenoh session cannot be opened, 2 when the outbox
    cannot be opened (logged)."""
    from common.shell import serve

    try:
        outbox = open_outbox(site, outbox_path)
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    stop = threading.Event()
    dispatchers: dict[str, Dispatcher] = {}
    notifier = Notifier(site, outbox, channels, wake=lambda name: dispatchers[name].wake.set())
    try:
        for channel in channels:
            if isinstance(channel, MqttChannel):
                channel.confirm = lambda event_id, name=channel.name: outbox.delivered(event_id, name, time.time_ns())
            dispatchers[channel.name] = Dispatcher(channel, outbox, stop)
        counts = outbox.counts([c.name for c in channels])
        log.info("notify: outbox %s (%s)", outbox_path,
                 ", ".join(f"{c.label}: {counts[c.name]['pending']} pending" for c in channels))
        for dispatcher in dispatchers.values():
            dispatcher.start()
        return serve(make_config, who="notify", endpoints=endpoints, log=log, stop=stop,
                     work=lambda session, stop: run(session, notifier, stop, status_every_s=status_every_s))
    finally:
        stop.set()
        deadline = time.monotonic() + STOP_WAIT_S
        for dispatcher in dispatchers.values():
            dispatcher.join(max(0.0, deadline - time.monotonic()))
        busy = [d.channel.label for d in dispatchers.values() if d.alive()]
        log.info("%s", notifier.status_line().replace("notify: ", "notify: stopping; ", 1))
        if busy:  # its attempt is cut short: the delivery stays pending in the outbox
            log.info("notify: not waiting for the attempt under way at %s", ", ".join(busy))
        for channel in channels:
            channel.close()
        if not busy:
            outbox.close()
