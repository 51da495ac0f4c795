"""``voxelwatch view``'s process: a zenoh reader on one side, an aiohttp web server on the other.

Zenoh side (a client or peer session like any reader's): subscribers on
``<p>/tracks``, ``<p>/events/**``, ``<p>/status``, the masks
``<p>/cam/*/mask`` (for the installer's page) and the fusion server's
liveliness token. Their callbacks only hand the payload to an :class:`Inbox`
under a lock -- the newest track frame, status and mask of each camera
replace older ones, events go into a bounded queue -- and wake the asyncio
loop at most once until it has drained the inbox
(``loop.call_soon_threadsafe``). Everything else happens on the loop:
decoding, :class:`~view.state.LiveState`, and the push to browsers.
History queries and acknowledgements are zenoh ``get`` calls, run in worker
threads so that the loop never waits on the network.

Web side:

| path | what |
|---|---|
| ``/`` | the live page (plan, alarm banner, events, timeline, cameras) |
| ``/install/<cam>`` | the installer's page of one camera |
| ``/login`` | the token form (GET), the login (POST: token, name) |
| ``/static/...`` | the page's own script and style (no data in them) |
| ``/api/plan`` | the plan geometry (:mod:`view.plan`) and the view settings |
| ``/api/stream`` | server-sent events: ``snapshot`` first, then ``tracks``, ``event``, ``alarms``, ``status``, ``fusion`` |
| ``/api/events`` | the history (``kind``, ``since``, ``until``, ``limit`` as the history queryable takes them) |
| ``/api/timeline`` | the day per person (since the home's midnight, or ``since``) |
| ``/api/ack`` | POST ``{"event": id}``: acknowledge an alarm through the fusion server |
| ``/api/install/<cam>`` | the floor outline and hot spots in the camera's pixels, and its status |
| ``/api/mask/<cam>.png`` | the camera's latest mask as a PNG |

Each browser has its own :class:`Client`: one slot for the newest track
frame and one for the newest status (a slow browser skips frames, it never
queues them), a bounded queue of events (an overflow is counted and the page
told to reload the list), and the alarm list (always whole). A frame goes
out as soon as it is decoded, so the page moves at the fusion rate.

Access: every page and API needs the site's token, once. The login form (or
``?token=`` in a link) checks it in constant time and sets an HttpOnly,
SameSite=Strict cookie holding the name typed at login and an HMAC of it
keyed with the token (so a new token logs everyone out, and a restart does
not). A wrong token is a 401 (form) or 403 (link) page that says so. POSTs
from another origin are refused.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import json
import logging
import re
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlencode

from aiohttp import web

from common import keys, messages
from common.messages import Event, Status, TrackFrame, WireError
from view.state import LiveState

log = logging.getLogger("voxelwatch.view")

STATIC = Path(__file__).resolve().parent / "static"
COOKIE = "voxelwatch_view"
MAX_CLIENTS = 64
"""Browsers served at once; the next one is told to try later (503)."""
CLIENT_EVENTS = 256
"""Events queued per browser before the oldest are dropped (and the page reloads its list)."""
INBOX_EVENTS = 4096
"""Events waiting for the loop before the oldest are dropped (counted)."""
HEARTBEAT_S = 15.0
QUERY_TIMEOUT_S = 10.0
ACK_TIMEOUT_S = 10.0
MAX_NAME = 64
DAY_NS = 86_400_000_000_000


# --------------------------------------------------------------------------- access


class Access:
    """The token check and the session cookie (see the module text)."""

    def __init__(self, token: str) -> None:
        if not token:
            raise ValueError("no access token")
        self._token = token.encode("utf-8")

    def token_ok(self, given: str | None) -> bool:
        return given is not None and hmac.compare_digest(given.encode("utf-8"), self._token)

    def cookie_for(self, name: str) -> str:
        body = base64.urlsafe_b64encode(name.encode("utf-8")).decode("ascii").rstrip("=")
        return f"{body}.{self._sign(body)}"

    def name_of(self, cookie: str | None) -> str | None:
        """The name in a valid cookie, None for a missing or forged one."""
        if not cookie or "." not in cookie:
            return None
        body, _, sig = cookie.rpartition(".")
        if not hmac.compare_digest(sig.encode("ascii", "replace"), self._sign(body).encode("ascii")):
            return None
        try:
            return base64.urlsafe_b64decode(body + "=" * (-len(body) % 4)).decode("utf-8")
        except ValueError:
            return None

    def _sign(self, body: str) -> str:
        return hmac.new(self._token, b"voxelwatch view\0" + body.encode("ascii", "replace"), hashlib.sha256).hexdigest()


def clean_name(name: str | None) -> str:
    """A name typed at login as it may go into an acknowledgement (``by=<name>``): printable,
    without the selector's separators, at most 64 characters; "view" when nothing is left."""
    text = "".join(c for c in (name or "") if c.isprintable() and c not in ";&=?#/*$").strip()[:MAX_NAME]
    return text or "view"


# --------------------------------------------------------------------------- zenoh to the loop


class Inbox:
    """What zenoh callbacks hand over, kept bounded, and the wake-up of the loop.

    ``put_*`` run on zenoh's threads: they only store under a lock and, when the
    loop is not already due to drain, schedule ``drain`` on it once.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, drain: Callable[[], None]) -> None:
        self._loop = loop
        self._drain = drain
        self._lock = threading.Lock()
        self._scheduled = False
        self.tracks: bytes | None = None
        self.status: bytes | None = None
        self.alive: bool | None = None
        self.events: deque[bytes] = deque(maxlen=INBOX_EVENTS)
        self.masks: dict[str, bytes] = {}
        self.events_dropped = 0
        self.frames_in = 0

    def put_tracks(self, payload: bytes) -> None:
        with self._lock:
            self.tracks = payload
            self.frames_in += 1
            self._wake()

    def put_status(self, payload: bytes) -> None:
        with self._lock:
            self.status = payload
            self._wake()

    def put_event(self, payload: bytes) -> None:
        with self._lock:
            if len(self.events) == self.events.maxlen:
                self.events_dropped += 1
            self.events.append(payload)
            self._wake()

    def put_alive(self, alive: bool) -> None:
        with self._lock:
            self.alive = alive
            self._wake()

    def put_mask(self, cam: str, payload: bytes) -> None:
        with self._lock:  # read on request only: no wake-up
            self.masks[cam] = payload

    def mask(self, cam: str) -> bytes | None:
        with self._lock:
            return self.masks.get(cam)

    def take(self) -> tuple[bytes | None, bytes | None, bool | None, list[bytes]]:
        """Everything waiting, emptied: (tracks, status, alive, events)."""
        with self._lock:
            out = (self.tracks, self.status, self.alive, list(self.events))
            self.tracks = self.status = self.alive = None
            self.events.clear()
            self._scheduled = False
            return out

    def _wake(self) -> None:
        if not self._scheduled:
            self._scheduled = True
            try:
                self._loop.call_soon_threadsafe(self._drain)
            except RuntimeError:  # the loop has closed: the process is stopping
                pass


# --------------------------------------------------------------------------- browsers


@dataclass(eq=False)
class Client:
    """One open page: the newest frame and status, a bounded event queue, and the alarm list."""

    wake: asyncio.Event = field(default_factory=asyncio.Event)
    frame: str | None = None
    status: str | None = None
    fusion: str | None = None
    alarms: str | None = None
    events: deque = field(default_factory=lambda: deque(maxlen=CLIENT_EVENTS))
    events_dropped: int = 0
    frames_sent: int = 0

    def push_event(self, text: str) -> None:
        if len(self.events) == self.events.maxlen:
            self.events_dropped += 1
        self.events.append(text)
        self.wake.set()

    def pending(self) -> list[tuple[str, str]]:
        """The SSE messages due, oldest kind first, emptied."""
        out: list[tuple[str, str]] = []
        if self.alarms is not None:
            out.append(("alarms", self.alarms))
        if self.events_dropped:
            out.append(("resync", json.dumps({"dropped": self.events_dropped})))
            self.events_dropped = 0
        while self.events:
            out.append(("event", self.events.popleft()))
        if self.status is not None:
            out.append(("status", self.status))
        if self.fusion is not None:
            out.append(("fusion", self.fusion))
        if self.frame is not None:
            out.append(("tracks", self.frame))
            self.frames_sent += 1
        self.alarms = self.status = self.fusion = self.frame = None
        return out


# --------------------------------------------------------------------------- the view


class View:
    """The live view of one site over one open zenoh session (the session is the caller's)."""

    def __init__(self, session: Any, site: Any, *, token: str, prefix: str | None = None,
                 plan: dict[str, Any] | None = None) -> None:
        from view.plan import plan_of

        self.session = session
        self.site = site
        self.prefix = prefix or site.prefix
        keys.validate_prefix(self.prefix)
        self.access = Access(token)
        self.settings = site.view
        self.state = LiveState(alarm_kinds=site.view.alarms, trail_s=site.view.trail_s)
        self.cameras = site.load_cameras()
        self.plan = plan if plan is not None else plan_of(site, self.cameras).to_dict()
        self.clients: set[Client] = set()
        self.fusion_alive: bool | None = None
        self.undecodable = 0
        self._install: dict[str, dict[str, Any]] = {}
        self._png: dict[str, tuple[bytes, bytes]] = {}
        self._entities: list[Any] = []
        self._pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="view-zenoh")
        self.inbox: Inbox | None = None
        self._seeded = False

    # ------------------------------------------------------------------ zenoh

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Declare the subscribers (callbacks feed the inbox of ``loop``) and ask the history once."""
        self.inbox = inbox = Inbox(loop, self._drain)
        p = self.prefix

        def mask(sample: Any) -> None:
            try:
                cam = keys.camera_of(str(sample.key_expr), p)
            except ValueError:
                return
            if cam in self.cameras:
                inbox.put_mask(cam, sample.payload.to_bytes())

        def alive(sample: Any) -> None:
            import zenoh

            inbox.put_alive(sample.kind == zenoh.SampleKind.PUT)

        s = self.session
        self._entities = [
            s.declare_subscriber(keys.tracks_key(p), lambda sample: inbox.put_tracks(sample.payload.to_bytes())),
            s.declare_subscriber(keys.events_wildcard(p), lambda sample: inbox.put_event(sample.payload.to_bytes())),
            s.declare_subscriber(keys.status_key(p), lambda sample: inbox.put_status(sample.payload.to_bytes())),
            s.declare_subscriber(keys.mask_wildcard(p), mask),
            s.liveliness().declare_subscriber(keys.alive_fusion_key(p), alive, history=True),
        ]
        loop.create_task(self._seed())

    def close(self) -> None:
        for entity in self._entities:
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing already
                pass
        self._entities.clear()
        self._pool.shutdown(wait=False, cancel_futures=True)

    def query_history(self, parameters: dict[str, str]) -> list[Event]:
        """The stored events matching ``parameters`` (blocking: run it in a thread). ValueError
        with the fusion server's reason for a refused query."""
        selector = f"{keys.history_key(self.prefix)}/**"
        params = ";".join(f"{k}={v}" for k, v in parameters.items() if v)
        events, errors = [], []
        for reply in self.session.get(f"{selector}?{params}" if params else selector, timeout=QUERY_TIMEOUT_S):
            if reply.ok is not None:
                try:
                    events.append(messages.decode_event(reply.ok.payload.to_bytes()))
                except WireError as exc:
                    log.warning("history: unreadable reply on %s: %s", reply.ok.key_expr, exc)
            else:
                errors.append(reply.err.payload.to_string())
        if errors and not events:
            raise ValueError(errors[0])
        events.sort(key=lambda e: e.stamp_ns)
        return events

    def acknowledge(self, event_id: str, name: str) -> Event:
        """Ask the fusion server to acknowledge the alarm ``event_id`` for ``name`` (blocking).
        Returns the stored ``alarm_ack`` event; ValueError with the reason otherwise."""
        key = keys.ack_key(self.prefix, event_id)
        for reply in self.session.get(f"{key}?by={quote(clean_name(name), safe='')}", timeout=ACK_TIMEOUT_S):
            if reply.ok is not None:
                return messages.decode_event(reply.ok.payload.to_bytes())
            raise ValueError(reply.err.payload.to_string())
        raise ValueError("the fusion server did not answer (is it running?)")

    async def _seed(self) -> None:
        """The alarms of the last day still waiting, and today's events for the timeline, from the
        history (postures are not stored: the timeline has them from when the view started)."""
        loop = asyncio.get_running_loop()
        since = min(time.time_ns() - DAY_NS, self.day_start_ns())
        try:
            events = await loop.run_in_executor(self._pool, self.query_history,
                                                {"since": str(since), "limit": "5000"})
        except Exception as exc:  # noqa: BLE001 - the history is a help, not a must
            log.warning("view: the history could not be read at start: %s", exc)
            return
        self._seeded = True
        before = len(self.state.alarms)
        self.state.seed(events)
        if events:
            log.info("view: %d events of the last day from the history, %d alarms waiting",
                     len(events), len(self.state.alarms))
        if len(self.state.alarms) != before:
            self._broadcast_alarms()

    # ------------------------------------------------------------------ the loop's side

    def _push(self, slot: str, text: str) -> None:
        """Hand ``text`` to every page as its newest ``slot`` (status, fusion, frame or alarms: a page
        keeps only the newest of each) and wake it."""
        for c in self.clients:
            setattr(c, slot, text)
            c.wake.set()

    def _drain(self) -> None:
        assert self.inbox is not None
        tracks, status, alive, events = self.inbox.take()
        for payload in events:
            try:
                event = messages.decode_event(payload)
            except WireError as exc:
                self._unreadable("event", exc)
                continue
            self.apply_event(event)
        if status is not None:
            try:
                st = messages.decode(status, Status)
            except WireError as exc:
                self._unreadable("status", exc)
            else:
                self._push("status", json.dumps(self.state.on_status(st), separators=(",", ":")))
        if alive is not None:
            was, self.fusion_alive = self.fusion_alive, alive
            self._push("fusion", json.dumps({"alive": alive}))
            if alive and not was and not self._seeded:
                asyncio.get_running_loop().create_task(self._seed())
        if tracks is not None:
            try:
                frame = messages.decode(tracks, TrackFrame)
            except WireError as exc:
                self._unreadable("tracks", exc)
            else:
                self._push("frame", json.dumps(self.state.on_tracks(frame), separators=(",", ":")))

    def apply_event(self, event: Event) -> None:
        """An event into the state and out to every page (once per id, however it came)."""
        out = self.state.on_event(event)
        if out is None:
            return
        text = json.dumps(out["event"], separators=(",", ":"))
        for c in self.clients:
            c.push_event(text)
        if out["alarms"] is not None:
            self._broadcast_alarms()

    def day_start_ns(self, now_ns: int | None = None) -> int:
        """Midnight of the home's day (the site's ``utc_offset_hours``), nanoseconds since the epoch."""
        now = time.time_ns() if now_ns is None else now_ns
        offset = int(self.site.utc_offset_hours * 3600 * 1e9)
        return (now + offset) // DAY_NS * DAY_NS - offset

    def _broadcast_alarms(self) -> None:
        self._push("alarms", json.dumps(self.state.alarm_list(), separators=(",", ":")))

    def _unreadable(self, what: str, exc: Exception) -> None:
        self.undecodable += 1
        if self.undecodable <= 5 or self.undecodable % 1000 == 0:
            log.warning("view: unreadable %s (%d so far): %s", what, self.undecodable, exc)

    # ------------------------------------------------------------------ installer data

    def install_info(self, cam: str) -> dict[str, Any]:
        from view.plan import image_outlines

        info = self._install.get(cam)
        if info is None:
            spec = self.site.camera(cam)
            info = image_outlines(self.site, self.cameras[cam])
            info.update(modality=spec.modality, fps=spec.fps)
            self._install[cam] = info
        status = None
        if self.state.status is not None:
            status = next((c for c in self.state.status["cameras"] if c["cam"] == cam), None)
        return {**info, "status": status}

    def mask_png(self, cam: str) -> bytes | None:
        """The newest mask of ``cam`` as PNG bytes (the mask's own size, which may be smaller than
        the capture's); None before the first."""
        import cv2

        from common import maskcodec

        assert self.inbox is not None
        payload = self.inbox.mask(cam)
        if payload is None:
            return None
        cached = self._png.get(cam)
        if cached is not None and cached[0] is payload:
            png = cached[1]
        else:
            msg = messages.decode(payload, messages.MaskFrame)
            mask = maskcodec.decode_mask(msg.data, msg.codec, msg.width, msg.height)
            ok, buf = cv2.imencode(".png", mask)
            if not ok:
                raise ValueError(f"camera {cam}: the mask could not be written as PNG")
            png = buf.tobytes()
            self._png[cam] = (payload, png)
        return png


# --------------------------------------------------------------------------- the web application


def make_app(view: View) -> web.Application:
    """The aiohttp application of ``view`` (its routes, the access check, start and stop)."""
    app = web.Application(middlewares=[_security(view)], client_max_size=64 * 1024)
    app["view"] = view
    app.router.add_get("/", _page("index.html"))
    app.router.add_get("/install/{cam}", _install_page)
    app.router.add_get("/login", _login_form)
    app.router.add_post("/login", _login)
    app.router.add_post("/logout", _logout)
    app.router.add_get("/api/plan", _plan)
    app.router.add_get("/api/stream", _stream)
    app.router.add_get("/api/events", _events)
    app.router.add_get("/api/timeline", _timeline)
    app.router.add_post("/api/ack", _ack)
    app.router.add_get("/api/install/{cam}", _install_api)
    app.router.add_get("/api/mask/{cam}.png", _mask)
    app.router.add_static("/static/", STATIC, show_index=False, follow_symlinks=False)
    app.router.add_get("/favicon.ico", _no_icon)

    async def on_startup(app: web.Application) -> None:
        view.start(asyncio.get_running_loop())

    async def on_shutdown(app: web.Application) -> None:
        for c in list(view.clients):
            c.wake.set()
        view.clients.clear()

    async def on_cleanup(app: web.Application) -> None:
        view.close()

    app.on_startup.append(on_startup)
    app.on_shutdown.append(on_shutdown)
    app.on_cleanup.append(on_cleanup)
    return app


_PUBLIC = ("/login", "/static/", "/favicon.ico")
_PARAM = re.compile(r"[A-Za-z0-9_,:.+-]{1,200}")
"""A history parameter's value as the page sends it (kinds, nanoseconds or ISO times, a limit): nothing
that could end the parameter and start another."""


def _security(view: View):
    @web.middleware
    async def check(request: web.Request, handler):
        path = request.path
        if request.method == "POST" and not _same_origin(request):
            return _text_page(403, "Refused", "This request came from another site.")
        if path.startswith(_PUBLIC):
            response = await handler(request)
        elif "token" in request.query and request.method == "GET":
            if not view.access.token_ok(request.query.get("token")):
                return _text_page(403, "Wrong token",
                                  "The link's token is not this home's view token. Ask for a new link, or "
                                  "<a href=\"/login\">type the token</a>.")
            query = {k: v for k, v in request.query.items() if k != "token"}
            target = path + ("?" + urlencode(query) if query else "")
            response = web.HTTPSeeOther(target)
            _set_cookie(response, view.access.cookie_for("view"), request)
            return response
        else:
            name = view.access.name_of(request.cookies.get(COOKIE))
            if name is None:
                if path.startswith("/api/"):
                    return web.json_response({"error": "not logged in: open the page and give the view token"},
                                             status=401)
                return _login_response(401, next_path=path)
            request["name"] = name
            response = await handler(request)
        response.headers.setdefault("Content-Security-Policy",
                                    "default-src 'self'; img-src 'self' data:; style-src 'self'; "
                                    "script-src 'self'; frame-ancestors 'none'; form-action 'self'")
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        response.headers.setdefault("Referrer-Policy", "same-origin")  # "no-referrer" would make POSTs say Origin: null
        return response

    return check


def _same_origin(request: web.Request) -> bool:
    origin = request.headers.get("Origin")
    return origin is None or origin.split("://", 1)[-1] == request.host


def _set_cookie(response: web.StreamResponse, value: str, request: web.Request) -> None:
    response.set_cookie(COOKIE, value, httponly=True, samesite="Strict", secure=request.secure, path="/",
                        max_age=30 * 86400)


def _page(name: str):
    async def handler(request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / name, headers={"Cache-Control": "no-store"})

    return handler


async def _no_icon(request: web.Request) -> web.StreamResponse:
    return web.Response(status=204)


async def _install_page(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    if request.match_info["cam"] not in view.cameras:
        return _text_page(404, "No such camera", f"This home's cameras are {', '.join(view.cameras)}.")
    return web.FileResponse(STATIC / "install.html", headers={"Cache-Control": "no-store"})


async def _login_form(request: web.Request) -> web.StreamResponse:
    return _login_response(200, next_path=request.query.get("next", "/"))


async def _login(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    form = await request.post()
    token = form.get("token")
    next_path = str(form.get("next") or "/")
    if not next_path.startswith("/") or next_path.startswith("//"):
        next_path = "/"
    if not isinstance(token, str) or not view.access.token_ok(token.strip()):
        return _login_response(401, next_path=next_path, error="Wrong token. Try again.")
    response = web.HTTPSeeOther(next_path)
    _set_cookie(response, view.access.cookie_for(clean_name(str(form.get("name") or ""))), request)
    return response


async def _logout(request: web.Request) -> web.StreamResponse:
    response = web.HTTPSeeOther("/login")
    response.del_cookie(COOKIE, path="/")
    return response


async def _plan(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    s = view.settings
    return web.json_response({"plan": view.plan, "alarms": list(s.alarms), "trail_s": s.trail_s,
                              "kinds": list(messages.EVENT_KINDS),
                              "name": request["name"], "prefix": view.prefix,
                              "utc_offset_hours": view.site.utc_offset_hours,
                              "cameras": [{"id": c.id, "modality": c.modality} for c in view.site.cameras]})


async def _stream(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    if len(view.clients) >= MAX_CLIENTS:
        return web.json_response({"error": "too many pages open; try again later"}, status=503)
    response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store",
                                           "X-Accel-Buffering": "no"})
    await response.prepare(request)
    client = Client()
    snapshot = {**view.state.snapshot(), "fusion_alive": view.fusion_alive}
    view.clients.add(client)  # before the first await: nothing that comes after the snapshot is missed
    try:
        await response.write(_sse("snapshot", json.dumps(snapshot, separators=(",", ":"))))
        while True:
            try:
                await asyncio.wait_for(client.wake.wait(), HEARTBEAT_S)
            except asyncio.TimeoutError:
                await response.write(b": still here\n\n")
                continue
            client.wake.clear()
            if client not in view.clients:
                break
            due = client.pending()
            if due:
                await response.write(b"".join(_sse(kind, text) for kind, text in due))
    except ConnectionResetError:  # the page went away (a cancelled handler goes on up)
        pass
    finally:
        view.clients.discard(client)
    return response


async def _events(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    params = {k: request.query[k] for k in ("kind", "since", "until", "limit") if request.query.get(k)}
    bad = [k for k, v in params.items() if not _PARAM.fullmatch(v)]
    if bad:
        return web.json_response({"error": f"parameter {bad[0]}: unexpected characters"}, status=400)
    try:
        events = await asyncio.get_running_loop().run_in_executor(view._pool, view.query_history, params)
    except ValueError as exc:
        return web.json_response({"error": str(exc)}, status=400)
    return web.json_response({"events": [view.state.event_dict(e) for e in events]})


async def _timeline(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    since = request.query.get("since")
    try:
        since_ns = int(since) if since else view.day_start_ns()  # the home's day so far
    except ValueError:
        return web.json_response({"error": f"since {since!r} is not integer nanoseconds"}, status=400)
    return web.json_response(view.state.timeline(since_ns=since_ns))


async def _ack(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    try:
        body = await request.json()
        event_id = keys.validate_chunk(str(body["event"]), "event id")
    except (ValueError, KeyError, TypeError) as exc:
        return web.json_response({"error": f"expected {{\"event\": \"<event id>\"}}: {exc}"}, status=400)
    try:
        ack = await asyncio.get_running_loop().run_in_executor(view._pool, view.acknowledge, event_id,
                                                               request["name"])
    except (ValueError, WireError) as exc:
        return web.json_response({"error": str(exc)}, status=502)
    view.apply_event(ack)  # at once, for every page; the published copy then counts as seen
    return web.json_response({"ack": ack.to_dict()})


async def _install_api(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    cam = request.match_info["cam"]
    if cam not in view.cameras:
        return web.json_response({"error": f"no camera {cam!r}"}, status=404)
    return web.json_response(view.install_info(cam))


async def _mask(request: web.Request) -> web.StreamResponse:
    view: View = request.app["view"]
    cam = request.match_info["cam"]
    if cam not in view.cameras:
        return web.json_response({"error": f"no camera {cam!r}"}, status=404)
    try:
        png = view.mask_png(cam)
    except ValueError as exc:  # WireError and the codec's errors are ValueErrors
        return web.json_response({"error": f"camera {cam}: unreadable mask: {exc}"}, status=502)
    if png is None:
        return web.json_response({"error": f"no mask from camera {cam} yet"}, status=404)
    return web.Response(body=png, content_type="image/png", headers={"Cache-Control": "no-store"})


# --------------------------------------------------------------------------- helpers


def _sse(kind: str, text: str) -> bytes:
    return f"event: {kind}\ndata: {text}\n\n".encode("utf-8")


def _login_response(status: int, *, next_path: str = "/", error: str = "") -> web.Response:
    import html

    page = (STATIC / "login.html").read_text(encoding="utf-8")
    page = page.replace("{{next}}", html.escape(next_path, quote=True))
    page = page.replace("{{error}}", f'<p class="error" role="alert">{html.escape(error)}</p>' if error else "")
    return web.Response(text=page, status=status, content_type="text/html",
                        headers={"Cache-Control": "no-store"})


def _text_page(status: int, title: str, body_html: str) -> web.Response:
    page = ("<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>voxelwatch: {title}</title><link rel=\"stylesheet\" href=\"/static/style.css\"></head>"
            f"<body class=\"plain\"><main class=\"card\"><h1>{title}</h1><p>{body_html}</p></main></body></html>")
    return web.Response(text=page, status=status, content_type="text/html", headers={"Cache-Control": "no-store"})
