"""The fusion server's process adapter: zenoh in, ``FusionPipeline.step`` in the middle, zenoh out.

:func:`run` is the only part that talks to zenoh or reads the clock; every
decision about voxels, people and events is made by
:class:`fusion_server.pipeline.FusionPipeline`. :func:`run_forever` opens the
session from the site's ``[zenoh]`` section (plus command-line overrides),
turns SIGINT/SIGTERM into a clean stop and always closes the session.

What :func:`run` does:

* **masks** (``<p>/cam/*/mask``): the subscriber callback only puts
  ``(key, bytes, receive time)`` into a bounded inbox (drop-oldest, counted).
  The main loop decodes each message (``WireError``, ``MaskCodecError``, a
  message whose ``cam`` differs from its key's camera, or a mask whose aspect
  ratio is not the camera's, are counted per camera as ``undecodable`` with a
  log line at most once per ``log_every_s`` per camera and reason), drops
  messages of cameras the site does not know (counted), and pushes the rest
  into a :class:`~fusion_server.sync.FrameSynchroniser` (lattice period from
  the slowest camera's fps). Each released frame set with at least
  ``min_cameras`` cameras waits in a queue of at most ``max_ready_sets``;
  beyond that the oldest set is dropped and counted (``frame_sets_dropped``),
  so a slow pipeline never makes memory grow. The frame number passed to
  ``step`` is the most common sequence number in the set.
* **tracks**: one :class:`~common.messages.TrackFrame` per fused frame on
  ``<p>/tracks`` (congestion control DROP).
* **events**: each event is first added to the
  :class:`~fusion_server.event_store.EventStore` (committed), then published
  as JSON text on ``<p>/events/<kind>/<track>`` (BLOCK, reliable), and
  written to ``events.jsonl`` when ``out_dir`` is set. An event whose id is
  already stored is not published again.
* **holds**: per camera, :class:`~common.messages.HoldRegions` on
  ``<p>/cam/<cam>/hold`` whenever the boxes change (by more than
  ``hold_slack_px`` on some side, or in number) and at least every
  ``hold_ttl_ms / 2`` while there are any; an empty list when they end.
  They are sent only after fused frames: when fusion stops, holds lapse.
* **liveliness**: the token ``<p>/alive/fusion``; a liveliness subscriber on
  ``<p>/alive/cam/*`` (with history). A camera whose token goes away is
  ``lost`` (a ``camera_lost`` event) and ``camera_back`` when it returns;
  the synchroniser goes on releasing sets without it.
* **clock skew**: per camera, the median of ``stamp_ns - receive time`` over
  the last ``skew_window`` masks; beyond ``max_clock_skew_ms`` the camera is
  ``skewed`` in the status and one ``clock_skew`` event is emitted; the mark
  clears once the median is back under 80 % of the threshold. Apart from
  that, a mask whose ``stamp_ns - receive time`` runs more than
  ``max_clock_skew_ms`` ahead of the other live cameras' newest masks is
  left out of the frame sets (counted ``late``, logged): one camera with a
  fast clock would otherwise push the synchroniser ahead and make every
  other camera's masks look stale.
* **status** on ``<p>/status`` every ``status_period_s``.
* **history**: a queryable on ``<p>/history/events/**`` (which includes
  ``<p>/history/events`` itself), declared only once the store is open.
  Queries are answered on a separate thread (the store is thread-safe), one
  reply per event: JSON text by default, msgpack with ``format=msgpack``; a
  bad selector gets ``reply_err`` with the reason. Every query is finalised
  (``with query:``). Each reply goes on ``<p>/history/events/<event id>`` when
  the query's key covers it: zenoh's default consolidation keeps only the
  last reply per key, so ``z_get -s '<p>/history/events/**?kind=fall'``
  prints every event, while a get on exactly ``<p>/history/events`` (all
  replies on that one key) needs consolidation ``NONE`` to see them all.
* ``exit_after_idle_s``: after the first mask, stop (exit 0) once no mask
  has arrived for that long, fusing the sets still pending first.

Per-camera counters in the status: ``received`` (masks that decoded),
``undecodable``, ``dropped`` (sequence gaps -- frames the camera, the network
or the inbox lost -- plus duplicates, superseded frames and synchroniser
overflow), ``late`` (out of order, stale, off the frame lattice, or stamped ahead of
the other cameras),
``rate_hz`` (masks per second over the last two seconds), ``latency_ms``
(mean receive time minus capture stamp; on one host this is the transport
and worker latency, across hosts it includes the clock offset),
``clock_offset_ms`` (median capture stamp minus receive time: the camera
clock's lead, less the latency), ``last_seen_ns`` (server time of the last
mask), ``state``: ``lost`` (its liveliness token went away, or no sign of
life at all), ``skewed``, ``degraded`` (no mask for ``stale_s``, or
undecodable masks within ``stale_s``), else ``ok``.
"""

from __future__ import annotations

import logging
import math
import queue
import signal
import statistics
import threading
import time
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from common import keys, maskcodec, messages
from common.camera import Camera
from common.maskcodec import MaskCodecError
from common.messages import (
    CameraStatus,
    Event,
    HoldRegions,
    MaskFrame,
    Status,
    TrackFrame,
    TrackState,
    WireError,
)
from common.site import Site, load_site
from fusion_server.event_store import EventStore, parse_history_selector
from fusion_server.events import EventRecord
from fusion_server.outputs import RunOutputs, plain_value
from fusion_server.sync import FrameSet, FrameSynchroniser

__all__ = ["DEFAULT_STORE_NAME", "FusionSettings", "FusionCounters", "run", "run_forever"]

log = logging.getLogger("voxelwatch.fusion")

DEFAULT_STORE_NAME = "voxelwatch-events.sqlite"
"""The event store's file name next to the site file when ``--store`` is not given."""

_FLAGS = {"min_cameras": "--min-cameras", "exit_after_idle_s": "--exit-after-idle",
          "max_clock_skew_ms": "--max-clock-skew-ms", "mode": "--mode"}
_SYNC_DROPS = ("duplicate", "superseded", "dropped_overflow")
_SYNC_LATE = ("out_of_order", "stale", "unmatched")


@dataclass(frozen=True)
class FusionSettings:
    """Everything :func:`run` needs; :meth:`from_args` builds it from the command line.

    site: the loaded site. prefix: the zenoh key prefix. store_path: the
    SQLite event store. out_dir: where tracks.csv/events.jsonl go (None: no
    files). mode/listen/connect: zenoh overrides of the site (None: the
    site's). cache_dir: carving lookup-table cache (None: the carver's
    default). min_cameras: fewest cameras a frame set needs (None: the
    site's carving vote). exit_after_idle_s: stop after this long without
    masks (None: never). The rest tune the adapter (see the module doc).
    """

    site: Site
    prefix: str
    store_path: Path
    out_dir: Path | None = None
    mode: str | None = None
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] | None = None
    cache_dir: Path | None = None
    min_cameras: int | None = None
    exit_after_idle_s: float | None = None
    seed: int = 0
    status_period_s: float = 1.0
    hold_ttl_ms: int = 2000
    hold_slack_px: int = 2
    max_clock_skew_ms: float = 250.0
    skew_window: int = 30
    inbox_per_camera: int = 32
    max_ready_sets: int = 4
    sync_buffer: int = 8
    stale_s: float = 2.0
    log_every_s: float = 10.0
    history_queue: int = 16

    def __post_init__(self) -> None:
        keys.validate_prefix(self.prefix)
        n_cams = len(self.site.cameras)
        if self.min_cameras is not None and (isinstance(self.min_cameras, bool) or not 1 <= self.min_cameras <= n_cams):
            raise ValueError(f"min_cameras must be an int in 1..{n_cams} (the site's cameras), got {self.min_cameras!r}")
        if self.exit_after_idle_s is not None and not (math.isfinite(self.exit_after_idle_s) and self.exit_after_idle_s > 0):
            raise ValueError(f"exit_after_idle_s must be a positive number of seconds, got {self.exit_after_idle_s!r}")
        for name in ("status_period_s", "max_clock_skew_ms", "stale_s", "log_every_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if isinstance(self.hold_slack_px, bool) or not isinstance(self.hold_slack_px, int) or self.hold_slack_px < 0:
            raise ValueError(f"hold_slack_px must be an int >= 0, got {self.hold_slack_px!r}")
        for name in ("hold_ttl_ms", "skew_window", "inbox_per_camera", "max_ready_sets", "sync_buffer", "history_queue"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if self.mode is not None and self.mode not in ("peer", "client", "router"):
            raise ValueError(f"mode must be peer, client or router, got {self.mode!r}")

    @classmethod
    def from_args(cls, args: Any) -> "FusionSettings":
        """Settings from parsed ``voxelwatch-fusion`` arguments. A bad site file raises its
        :class:`~common.site.SiteError` (a ValueError), any other bad value a ValueError."""
        site_path = Path(args.site)
        site = load_site(site_path)
        prefix = args.prefix or site.prefix
        try:
            keys.validate_prefix(prefix)
        except ValueError as exc:
            raise ValueError(f"--prefix: {exc}") from None
        store = Path(args.store) if args.store is not None else site_path.resolve().parent / DEFAULT_STORE_NAME
        extra = {}
        skew = getattr(args, "max_clock_skew_ms", None)
        if skew is not None:
            extra["max_clock_skew_ms"] = skew
        try:
            return cls(
                site=site,
                prefix=prefix,
                store_path=store,
                out_dir=Path(args.out) if args.out is not None else None,
                mode=args.mode,
                listen=tuple(args.listen) if args.listen is not None else None,
                connect=tuple(args.connect) if args.connect is not None else None,
                cache_dir=Path(args.cache_dir) if args.cache_dir is not None else None,
                min_cameras=args.min_cameras,
                exit_after_idle_s=args.exit_after_idle,
                **extra,
            )
        except ValueError as exc:
            text = str(exc)
            for name, flag in _FLAGS.items():
                if text.startswith(name + " "):
                    text = flag + text[len(name):]
            raise ValueError(text) from None


@dataclass
class FusionCounters:
    """What the server has done since it started (also logged at exit)."""

    frames_fused: int = 0
    events: int = 0
    events_not_stored: int = 0
    events_unpublishable: int = 0
    frame_sets_dropped: int = 0
    frame_sets_too_few: int = 0
    inbox_dropped: int = 0
    unknown_camera: int = 0
    pipeline_errors: int = 0
    queries: int = 0
    queries_refused: int = 0


def run_forever(settings: FusionSettings) -> int:
    """Build the pipeline, open the zenoh session and :func:`run` until stopped.

    Returns the exit code: 0 after a stop (signal or idle), 1 when the zenoh
    session cannot be opened, 2 when the calibrations, zenoh settings, event
    store or output folder are unusable (the reason is logged).
    """
    from common.transport import zenoh_config
    from fusion_server.pipeline import FusionPipeline

    try:
        cameras = settings.site.load_cameras()
        pipeline = FusionPipeline.from_site(settings.site, cameras=cameras, cache_dir=settings.cache_dir,
                                            seed=settings.seed, min_cameras=settings.min_cameras)
        conf = zenoh_config(settings.site.zenoh, mode=settings.mode, listen=settings.listen,
                            connect=settings.connect)
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt:  # interrupted while the lookup tables were being built
        log.info("fusion: interrupted before start")
        return 130
    stop = threading.Event()
    previous = _install_signal_handlers(stop)
    try:
        try:
            session = zenoh.open(conf)
        except Exception as exc:  # noqa: BLE001 - zenoh reports every failure as ZError
            log.error("cannot open the zenoh session: %s", exc)
            return 1
        try:
            return run(session, settings, stop, pipeline=pipeline)
        finally:
            session.close()
    finally:
        _restore_signal_handlers(previous)


def run(session: Any, settings: FusionSettings, stop_event: threading.Event, *, pipeline: Any = None,
        counters: FusionCounters | None = None) -> int:
    """Serve on an open zenoh ``session`` until ``stop_event`` is set (or the idle timeout).

    pipeline: a ``FusionPipeline`` (default: built from the site). The caller
    owns and closes the session. Returns 0 on a normal stop, 2 when the event
    store or the output folder cannot be opened.
    """
    if pipeline is None:
        from fusion_server.pipeline import FusionPipeline

        pipeline = FusionPipeline.from_site(settings.site, cache_dir=settings.cache_dir, seed=settings.seed,
                                            min_cameras=settings.min_cameras)
    try:
        store = EventStore(settings.store_path)
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    outputs = None
    try:
        if settings.out_dir is not None:
            outputs = RunOutputs(settings.out_dir)
    except ValueError as exc:
        log.error("%s", exc)
        store.close()
        return 2
    server = _Server(session, settings, pipeline, store, outputs, counters or FusionCounters(), stop_event)
    try:
        server.declare()
        return server.loop()
    finally:
        server.close()
        if outputs is not None:
            outputs.close()
        store.close()


# --------------------------------------------------------------------------- the loop


@dataclass
class _CameraHealth:
    """One camera as the server sees it (see the module doc for the meaning of each counter)."""

    cam: str
    window: int
    received: int = 0
    undecodable: int = 0
    seq_gaps: int = 0
    ahead: int = 0
    last_seq: int | None = None
    last_seen_ns: int = 0
    last_mono: float | None = None
    last_bad_mono: float | None = None
    token: bool | None = None  # None: no liveliness news yet
    lost: bool = False
    skewed: bool = False
    arrivals: deque = field(default_factory=lambda: deque(maxlen=256))
    latency_ms: deque = field(init=False)
    offset_ms: deque = field(init=False)

    def __post_init__(self) -> None:
        self.latency_ms = deque(maxlen=self.window)
        self.offset_ms = deque(maxlen=self.window)

    def on_mask(self, seq: int, stamp_ns: int, recv_ns: int, mono: float) -> None:
        self.received += 1
        if self.last_seq is not None and seq > self.last_seq + 1:
            self.seq_gaps += seq - self.last_seq - 1
        self.last_seq = seq  # a restarted worker starts again from 0: no gap is counted
        self.last_seen_ns = recv_ns
        self.last_mono = mono
        self.arrivals.append(mono)
        self.latency_ms.append((recv_ns - stamp_ns) / 1e6)
        self.offset_ms.append((stamp_ns - recv_ns) / 1e6)

    def rate_hz(self, mono: float, span_s: float = 2.0) -> float:
        recent = [t for t in self.arrivals if mono - t <= span_s]
        if len(recent) < 2 or recent[-1] <= recent[0]:
            return 0.0
        return (len(recent) - 1) / (recent[-1] - recent[0])

    def median_offset_ms(self) -> float | None:
        return statistics.median(self.offset_ms) if self.offset_ms else None

    def state(self, mono: float, stale_s: float) -> str:
        recent = self.last_mono is not None and mono - self.last_mono <= stale_s
        if self.lost or (self.token is not True and not recent):
            return "lost"
        if self.skewed:
            return "skewed"
        if not recent or (self.last_bad_mono is not None and mono - self.last_bad_mono <= stale_s):
            return "degraded"
        return "ok"


class _Inbox:
    """Bounded drop-oldest queue filled by zenoh callbacks; ``wake`` is set on every put."""

    def __init__(self, maxlen: int, wake: threading.Event) -> None:
        self._items: deque = deque()
        self._lock = threading.Lock()
        self.maxlen = maxlen
        self.dropped = 0
        self.wake = wake

    def put(self, item: Any) -> None:
        with self._lock:
            if len(self._items) >= self.maxlen:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
        self.wake.set()

    def drain(self) -> list:
        with self._lock:
            items = list(self._items)
            self._items.clear()
        return items


class _RateLimitedLog:
    """At most one line per (subject, reason) every ``period_s``, with the count suppressed meanwhile."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._last: dict[tuple[str, str], tuple[float, int]] = {}

    def warn(self, subject: str, reason: str, text: str, mono: float) -> None:
        last, suppressed = self._last.get((subject, reason), (-math.inf, 0))
        if mono - last >= self.period_s:
            more = f" ({suppressed} more since the last report)" if suppressed else ""
            log.warning("%s: %s%s", subject, text, more)
            self._last[(subject, reason)] = (mono, 0)
        else:
            self._last[(subject, reason)] = (last, suppressed + 1)


class _HistoryResponder:
    """Answers history queries on its own thread; the queryable callback only hands them over."""

    def __init__(self, store: EventStore, prefix: str, utc_offset_h: float, maxsize: int,
                 counters: FusionCounters) -> None:
        self.store = store
        self.key = keys.history_key(prefix)
        self.utc_offset_h = utc_offset_h
        self.counters = counters
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="history", daemon=True)
        self._thread.start()

    def offer(self, query: Any) -> None:
        """The queryable callback: queue the query, or refuse it at once when the queue is full."""
        if self._stopping.is_set():
            with query:
                query.reply_err("voxelwatch history: the fusion server is stopping")
            return
        try:
            self._queue.put_nowait(query)
        except queue.Full:
            self.counters.queries_refused += 1
            with query:
                query.reply_err("voxelwatch history: too many queries waiting, try again")

    def close(self) -> None:
        self._stopping.set()
        self._thread.join(timeout=10)
        while True:
            try:
                query = self._queue.get_nowait()
            except queue.Empty:
                break
            with query:
                query.reply_err("voxelwatch history: the fusion server is stopping")

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                query = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                with query:
                    self._answer(query)
            except Exception as exc:  # noqa: BLE001 - a failed reply must not end the thread
                log.warning("history query failed: %s", exc)

    def _answer(self, query: Any) -> None:
        self.counters.queries += 1
        try:
            flt = parse_history_selector(str(query.parameters), utc_offset_h=self.utc_offset_h)
            records = self.store.query_filter(flt)
        except ValueError as exc:
            query.reply_err(str(exc), encoding="text/plain")
            return
        asked = zenoh.KeyExpr(str(query.key_expr))
        for rec in records:
            try:
                msg = _wire_event(rec)
            except WireError as exc:
                log.warning("history: stored event %s cannot be sent: %s", rec.id, exc)
                continue
            key = self._reply_key(asked, rec.id)
            if flt.format == "msgpack":
                query.reply(key, messages.encode(msg), encoding=messages.MSGPACK_ENCODING)
            else:
                query.reply(key, msg.to_json(), encoding=messages.JSON_ENCODING)

    def _reply_key(self, asked: Any, event_id: str) -> str:
        """``<p>/history/events/<id>`` when the query covers it (its own key per event survives
        zenoh's default consolidation, which keeps one reply per key), else the history key."""
        try:
            key = f"{self.key}/{keys.validate_chunk(event_id, 'event id')}"
            if asked.intersects(zenoh.KeyExpr(key)):
                return key
        except (ValueError, zenoh.ZError):
            pass
        return self.key


class _Server:
    """State of :func:`run`: the declared zenoh entities, the synchroniser, the per-camera health."""

    def __init__(self, session: Any, settings: FusionSettings, pipeline: Any, store: EventStore,
                 outputs: RunOutputs | None, counters: FusionCounters, stop: threading.Event) -> None:
        self.session = session
        self.s = settings
        self.pipeline = pipeline
        self.store = store
        self.outputs = outputs
        self.c = counters
        self.stop = stop
        self.prefix = settings.prefix
        site = settings.site
        self.camera_ids: tuple[str, ...] = tuple(site.camera_ids)
        self.cameras: dict[str, Camera] = dict(getattr(pipeline, "cameras", {}) or {})
        self.min_cameras = int(settings.min_cameras if settings.min_cameras is not None else pipeline.min_cameras)
        fps = min(spec.fps for spec in site.cameras)
        self.sync = FrameSynchroniser(camera_ids=self.camera_ids, fps=fps, max_buffer=settings.sync_buffer)
        self.health = {cam: _CameraHealth(cam, settings.skew_window) for cam in self.camera_ids}
        self.wake = threading.Event()
        self.masks = _Inbox(settings.inbox_per_camera * len(self.camera_ids), self.wake)
        self.alive = _Inbox(1024, self.wake)
        self.ready: deque[FrameSet] = deque()
        self.rlog = _RateLimitedLog(settings.log_every_s)
        self.holds_sent: dict[str, tuple[list, float]] = {cam: ([], -math.inf) for cam in self.camera_ids}
        self.last_frame = 0
        self.last_stamp: tuple[int, int] | None = None  # (stamp_ns of the last fused set, server time_ns then)
        self.first_mask_mono: float | None = None
        self.last_mask_mono: float | None = None
        self._entities: list[Any] = []
        self._event_pubs: OrderedDict[str, Any] = OrderedDict()
        self._history: _HistoryResponder | None = None
        self._next_status = 0.0

    # ------------------------------------------------------------------ zenoh entities

    def declare(self) -> None:
        p = self.prefix
        self.tracks_pub = self._keep(self.session.declare_publisher(
            keys.tracks_key(p), encoding=messages.MSGPACK_ENCODING, congestion_control=zenoh.CongestionControl.DROP))
        self.status_pub = self._keep(self.session.declare_publisher(
            keys.status_key(p), encoding=messages.MSGPACK_ENCODING, congestion_control=zenoh.CongestionControl.DROP))
        self.hold_pubs = {cam: self._keep(self.session.declare_publisher(
            keys.hold_key(p, cam), encoding=messages.MSGPACK_ENCODING,
            congestion_control=zenoh.CongestionControl.DROP)) for cam in self.camera_ids}
        # the store is open (run() opened it) before anyone can ask it anything
        self._history = _HistoryResponder(self.store, p, self.s.site.utc_offset_hours, self.s.history_queue, self.c)
        self._keep(self.session.declare_queryable(f"{keys.history_key(p)}/**", self._history.offer))
        self._keep(self.session.liveliness().declare_subscriber(
            keys.alive_cameras_wildcard(p), self._on_alive, history=True))
        self._keep(self.session.declare_subscriber(keys.mask_wildcard(p), self._on_mask))
        self._keep(self.session.liveliness().declare_token(keys.alive_fusion_key(p)))
        log.info("fusion: site %s, cameras %s, prefix %s, store %s%s", self.s.site.name, ", ".join(self.camera_ids),
                 p, self.s.store_path, f", files in {self.s.out_dir}" if self.s.out_dir else "")

    def _keep(self, entity: Any) -> Any:
        self._entities.append(entity)
        return entity

    def close(self) -> None:
        if self._history is not None:
            self._history.close()
        for entity in reversed(self._entities + list(self._event_pubs.values())):
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001 - the session may already be closing
                pass
        self._entities.clear()
        self._event_pubs.clear()

    # callbacks: enqueue only
    def _on_mask(self, sample: Any) -> None:
        payload = sample.payload
        n = len(payload)
        data = payload.to_bytes() if n <= MaskFrame.MAX_BYTES else n  # oversize: never copied
        self.masks.put((str(sample.key_expr), data, time.time_ns(), time.monotonic()))

    def _on_alive(self, sample: Any) -> None:
        self.alive.put((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

    # ------------------------------------------------------------------ main loop

    def loop(self) -> int:
        while not self.stop.is_set():
            self.wake.wait(0.0 if self.ready else 0.05)
            self.wake.clear()
            mono = time.monotonic()
            for key, present in self.alive.drain():
                self._on_liveliness(key, present)
            for key, data, recv_ns, arrived in self.masks.drain():
                self._take_mask(key, data, recv_ns, arrived)
            self.c.inbox_dropped = self.masks.dropped
            if self.ready:
                self._fuse(self.ready.popleft())
            mono = time.monotonic()
            if mono >= self._next_status:
                self._publish_status(mono)
                self._next_status = mono + self.s.status_period_s
            if self._idle(mono):
                log.info("fusion: no mask for %.1f s: finishing", self.s.exit_after_idle_s)
                self._finish()
                break
        self._publish_status(time.monotonic())
        log.info("fusion stopped: %s", self.summary())
        return 0

    def _idle(self, mono: float) -> bool:
        return (self.s.exit_after_idle_s is not None and self.last_mask_mono is not None
                and mono - self.last_mask_mono >= self.s.exit_after_idle_s)

    def _finish(self) -> None:
        """Fuse whatever is still pending (the tail of a recording)."""
        for fs in self.sync.flush():
            self._queue_set(fs)
        while self.ready:
            self._fuse(self.ready.popleft())

    # ------------------------------------------------------------------ masks

    def _take_mask(self, key: str, data: bytes | int, recv_ns: int, mono: float) -> None:
        if self.first_mask_mono is None:
            self.first_mask_mono = mono
        self.last_mask_mono = mono
        try:
            cam = keys.camera_of(key, self.prefix)
        except ValueError:
            cam = None
        health = self.health.get(cam) if cam is not None else None
        if health is None:
            self.c.unknown_camera += 1
            self.rlog.warn(f"mask on {key}", "unknown", "camera is not in the site: dropped "
                           f"(cameras: {', '.join(self.camera_ids)})", mono)
            return
        try:
            if isinstance(data, int):
                raise WireError(f"MaskFrame: payload of {data} bytes exceeds the {MaskFrame.MAX_BYTES}-byte limit")
            msg = messages.decode(data, MaskFrame)
            if msg.cam != cam:
                raise _Mismatch(f"MaskFrame says camera {msg.cam!r} but came on {cam!r}'s key")
            self._check_shape(msg)
            mask = maskcodec.decode_mask(msg.data, msg.codec, msg.width, msg.height)
        except (WireError, MaskCodecError) as exc:
            health.undecodable += 1
            health.last_bad_mono = mono
            reason = type(exc).__name__
            self.rlog.warn(f"camera {cam}", reason, f"undecodable mask dropped: {exc}", mono)
            return
        health.on_mask(msg.seq, msg.stamp_ns, recv_ns, mono)
        self._check_skew(health, mono)
        lead_ms = self._lead_ms(health, mono)
        if lead_ms is not None and lead_ms > self.s.max_clock_skew_ms:
            health.ahead += 1
            self.rlog.warn(f"camera {cam}", "ahead", f"mask {msg.seq} is stamped {lead_ms:.0f} ms ahead of the "
                           f"other cameras: left out of the frame sets (its clock runs fast)", mono)
            return
        count = self.sync.counters[cam]
        before = dict(count)
        for fs in self.sync.push(cam, msg.seq, msg.stamp_ns, mask):
            self._queue_set(fs)
        for name in _SYNC_DROPS + _SYNC_LATE:
            if count[name] > before[name]:
                self.rlog.warn(f"camera {cam}", name, f"a mask was dropped by the frame-set synchroniser "
                               f"({name.replace('_', ' ')}; on arrival of mask {msg.seq})", mono)

    def _lead_ms(self, health: _CameraHealth, mono: float) -> float | None:
        """How far the newest mask's stamp runs ahead of the other cameras' clocks, in ms: its
        ``stamp - receive time`` less the median of the same for the other live cameras' newest
        masks (newest against newest, so that recordings played faster than real time, where
        every camera's stamps run ahead alike, compare equal). None when no other camera has
        sent masks lately."""
        others = [h.offset_ms[-1] for h in self.health.values()
                  if h is not health and not h.lost and h.offset_ms and h.last_mono is not None
                  and mono - h.last_mono <= self.s.stale_s]
        if not others or not health.offset_ms:
            return None
        return health.offset_ms[-1] - statistics.median(others)

    def _check_shape(self, msg: MaskFrame) -> None:
        cam = self.cameras.get(msg.cam)
        if cam is None:
            return
        expected_w = msg.height * cam.width / cam.height
        if abs(msg.width - expected_w) > 1.0 + 0.01 * expected_w:
            raise _Shape(f"MaskFrame: a {msg.width}x{msg.height} mask does not have the {cam.width}x{cam.height} "
                         f"aspect of camera {msg.cam!r}")

    def _queue_set(self, fs: FrameSet) -> None:
        if len(fs.payloads) < self.min_cameras:
            self.c.frame_sets_too_few += 1
            return
        self.ready.append(fs)
        while len(self.ready) > self.s.max_ready_sets:
            self.ready.popleft()
            self.c.frame_sets_dropped += 1

    # ------------------------------------------------------------------ fusion and outputs

    def _fuse(self, fs: FrameSet) -> None:
        frame = Counter(fs.seqs.values()).most_common(1)[0][0]
        try:
            fused = self.pipeline.step(fs.payloads, fs.stamp_ns, frame)
        except Exception as exc:  # noqa: BLE001 - one bad frame set must not stop the server
            self.c.pipeline_errors += 1
            if self.c.pipeline_errors == 1:
                log.exception("fusion: frame %d could not be fused", frame)
            else:
                self.rlog.warn("fusion", "step", f"frame {frame} could not be fused: {exc!r}", time.monotonic())
            return
        self.c.frames_fused += 1
        self.last_frame = int(fused.frame)
        self.last_stamp = (int(fused.stamp_ns), time.time_ns())
        tracks = [t for t in fused.tracks if all(math.isfinite(float(v)) for v in (t.x, t.y, t.z_top))]
        self._publish_tracks(fused, tracks)
        if self.outputs is not None:
            self.outputs.write_frame(fused.frame, fused.stamp_ns, tracks)
        for rec in fused.events:
            self._emit(rec)
        self._publish_holds(fused)

    def _publish_tracks(self, fused: Any, tracks: list) -> None:
        try:
            msg = TrackFrame(frame=int(fused.frame), stamp_ns=int(fused.stamp_ns),
                             tracks=[_track_state(t) for t in tracks][: messages.MAX_TRACKS],
                             cameras=list(dict.fromkeys(fused.cameras)))
            self.tracks_pub.put(messages.encode(msg))
        except (ValueError, WireError) as exc:
            self.rlog.warn("fusion", "tracks", f"tracks of frame {fused.frame} not published: {exc}", time.monotonic())

    def _publish_holds(self, fused: Any) -> None:
        mono = time.monotonic()
        for cam in self.camera_ids:
            boxes = _clean_boxes(fused.holds.get(cam, []))
            last, sent_mono = self.holds_sent[cam]
            due = bool(boxes) and mono - sent_mono >= self.s.hold_ttl_ms / 2000.0
            if not due and _same_boxes(boxes, last, self.s.hold_slack_px):
                continue
            try:
                msg = HoldRegions(cam=cam, stamp_ns=int(fused.stamp_ns), boxes=boxes, ttl_ms=self.s.hold_ttl_ms)
                self.hold_pubs[cam].put(messages.encode(msg))
            except (ValueError, WireError) as exc:
                self.rlog.warn(f"camera {cam}", "hold", f"hold regions not published: {exc}", mono)
                continue
            self.holds_sent[cam] = (boxes, mono)

    def _emit(self, rec: EventRecord) -> None:
        """Store (committed), then publish, then write one event."""
        try:
            if not self.store.add(rec):
                log.debug("event %s is already stored: not published again", rec.id)
                return
        except ValueError as exc:
            self.c.events_not_stored += 1
            log.error("event %s could not be stored (publishing it anyway): %s", rec.id, exc)
        self.c.events += 1
        log.info("event %s: track %d at (%.2f, %.2f) %s", rec.kind, rec.track, rec.x, rec.y, rec.details or "")
        try:
            msg = _wire_event(rec)
            self._event_publisher(rec.kind, rec.track).put(msg.to_json())
        except (ValueError, WireError) as exc:
            self.c.events_unpublishable += 1
            log.error("event %s could not be published: %s", rec.id, exc)
        if self.outputs is not None:
            self.outputs.write_event(rec)

    def _event_publisher(self, kind: str, track: int) -> Any:
        key = keys.event_key(self.prefix, kind, int(track))
        pub = self._event_pubs.get(key)
        if pub is None:
            pub = self.session.declare_publisher(
                key, encoding=messages.JSON_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE)
            self._event_pubs[key] = pub
            while len(self._event_pubs) > 32:
                _, old = self._event_pubs.popitem(last=False)
                old.undeclare()
        else:
            self._event_pubs.move_to_end(key)
        return pub

    # ------------------------------------------------------------------ camera health

    def _event_time(self) -> tuple[int, int]:
        """(stamp_ns, frame) for an event not tied to a frame set: the capture clock of the
        last fused set carried forward by the server's elapsed time; the server's clock before any."""
        now = time.time_ns()
        if self.last_stamp is None:
            return now, self.last_frame
        stamp, then = self.last_stamp
        return stamp + max(0, now - then), self.last_frame

    def _on_liveliness(self, key: str, present: bool) -> None:
        try:
            cam = keys.camera_of(key, self.prefix)
        except ValueError:
            return
        health = self.health.get(cam)
        if health is None:
            log.info("liveliness: camera %s is not in the site; ignored", cam)
            return
        had_token = health.token
        health.token = present
        if not present and had_token and not health.lost:
            health.lost = True
            log.warning("camera %s lost (its liveliness token went away); tracking with the others", cam)
            stamp, frame = self._event_time()
            self._emit(self.pipeline.camera_event("camera_lost", cam, stamp, frame))
        elif present and health.lost:
            health.lost = False
            log.info("camera %s is back", cam)
            stamp, frame = self._event_time()
            self._emit(self.pipeline.camera_event("camera_back", cam, stamp, frame))
        elif present and had_token is None:
            log.info("camera %s is alive", cam)

    def _check_skew(self, health: _CameraHealth, mono: float) -> None:
        if len(health.offset_ms) < min(10, health.offset_ms.maxlen):
            return
        offset = health.median_offset_ms()
        limit = self.s.max_clock_skew_ms
        if not health.skewed and abs(offset) > limit:
            health.skewed = True
            log.warning("camera %s: clock off by %.0f ms (median of its last %d masks; limit %.0f ms)",
                        health.cam, offset, len(health.offset_ms), limit)
            stamp, frame = self._event_time()
            self._emit(self.pipeline.camera_event("clock_skew", health.cam, stamp, frame,
                                                  offset_ms=round(offset, 1), max_ms=float(limit)))
        elif health.skewed and abs(offset) < 0.8 * limit:
            health.skewed = False
            log.info("camera %s: clock back in step (offset %.0f ms)", health.cam, offset)

    # ------------------------------------------------------------------ status

    def status(self, mono: float) -> Status:
        cams = []
        for cam in self.camera_ids:
            h = self.health[cam]
            sc = self.sync.counters[cam]
            offset = h.median_offset_ms()
            cams.append(CameraStatus(
                cam=cam,
                state=h.state(mono, self.s.stale_s),
                received=h.received,
                dropped=h.seq_gaps + sum(sc[k] for k in _SYNC_DROPS),
                late=sum(sc[k] for k in _SYNC_LATE) + h.ahead,
                undecodable=h.undecodable,
                rate_hz=float(h.rate_hz(mono)),
                latency_ms=float(statistics.fmean(h.latency_ms)) if h.latency_ms else 0.0,
                last_seen_ns=h.last_seen_ns,
                clock_offset_ms=float(offset) if offset is not None else 0.0,
            ))
        return Status(stamp_ns=time.time_ns(), cameras=cams, frame_sets=self.c.frames_fused,
                      frame_sets_dropped=self.c.frame_sets_dropped)

    def _publish_status(self, mono: float) -> None:
        try:
            self.status_pub.put(messages.encode(self.status(mono)))
        except (ValueError, WireError) as exc:
            self.rlog.warn("fusion", "status", f"status not published: {exc}", mono)

    def summary(self) -> str:
        c = self.c
        parts = [f"{c.frames_fused} frames fused", f"{c.events} events",
                 f"{c.frame_sets_dropped} frame sets dropped (slow)", f"{c.frame_sets_too_few} with too few cameras",
                 f"{c.inbox_dropped} masks dropped on arrival", f"{c.unknown_camera} from unknown cameras",
                 f"{c.pipeline_errors} fusion errors", f"{c.queries} history queries"]
        st = self.status(time.monotonic())
        for cs in st.cameras:
            parts.append(f"{cs.cam}: received {cs.received}, undecodable {cs.undecodable}, dropped {cs.dropped}, "
                         f"late {cs.late}, {cs.state}")
        return "; ".join(parts)


# --------------------------------------------------------------------------- helpers


class _Mismatch(WireError):
    """A mask message whose camera differs from its key's camera."""


class _Shape(WireError):
    """A mask whose shape cannot be the camera's."""


def _track_state(t: Any) -> TrackState:
    posture = t.posture if t.posture in messages.POSTURES else "unknown"
    return TrackState(
        id=int(t.id), x=float(t.x), y=float(t.y), z_top=max(0.0, float(t.z_top)),
        volume_m3=max(0.0, _finite(t.volume_m3)), posture=posture,
        reliability=min(1.0, max(0.0, _finite(t.reliability))), vx=_finite(t.vx), vy=_finite(t.vy),
        still=bool(t.still),
    )


def _finite(value: Any) -> float:
    v = float(value)
    return v if math.isfinite(v) else 0.0


def _clean_boxes(boxes: Any) -> list[tuple[int, int, int, int]]:
    """Boxes as plain int tuples, empty ones left out, at most the wire's maximum."""
    out = []
    hi = maskcodec.MAX_MASK_SIDE
    for box in boxes:
        x0, y0, x1, y1 = (min(hi, max(0, int(v))) for v in box)
        if x0 < x1 and y0 < y1:
            out.append((x0, y0, x1, y1))
    return out[: messages.MAX_HOLD_BOXES]


def _same_boxes(a: list, b: list, slack_px: int) -> bool:
    """Same number of boxes, each within ``slack_px`` of its counterpart on every side."""
    return len(a) == len(b) and all(max(abs(u - v) for u, v in zip(p, q)) <= slack_px for p, q in zip(a, b))


def _wire_event(rec: EventRecord) -> Event:
    """The wire message of an event; lists or maps in ``details`` travel as JSON text."""
    import json

    obj = plain_value(rec.to_dict())
    details = {}
    for k, v in obj["details"].items():
        details[k] = json.dumps(v, separators=(",", ":")) if isinstance(v, (list, dict)) else v
    obj["details"] = details
    obj["x"] = obj["x"] if obj["x"] is not None else 0.0
    obj["y"] = obj["y"] if obj["y"] is not None else 0.0
    try:
        return Event.model_validate(obj)
    except ValueError as exc:
        raise WireError(f"Event {rec.id}: {exc}") from None


def _install_signal_handlers(stop: threading.Event) -> dict:
    previous = {}
    if threading.current_thread() is not threading.main_thread():
        return previous
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, lambda signum, frame: stop.set())
    return previous


def _restore_signal_handlers(previous: dict) -> None:
    for sig, handler in previous.items():
        signal.signal(sig, handler)
