"""MQTT (paho-mqtt, QoS 1): alarms, each person's state, and Home Assistant discovery.

Topics, under ``topic_prefix`` (default ``voxelwatch/<site>``):

| topic                              | retained | payload                                          |
|------------------------------------|----------|--------------------------------------------------|
| ``<t>/events/<kind>``              | no       | the event's JSON text (as zenoh carries it; ``id``) |
| ``<t>/person/<id>/state``          | yes      | ``{"id", "person", "posture", "x", "y", "place", "last_seen_ns", "last_seen"}`` |
| ``<t>/camera/<cam>/state``         | yes      | ``{"camera", "state"}``                          |
| ``<t>/availability``               | yes      | ``online``; ``offline`` (also the last will)     |

An event counts as delivered when the broker acknowledges it (PUBACK); until
then it stays in the outbox. While the broker is away the channel is not
ready and nothing is attempted; paho reconnects with back-off, and after a
reconnection the channel waits :data:`SETTLE_S` before sending what is
pending, so that subscribers which lost the broker with us have subscribed
again (a broker without persistence forgets them) and paho's own resending
of unacknowledged messages can be acknowledged first. A message resent by
paho and by the outbox arrives twice, with the same ``id``.

Person and camera states are the newest value, not a queue: they are
published (retained) when they change and all again on each connection, and
never wait in the outbox.

Home Assistant discovery (retained, under ``discovery_prefix``, node
``voxelwatch_<site>``, one device): a ``sensor`` per person (its posture,
the rest of the state as attributes) and per camera (its state), and an
``event`` entity per alarm kind the channel publishes (``fall``,
``long_lie`` ...) reading ``<t>/events/<kind>``; see :func:`person_config`,
:func:`camera_config` and :func:`alarm_config`. A visitor's sensor is removed
(empty retained config) once the visitor has been gone for the
re-identification window. Everything is announced again when Home Assistant
says it has restarted (``<discovery_prefix>/status`` = ``online``).
"""

from __future__ import annotations

import json
import logging
import re
import ssl
import threading
import time
from collections.abc import Callable, Mapping

import paho.mqtt.client as paho

from common.messages import Event
from notify.channel import DELIVERED, Channel, Outcome
from notify.people import PersonState

log = logging.getLogger("voxelwatch.notify")

SETTLE_S = 2.0
"""After (re)connecting, wait this long before sending pending alarms."""
ACK_TIMEOUT_S = 10.0
"""An alarm without PUBACK within this long is tried again."""
MANUFACTURER = "voxelwatch"


def node_id(site: str) -> str:
    """Home Assistant's node id for a site: ``voxelwatch_<site>`` with only ``[A-Za-z0-9_-]``."""
    return "voxelwatch_" + re.sub(r"[^A-Za-z0-9_-]", "_", site)


def device(site: str) -> dict:
    """The one Home Assistant device every entity of the site belongs to."""
    return {"identifiers": [node_id(site)], "name": f"voxelwatch {site}", "manufacturer": MANUFACTURER,
            "model": "multi-camera people sensing"}


def _common(site: str, topic_prefix: str) -> dict:
    return {"availability_topic": f"{topic_prefix}/availability", "payload_available": "online",
            "payload_not_available": "offline", "device": device(site), "origin": {"name": MANUFACTURER}}


def person_config(site: str, topic_prefix: str, discovery_prefix: str, person_id: int,
                  name: str | None) -> tuple[str, dict]:
    """``(topic, payload)`` announcing one person's posture sensor to Home Assistant."""
    node = node_id(site)
    state = f"{topic_prefix}/person/{person_id}/state"
    return f"{discovery_prefix}/sensor/{node}/person_{person_id}/config", {
        "name": f"{name or f'Person {person_id}'} posture",
        "unique_id": f"{node}_person_{person_id}",
        "state_topic": state,
        "value_template": "{{ value_json.posture }}",
        "json_attributes_topic": state,
        "icon": "mdi:human",
        **_common(site, topic_prefix),
    }


def camera_config(site: str, topic_prefix: str, discovery_prefix: str, cam: str) -> tuple[str, dict]:
    """``(topic, payload)`` announcing one camera's state sensor to Home Assistant."""
    node = node_id(site)
    return f"{discovery_prefix}/sensor/{node}/camera_{cam}/config", {
        "name": f"Camera {cam}",
        "unique_id": f"{node}_camera_{cam}",
        "state_topic": f"{topic_prefix}/camera/{cam}/state",
        "value_template": "{{ value_json.state }}",
        "icon": "mdi:cctv",
        "entity_category": "diagnostic",
        **_common(site, topic_prefix),
    }


def alarm_config(site: str, topic_prefix: str, discovery_prefix: str, kind: str) -> tuple[str, dict]:
    """``(topic, payload)`` announcing the event entity of one alarm kind to Home Assistant:
    each ``<t>/events/<kind>`` message fires it, with the event's id, track and place as
    attributes."""
    node = node_id(site)
    return f"{discovery_prefix}/event/{node}/{kind}/config", {
        "name": kind.replace("_", " ").capitalize(),
        "unique_id": f"{node}_{kind}",
        "state_topic": f"{topic_prefix}/events/{kind}",
        "event_types": [kind],
        "value_template": ("{{ {'event_type': value_json.kind, 'id': value_json.id, 'track': value_json.track, "
                           "'x': value_json.x, 'y': value_json.y, 'stamp_ns': value_json.stamp_ns} | to_json }}"),
        "icon": "mdi:alert",
        **_common(site, topic_prefix),
    }


class MqttChannel(Channel):
    """One broker connection: alarms through the outbox, states and discovery directly."""

    name = "mqtt"

    def __init__(self, *, host: str, port: int, username: str = "", password: str = "", tls_ca: str = "",
                 topic_prefix: str, discovery: bool = True, discovery_prefix: str = "homeassistant",
                 kinds: frozenset[str], site: str, utc_offset_hours: float = 0.0, retry_max_s: float = 300.0,
                 settle_s: float = SETTLE_S, ack_timeout_s: float = ACK_TIMEOUT_S,
                 confirm: Callable[[str], None] | None = None) -> None:
        self.host, self.port = host, int(port)
        self.label = f"MQTT {host}:{port}"
        self.kinds = frozenset(kinds)
        self.topic_prefix = topic_prefix.rstrip("/")
        self.discovery, self.discovery_prefix = discovery, discovery_prefix.rstrip("/")
        self.site, self.utc_offset_hours = site, utc_offset_hours
        self.settle_s, self.ack_timeout_s = float(settle_s), float(ack_timeout_s)
        self.confirm = confirm
        """Called with an event id whose PUBACK came after its attempt had timed out."""
        self._lock = threading.Lock()
        self._wake: Callable[[], None] = lambda: None
        self._ready_at: float | None = None  # monotonic time from which alarms may go; None: disconnected
        self._down_logged = False
        self._closing = False
        self._late: dict[int, str] = {}  # mid -> event id of attempts that timed out
        self._people: dict[int, PersonState] = {}
        self._cameras: dict[str, str] = {}
        self._announced: dict[str, str] = {}  # discovery topic -> payload sent on this connection
        self._ann_lock = threading.RLock()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=f"voxelwatch-notify-{site}",
                                  clean_session=True)
        if username:
            self.client.username_pw_set(username, password or None)
        if tls_ca:
            self.client.tls_set(ca_certs=tls_ca, cert_reqs=ssl.CERT_REQUIRED)
        self.client.will_set(self.availability_topic, "offline", qos=1, retain=True)
        self.client.reconnect_delay_set(1, int(max(1, min(retry_max_s, 60))))
        self.client.max_queued_messages_set(1000)
        self.client.on_connect = self._on_connect
        self.client.on_connect_fail = self._on_connect_fail
        self.client.on_disconnect = self._on_disconnect
        self.client.on_publish = self._on_publish
        self.client.on_message = self._on_message

    @property
    def availability_topic(self) -> str:
        return f"{self.topic_prefix}/availability"

    def event_topic(self, kind: str) -> str:
        return f"{self.topic_prefix}/events/{kind}"

    # ------------------------------------------------------------------ Channel

    def start(self, wake: Callable[[], None]) -> None:
        self._wake = wake
        self.client.connect_async(self.host, self.port, keepalive=30)
        self.client.loop_start()

    def ready(self) -> bool:
        ready_at = self._ready_at
        return ready_at is not None and time.monotonic() >= ready_at

    def deliver(self, event: Event, context: Mapping[str, str]) -> Outcome:
        # never publish holding self._lock: paho calls on_publish holding its own message lock
        info = self.client.publish(self.event_topic(event.kind), event.to_json(), qos=1)
        if info.rc != paho.MQTT_ERR_SUCCESS:
            self._watch_late(info, event.id)
            return Outcome("retry", f"the broker is unreachable ({paho.error_string(info.rc)})")
        deadline = time.monotonic() + self.ack_timeout_s
        while not info.is_published() and time.monotonic() < deadline and self._ready_at is not None:
            time.sleep(0.01)
        if info.is_published():
            return DELIVERED
        self._watch_late(info, event.id)
        return Outcome("retry", "no acknowledgement (PUBACK) from the broker"
                       + ("" if self._ready_at is not None else ": the connection was lost"))

    def close(self) -> None:
        self._closing = True
        try:
            if self.client.is_connected():
                self.client.publish(self.availability_topic, "offline", qos=1, retain=True).wait_for_publish(2.0)
        except (RuntimeError, ValueError):
            pass
        self.client.disconnect()
        self.client.loop_stop()

    # ------------------------------------------------------------------ states

    def publish_person(self, state: PersonState) -> None:
        """Publish (retained) one person's state, announcing the person first when new."""
        with self._lock:
            self._people[state.id] = state
        if self.client.is_connected():
            self._announce_person(state)
            self._retain(f"{self.topic_prefix}/person/{state.id}/state", state.to_dict(self.utc_offset_hours))

    def forget_person(self, person_id: int) -> None:
        """Remove a person's sensor and retained state (a visitor gone for good)."""
        with self._lock:
            self._people.pop(person_id, None)
        if self.client.is_connected():
            topic, _ = person_config(self.site, self.topic_prefix, self.discovery_prefix, person_id, None)
            if self.discovery:
                with self._ann_lock:
                    self._raw(topic, "")
                    self._announced.pop(topic, None)
            self._raw(f"{self.topic_prefix}/person/{person_id}/state", "")

    def publish_camera(self, cam: str, state: str) -> None:
        with self._lock:
            self._cameras[cam] = state
        if self.client.is_connected():
            if self.discovery:
                self._announce(*camera_config(self.site, self.topic_prefix, self.discovery_prefix, cam))
            self._retain(f"{self.topic_prefix}/camera/{cam}/state", {"camera": cam, "state": state})

    # ------------------------------------------------------------------ helpers

    def _watch_late(self, info: paho.MQTTMessageInfo, event_id: str) -> None:
        """Remember an attempt given up on: paho may still deliver it (it resends unacknowledged
        messages after reconnecting), and its PUBACK then confirms the event."""
        with self._lock:
            self._late[info.mid] = event_id
            while len(self._late) > 1000:
                self._late.pop(next(iter(self._late)))
        if info.is_published():  # acknowledged while it was being given up on
            self._on_publish(None, None, info.mid, None, None)

    def _announce_all(self) -> None:
        with self._ann_lock:
            self._announced.clear()
        if self.discovery:
            for kind in sorted(self.kinds):
                self._announce(*alarm_config(self.site, self.topic_prefix, self.discovery_prefix, kind))
        with self._lock:
            people, cameras = list(self._people.values()), dict(self._cameras)
        for state in people:
            self._announce_person(state)
            self._retain(f"{self.topic_prefix}/person/{state.id}/state", state.to_dict(self.utc_offset_hours))
        for cam, state in cameras.items():
            if self.discovery:
                self._announce(*camera_config(self.site, self.topic_prefix, self.discovery_prefix, cam))
            self._retain(f"{self.topic_prefix}/camera/{cam}/state", {"camera": cam, "state": state})

    def _announce_person(self, state: PersonState) -> None:
        if self.discovery:
            self._announce(*person_config(self.site, self.topic_prefix, self.discovery_prefix, state.id, state.name))

    def _announce(self, topic: str, payload: dict) -> None:
        text = json.dumps(payload, separators=(",", ":"))
        with self._ann_lock:
            if self._announced.get(topic) != text:
                self._raw(topic, text)
                self._announced[topic] = text

    def _retain(self, topic: str, payload: dict) -> None:
        self._raw(topic, json.dumps(payload, separators=(",", ":")))

    def _raw(self, topic: str, text: str) -> None:
        self.client.publish(topic, text, qos=1, retain=True)

    # ------------------------------------------------------------------ paho callbacks (paho's thread)

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            if not self._down_logged:
                log.warning("%s: the broker refused the connection: %s; retrying with back-off", self.label,
                            reason_code)
                self._down_logged = True
            return
        was_down = self._down_logged
        self._down_logged = False
        log.info("%s: connected%s", self.label, " again" if was_down else "")
        client.publish(self.availability_topic, "online", qos=1, retain=True)
        if self.discovery:
            client.subscribe(f"{self.discovery_prefix}/status", qos=1)
        self._announce_all()
        self._ready_at = time.monotonic() + self.settle_s
        timer = threading.Timer(self.settle_s + 0.05, self._wake)
        timer.daemon = True
        timer.start()

    def _on_connect_fail(self, client, userdata) -> None:
        if not self._down_logged:
            log.warning("%s: the broker is unreachable; alarms wait in the outbox, reconnecting with back-off",
                        self.label)
            self._down_logged = True

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        self._ready_at = None
        if not self._down_logged and not self._closing:
            log.warning("%s: lost the broker (%s); alarms wait in the outbox, reconnecting with back-off",
                        self.label, reason_code)
            self._down_logged = True

    def _on_publish(self, client, userdata, mid, reason_code, properties) -> None:
        with self._lock:
            late = self._late.pop(mid, None)
        if late is not None and self.confirm is not None:
            self.confirm(late)

    def _on_message(self, client, userdata, message) -> None:
        if message.topic == f"{self.discovery_prefix}/status" and message.payload == b"online":
            self._announce_all()
