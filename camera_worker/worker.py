"""The camera worker's process adapter: frames in, compressed masks out over zenoh.

:func:`run` is the only part that talks to zenoh, reads the clock or
sleeps. Per frame it calls the pure pieces: :meth:`HoldBook.boxes` (hold
regions still in force), ``ForegroundSegmenter.apply``,
:meth:`~camera_worker.looks.LookAnswerer.answer` (only while a look request
is pending), the view check and :func:`build_mask_frame`: :func:`step` is them
together, the one per-frame path that the worker, its tests and its benchmark
(``evaluation/worker_bench.py``) all run.

What :func:`run` does:

* learns the background clip (if any), then reads the source; a recorded
  source plays at its own rate (``paced``) or as fast as possible, and ends
  the run (exit 0) unless ``loop``; a live source is read on a thread into a
  one-slot newest-wins buffer (older frames dropped and counted) and
  reopened with exponential back-off when it drops, the worker reporting
  itself ``degraded`` meanwhile;
* publishes one :class:`~common.messages.MaskFrame` per frame on
  ``<p>/cam/<cam>/mask`` (congestion control DROP: masks are newest-wins),
  declares the liveliness token ``<p>/alive/cam/<cam>``, and takes
  :class:`~common.messages.HoldRegions` from ``<p>/cam/<cam>/hold`` through a
  ring channel (never a growing queue); broken hold messages are counted and
  dropped with a rate-limited log line;
* takes :class:`~common.messages.LookRequest` from ``<p>/cam/<cam>/look`` the
  same way (a broken one, or one for another camera, is counted and dropped
  with a rate-limited line naming the key and the problem); the newest
  request is answered on the next frame segmented, its colour descriptors
  travelling in that frame's ``MaskFrame.looks`` (a request older than its
  time to live by then is counted as expired and left unanswered);
* counts frames read, dropped and published, look requests answered,
  expired and rejected, and the time of each stage (:data:`STAGES`), logged
  every ``stats_period_s``;
* when it stops on purpose (the recording ended, or SIGTERM/SIGINT), sends a
  DELETE on its mask key before withdrawing its token: the fusion server then
  reports the camera ``stopped`` (event ``camera_stopped``), not ``lost``.

:func:`measure_worker` times the same stages on a synthetic 640x480 clip for
the benchmark command.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from pydantic import Field, field_validator, model_validator

import numpy as np

from camera_worker.looks import LookAnswerer
from camera_worker.segmentation import Box, ForegroundSegmenter, SegmentStats, window_frames_for
from camera_worker.segmenters import MODALITIES, Segmenter, foreground_depth, segmenter_for
from camera_worker.viewcheck import ViewCheck, load_reference, save_reference
from camera_worker.sources import (
    Frame,
    FrameSource,
    LiveReader,
    SourceError,
    open_source,
)
from common import keys, maskcodec, messages, sharedstart
from common.messages import Appearance, HoldRegions, LookRequest, MaskFrame, WireError
from common.ratelog import RateLimitedLog
from common.settings import Settings

__all__ = [
    "STAGES",
    "HoldBook",
    "HoldRegionsRejected",
    "WorkerCounters",
    "WorkerSettings",
    "build_mask_frame",
    "run",
    "step",
]

log = logging.getLogger("voxelwatch.camera")

STAGES = ("read", "segment", "looks", "view", "encode", "publish")
_STOP_NOTICE_S = 0.2
ORPHAN_HOLD_S = 300.0
"""How long hold boxes stay in force, at most, while no fusion server is live (:class:`HoldBook`)."""
"""The timed stages of one frame, in order (``looks``: answering a look request, nearly
nothing on the frames without one)."""


class WorkerSettings(Settings):
    """Everything :func:`run` needs; built by the command line from the site file and flags.

    ``source``/``background``: spec strings (see ``camera_worker.sources``),
    relative paths against ``base_dir``. ``fps`` overrides a recording's own
    rate; ``default_fps`` (the site's camera fps) serves image folders and
    files without a rate. ``start_ns``: stamp of the first
    recorded frame (None: the host clock at start). ``paced``: play recorded
    sources at their rate -- from the first frame read, or, when ``start_ns``
    is given, on the host clock (each frame at its stamp, so workers given the
    same start stay in step; frames already late are skipped where the source
    can seek). ``start_file``: instead of ``start_ns``, a file the shared start
    is read from once the worker is ready (:mod:`common.sharedstart`).
    ``modality``: the camera's (site ``cameras[].modality``), which picks the
    segmenter (:func:`camera_worker.segmenters.segmenter_for`); a depth camera's
    messages carry the foreground range. ``segmenter``: keyword arguments of
    :class:`ForegroundSegmenter` (the thermal and depth segmenters take the common ones). ``max_frames``: stop after this many frames
    (None: no limit). ``expected_size``: the ``(width, height)`` the site
    states for this camera; frames of another size are reported once.
    ``view_check``: register the frames against a reference picture of the room
    about once a second and send the view's shift with the masks (colour and
    infrared cameras; :mod:`camera_worker.viewcheck`). ``view_reference``: a PNG
    file keeping that picture across restarts (read at start when it exists,
    written when the picture is first taken; None: a new one each start).
    """

    cam: str
    prefix: str
    source: str
    background: str = ""
    background_frames: int | None = None
    fps: float | None = None
    default_fps: float = 15.0
    start_ns: int | None = None
    start_file: Path | None = None
    paced: bool = True
    loop: bool = False
    seed: int = 0
    codec: str = maskcodec.DEFAULT_CODEC
    segmenter: dict[str, Any] = Field(default_factory=dict)
    base_dir: Path | None = None
    max_frames: int | None = Field(default=None, ge=1)
    stats_period_s: float = Field(default=10.0, gt=0.0)
    backoff_s: float = 0.5
    max_backoff_s: float = 30.0
    hold_queue: int = Field(default=8, ge=1)
    orphan_hold_s: float = Field(default=ORPHAN_HOLD_S, ge=0.0, allow_inf_nan=False)
    look_queue: int = Field(default=4, ge=1)
    expected_size: tuple[int, int] | None = None
    modality: str = "colour"
    view_check: bool = True
    view_reference: Path | None = None

    @model_validator(mode="after")
    def _one_start(self) -> WorkerSettings:
        if self.start_ns is not None and self.start_file is not None:
            raise ValueError("give the shared start as start_ns or start_file, not both")
        return self

    @field_validator("cam")
    @classmethod
    def _cam_ok(cls, cam: str) -> str:
        keys.validate_chunk(cam, "camera id")
        return cam

    @field_validator("prefix")
    @classmethod
    def _prefix_ok(cls, prefix: str) -> str:
        keys.validate_prefix(prefix)
        return prefix

    @field_validator("modality")
    @classmethod
    def _modality_ok(cls, modality: str) -> str:
        if modality not in MODALITIES:
            raise ValueError(f"must be one of {', '.join(MODALITIES)}")
        return modality

    @field_validator("codec")
    @classmethod
    def _codec_ok(cls, codec: str) -> str:
        if codec not in maskcodec.CODECS:
            raise ValueError(f"must be one of {', '.join(maskcodec.CODECS)}")
        return codec


@dataclass
class WorkerCounters:
    """What a worker has done since it started; ``state`` is ``ok``, ``degraded`` or ``stopped``.

    ``dropped``: frames captured but never segmented (newest-wins buffer
    overwrote them, or a paced recording fell behind the host clock).
    ``skipped``: frames of a recording passed over to join a shared start
    that was already past when the worker started. ``looks_answered``/``looks_expired``: look requests
    answered on a frame, or found older than their time to live;
    ``looks_rejected``: look messages dropped (broken, or for another camera).
    ``stage_s``: total seconds per stage; ``timed``: frames timed.
    """

    read: int = 0
    dropped: int = 0
    skipped: int = 0
    published: int = 0
    publish_errors: int = 0
    holds_accepted: int = 0
    holds_rejected: int = 0
    looks_answered: int = 0
    looks_expired: int = 0
    looks_rejected: int = 0
    source_failures: int = 0
    reconnects: int = 0
    light_changes: int = 0
    view_errors: int = 0
    state: str = "ok"
    stage_s: dict[str, float] = field(default_factory=lambda: {s: 0.0 for s in STAGES})
    timed: int = 0

    def stage_ms(self) -> dict[str, float]:
        """Mean milliseconds per frame for each stage."""
        n = max(self.timed, 1)
        return {s: 1e3 * self.stage_s[s] / n for s in STAGES}


class HoldRegionsRejected(ValueError):
    """A hold message that does not apply to this camera or comes too late."""


class HoldBook:
    """The hold boxes in force for one camera.

    Each accepted :class:`HoldRegions` replaces the previous set (an empty
    list releases all). Its time-to-live is counted in this camera's own
    time, from ``now_ns`` (the stamp of the latest frame) when it arrived, so
    a fusion host whose clock differs cannot make a hold last forever.
    Messages for another camera, or older (``stamp_ns``) than the one in
    force, are rejected.

    While no fusion server is live (:meth:`server_gone`: its liveliness token
    went, a crash or a restart), the boxes in force do not lapse: nobody can
    say the still person has gone, and a person lying on the floor must not
    fade into the background before a server is back to watch. They last
    ``orphan_s`` after the server went at most (then they lapse as usual),
    and once a server is back (:meth:`server_back`), one time-to-live more,
    for it to send its own.
    """

    def __init__(self, cam: str, orphan_s: float = ORPHAN_HOLD_S) -> None:
        if not (math.isfinite(orphan_s) and orphan_s >= 0):
            raise ValueError(f"orphan_s must be a non-negative number of seconds, got {orphan_s!r}")
        self.cam = cam
        self.orphan_ns = int(round(orphan_s * 1e9))
        self._boxes: list[Box] = []
        self._stamp_ns = -1
        self._expires_ns = -1
        self._ttl_ns = 0
        self._gone_ns: int | None = None   # when the last fusion server went (this camera's time)

    def server_gone(self, now_ns: int) -> None:
        """No fusion server is live since ``now_ns``: the boxes in force stay, ``orphan_s`` at most."""
        if self._gone_ns is None:
            self._gone_ns = int(now_ns)

    def server_back(self, now_ns: int) -> None:
        """A fusion server is live again: the boxes held meanwhile last one time-to-live more."""
        if self._gone_ns is not None and now_ns <= self._gone_ns + self.orphan_ns:
            self._expires_ns = max(self._expires_ns, int(now_ns) + self._ttl_ns)
        self._gone_ns = None

    def offer(self, msg: HoldRegions, now_ns: int) -> None:
        """Take ``msg`` into force at ``now_ns``; raise :class:`HoldRegionsRejected` if it does not apply."""
        if msg.cam != self.cam:
            raise HoldRegionsRejected(f"HoldRegions for camera {msg.cam!r} received by camera {self.cam!r}")
        if msg.stamp_ns < self._stamp_ns:
            raise HoldRegionsRejected(f"HoldRegions stamped {msg.stamp_ns} is older than the one in force "
                                      f"({self._stamp_ns})")
        self._stamp_ns = msg.stamp_ns
        self._boxes = [tuple(int(v) for v in b) for b in msg.boxes]
        self._ttl_ns = int(msg.ttl_ms) * 1_000_000
        self._expires_ns = int(now_ns) + self._ttl_ns

    def boxes(self, now_ns: int) -> list[Box]:
        """Boxes ``(x0, y0, x1, y1)`` (full-resolution pixels, exclusive) in force at ``now_ns``."""
        expires = self._expires_ns
        if self._gone_ns is not None and self._expires_ns >= self._gone_ns:   # in force when the server went
            expires = max(expires, self._gone_ns + self.orphan_ns)
        if not self._boxes or now_ns > expires:
            return []
        return list(self._boxes)


def build_mask_frame(
    mask: np.ndarray,
    *,
    cam: str,
    seq: int,
    stamp_ns: int,
    src_size: tuple[int, int],
    codec: str = maskcodec.DEFAULT_CODEC,
    fg_fraction: float | None = None,
    looks: Sequence[Appearance] = (),
    depth_mm: np.ndarray | None = None,
    view_shift_px: float | None = None,
) -> MaskFrame:
    """The wire message of one mask. ``mask``: ``(h, w) uint8`` 0/255; ``src_size``: capture ``(W, H)``;
    ``looks``: the colour descriptors answering a look request on this frame; ``depth_mm``: a
    depth camera's foreground range, ``(h, w) uint16`` millimetres (sent at the mask's pixels);
    ``view_shift_px``: the view's latest measured shift (:mod:`camera_worker.viewcheck`)."""
    h, w = mask.shape
    if fg_fraction is None:
        fg_fraction = float(np.count_nonzero(mask)) / mask.size
    return MaskFrame(
        cam=cam, seq=int(seq), stamp_ns=int(stamp_ns), width=int(w), height=int(h),
        src_width=int(src_size[0]), src_height=int(src_size[1]), codec=codec,
        data=maskcodec.encode_mask(mask, codec), fg_fraction=min(1.0, max(0.0, float(fg_fraction))),
        looks=list(looks),
        depth=maskcodec.encode_depth(depth_mm, mask) if depth_mm is not None else b"",
        view_shift_px=None if view_shift_px is None else round(float(view_shift_px), 2),
    )


def step(
    segmenter: Segmenter,
    frame: Frame,
    *,
    cam: str,
    seq: int,
    holds: Sequence[Box] = (),
    codec: str = maskcodec.DEFAULT_CODEC,
    answerer: LookAnswerer | None = None,
    view: Callable[[Frame, np.ndarray, SegmentStats], float | None] | None = None,
    stage_s: dict[str, float] | None = None,
) -> tuple[MaskFrame, np.ndarray, SegmentStats]:
    """Segment one frame and wrap its mask for the wire: ``(message, mask, stats)``.

    With an ``answerer`` holding a request, the message carries its answer on this frame (a
    thermal or range camera has no colours: the request is taken and left unanswered). ``view``:
    the view check, given the frame, its mask and stats, returning the view's latest shift in
    pixels (None: none yet). ``stage_s``: the seconds of the ``segment``, ``looks``, ``view`` and
    ``encode`` stages are added to it. Raises ValueError when the frame's size differs from the
    background model's (nothing else is done then)."""
    t0 = time.perf_counter()
    mask, stats = segmenter.apply(frame.image, holds=holds)
    t1 = time.perf_counter()
    image = frame.image if isinstance(segmenter, ForegroundSegmenter) else None   # thermal, range: no colours
    looks = answerer.answer(image, mask, frame.stamp_ns) if answerer is not None and answerer.pending else []
    t2 = time.perf_counter()
    shift = view(frame, mask, stats) if view is not None else None
    t3 = time.perf_counter()
    h, w = frame.image.shape[:2]
    msg = build_mask_frame(mask, cam=cam, seq=seq, stamp_ns=frame.stamp_ns, src_size=(w, h), codec=codec,
                           fg_fraction=stats.fg_fraction, looks=looks, depth_mm=foreground_depth(segmenter),
                           view_shift_px=shift)
    if stage_s is not None:
        for name, dt in (("segment", t1 - t0), ("looks", t2 - t1), ("view", t3 - t2),
                         ("encode", time.perf_counter() - t3)):
            stage_s[name] += dt
    return msg, mask, stats


# --- the adapter ---------------------------------------------------------------------------------


def run(session: Any, settings: WorkerSettings, *, stop: threading.Event | None = None,
        counters: WorkerCounters | None = None) -> int:
    """Run one camera worker on an open zenoh ``session`` until the source ends or ``stop`` is set.

    Returns the process exit code: 0 after a recorded source ended (or on
    ``stop``), 1 when a source or the background clip cannot be used (the
    reason is logged, naming it). The caller owns and closes the session.
    """
    import zenoh

    stop = stop or threading.Event()
    counters = counters if counters is not None else WorkerCounters()
    start_ns = settings.start_ns if settings.start_ns is not None else time.time_ns()
    try:
        source = open_source(settings.source, cam_id=settings.cam, start_ns=start_ns, fps=settings.fps,
                             seed=settings.seed, base_dir=settings.base_dir, default_fps=settings.default_fps,
                             modality=settings.modality)
    except (SourceError, ValueError, TypeError) as exc:
        log.error("camera %s: %s", settings.cam, exc)
        return 1

    if not source.live:
        try:
            source.open()
        except SourceError as exc:
            log.error("camera %s: %s", settings.cam, exc)
            return 1
    seg_kwargs = dict(settings.segmenter)
    if seg_kwargs.get("window_frames") is None:
        seg_kwargs["window_frames"] = window_frames_for(source.fps or settings.default_fps or 15.0)
    try:
        segmenter = segmenter_for(settings.modality, **seg_kwargs)
    except (ValueError, TypeError) as exc:
        log.error("camera %s: %s", settings.cam, exc)
        source.close()
        return 1
    try:
        if settings.background:
            _learn_background(segmenter, settings, start_ns, stop)
        view = _view_check(settings, segmenter)
    except (SourceError, ValueError) as exc:
        log.error("camera %s: %s", settings.cam, exc)
        source.close()
        return 1

    token = session.liveliness().declare_token(keys.alive_camera_key(settings.prefix, settings.cam))
    if settings.start_file is not None:
        try:
            settings = _await_shared_start(settings, source, stop)
        except ValueError as exc:
            log.error("camera %s: %s", settings.cam, exc)
            token.undeclare()
            source.close()
            return 1
    publisher = session.declare_publisher(
        keys.mask_key(settings.prefix, settings.cam), encoding=messages.MSGPACK_ENCODING,
        congestion_control=zenoh.CongestionControl.DROP, express=True)
    hold_sub = session.declare_subscriber(keys.hold_key(settings.prefix, settings.cam),
                                          zenoh.handlers.RingChannel(settings.hold_queue))
    server = _ServerPresence()
    server_sub = session.liveliness().declare_subscriber(
        keys.alive_fusion_key(settings.prefix), lambda sample: server.seen(sample.kind == zenoh.SampleKind.PUT),
        history=True)
    look_sub = session.declare_subscriber(keys.look_key(settings.prefix, settings.cam),
                                          zenoh.handlers.RingChannel(settings.look_queue))
    loop = _Loop(settings, segmenter, source, publisher, hold_sub, look_sub, counters, stop, view, server)
    code = 1
    try:
        code = loop.run()
        return code
    finally:
        counters.state = "stopped"
        loop.close()
        if code == 0:
            _say_stopping(session, settings)
        for entity in (server_sub, look_sub, hold_sub, publisher, token):
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001 - the session may already be closing
                pass
        log.info("camera %s: stopped: %s", settings.cam, _summary(counters))


def _say_stopping(session: Any, settings: WorkerSettings) -> None:
    """Tell the fusion server this camera stops on purpose (its recording ended, or it was told to
    stop): a DELETE on its own mask key, sent reliably before its liveliness token goes, so that
    the server reports the camera ``stopped`` instead of raising ``camera_lost``. A worker that
    dies never sends it."""
    import zenoh

    try:
        session.delete(keys.mask_key(settings.prefix, settings.cam), congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(_STOP_NOTICE_S)  # the notice leaves before the token's withdrawal
    except Exception as exc:  # noqa: BLE001 - the session may already be closing
        log.debug("camera %s: stop notice not sent: %s", settings.cam, exc)


class _ServerPresence:
    """Whether a fusion server is live, from its liveliness token (set on zenoh's thread, taken
    by the frame loop): :meth:`take` is the news since the last call, None for none."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._news: bool | None = None
        self._live = False

    def seen(self, live: bool) -> None:
        with self._lock:
            if live != self._live:
                self._live = live
                self._news = live

    def take(self) -> bool | None:
        with self._lock:
            news, self._news = self._news, None
            return news


class _Loop:
    """The per-frame loop of :func:`run` (state that the loop shares between its stages)."""

    def __init__(self, settings: WorkerSettings, segmenter: Segmenter, source: FrameSource,
                 publisher: Any, hold_sub: Any, look_sub: Any, counters: WorkerCounters,
                 stop: threading.Event, view: ViewCheck | None = None,
                 server: "_ServerPresence | None" = None) -> None:
        self.s = settings
        self.segmenter = segmenter
        self.source = source
        self.publisher = publisher
        self.hold_sub = hold_sub
        self.look_sub = look_sub
        self.look_key = keys.look_key(settings.prefix, settings.cam)
        self.c = counters
        self.stop = stop
        self.holds = HoldBook(settings.cam, settings.orphan_hold_s)
        self.server = server if server is not None else _ServerPresence()
        self.answerer = LookAnswerer()
        self.view = view
        self.reader: LiveReader | None = None
        self.seq_offset = 0          # added to a recorded source's index: sequence numbers go on when looping
        self.last_seq = -1
        self.last_stamp_ns = 0
        self._failed_recorded = False
        self._size_warned: tuple[int, int] | None = None
        self.pace_origin: tuple[float, int] | None = None   # (monotonic s, stamp_ns) of the paced start
        self._bad_holds = RateLimitedLog(log, 5.0)
        self._bad_looks = RateLimitedLog(log, 5.0)
        self._view_log = RateLimitedLog(log, 60.0)
        self._next_stats = time.monotonic() + settings.stats_period_s

    def run(self) -> int:
        if self.source.live:
            self.reader = LiveReader(self.source, backoff_s=self.s.backoff_s, max_backoff_s=self.s.max_backoff_s,
                                     on_event=self._source_event).start()
        log.info("camera %s: reading %s, publishing on %s", self.s.cam, self.source.name,
                 keys.mask_key(self.s.prefix, self.s.cam))
        frames = 0
        while not self.stop.is_set():
            t0 = time.perf_counter()
            frame = self._next_frame()
            if frame is None:
                if self.source.live:
                    continue
                return 0 if self.stop.is_set() or not self._failed_recorded else 1
            frame_s = dict.fromkeys(STAGES, 0.0)
            frame_s["read"] = time.perf_counter() - t0
            self._check_size(frame)
            self._take_holds(frame.stamp_ns)
            self._take_looks()
            try:
                msg, _, stats = step(self.segmenter, frame, cam=self.s.cam, seq=self.seq_offset + frame.index,
                                     holds=self.holds.boxes(frame.stamp_ns), codec=self.s.codec,
                                     answerer=self.answerer, view=self._check_view, stage_s=frame_s)
            except ValueError as exc:   # the frame size changed (a camera reopened at another size)
                log.warning("camera %s: %s; starting a new background model", self.s.cam, exc)
                self.segmenter.reset()
                continue
            self.c.looks_answered, self.c.looks_expired = self.answerer.answered, self.answerer.expired
            self.last_seq = msg.seq
            t = time.perf_counter()
            payload = messages.encode(msg)
            t_put = time.perf_counter()
            frame_s["encode"] += t_put - t
            try:
                self.publisher.put(payload)
                self.c.published += 1
            except Exception as exc:  # noqa: BLE001 - zenoh errors must not stop the camera
                self.c.publish_errors += 1
                log.warning("camera %s: publish failed: %s", self.s.cam, exc)
            frame_s["publish"] = time.perf_counter() - t_put
            if stats.light_change:
                self.c.light_changes += 1
                log.info("camera %s: sudden light change at frame %d: re-learning the background",
                         self.s.cam, msg.seq)
            for name, dt in frame_s.items():
                self.c.stage_s[name] += dt
            self.c.timed += 1
            frames += 1
            self._maybe_log_stats()
            if self.s.max_frames is not None and frames >= self.s.max_frames:
                break
        return 0

    def _next_frame(self) -> Frame | None:
        if self.reader is not None:
            frame = self.reader.get(timeout_s=0.5)
            self.c.read, self.c.dropped = self.reader.read, self.reader.dropped
            self.c.source_failures, self.c.reconnects = self.reader.failures, self.reader.reconnects
            self.c.state = "degraded" if self.reader.degraded else "ok"
            if frame is not None:
                self.last_stamp_ns = frame.stamp_ns
            return frame
        try:
            frame = self.source.read()
            if frame is None and self.s.loop and not self.stop.is_set():
                frame = self._restart_recorded()
        except SourceError as exc:
            log.error("camera %s: %s", self.s.cam, exc)
            self._failed_recorded = True
            return None
        if frame is None:
            return None
        self.c.read += 1
        if self.s.paced and self.s.start_ns is not None:
            frame = self._catch_up(frame)
            if frame is None:
                return None
        self.last_stamp_ns = frame.stamp_ns
        if self.s.paced:
            self._pace(frame.stamp_ns)
        return frame

    def _catch_up(self, frame: Frame) -> Frame | None:
        """On the host clock, a worker that fell behind drops the frames it is late
        for (counted) instead of publishing ever older ones. A worker started (or
        restarted) after the shared start joins the shared lattice at the frame for
        now instead of playing the recording from its first frame (``skipped``)."""
        period_ns = 1e9 / (self.source.fps or 15.0)
        behind = int((time.time_ns() - frame.stamp_ns) / period_ns)
        if behind < 2 or getattr(self.source, "seek", None) is None:
            return frame
        first = self.c.read == 1 and self.seq_offset == 0
        target = self.seq_offset + frame.index + behind  # frame number on the shared lattice
        if first:
            self.c.skipped += behind
            log.info("camera %s: %.1f s after the shared start: joining it at frame %d",
                     self.s.cam, behind * period_ns / 1e9, target)
        else:
            self.c.dropped += behind
        nxt = self._seek_lattice(target, period_ns)
        if nxt is not None:
            self.c.read += 1
        elif not self.s.loop:
            log.info("camera %s: the recording ended before now on the shared clock", self.s.cam)
        return nxt

    def _seek_lattice(self, target: int, period_ns: float) -> Frame | None:
        """Read frame ``target`` of the shared lattice: with ``loop``, lap ``target // n``
        of an ``n``-frame recording, its stamps and sequence numbers carrying on."""
        n = getattr(self.source, "n_frames", None)
        index = target
        if self.s.loop and n:
            laps, index = divmod(target, n)
            self.seq_offset = laps * n
            self.source.start_ns = int(self.s.start_ns) + int(round(laps * n * period_ns))
        self.source.seek(index)
        return self.source.read()

    def _restart_recorded(self) -> Frame | None:
        """Play a recorded source again, its stamps and sequence numbers carrying on."""
        period_ns = int(round(1e9 / (self.source.fps or 15.0)))
        self.source.close()
        self.source.start_ns = self.last_stamp_ns + period_ns
        self.source.open()
        self.seq_offset = self.last_seq + 1
        return self.source.read()

    def _pace(self, stamp_ns: int) -> None:
        if self.s.start_ns is not None:
            # A shared start stamp puts every worker on the host clock: frame i is
            # published at its own stamp, so workers started apart stay in step.
            wait_s = (stamp_ns - time.time_ns()) / 1e9
            if wait_s > 0:
                self.stop.wait(wait_s)
            return
        now = time.monotonic()
        if self.pace_origin is None:
            self.pace_origin = (now, stamp_ns)
            return
        due = self.pace_origin[0] + (stamp_ns - self.pace_origin[1]) / 1e9
        if due > now:
            self.stop.wait(due - now)

    def _check_size(self, frame: Frame) -> None:
        size = (frame.image.shape[1], frame.image.shape[0])
        if self.s.expected_size is not None and size != tuple(self.s.expected_size) and size != self._size_warned:
            self._size_warned = size
            log.warning("camera %s: frames are %dx%d but the site file says %dx%d (cameras[].resolution); "
                        "the fusion projects masks with the site's size", self.s.cam, size[0], size[1],
                        *self.s.expected_size)

    def _take_holds(self, now_ns: int) -> None:
        live = self.server.take()
        if live is True:
            self.holds.server_back(now_ns)
        elif live is False:
            self.holds.server_gone(now_ns)
            log.info("camera %s: no fusion server is live: the hold boxes in force stay (%.0f s at most)",
                     self.s.cam, self.s.orphan_hold_s)
        while True:
            sample = self.hold_sub.try_recv()
            if sample is None:
                return
            try:
                msg = messages.decode(sample.payload.to_bytes(), HoldRegions)
                self.holds.offer(msg, now_ns)
                self.c.holds_accepted += 1
            except (WireError, HoldRegionsRejected) as exc:
                self.c.holds_rejected += 1
                self._bad_holds.warn(f"camera {self.s.cam}", "hold", f"hold message dropped: {exc}", time.monotonic())

    def _take_looks(self) -> None:
        """Take the look requests that arrived (the newest is answered on the next frame): one
        ``try_recv`` is all a frame without a request costs."""
        while (sample := self.look_sub.try_recv()) is not None:
            # broken messages and requests for another camera are two faults (a bad sender, a fusion
            # server with the wrong site file): each is reported on its own line
            reason = "broken look"
            try:
                msg = messages.decode(sample.payload.to_bytes(), LookRequest)
                if msg.cam != self.s.cam:
                    reason = "look for another camera"
                    raise WireError(f"LookRequest for camera {msg.cam!r} received by camera {self.s.cam!r}")
            except WireError as exc:
                self.c.looks_rejected += 1
                self._bad_looks.warn(f"camera {self.s.cam}", reason,
                                     f"look request on {self.look_key} dropped: {exc}", time.monotonic())
                continue
            self.answerer.ask(msg)

    def _check_view(self, frame: Frame, mask: np.ndarray, stats: SegmentStats) -> float | None:
        """The view's latest shift (:mod:`camera_worker.viewcheck`); a reference picture taken on the
        way is kept in the settings' file."""
        if self.view is None:
            return None
        had = self.view.has_reference
        try:
            shift = self.view.follow(self.segmenter, frame.image, mask, stats.fg_fraction, stats.relearning,
                                     frame.stamp_ns)
        except Exception as exc:  # noqa: BLE001 - the check must never stop the camera's masks
            self.c.view_errors += 1
            self._view_log.warn(f"camera {self.s.cam}", "view", f"view check failed ({type(exc).__name__}: {exc}); "
                                "the masks go on without it", time.monotonic())
            return None
        if not had and self.view.has_reference:
            log.info("camera %s: took the reference view of the room", self.s.cam)
            if self.s.view_reference is not None:
                try:
                    save_reference(self.s.view_reference, self.segmenter.background_image())
                except OSError as exc:
                    log.warning("camera %s: %s (the view is checked against this run's picture only)",
                                self.s.cam, exc)
        return shift

    def _source_event(self, text: str) -> None:
        log.warning("camera %s: %s", self.s.cam, text)

    def _maybe_log_stats(self) -> None:
        now = time.monotonic()
        if now >= self._next_stats:
            self._next_stats = now + self.s.stats_period_s
            log.info("camera %s: %s", self.s.cam, _summary(self.c))

    def close(self) -> None:
        if self.reader is not None:
            self.reader.stop()
        self.source.close()


def _view_check(settings: WorkerSettings, segmenter: Segmenter) -> ViewCheck | None:
    """The view check of a colour or infrared camera (None: off, or another kind of camera), with the
    reference picture kept at ``settings.view_reference`` when there is one (SourceError when that
    file is not a picture)."""
    if not settings.view_check or not isinstance(segmenter, ForegroundSegmenter):
        return None
    check = ViewCheck()
    if settings.view_reference is not None:
        try:
            picture = load_reference(settings.view_reference)
        except ValueError as exc:
            raise SourceError(f"view reference {exc}") from None
        if picture is not None:
            check.set_reference(picture)
            log.info("camera %s: checking the view against %s", settings.cam, settings.view_reference)
    return check


def _await_shared_start(settings: WorkerSettings, source: FrameSource, stop: threading.Event) -> WorkerSettings:
    """Ready (the liveliness token is out): wait for the shared start in the settings' start file
    and stamp the source from it; the settings returned carry it as ``start_ns``."""
    if sharedstart.read_start(settings.start_file) is None:
        log.info("camera %s: ready; waiting for the shared start in %s", settings.cam, settings.start_file)
    start_ns = sharedstart.wait_start(settings.start_file, stop)
    if start_ns is None:       # stopped while waiting: the loop ends at once
        return settings
    source.start_ns = start_ns
    return settings.model_copy(update={"start_ns": start_ns})


def _learn_background(segmenter: Segmenter, settings: WorkerSettings, start_ns: int,
                      stop: threading.Event) -> int:
    """Learn every frame of the background clip (until ``stop``); returns the number of frames learned."""
    bg = open_source(settings.background, cam_id=settings.cam, start_ns=start_ns, fps=settings.fps,
                     seed=settings.seed, base_dir=settings.base_dir, background=True,
                     n_frames=settings.background_frames, default_fps=settings.default_fps,
                     modality=settings.modality)
    if bg.live:
        raise SourceError(f"background {bg.name}: must be a recording (file, folder or synthetic), not live")
    try:
        bg.open()
    except SourceError as exc:
        raise SourceError(f"background {exc}") from None
    n = 0
    try:
        while (settings.background_frames is None or n < settings.background_frames) and not stop.is_set():
            frame = bg.read()
            if frame is None:
                break
            try:
                segmenter.learn(frame.image)
            except ValueError as exc:
                raise SourceError(f"background {bg.name}: {exc}") from None
            n += 1
    finally:
        bg.close()
    if n == 0 and not stop.is_set():
        raise SourceError(f"background {bg.name}: holds no frames")
    log.info("camera %s: learned the background from %d frames of %s", settings.cam, n, bg.name)
    return n


def _summary(c: WorkerCounters) -> str:
    ms = c.stage_ms()
    stages = ", ".join(f"{s} {ms[s]:.2f}" for s in STAGES)
    return (f"state {c.state}, read {c.read}, skipped {c.skipped}, dropped {c.dropped}, published {c.published}, "
            f"holds {c.holds_accepted} (rejected {c.holds_rejected}), looks answered {c.looks_answered} "
            f"(expired {c.looks_expired}, rejected {c.looks_rejected}), source failures {c.source_failures}, "
            f"ms/frame: {stages}")
