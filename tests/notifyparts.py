"""Real receivers for the notifier's tests: a mosquitto broker, an HTTP hook server, an SMTP
server, an MQTT subscriber, and a zenoh history queryable served from a real event store.

Each records what it received and nothing else; none stands in for something that can run.
"""

from __future__ import annotations

import email
import email.policy
import json
import shutil
import socket
import subprocess
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from common.transport import free_port

MOSQUITTO = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)


def wait_port(port: int, timeout_s: float = 20.0) -> None:
    """Until something accepts TCP connections on 127.0.0.1:``port``."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise AssertionError(f"nothing listens on port {port} after {timeout_s:.0f} s") from None
            time.sleep(0.05)


class Mosquitto:
    """A mosquitto broker on a free loopback port: anonymous, no persistence, stoppable and
    restartable on the same port."""

    def __init__(self, folder: Path) -> None:
        assert MOSQUITTO is not None
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.conf = self.folder / "mosquitto.conf"
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
                             f"log_dest file {self.folder / 'mosquitto.log'}\n")
        self.proc: subprocess.Popen | None = None

    def start(self) -> "Mosquitto":
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, start_new_session=True)
        wait_port(self.port)
        return self

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self.proc = None


@dataclass
class Hit:
    """One request the hook server answered."""

    path: str
    headers: dict
    body: bytes
    status: int

    def json(self) -> dict:
        return json.loads(self.body)


class HookServer:
    """An HTTP server on a free loopback port that records POSTs and answers each path from its
    script: ``script[path]`` is a list of statuses, taken one per request, the last one repeated."""

    def __init__(self) -> None:
        self.hits: list[Hit] = []
        self.script: dict[str, list[int]] = {}
        self.lock = threading.Lock()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                with outer.lock:
                    plan = outer.script.setdefault(self.path, [200])
                    status = plan.pop(0) if len(plan) > 1 else plan[0]
                    outer.hits.append(Hit(self.path, dict(self.headers), body, status))
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def at(self, path: str) -> list[Hit]:
        with self.lock:
            return [h for h in self.hits if h.path == path]

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


class SmtpReceiver:
    """aiosmtpd on a free loopback port; ``messages`` holds each received message, parsed.
    With ``password``, it requires AUTH (over plain text: loopback only) with user ``notify``."""

    def __init__(self, password: str | None = None) -> None:
        from aiosmtpd.controller import Controller
        from aiosmtpd.smtp import AuthResult

        self.messages: list[email.message.EmailMessage] = []
        self.envelopes: list[tuple[str, list[str]]] = []
        outer = self

        class Handler:
            async def handle_DATA(self, server, session, envelope):  # noqa: N802 - aiosmtpd's name
                outer.envelopes.append((envelope.mail_from, list(envelope.rcpt_tos)))
                outer.messages.append(email.message_from_bytes(envelope.content, policy=email.policy.default))
                return "250 OK"

        def authenticator(server, session, envelope, mechanism, auth_data):
            ok = password is not None and auth_data.login == b"notify" and auth_data.password == password.encode()
            return AuthResult(success=ok, handled=False)

        kwargs = {}
        if password is not None:
            kwargs = dict(authenticator=authenticator, auth_required=True, auth_require_tls=False)
        self.controller = Controller(Handler(), hostname="127.0.0.1", port=free_port(), **kwargs)
        self.controller.start()
        self.port = self.controller.port

    def close(self) -> None:
        self.controller.stop()


@dataclass
class MqttWatcher:
    """A paho subscriber to ``topics`` (QoS 1) that subscribes again on every reconnection
    and records ``(topic, payload text, retained)``."""

    port: int
    topics: tuple[str, ...]
    got: list[tuple[str, str, bool]] = field(default_factory=list)
    first_at: dict[str, float] = field(default_factory=dict)  # topic -> time.monotonic() of its first message
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        import paho.mqtt.client as paho

        self.connected = threading.Event()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=f"watcher-{id(self)}")
        self.client.reconnect_delay_set(1, 1)

        def on_connect(client, userdata, flags, reason_code, properties):
            for topic in self.topics:
                client.subscribe(topic, qos=1)
            self.connected.set()

        def on_disconnect(client, userdata, flags, reason_code, properties):
            self.connected.clear()

        def on_message(client, userdata, message):
            with self.lock:
                self.got.append((message.topic, message.payload.decode("utf-8"), bool(message.retain)))
                self.first_at.setdefault(message.topic, time.monotonic())

        self.client.on_connect, self.client.on_disconnect, self.client.on_message = on_connect, on_disconnect, on_message
        self.client.connect_async("127.0.0.1", self.port)
        self.client.loop_start()

    def on(self, topic: str) -> list[tuple[str, bool]]:
        with self.lock:
            return [(payload, retained) for t, payload, retained in self.got if t == topic]

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


class History:
    """The history queryable on ``<p>/history/events/**`` as the fusion server serves it: a real
    :class:`~fusion_server.event_store.EventStore` and :func:`~fusion_server.node.history_replies`;
    ``queries`` records each selector's parameters."""

    def __init__(self, session, prefix: str, store_path: Path) -> None:
        from common import keys
        from fusion_server.event_store import EventStore
        from fusion_server.node import history_replies

        self.store = EventStore(store_path)
        self.queries: list[str] = []
        key = keys.history_key(prefix)

        def on_query(query) -> None:
            with query:
                self.queries.append(str(query.parameters))
                for reply_key, payload, encoding in history_replies(self.store, key, str(query.key_expr),
                                                                    str(query.parameters)):
                    query.reply(reply_key, payload, encoding=encoding)

        self.queryable = session.declare_queryable(f"{key}/**", on_query)

    def close(self) -> None:
        self.queryable.undeclare()
        self.store.close()
