"""The fusion server's core: masks and liveliness in, messages to publish out, time passed in.

:class:`FusionNode` makes every decision the live server makes between zenoh
and :class:`~fusion_server.pipeline.FusionPipeline`; the process adapter
(:mod:`fusion_server.server`) only receives samples, hands them to the node
with their arrival time, and publishes what :meth:`FusionNode.tick` returns.
Nothing here opens a session or reads a clock, so a test drives the node frame
by frame with its own clock, and the offline replay fuses through the same
:meth:`FusionNode.fuse`.

What the node does:

* **masks** (:meth:`~FusionNode.on_mask`, one ``<p>/cam/<cam>/mask`` sample):
  decodes it (``WireError``, ``MaskCodecError``, a message whose ``cam``
  differs from its key's camera, or a mask of a size the camera cannot send
  (:func:`mask_size_fits`, refused before it is inflated), are counted per
  camera as ``undecodable`` with a log line at most
  once per ``log_every_s`` per camera and reason), drops masks of cameras the
  site does not know (counted), and pushes the rest into a
  :class:`~fusion_server.sync.FrameSynchroniser` (lattice period from the
  slowest camera's fps). Each released frame set with at least
  ``min_cameras`` cameras waits in a queue of at most ``max_ready_sets``;
  beyond that the oldest set is dropped and counted (``frame_sets_dropped``),
  so a slow pipeline never makes memory grow. The frame number of a set is the
  most common sequence number in it.
* **fusing** (:meth:`~FusionNode.tick`, one ready set per call): the tracks of
  the frame as one :class:`~common.messages.TrackFrame` (non-finite tracks left
  out), each event first added to the event store (committed; an event whose
  id is already stored is neither published nor written again; one the
  store cannot write is still published -- an alarm must go out -- logged,
  counted as ``events_not_stored`` in the status and kept in the store's
  fallback file, ``events_pending`` until merged), then queued for
  ``<p>/events/<kind>/<track>`` as JSON text and written to ``events.jsonl``
  when files are kept. A frame set the pipeline fails on is
  counted and logged; the next one is fused as usual.
* **holds**: per camera, :class:`~common.messages.HoldRegions` whenever the
  boxes change (by more than ``hold_slack_px`` on some side, or in number) and
  at least every ``hold_ttl_ms / 2`` while there are any; an empty list when
  they end. They are sent only after fused frames: when fusion stops, holds
  lapse.
* **liveliness** (:meth:`~FusionNode.on_liveliness`): a camera whose token goes
  away is ``lost`` (a ``camera_lost`` event) and ``camera_back`` when it
  returns; the synchroniser goes on releasing sets without it.
* **time** belongs to the server: a mask stamped more than
  ``max_clock_skew_ms`` ahead of its arrival on the server's clock never
  reaches the frame sets (counted ``future``, in ``late`` and ``refused``);
  its camera is ``skewed`` at once and stays so while its masks are refused.
  A mask stamped no later than the camera's newest mask taken (a replay, or a
  worker replaying a recording from its start) is refused as ``replayed``, one
  repeating the newest mask's sequence number as ``repeated`` (both in
  ``dropped`` and ``refused``; the camera reads ``degraded`` meanwhile,
  except for a second delivery of its newest mask itself).
  Refused masks never become a camera's newest. A sequence gap counts at most
  the frame periods between the two stamps as lost. With ``free_timeline``
  (recordings played faster than real time) the server's clock is not
  checked and the timeline follows the stamps.
* **clock skew**: per camera, the largest ``stamp_ns - receive time`` over
  the last ``skew_window`` masks taken (the fastest one: queueing only
  delays masks, so the median of a loaded server would be its own queue),
  or the lead of the last mask refused as stamped ahead while they are
  refused; beyond ``max_clock_skew_ms`` either way the camera is ``skewed``
  in the status; the mark clears once the estimate is back under 80 % of
  the threshold. A camera that seems to lag is judged so once it has for two
  status periods in which the server was not ``overloaded`` (below): on a
  busy server the masks wait in its own queue. A camera
  turning skewed emits a ``clock_skew`` event (at most one a minute per
  camera). A camera whose clock lags is left out by the synchroniser (its
  masks are stale). With ``free_timeline``, where the server's clock is not
  the reference, a mask whose ``stamp_ns - receive time`` runs more than
  ``max_clock_skew_ms`` ahead of the other live cameras' newest masks is
  left out of the frame sets instead (counted ``late``, logged): one camera
  with a fast clock would otherwise push the synchroniser ahead and make
  every other camera's masks look stale. The skew mark and its event then
  follow that lead on the other cameras (ahead or behind), never the
  server's clock: a recording's stamps lie days before it.
* **load**: the process adapter says how long it worked (:meth:`~FusionNode.note_work`:
  decoding and fusing); over each status period the share of the time so spent is the
  status's ``load``, and from 90 % (or a frame set dropped for being slow) the server
  reads ``overloaded`` until the share is under 70 % with none dropped for a period.
* **status** every ``status_period_s`` (:meth:`~FusionNode.status`).
* **history** (:func:`history_replies`): the replies to one query on
  ``<p>/history/events/**``.

Per-camera counters in the status: ``received`` (masks that decoded),
``undecodable``, ``dropped`` (sequence gaps -- frames the camera, the network
or the server's inbox lost -- plus duplicates, replays, repeated numbers,
superseded frames and synchroniser overflow), ``late`` (out of order, stale,
off the frame lattice, stamped ahead of the server's clock or of the other
cameras), ``refused`` (future, replayed and repeated masks), ``rate_hz`` (masks per second over the
last two seconds), ``latency_ms`` (mean receive time minus capture stamp; on
one host this is the transport and worker latency, across hosts it includes
the clock offset), ``clock_offset_ms`` (the largest capture stamp minus receive
time of the recent masks: the camera clock's lead, less the shortest latency), ``last_seen_ns`` (server
time of the last mask), ``state``: ``lost`` (its liveliness token went away,
or no sign of life at all), ``skewed``, ``degraded`` (no mask for
``stale_s``, or undecodable masks within ``stale_s``), else ``ok``.
"""

from __future__ import annotations

import logging
import math
import statistics
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Mapping

from common import keys, maskcodec, messages
from common.camera import Camera
from common.maskcodec import MaskCodecError
from common.messages import (
    CameraStatus, Event, HoldRegions, LookRequest, MaskFrame, Status, TrackFrame, TrackState, WireError, event_id,
)
from common.ratelog import RateLimitedLog
from common.settings import bounds_of
from common.site import Carving
from fusion_server.event_store import EventStore, parse_history_selector
from fusion_server.outputs import RunOutputs
from fusion_server.pipeline import FusedFrame, FusionPipeline
from fusion_server.settings import FusionSettings
from fusion_server.snapshot import SNAPSHOT_EVERY_S, Snapshot
from fusion_server.sync import FrameSet, FrameSynchroniser

__all__ = ["FusionCounters", "FusionNode", "FusionSettings", "Outbox", "camera_event", "history_replies"]

_MAX_PENDING_DEPTHS = 64
"""Depth images kept for frame sets not fused yet (a few sets of a few depth cameras)."""
log = logging.getLogger("voxelwatch.fusion")

_BUDGET_RATE = 2.0
"""A camera's masks are decoded at up to this many times its frame rate (see ``_within_budget``)."""
_MAX_REASON = 160
OVERLOADED_LOAD = 0.9
"""Share of its time the server works from which it reads ``overloaded`` ..."""
RELIEVED_LOAD = 0.7
"""... and under which it no longer does."""
_SYNC_DROPS = ("duplicate", "superseded", "dropped_overflow")
_SYNC_LATE = ("out_of_order", "stale", "unmatched")
_SKEW_EVENT_EVERY_S = 60.0
_MASK_SCALES = bounds_of(Carving, "mask_scale")
"""The range of ``mask_scale`` the site file accepts: a worker's masks are its image at one of these."""


@dataclass
class FusionCounters:
    """What the node has done since it started (also logged at exit)."""

    frames_fused: int = 0
    frames_with_range: int = 0  # of those, sets carrying a depth camera's foreground range
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


@dataclass
class Outbox:
    """What to publish, in order: encoded messages ready for their keys.

    tracks: encoded :class:`~common.messages.TrackFrame`, one per fused frame.
    events: ``(key expression, JSON text)`` per event.
    holds: ``(camera id, encoded HoldRegions)``.
    looks: ``(camera id, encoded LookRequest)``.
    status: the encoded :class:`~common.messages.Status`, or None when not due.
    """

    tracks: list[bytes] = field(default_factory=list)
    events: list[tuple[str, str]] = field(default_factory=list)
    holds: list[tuple[str, bytes]] = field(default_factory=list)
    looks: list[tuple[str, bytes]] = field(default_factory=list)
    status: bytes | None = None


@dataclass
class _CameraHealth:
    """One camera as the node sees it (see the module doc for the meaning of each counter)."""

    cam: str
    window: int
    received: int = 0
    undecodable: int = 0
    seq_gaps: int = 0
    ahead: int = 0
    future: int = 0
    replayed: int = 0
    repeated: int = 0
    last_seq: int | None = None
    newest_stamp_ns: int | None = None  # of the newest mask taken (refused masks never count)
    last_offset_ms: float | None = None  # stamp - receive time of that mask
    refusing: bool = False  # its masks are stamped ahead of the server's clock
    refused_lead_ms: float = 0.0  # stamp - receive time of the last mask refused for it
    bad_reason: str = ""  # why its last bad mask was dropped (the status's reason while degraded)
    throttled: int = 0  # masks beyond its decoding budget, dropped before decoding
    budget: float = 0.0  # masks it may still have decoded at budget_mono (see FusionNode._within_budget)
    budget_mono: float | None = None  # None: a full bucket
    behind_since_mono: float | None = None  # its clock has seemed to lag since, on a server keeping up
    skew_event_mono: float | None = None
    last_seen_ns: int = 0
    last_mono: float | None = None
    last_bad_mono: float | None = None
    token: bool | None = None  # None: no liveliness news yet
    lost: bool = False
    skewed: bool = False
    stopped: bool = False
    arrivals: deque = field(default_factory=lambda: deque(maxlen=256))
    latency_ms: deque = field(init=False)
    offset_ms: deque = field(init=False)

    def __post_init__(self) -> None:
        self.latency_ms = deque(maxlen=self.window)
        self.offset_ms = deque(maxlen=self.window)

    def seen(self, recv_ns: int, mono: float) -> None:
        """A mask that decoded arrived (taken or refused: either way a sign of life)."""
        self.received += 1
        self.last_seen_ns = recv_ns
        self.last_mono = mono
        self.arrivals.append(mono)

    def take(self, seq: int, stamp_ns: int, recv_ns: int, period_ns: float) -> None:
        """A mask passed the time and sequence checks: it becomes the camera's newest."""
        if self.last_seq is not None and seq > self.last_seq + 1:
            # frames lost cannot outnumber the frame periods between the two stamps: a forged
            # or corrupted number far ahead is a renumbering, not millions of drops
            elapsed_ns = stamp_ns - self.newest_stamp_ns if self.newest_stamp_ns is not None else 0
            possible = max(0, int(round(elapsed_ns / period_ns)) - 1)
            self.seq_gaps += min(seq - self.last_seq - 1, possible)
        self.last_seq = seq  # a restarted worker starts again from 0: no gap is counted
        self.newest_stamp_ns = stamp_ns
        self.last_offset_ms = (stamp_ns - recv_ns) / 1e6
        self.latency_ms.append((recv_ns - stamp_ns) / 1e6)
        self.offset_ms.append(self.last_offset_ms)

    @property
    def refused(self) -> int:
        return self.future + self.replayed + self.repeated

    def rate_hz(self, mono: float, span_s: float = 2.0) -> float:
        recent = [t for t in self.arrivals if mono - t <= span_s]
        if len(recent) < 2 or recent[-1] <= recent[0]:
            return 0.0
        return (len(recent) - 1) / (recent[-1] - recent[0])

    def clock_offset_ms(self) -> float | None:
        """The camera clock's lead on the server's, from the fastest of its recent masks: every
        mask's ``stamp - arrival`` is the lead less that mask's latency, which queueing only
        lengthens, so the largest is the least delayed (the median of a loaded server's masks
        is its queue, not the camera's clock). While its masks are refused as stamped ahead, the
        lead of the last one refused."""
        if self.refusing:
            return self.refused_lead_ms
        return max(self.offset_ms) if self.offset_ms else None

    def recent(self, mono: float, stale_s: float) -> bool:
        return self.last_mono is not None and mono - self.last_mono <= stale_s

    def state(self, mono: float, stale_s: float) -> str:
        recent = self.recent(mono, stale_s)
        if self.stopped and self.token is not True:
            return "stopped"
        if self.lost or (self.token is not True and not recent):
            return "lost"
        if self.skewed or self.refusing:
            return "skewed"
        if not recent or (self.last_bad_mono is not None and mono - self.last_bad_mono <= stale_s):
            return "degraded"
        return "ok"

    def reason(self, state: str, mono: float, stale_s: float) -> str | None:
        """In a few words, why the camera is in ``state`` (None for ``ok``)."""
        if state == "degraded":
            if not self.recent(mono, stale_s):
                return f"no mask for {stale_s:g} s"
            return self.bad_reason or "bad masks"
        if state == "skewed":
            offset = self.clock_offset_ms()
            return f"clock off by {offset:.0f} ms" if offset is not None else "clock off"
        if state == "lost":
            return "its liveliness token went away" if self.lost else "no sign of life"
        if state == "stopped":
            return "its worker stopped on purpose"
        return None

    def bad(self, reason: str, mono: float) -> None:
        """A mask of this camera was dropped as bad (``reason``, a few words)."""
        self.last_bad_mono = mono
        self.bad_reason = reason[:_MAX_REASON]


class FusionNode:
    """The fusion server between its inputs and its outputs; see the module doc.

    settings: the server's settings (the node reads the site, prefix and its
    tuning). pipeline: the fusion pipeline of the site. store: the event store
    (None: events are not stored, every new one is published). outputs: the
    tracks/events files (None: none written). counters: shared with the
    process adapter, which counts inbox drops and history queries in it.
    """

    def __init__(self, settings: FusionSettings, pipeline: FusionPipeline, *, store: EventStore | None = None,
                 outputs: RunOutputs | None = None, counters: FusionCounters | None = None) -> None:
        self.s = settings
        self.pipeline = pipeline
        self.store = store
        self.outputs = outputs
        self.c = counters if counters is not None else FusionCounters()
        self.prefix = settings.prefix
        site = settings.site
        self.camera_ids: tuple[str, ...] = tuple(site.camera_ids)
        self.cameras: dict[str, Camera] = dict(pipeline.cameras)
        self.min_cameras = int(settings.min_cameras if settings.min_cameras is not None else pipeline.min_cameras)
        fps = min(spec.fps for spec in site.cameras)
        self._fps = {spec.id: float(spec.fps) for spec in site.cameras}
        self.sync = FrameSynchroniser(camera_ids=self.camera_ids, fps=fps, max_buffer=settings.sync_buffer)
        self.health = {cam: _CameraHealth(cam, settings.skew_window) for cam in self.camera_ids}
        self.ready: deque[FrameSet] = deque()
        self.rlog = RateLimitedLog(log, settings.log_every_s)
        self.holds_sent: dict[str, tuple[list, float]] = {cam: ([], -math.inf) for cam in self.camera_ids}
        self.last_frame = 0
        self.last_stamp: tuple[int, int] | None = None  # (stamp_ns of the last fused set, server time_ns then)
        self.last_mask_mono: float | None = None
        self._next_status = -math.inf
        self._out = Outbox()
        self._looks: dict[tuple[str, int], list] = {}  # (camera, mask stamp) -> its descriptors
        self._depths: dict[tuple[str, int], Any] = {}  # (camera, mask stamp) -> its foreground range
        self.load = 0.0            # share of the last status period spent working (note_work)
        self.overloaded = False
        self._busy_s = 0.0
        self._load_since: float | None = None
        self._dropped_then = 0
        self.keep_snapshots = False   # the live server keeps one in its store (fusion_server.snapshot)
        self._snapshot_ns = -math.inf
        self._restored_holds: dict[str, list] = {}   # a restored snapshot's holds, sent while its people are sought

    # ------------------------------------------------------------------ inputs

    def on_mask(self, key: str, data: bytes | int, recv_ns: int, mono: float) -> None:
        """One mask sample: its key, its payload (or its size when it was too large to copy),
        the server's wall-clock time and monotonic time of its arrival.

        Before a mask reaches the frame sets it passes the server's time and
        sequence checks (see the module doc): stamped no more than
        ``max_clock_skew_ms`` ahead of ``recv_ns``, newer than the camera's
        newest mask taken, and not repeating its sequence number."""
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
            if not self._within_budget(health, mono):
                health.throttled += 1
                health.bad(f"masks faster than {_BUDGET_RATE:g} times its frame rate: dropped before decoding", mono)
                self.rlog.warn(f"camera {cam}", "budget", "masks arrive faster than the camera's frame rate allows: "
                               "dropped before decoding", mono)
                return
            mask = maskcodec.decode_mask(msg.data, msg.codec, msg.width, msg.height)
            depth = maskcodec.decode_depth(msg.depth, mask) if msg.depth else None
        except (WireError, MaskCodecError) as exc:
            health.undecodable += 1
            health.bad(f"undecodable masks ({exc})", mono)
            self.rlog.warn(f"camera {cam}", type(exc).__name__, f"undecodable mask dropped: {exc}", mono)
            return
        health.seen(recv_ns, mono)
        if not self._admit(health, msg, recv_ns, mono):
            self._check_skew(health, recv_ns, mono)
            return
        self._check_skew(health, recv_ns, mono)
        # with the server's clock as the reference a fast camera was refused above; comparing with
        # the other cameras would make a camera whose clock lags push the right ones out
        lead_ms = self._lead_ms(health, mono) if self.s.free_timeline else None
        if lead_ms is not None and lead_ms > self.s.max_clock_skew_ms:
            health.ahead += 1
            self.rlog.warn(f"camera {cam}", "ahead", f"mask {msg.seq} is stamped {lead_ms:.0f} ms ahead of the "
                           f"other cameras: left out of the frame sets (its clock runs fast)", mono)
            return
        if msg.looks:
            self.add_looks(cam, msg.stamp_ns, msg.looks)
        if msg.view_shift_px is not None:
            self.pipeline.consistency.report_view(cam, msg.view_shift_px, msg.stamp_ns, msg.src_width)
        if depth is not None:
            self._depths[(cam, int(msg.stamp_ns))] = depth
            while len(self._depths) > _MAX_PENDING_DEPTHS:   # sets dropped unfused leave theirs behind
                self._depths.pop(next(iter(self._depths)))
        count = self.sync.counters[cam]
        before = dict(count)
        for fs in self.sync.push(cam, msg.seq, msg.stamp_ns, mask):
            self._queue_set(fs)
        for name in _SYNC_DROPS + _SYNC_LATE:
            if count[name] > before[name]:
                self.rlog.warn(f"camera {cam}", name, f"a mask was dropped by the frame-set synchroniser "
                               f"({name.replace('_', ' ')}; on arrival of mask {msg.seq})", mono)

    def on_liveliness(self, key: str, present: bool, now_ns: int) -> None:
        """A camera's liveliness token appeared (``present``) or went away, at server time ``now_ns``."""
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
        if present and health.stopped:
            health.stopped = False
            log.info("camera %s started again", cam)
        elif not present and health.stopped:
            log.info("camera %s: its worker has gone (stopped on purpose)", cam)
        elif not present and had_token and not health.lost:
            health.lost = True
            log.warning("camera %s lost (its liveliness token went away); tracking with the others", cam)
            self._emit(camera_event("camera_lost", cam, *self._event_time(now_ns)))
        elif present and health.lost:
            health.lost = False
            log.info("camera %s is back", cam)
            self._emit(camera_event("camera_back", cam, *self._event_time(now_ns)))
        elif present and had_token is None:
            log.info("camera %s is alive", cam)

    def on_stopping(self, key: str, now_ns: int) -> None:
        """Camera ``key``'s worker says it stops on purpose (a DELETE on its mask key): it reads
        ``stopped``, one ``camera_stopped`` event goes out, and its token's withdrawal raises no
        ``camera_lost``."""
        try:
            cam = keys.camera_of(key, self.prefix)
        except ValueError:
            return
        health = self.health.get(cam)
        if health is None or health.stopped:
            return
        health.stopped = True
        log.info("camera %s is stopping on purpose", cam)
        self._emit(camera_event("camera_stopped", cam, *self._event_time(now_ns)))

    def acknowledge(self, alarm_id: str, by: str, now_ns: int) -> Event:
        """Someone (``by``) acknowledged the alarm ``alarm_id``: the ``alarm_ack`` event, stored and
        queued for publishing like any event. Acknowledging again returns the first acknowledgement
        (nothing new is published). ValueError naming the problem when there is no store, no such
        event, or it is not an alarm (an acknowledgement of an acknowledgement)."""
        if self.store is None:
            raise ValueError("this fusion server keeps no event store: nothing to acknowledge")
        by = " ".join(str(by).split())[:64] or "someone"
        alarm = self.store.get(alarm_id)
        if alarm is None:
            raise ValueError(f"no stored event {alarm_id[:80]!r}")
        if alarm.kind in messages.ACK_EVENT_KINDS:
            raise ValueError(f"event {alarm_id!r} is an acknowledgement, not an alarm")
        ack_id = f"{alarm.id}-ack"
        first = self.store.get(ack_id)
        if first is not None:
            return first
        stamp_ns, frame = self._event_time(now_ns)
        ack = Event(id=ack_id, kind="alarm_ack", track=alarm.track, stamp_ns=stamp_ns, frame=frame, x=alarm.x,
                    y=alarm.y, details={"event": alarm.id, "alarm": alarm.kind, "by": by})
        self._emit(ack)
        return ack

    def _admit(self, health: _CameraHealth, msg: MaskFrame, recv_ns: int, mono: float) -> bool:
        """The time and sequence checks; True when the mask may go on to the frame sets."""
        cam = health.cam
        lead_ns = msg.stamp_ns - recv_ns
        if not self.s.free_timeline and lead_ns > self.s.max_clock_skew_ms * 1e6:
            # time belongs to the server: a mask from the future never moves the frame-set timeline
            health.future += 1
            health.refused_lead_ms = lead_ns / 1e6
            if not health.refusing:
                health.refusing = True
                log.warning("camera %s: mask %d is stamped %.0f ms ahead of the server's clock (limit %.0f ms): "
                            "its masks are refused until its clock is back", cam, msg.seq, lead_ns / 1e6,
                            self.s.max_clock_skew_ms)
                self._skew_event(health, lead_ns / 1e6, recv_ns, mono)
            else:
                self.rlog.warn(f"camera {cam}", "future", f"mask {msg.seq} stamped {lead_ns / 1e6:.0f} ms ahead "
                               "of the server's clock: refused", mono)
            return False
        if health.newest_stamp_ns is not None and msg.stamp_ns <= health.newest_stamp_ns:
            health.replayed += 1
            if (msg.seq, msg.stamp_ns) == (health.last_seq, health.newest_stamp_ns):
                return False  # the newest mask delivered twice (two network paths): harmless
            health.bad("masks replayed (stamped before its newest)", mono)
            self.rlog.warn(f"camera {cam}", "replayed", f"mask {msg.seq} is stamped {msg.stamp_ns} ns, not after "
                           f"the camera's newest mask ({health.newest_stamp_ns} ns): refused as a replay", mono)
            return False
        if msg.seq == health.last_seq:
            health.repeated += 1
            health.bad("masks repeating a sequence number", mono)
            self.rlog.warn(f"camera {cam}", "repeated", f"mask {msg.seq} repeats the sequence number of the "
                           "camera's newest mask: refused", mono)
            return False
        if health.refusing:
            health.refusing = False
            log.info("camera %s: masks stamped in step with the server's clock again (%.0f ms ahead)",
                     cam, lead_ns / 1e6)
        health.take(msg.seq, msg.stamp_ns, recv_ns, self.sync.period_ns)
        return True

    # ------------------------------------------------------------------ time

    @property
    def pending(self) -> int:
        """Frame sets waiting to be fused."""
        return len(self.ready)

    def tick(self, now_ns: int, mono: float) -> Outbox:
        """Fuse the oldest ready frame set (if any), add the status when it is due, and
        return everything to publish since the last call."""
        if self.ready:
            self._fuse_next(now_ns, mono)
        if mono >= self._next_status:
            self._queue_status(now_ns, mono)
            self._next_status = mono + self.s.status_period_s
        return self.take()

    def idle(self, mono: float) -> bool:
        """True once no mask has arrived for ``exit_after_idle_s`` (never before the first mask)."""
        return (self.s.exit_after_idle_s is not None and self.last_mask_mono is not None
                and mono - self.last_mask_mono >= self.s.exit_after_idle_s)

    def finish(self, now_ns: int, mono: float) -> Outbox:
        """Fuse every frame set still pending (the tail of a recording), ready or not."""
        for fs in self.sync.flush():
            self._queue_set(fs)
        while self.ready:
            self._fuse_next(now_ns, mono)
        return self.take()

    def report(self, now_ns: int, mono: float) -> Outbox:
        """The status now, due or not (and anything else not yet taken)."""
        self._queue_status(now_ns, mono)
        return self.take()

    # ------------------------------------------------------------------ fusing

    def add_looks(self, cam: str, stamp_ns: int, looks: list) -> None:
        """The colour descriptors camera ``cam`` measured on its frame stamped ``stamp_ns``
        (they arrive with its mask); they join that mask's frame set."""
        self._looks[(cam, int(stamp_ns))] = list(looks)

    def fuse(self, fs: FrameSet, now_ns: int, mono: float, *,
             depths: Mapping[str, Any] | None = None) -> FusedFrame:
        """Fuse one frame set: tracks, events (stored, written, queued), holds and look
        requests. ``depths``: depth cameras' foreground range, camera id -> ``(h, w) uint16``
        millimetres at the mask's size, passed to the pipeline (default: the ranges that came
        with the set's masks). Errors of the pipeline propagate (:meth:`tick` counts them; the
        offline replay stops on them)."""
        frame = _frame_of(fs)
        newest = max(fs.stamps_ns.values(), default=fs.stamp_ns)
        looks = {cam: self._looks[(cam, stamp)] for cam, stamp in fs.stamps_ns.items() if (cam, stamp) in self._looks}
        self._looks = {k: v for k, v in self._looks.items() if k[1] > newest}
        if depths is None:
            depths = {cam: self._depths[(cam, stamp)] for cam, stamp in fs.stamps_ns.items()
                      if (cam, stamp) in self._depths}
        self._depths = {k: v for k, v in self._depths.items() if k[1] > newest}
        fused = self.pipeline.step(fs.payloads, fs.stamp_ns, frame, looks, depths=depths)
        self.c.frames_fused += 1
        self.c.frames_with_range += bool(depths)
        self.last_frame = int(fused.frame)
        self.last_stamp = (int(fused.stamp_ns), int(now_ns))
        tracks = [t for t in fused.tracks if all(math.isfinite(float(v)) for v in (t.x, t.y, t.z_top))]
        self._queue_tracks(fused, tracks, mono)
        if self.outputs is not None:
            self.outputs.write_frame(fused.frame, fused.stamp_ns, tracks)
        for rec in fused.events:
            self._emit(rec)
        for alarm in fused.moved:
            log.warning("camera %s: %s", alarm.cam, alarm.describe())
            self._emit(camera_event("camera_moved", alarm.cam, int(fused.stamp_ns), int(fused.frame),
                                    **alarm.details()))
        self._queue_holds(fused, mono)
        self._queue_looks(fused, mono)
        if self.keep_snapshots and fused.stamp_ns - self._snapshot_ns >= SNAPSHOT_EVERY_S * 1e9:
            self._save_snapshot(mono)
        return fused

    def restore(self, now_ns: int, mono: float) -> Snapshot | None:
        """Go on from the snapshot in the store (a restart): its people are sought where they were
        and its holds sent at once and kept while they are sought. Nothing when the store has none,
        or one older than ``restore_within_s`` or unreadable (said in the log). Returns it."""
        found = self.store.load_snapshot() if self.store is not None else None
        if found is None:
            return None
        stamp_ns, body = found
        age_s = (now_ns - stamp_ns) * 1e-9
        try:
            snap = Snapshot.from_json(body, where=f"event store {self.store.path}: snapshot")
        except ValueError as exc:
            log.warning("fusion: %s; starting afresh", exc)
            return None
        if age_s > self.s.restore_within_s:
            log.info("fusion: the snapshot in the store is %.0f s old (restore_within_s %.0f): starting afresh",
                     age_s, self.s.restore_within_s)
            return None
        self.pipeline.restore(snap)
        self._restored_holds = {cam: _clean_boxes(boxes) for cam, boxes in snap.holds.items()
                                if cam in self.holds_sent and boxes}
        for cam, boxes in self._restored_holds.items():
            # stamped now: newer than what the workers hold from the last server, older than the
            # frame sets this one will fuse
            msg = HoldRegions(cam=cam, stamp_ns=int(now_ns), boxes=boxes, ttl_ms=self.s.hold_ttl_ms)
            self._out.holds.append((cam, messages.encode(msg)))
            self.holds_sent[cam] = (boxes, mono)
        people = ", ".join(f"person {p.label}" + (f" ({p.name})" if p.name else "") + f" {p.posture or '?'}"
                           f" at ({p.x:.1f}, {p.y:.1f})" for p in snap.people) or "nobody"
        log.info("fusion: going on from the snapshot of %.1f s ago: %s; holds sent to %d camera(s)",
                 age_s, people, len(self._restored_holds))
        return snap

    def _save_snapshot(self, mono: float) -> None:
        snap = self.pipeline.snapshot()
        if snap is None or self.store is None:
            return
        self._snapshot_ns = snap.stamp_ns
        try:
            self.store.save_snapshot(snap.stamp_ns, snap.to_json())
        except ValueError as exc:
            self.rlog.warn("fusion", "snapshot", str(exc), mono)

    def _fuse_next(self, now_ns: int, mono: float) -> None:
        """Fuse the oldest ready set; a set the pipeline fails on is counted and logged."""
        fs = self.ready.popleft()
        try:
            self.fuse(fs, now_ns, mono)
        except Exception as exc:  # noqa: BLE001 - one bad frame set must not stop the server
            self.c.pipeline_errors += 1
            frame = _frame_of(fs)
            if self.c.pipeline_errors == 1:
                log.exception("fusion: frame %d could not be fused", frame)
            else:
                self.rlog.warn("fusion", "step", f"frame {frame} could not be fused: {exc!r}", mono)

    def _queue_set(self, fs: FrameSet) -> None:
        if len(fs.payloads) < self.min_cameras:
            self.c.frame_sets_too_few += 1
            return
        self.ready.append(fs)
        while len(self.ready) > self.s.max_ready_sets:
            self.ready.popleft()
            self.c.frame_sets_dropped += 1

    def _queue_tracks(self, fused: FusedFrame, tracks: list, mono: float) -> None:
        try:
            msg = TrackFrame(frame=int(fused.frame), stamp_ns=int(fused.stamp_ns),
                             tracks=[_track_state(t) for t in tracks][: messages.MAX_TRACKS],
                             cameras=list(dict.fromkeys(fused.cameras)))
            self._out.tracks.append(messages.encode(msg))
        except (ValueError, WireError) as exc:
            self.rlog.warn("fusion", "tracks", f"tracks of frame {fused.frame} not published: {exc}", mono)

    def _queue_looks(self, fused: FusedFrame, mono: float) -> None:
        for cam, people in fused.looks.items():
            try:
                msg = LookRequest(cam=cam, stamp_ns=int(fused.stamp_ns), people=people[: messages.MAX_TRACKS])
                self._out.looks.append((cam, messages.encode(msg)))
            except (ValueError, WireError) as exc:
                self.rlog.warn(f"camera {cam}", "look", f"look request not published: {exc}", mono)

    def _queue_holds(self, fused: FusedFrame, mono: float) -> None:
        if self._restored_holds and not self.pipeline.restoring:
            self._restored_holds = {}
        for cam in self.camera_ids:
            boxes = _clean_boxes(fused.holds.get(cam, []) + self._restored_holds.get(cam, []))
            last, sent_mono = self.holds_sent[cam]
            due = bool(boxes) and mono - sent_mono >= self.s.hold_ttl_ms / 2000.0
            if not due and _same_boxes(boxes, last, self.s.hold_slack_px):
                continue
            try:
                msg = HoldRegions(cam=cam, stamp_ns=int(fused.stamp_ns), boxes=boxes, ttl_ms=self.s.hold_ttl_ms)
                self._out.holds.append((cam, messages.encode(msg)))
            except (ValueError, WireError) as exc:
                self.rlog.warn(f"camera {cam}", "hold", f"hold regions not published: {exc}", mono)
                continue
            self.holds_sent[cam] = (boxes, mono)

    def _emit(self, rec: Event) -> None:
        """Store (committed), then queue for publishing, then write one event."""
        if self.store is not None:
            try:
                if not self.store.add(rec):
                    log.debug("event %s is already stored: not published again", rec.id)
                    return
            except ValueError as exc:  # EventNotStored: in the store's fallback file if it could be written
                self.c.events_not_stored += 1
                log.error("event %s could not be stored (publishing it anyway): %s", rec.id, exc)
        self.c.events += 1
        log.info("event %s: track %d at (%.2f, %.2f) %s", rec.kind, rec.track, rec.x, rec.y, rec.details or "")
        try:
            key = keys.event_key(self.prefix, rec.kind, int(rec.track))
            self._out.events.append((key, rec.to_json()))
        except (ValueError, WireError) as exc:
            self.c.events_unpublishable += 1
            log.error("event %s could not be published: %s", rec.id, exc)
        if self.outputs is not None:
            self.outputs.write_event(rec)

    def take(self) -> Outbox:
        """Everything queued for publishing since the last call (the offline replay discards it)."""
        out, self._out = self._out, Outbox()
        return out

    # ------------------------------------------------------------------ camera health

    def _event_time(self, now_ns: int) -> tuple[int, int]:
        """(stamp_ns, frame) for an event not tied to a frame set: the capture clock of the
        last fused set carried forward by the server's elapsed time; the server's clock before any."""
        if self.last_stamp is None:
            return int(now_ns), self.last_frame
        stamp, then = self.last_stamp
        return stamp + max(0, int(now_ns) - then), self.last_frame

    def _lead_ms(self, health: _CameraHealth, mono: float, *, own_included: bool = False) -> float | None:
        """How far the newest mask's stamp runs ahead of the other cameras' clocks, in ms: its
        ``stamp - receive time`` less the median of the same for the other live cameras' newest
        masks (newest against newest, so that recordings played faster than real time, where
        every camera's stamps run ahead alike, compare equal); with ``own_included``, the median
        over every live camera's, its own among them (one wrong clock then does not move the
        reference of the right ones). None when no other camera has sent masks lately."""
        others = [h.last_offset_ms for h in self.health.values()
                  if h is not health and not h.lost and h.last_offset_ms is not None and h.recent(mono, self.s.stale_s)]
        if not others or health.last_offset_ms is None:
            return None
        return health.last_offset_ms - statistics.median([*others, health.last_offset_ms] if own_included else others)

    def _check_shape(self, msg: MaskFrame) -> None:
        """Refuse, before it is inflated, a mask of a size the camera cannot send."""
        cam = self.cameras.get(msg.cam)
        if cam is None:
            return
        if not mask_size_fits(cam.width, cam.height, msg.width, msg.height):
            low, high = _MASK_SCALES
            raise _Shape(f"MaskFrame: a {msg.width}x{msg.height} mask is not a size camera {msg.cam!r} sends (its "
                         f"{cam.width}x{cam.height} image scaled by a mask_scale in {low:g}..{high:g})")

    def _within_budget(self, health: _CameraHealth, mono: float) -> bool:
        """Whether the camera's mask arriving at ``mono`` may be decoded: a bucket of a second's masks
        at its frame rate, refilled at :data:`_BUDGET_RATE` times that rate, so that however many masks
        a camera (or whoever publishes on its key) sends, decoding them costs a bounded share of each
        frame period; a catching-up burst passes. Asked only for masks whose header passed its checks
        (the image inflation is the cost it bounds; unreadable messages cost next to nothing and
        must not starve the camera's own masks). Not with ``free_timeline`` (recordings played faster
        than real time)."""
        if self.s.free_timeline:
            return True
        fps = self._fps[health.cam]
        if health.budget_mono is None:
            health.budget = fps
        else:
            health.budget = min(fps, health.budget + _BUDGET_RATE * fps * max(0.0, mono - health.budget_mono))
        health.budget_mono = mono
        if health.budget < 1.0:
            return False
        health.budget -= 1.0
        return True

    def _check_skew(self, health: _CameraHealth, now_ns: int, mono: float) -> None:
        if not health.refusing and len(health.offset_ms) < min(10, health.offset_ms.maxlen):
            return
        if self.s.free_timeline:
            # the stamps are the recording's own (days or years before the server's clock, or played
            # faster than it): a camera is judged against the other cameras only
            offset = self._lead_ms(health, mono, own_included=True)
            if offset is None:
                return
        else:
            offset = health.clock_offset_ms()
        limit = self.s.max_clock_skew_ms
        # Late masks on a busy server are its own queue: a camera that seems to lag is judged once it
        # has for two status periods (the load is measured over one) in which the server kept up.
        if offset < -limit and not self.overloaded:
            if health.behind_since_mono is None:
                health.behind_since_mono = mono
        else:
            health.behind_since_mono = None
        behind = health.behind_since_mono is not None and mono - health.behind_since_mono >= 2 * self.s.status_period_s
        if not health.skewed and (offset > limit or behind):
            health.skewed = True
            log.warning("camera %s: clock off by %.0f ms (the fastest of its last %d masks; limit %.0f ms)",
                        health.cam, offset, len(health.offset_ms), limit)
            self._skew_event(health, offset, now_ns, mono)
        elif health.skewed and abs(offset) < 0.8 * limit:
            health.skewed = False
            log.info("camera %s: clock back in step (offset %.0f ms)", health.cam, offset)

    def _skew_event(self, health: _CameraHealth, offset_ms: float, now_ns: int, mono: float) -> None:
        """One ``clock_skew`` event, at most one per camera every ``_SKEW_EVENT_EVERY_S``."""
        if health.skew_event_mono is not None and mono - health.skew_event_mono < _SKEW_EVENT_EVERY_S:
            return
        health.skew_event_mono = mono
        self._emit(camera_event("clock_skew", health.cam, *self._event_time(now_ns),
                                offset_ms=round(max(-1e12, min(1e12, offset_ms)), 1),
                                max_ms=float(self.s.max_clock_skew_ms)))

    # ------------------------------------------------------------------ status

    def status(self, now_ns: int, mono: float) -> Status:
        """Every camera's health and the fusion counters, as of ``now_ns``/``mono``."""
        cams = []
        for cam in self.camera_ids:
            h = self.health[cam]
            sc = self.sync.counters[cam]
            offset = h.clock_offset_ms()
            state = h.state(mono, self.s.stale_s)
            cams.append(CameraStatus(
                cam=cam,
                state=state,
                reason=h.reason(state, mono, self.s.stale_s),
                received=h.received,
                dropped=h.seq_gaps + sum(sc[k] for k in _SYNC_DROPS) + h.replayed + h.repeated + h.throttled,
                late=sum(sc[k] for k in _SYNC_LATE) + h.ahead + h.future,
                undecodable=h.undecodable,
                rate_hz=float(h.rate_hz(mono)),
                latency_ms=float(statistics.fmean(h.latency_ms)) if h.latency_ms else 0.0,
                last_seen_ns=h.last_seen_ns,
                clock_offset_ms=float(offset) if offset is not None else 0.0,
                refused=h.refused,
                consistency=self.pipeline.consistency.figure(cam),
                view_deg=self.pipeline.consistency.view_deg(cam),
            ))
        return Status(stamp_ns=int(now_ns), cameras=cams, frame_sets=self.c.frames_fused,
                      frame_sets_dropped=self.c.frame_sets_dropped, events_not_stored=self.c.events_not_stored,
                      events_pending=self.store.pending if self.store is not None else 0,
                      state="overloaded" if self.overloaded else "ok", load=round(min(self.load, 100.0), 3))

    def note_work(self, busy_s: float, mono: float) -> None:
        """The process adapter spent ``busy_s`` on the node's work (decoding, fusing) up to ``mono``.
        Over each ``status_period_s`` the share of the time so spent is :attr:`load`; the server
        is :attr:`overloaded` from a share of :data:`OVERLOADED_LOAD` or a frame set dropped for
        being slow, until the share is under :data:`RELIEVED_LOAD` with none dropped for a period."""
        self._busy_s += max(0.0, float(busy_s))
        if self._load_since is None:
            self._load_since, self._dropped_then = mono, self.c.frame_sets_dropped
            return
        span = mono - self._load_since
        if span < self.s.status_period_s:
            return
        self.load = self._busy_s / span
        dropped = self.c.frame_sets_dropped > self._dropped_then
        was = self.overloaded
        if self.load >= OVERLOADED_LOAD or dropped:
            self.overloaded = True
        elif self.load < RELIEVED_LOAD:
            self.overloaded = False
        if self.overloaded != was:
            (log.warning if self.overloaded else log.info)(
                "fusion: %s (busy %.0f %% of the last %.1f s%s)", "overloaded: frame sets wait or are dropped"
                if self.overloaded else "no longer overloaded", 100 * self.load, span,
                f", {self.c.frame_sets_dropped - self._dropped_then} sets dropped" if dropped else "")
        self._busy_s, self._load_since, self._dropped_then = 0.0, mono, self.c.frame_sets_dropped

    def _queue_status(self, now_ns: int, mono: float) -> None:
        try:
            self._out.status = messages.encode(self.status(now_ns, mono))
        except (ValueError, WireError) as exc:
            self.rlog.warn("fusion", "status", f"status not published: {exc}", mono)

    def summary(self, now_ns: int, mono: float) -> str:
        """One line of what the node has done, for the log at exit."""
        c = self.c
        parts = [f"{c.frames_fused} frames fused ({c.frames_with_range} with range)", f"{c.events} events",
                 f"{c.events_not_stored} not stored",
                 f"{c.frame_sets_dropped} frame sets dropped (slow)", f"{c.frame_sets_too_few} with too few cameras",
                 f"{c.inbox_dropped} masks dropped on arrival", f"{c.unknown_camera} from unknown cameras",
                 f"{c.pipeline_errors} fusion errors", f"{c.queries} history queries"]
        for cs in self.status(now_ns, mono).cameras:
            parts.append(f"{cs.cam}: received {cs.received}, undecodable {cs.undecodable}, dropped {cs.dropped}, "
                         f"late {cs.late}, {cs.state}")
        return "; ".join(parts)


# --------------------------------------------------------------------------- history


def history_replies(store: EventStore, history_key: str, asked_key: str, parameters: str, *,
                    utc_offset_h: float = 0.0) -> list[tuple[str, bytes | str, str]]:
    """The replies to one history query: ``(key, payload, encoding)`` per stored event.

    history_key: ``<p>/history/events``. asked_key: the key expression the query
    asked for. parameters: its selector parameters (``since``, ``until``,
    ``kind``, ``track``, ``limit``, ``format``). Each reply goes on
    ``<history_key>/<event id>`` when the asked key covers it (zenoh's default
    consolidation keeps one reply per key, so one key per event lets stock
    clients see them all), else on the history key. Payloads are JSON text, or
    msgpack with ``format=msgpack``. ValueError (the reply-error text) on a bad
    selector. A stored event too large to send is logged and left out.
    """
    import zenoh  # key expressions only: no session

    flt = parse_history_selector(parameters, utc_offset_h=utc_offset_h)
    records = store.query_filter(flt)
    asked = zenoh.KeyExpr(asked_key)
    replies: list[tuple[str, bytes | str, str]] = []
    for rec in records:
        key = history_key
        try:
            own = f"{history_key}/{keys.validate_chunk(rec.id, 'event id')}"
            if asked.intersects(zenoh.KeyExpr(own)):
                key = own
        except (ValueError, zenoh.ZError):
            pass
        try:
            if flt.format == "msgpack":
                replies.append((key, messages.encode(rec), messages.MSGPACK_ENCODING))
            else:
                replies.append((key, rec.to_json(), messages.JSON_ENCODING))
        except (ValueError, WireError) as exc:
            log.warning("history: stored event %s cannot be sent: %s", rec.id, exc)
    return replies


# --------------------------------------------------------------------------- wire conversion


def camera_event(kind: str, cam: str, stamp_ns: int, frame: int, **details: Any) -> Event:
    """A camera-health event (``camera_lost``, ``camera_back``, ``clock_skew``, ``camera_moved``) at a
    server time (``camera_moved``: at its frame set's capture time)."""
    return Event(id=event_id(stamp_ns, f"{kind}-{cam}", -1), kind=kind, track=-1, stamp_ns=int(stamp_ns),
                 frame=int(frame), x=0.0, y=0.0, details={"camera": cam, **details})


def mask_size_fits(image_width: int, image_height: int, width: int, height: int) -> bool:
    """Whether a ``width`` x ``height`` mask is the size a worker makes of an ``image_width`` x
    ``image_height`` image at some ``mask_scale`` the site file accepts: both sides rounded from the same
    scale (``round(image side * scale)``, as ``Camera.scaled`` and the segmenter do). Bigger masks, and masks
    of another shape, are refused before they are decoded: a camera cannot make the server inflate more
    than its own image's pixels."""
    low, high = _MASK_SCALES
    # the scales that round to each side, closed at both ends (a half rounds either way)
    lo = max(low, (width - 0.5) / image_width, (height - 0.5) / image_height)
    hi = min(high, (width + 0.5) / image_width, (height + 0.5) / image_height)
    return width >= 1 and height >= 1 and lo <= hi + 1e-12


class _Mismatch(WireError):
    """A mask message whose camera differs from its key's camera."""


class _Shape(WireError):
    """A mask whose shape cannot be the camera's."""


def _frame_of(fs: FrameSet) -> int:
    """A frame set's frame number: the most common sequence number among its masks."""
    return Counter(fs.seqs.values()).most_common(1)[0][0]


def _track_state(t: Any) -> TrackState:
    posture = t.posture if t.posture in messages.POSTURES else "unknown"
    return TrackState(
        id=int(t.id), x=float(t.x), y=float(t.y), z_top=max(0.0, float(t.z_top)),
        volume_m3=max(0.0, _finite(t.volume_m3)), posture=posture,
        reliability=min(1.0, max(0.0, _finite(t.reliability))), vx=_finite(t.vx), vy=_finite(t.vy),
        still=bool(t.still), person=getattr(t, "person", None),
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
