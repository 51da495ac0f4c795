"""The fusion server's process: zenoh in, :class:`~fusion_server.node.FusionNode` in the middle, zenoh out.

Every decision (decoding, camera health and clock skew, frame sets, holds,
events, status) is the node's; this module only declares the zenoh entities,
feeds the node what arrives with its arrival time, and publishes what the
node hands back:

* masks on ``<p>/cam/*/mask`` and camera liveliness on ``<p>/alive/cam/*``
  (with history), and a worker's stop notice (a DELETE on its mask key, put
  in the liveliness inbox to keep its order with the token): the callbacks only put ``(key, payload, receive time)`` into
  bounded inboxes (drop-oldest, counted as ``inbox_dropped``); a payload over
  the mask size limit is never copied, only its size goes on;
* ``<p>/tracks`` and ``<p>/status`` (congestion control DROP),
  ``<p>/cam/<cam>/hold`` and ``<p>/cam/<cam>/look`` (DROP: a newer request
  replaces a lost one), ``<p>/events/<kind>/<track>`` (JSON text,
  BLOCK, reliable; the 32 most recent event keys keep their publishers);
* the token ``<p>/alive/fusion``;
* a queryable on ``<p>/history/events/**`` (which includes
  ``<p>/history/events`` itself), declared only once the store is open.
  Queries are answered on their own thread (the store is thread-safe) with
  :func:`~fusion_server.node.history_replies`; a bad selector gets
  ``reply_err`` with the reason, a full queue ``reply_err`` at once, and every
  query is finalised (``with query:``). On exactly ``<p>/history/events`` all
  replies share one key, so a get there needs consolidation ``NONE`` to see
  them all; under ``<p>/history/events/**`` each event has its own key.
* a queryable on ``<p>/ack/*``: a query on ``<p>/ack/<event id>?by=<name>``
  acknowledges that alarm. The loop answers it (the node stores and
  publishes the ``alarm_ack`` event, then the reply carries it); a second
  acknowledgement gets the first one back; an unknown id gets ``reply_err``.

:func:`run_forever` opens the session from the site's ``[zenoh]`` section
(plus command-line overrides), turns SIGINT/SIGTERM into a clean stop and
always closes the session; with ``exit_after_idle_s`` it stops (exit 0) once
no mask has arrived for that long, fusing the sets still pending first.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import OrderedDict, deque
from typing import Any

import zenoh

from common import keys, messages
from common.camera import Camera
from common.messages import MaskFrame
from fusion_server.event_store import EventStore
from fusion_server.node import FusionCounters, FusionNode, FusionSettings, Outbox, history_replies
from fusion_server.outputs import RunOutputs
from fusion_server.pipeline import FusionPipeline
from fusion_server.settings import DEFAULT_STORE_NAME

__all__ = ["DEFAULT_STORE_NAME", "FusionCounters", "FusionSettings", "run", "run_forever"]

log = logging.getLogger("voxelwatch.fusion")

_EVENT_PUBLISHERS = 32
_MAX_ERROR = 400
_MAX_ACKS_WAITING = 64


def run_forever(settings: FusionSettings, cameras: dict[str, Camera]) -> int:
    """Build the pipeline, open the zenoh session and :func:`run` until stopped. ``cameras``: the
    calibrations :meth:`FusionSettings.announce` checked and loaded.

    Returns the exit code: 0 after a stop (a signal at any moment, the lookup
    tables' building included, or idle; also while still waiting for zenoh: an
    unreachable router is logged once and retried with back-off), 1 when the
    zenoh session cannot be opened (a port that cannot be listened on), 2 when
    the pipeline cannot be built or the event store or output folder is unusable
    (the reason is logged).
    """
    from common.shell import Stopped, serve, stop_if_asked, stopped_raises

    try:
        with stopped_raises(who="fusion", log=log):   # a signal while the lookup tables are built
            try:
                pipeline = settings.build_pipeline(cameras)
            except ValueError as exc:
                log.error("%s", exc)
                return 2
            stop_if_asked()
            return serve(settings.zenoh_config, who="fusion", endpoints=list(settings.endpoints()), log=log,
                         work=lambda session, stop: run(session, settings, stop, pipeline))
    except Stopped:
        return 0


def run(session: Any, settings: FusionSettings, stop_event: threading.Event, pipeline: FusionPipeline) -> int:
    """Serve on an open zenoh ``session`` until ``stop_event`` is set (or the idle timeout).

    The caller owns and closes the session. Returns 0 on a normal stop, 2 when
    the event store or the output folder cannot be opened.
    """
    try:
        if settings.store_path is None:
            raise ValueError("fusion: no event store given (settings.store_path)")
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
    node = FusionNode(settings, pipeline, store=store, outputs=outputs)
    node.keep_snapshots = True
    try:
        node.restore(time.time_ns(), time.monotonic())
    except ValueError as exc:   # a store that cannot be read: go on without
        log.warning("fusion: %s; starting afresh", exc)
    server = _Server(session, node, stop_event)
    try:
        server.declare()
        return server.loop()
    finally:
        server.close()
        if outputs is not None:
            outputs.close()
        store.close()


# --------------------------------------------------------------------------- the process


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
        """Every query gets an answer: its events, or one error of at most ``_MAX_ERROR`` characters."""
        self.counters.queries += 1
        try:
            replies = history_replies(self.store, self.key, str(query.key_expr), str(query.parameters),
                                      utc_offset_h=self.utc_offset_h)
        except ValueError as exc:
            query.reply_err(_bounded(str(exc)), encoding="text/plain")
            return
        except Exception as exc:  # noqa: BLE001 - a query the store chokes on still gets an answer
            log.warning("history query %s failed: %s", _bounded(str(query.parameters), 80), _bounded(repr(exc)))
            query.reply_err("voxelwatch history: the query could not be answered (see the fusion server's log)",
                            encoding="text/plain")
            return
        for key, payload, encoding in replies:
            query.reply(key, payload, encoding=encoding)


class _Server:
    """The declared zenoh entities, the inboxes and the loop around one :class:`FusionNode`."""

    def __init__(self, session: Any, node: FusionNode, stop: threading.Event) -> None:
        self.session = session
        self.node = node
        self.s = node.s
        self.stop = stop
        self.wake = threading.Event()
        self.masks = _Inbox(self.s.inbox_per_camera * len(node.camera_ids), self.wake)
        self.alive = _Inbox(1024, self.wake)
        self._entities: list[Any] = []
        self._event_pubs: OrderedDict[str, Any] = OrderedDict()
        self._history: _HistoryResponder | None = None
        self._acks: deque = deque()
        self._acks_lock = threading.Lock()

    def declare(self) -> None:
        p = self.node.prefix
        drop = zenoh.CongestionControl.DROP
        self.tracks_pub = self._keep(self.session.declare_publisher(
            keys.tracks_key(p), encoding=messages.MSGPACK_ENCODING, congestion_control=drop))
        self.status_pub = self._keep(self.session.declare_publisher(
            keys.status_key(p), encoding=messages.MSGPACK_ENCODING, congestion_control=drop))
        self.hold_pubs = {cam: self._keep(self.session.declare_publisher(
            keys.hold_key(p, cam), encoding=messages.MSGPACK_ENCODING, congestion_control=drop))
            for cam in self.node.camera_ids}
        self.look_pubs = {cam: self._keep(self.session.declare_publisher(
            keys.look_key(p, cam), encoding=messages.MSGPACK_ENCODING, congestion_control=drop))
            for cam in self.node.camera_ids}
        # the store is open (run() opened it) before anyone can ask it anything
        self._history = _HistoryResponder(self.node.store, p, self.s.site.utc_offset_hours, self.s.history_queue,
                                          self.node.c)
        self._keep(self.session.declare_queryable(f"{keys.history_key(p)}/**", self._history.offer))
        self._keep(self.session.declare_queryable(keys.ack_wildcard(p), self._on_ack))
        self._keep(self.session.liveliness().declare_subscriber(
            keys.alive_cameras_wildcard(p), self._on_alive, history=True))
        self._keep(self.session.declare_subscriber(keys.mask_wildcard(p), self._on_mask))
        self._keep(self.session.liveliness().declare_token(keys.alive_fusion_key(p)))
        log.info("fusion: site %s, cameras %s, prefix %s, store %s%s", self.s.site.name,
                 ", ".join(self.node.camera_ids), p, self.s.store_path,
                 f", files in {self.s.out_dir}" if self.s.out_dir else "")

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
        if sample.kind == zenoh.SampleKind.DELETE:  # a worker stopping on purpose; in order with its token
            self.alive.put((str(sample.key_expr), None, time.time_ns()))
            return
        payload = sample.payload
        n = len(payload)
        data = payload.to_bytes() if n <= MaskFrame.MAX_BYTES else n  # oversize: never copied
        self.masks.put((str(sample.key_expr), data, time.time_ns(), time.monotonic()))

    def _on_ack(self, query: Any) -> None:
        """An acknowledgement query: answered from the loop (the node stores and publishes it)."""
        with self._acks_lock:
            if len(self._acks) < _MAX_ACKS_WAITING:
                self._acks.append(query)
                self.wake.set()
                return
        with query:
            query.reply_err("voxelwatch ack: too many acknowledgements waiting, try again", encoding="text/plain")

    def _answer_acks(self) -> None:
        """Every acknowledgement query gets an answer: the ``alarm_ack`` event, or one bounded error."""
        with self._acks_lock:
            waiting, self._acks = list(self._acks), deque()
        for query in waiting:
            try:
                with query:
                    try:
                        alarm_id = str(query.key_expr).rsplit("/", 1)[-1]
                        by = _parameter(str(query.parameters), "by")
                        ack = self.node.acknowledge(alarm_id, by, time.time_ns())
                    except ValueError as exc:
                        query.reply_err(_bounded(f"voxelwatch ack: {exc}"), encoding="text/plain")
                        continue
                    query.reply(str(query.key_expr), ack.to_json(), encoding=messages.JSON_ENCODING)
            except Exception as exc:  # noqa: BLE001 - a failed reply must not stop the loop
                log.warning("acknowledgement query failed: %s", _bounded(repr(exc)))

    def _on_alive(self, sample: Any) -> None:
        self.alive.put((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, time.time_ns()))

    def loop(self) -> int:
        node = self.node
        while not self.stop.is_set():
            self.wake.wait(0.0 if node.pending else 0.05)
            self.wake.clear()
            for key, present, now_ns in self.alive.drain():
                if present is None:
                    node.on_stopping(key, now_ns)
                else:
                    node.on_liveliness(key, present, now_ns)
            work = time.monotonic()
            for key, data, recv_ns, arrived in self.masks.drain():
                node.on_mask(key, data, recv_ns, arrived)
            node.c.inbox_dropped = self.masks.dropped
            if self._acks:
                self._answer_acks()
            out = node.tick(time.time_ns(), time.monotonic())
            done = time.monotonic()
            node.note_work(done - work, done)
            self._publish(out)
            if node.idle(time.monotonic()):
                log.info("fusion: no mask for %.1f s: finishing", self.s.exit_after_idle_s)
                self._publish(node.finish(time.time_ns(), time.monotonic()))
                break
        self._publish(node.report(time.time_ns(), time.monotonic()))
        log.info("fusion stopped: %s", node.summary(time.time_ns(), time.monotonic()))
        return 0

    def _publish(self, out: Outbox) -> None:
        for payload in out.tracks:
            self._put(self.tracks_pub, payload, "tracks")
        for key, text in out.events:
            self._put(self._event_publisher(key), text, f"event on {key}")
        for cam, payload in out.holds:
            self._put(self.hold_pubs[cam], payload, f"hold regions of camera {cam}")
        for cam, payload in out.looks:
            self._put(self.look_pubs[cam], payload, f"look request of camera {cam}")
        if out.status is not None:
            self._put(self.status_pub, out.status, "status")

    def _put(self, publisher: Any, payload: bytes | str, what: str) -> None:
        try:
            publisher.put(payload)
        except Exception as exc:  # noqa: BLE001 - zenoh reports every failure as ZError
            self.node.rlog.warn("fusion", f"put {what}", f"{what} not published: {exc}", time.monotonic())

    def _event_publisher(self, key: str) -> Any:
        pub = self._event_pubs.get(key)
        if pub is None:
            pub = self.session.declare_publisher(
                key, encoding=messages.JSON_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE)
            self._event_pubs[key] = pub
            while len(self._event_pubs) > _EVENT_PUBLISHERS:
                _, old = self._event_pubs.popitem(last=False)
                old.undeclare()
        else:
            self._event_pubs.move_to_end(key)
        return pub


def _parameter(parameters: str, name: str) -> str:
    """The value of ``name`` in a selector's parameters (``a=1;b=2``, ``&`` also separates; values
    percent-decoded); "" if absent."""
    from urllib.parse import unquote

    for item in parameters.replace("&", ";").split(";"):
        key, _, value = item.partition("=")
        if key.strip() == name:
            return unquote(value).strip()
    return ""


def _bounded(text: str, limit: int = _MAX_ERROR) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."
