"""Webhooks: each event as an HTTP POST of its JSON text.

The body is the event exactly as zenoh carries it (:meth:`Event.to_json`:
``v``, ``type``, ``id``, ``kind`` ...); the header ``Idempotency-Key`` repeats
the event id so that a receiver can drop a repeated delivery without parsing
the body. Answers: 2xx delivered; 408, 429 and 5xx, timeouts and connection
errors are tried again (a ``Retry-After`` of seconds is honoured within the
back-off limit); any other answer (4xx: a wrong URL, a refused token, a body
the receiver does not take) is given up and logged, since sending the same
request again would not change it. Redirects are not followed: a hook that
moved is a configuration to fix, not something to guess.
"""

from __future__ import annotations

import http.client
import socket
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Mapping

from common.messages import Event
from notify.channel import DELIVERED, Channel, Outcome

USER_AGENT = "voxelwatch-notify"
RETRIED_STATUS = frozenset({408, 429})


class WebhookChannel(Channel):
    """POST to ``url`` with ``headers`` (e.g. an authorisation token), ``timeout_s`` per attempt."""

    def __init__(self, url: str, *, kinds: frozenset[str], headers: Mapping[str, str] | None = None,
                 timeout_s: float = 10.0) -> None:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.netloc:
            raise ValueError(f"webhook url {url!r}: expected http(s)://host/path")
        self.url = url
        self.name = f"webhook:{url}"
        self.label = f"webhook {parts.scheme}://{parts.hostname}{f':{parts.port}' if parts.port else ''}{parts.path}"
        self.kinds = frozenset(kinds)
        self.headers = dict(headers or {})
        self.timeout_s = float(timeout_s)
        self._opener = urllib.request.build_opener(_NoRedirect())

    def deliver(self, event: Event, context: Mapping[str, str]) -> Outcome:
        body = event.to_json().encode("utf-8")
        request = urllib.request.Request(self.url, data=body, method="POST", headers={
            "Content-Type": "application/json; charset=utf-8", "User-Agent": USER_AGENT,
            **self.headers, "Idempotency-Key": event.id})
        try:
            with self._opener.open(request, timeout=self.timeout_s) as response:
                response.read(64 * 1024)
                status = response.status
        except urllib.error.HTTPError as exc:
            status = exc.code
            retry_after = _retry_after(exc.headers.get("Retry-After"))
            exc.close()
            return classify(status, retry_after)
        except (urllib.error.URLError, http.client.HTTPException, socket.timeout, TimeoutError, OSError) as exc:
            reason = getattr(exc, "reason", None) or exc
            return Outcome("retry", f"cannot reach the hook: {_short(reason)}")
        return classify(status)


def classify(status: int, retry_after_s: float | None = None) -> Outcome:
    """The outcome of an HTTP answer with ``status``."""
    if 200 <= status < 300:
        return DELIVERED
    if status in RETRIED_STATUS or status >= 500:
        return Outcome("retry", f"HTTP {status}", retry_after_s)
    return Outcome("give_up", f"HTTP {status}")


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, req, fp, code, msg, headers, newurl):  # noqa: D102 - urllib's hook
        return None


def _retry_after(value: str | None) -> float | None:
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:  # an HTTP date: the back-off decides
        return None


def _short(reason: object) -> str:
    text = str(reason) or type(reason).__name__
    return text if len(text) <= 200 else text[:197] + "..."
