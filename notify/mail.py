"""E-mail: one plain-text message per alarm through an SMTP server (:mod:`smtplib`).

Subject ``voxelwatch <site>: fall (Ada, sofa) 14:03``; the body says what,
who, where and when (site time) and gives the event id
(:func:`notify.people.describe`). The ``Message-ID`` is made from the
event id (``<event id@voxelwatch.site>``), so a mail client or a filter can
tell a repeated delivery (after a restart) from a new alarm.

``security``: ``starttls`` (port 587: plain connection upgraded before the
login), ``tls`` (port 465: TLS from the start) or ``none`` (a relay on the
local network). The login is made only when a user name is set. Faults:
connection problems, timeouts, 4xx answers and a refused login are tried
again with back-off (a password can be fixed while the alarm waits); a 5xx
answer to the message or its recipients (the server will never take it) is
given up.
"""

from __future__ import annotations

import smtplib
import socket
import ssl
from collections.abc import Mapping, Sequence
from email.message import EmailMessage
from email.utils import formatdate

from common.messages import Event
from notify.channel import DELIVERED, Channel, Outcome
from notify.people import describe


class EmailChannel(Channel):
    """Mail each event to ``to`` from ``sender`` through ``host:port``."""

    name = "email"

    def __init__(self, *, host: str, port: int, security: str, username: str, password: str, sender: str,
                 to: Sequence[str], kinds: frozenset[str], site: str, utc_offset_hours: float = 0.0,
                 timeout_s: float = 30.0, ssl_context: ssl.SSLContext | None = None) -> None:
        if security not in ("starttls", "tls", "none"):
            raise ValueError(f"security must be starttls, tls or none, got {security!r}")
        self.host, self.port, self.security = host, int(port), security
        self.username, self.password = username, password
        self.sender, self.to = sender, list(to)
        self.kinds = frozenset(kinds)
        self.site, self.utc_offset_hours = site, float(utc_offset_hours)
        self.timeout_s = float(timeout_s)
        self.ssl_context = ssl_context or ssl.create_default_context()
        self.label = f"e-mail via {host}:{port}"

    def message(self, event: Event, context: Mapping[str, str]) -> EmailMessage:
        """The message for ``event`` (``context``: ``person`` and ``place`` as heard)."""
        subject, body = describe(event, site=self.site, person=context.get("person", ""),
                                 place=context.get("place", ""), utc_offset_hours=self.utc_offset_hours)
        msg = EmailMessage()
        msg["Subject"] = subject
        msg["From"] = self.sender
        msg["To"] = ", ".join(self.to)
        msg["Date"] = formatdate(event.stamp_ns / 1e9, localtime=False)
        msg["Message-ID"] = message_id(event.id, self.site)
        msg["X-Voxelwatch-Event"] = event.id
        msg.set_content(body)
        return msg

    def deliver(self, event: Event, context: Mapping[str, str]) -> Outcome:
        msg = self.message(event, context)
        try:
            with self._connect() as smtp:
                if self.username:
                    smtp.login(self.username, self.password)
                refused = smtp.send_message(msg)
        except smtplib.SMTPAuthenticationError as exc:
            return Outcome("retry", f"the SMTP server refused the login of {self.username!r}: "
                                    f"{exc.smtp_code} {_text(exc.smtp_error)}")
        except smtplib.SMTPRecipientsRefused as exc:
            return _refused(exc.recipients)
        except smtplib.SMTPResponseException as exc:
            what = f"SMTP {exc.smtp_code} {_text(exc.smtp_error)}"
            return Outcome("give_up" if 500 <= exc.smtp_code < 600 else "retry", what)
        except (smtplib.SMTPException, OSError, socket.timeout, ssl.SSLError) as exc:
            return Outcome("retry", f"cannot reach the SMTP server: {type(exc).__name__}: {exc}")
        if refused:  # some recipients took it: delivered; the others are named once
            return Outcome("delivered", f"refused by {sorted(refused)}")
        return DELIVERED

    def _connect(self) -> smtplib.SMTP:
        if self.security == "tls":
            return smtplib.SMTP_SSL(self.host, self.port, timeout=self.timeout_s, context=self.ssl_context)
        smtp = smtplib.SMTP(self.host, self.port, timeout=self.timeout_s)
        if self.security == "starttls":
            try:
                smtp.starttls(context=self.ssl_context)
            except BaseException:
                smtp.close()
                raise
        return smtp


def message_id(event_id: str, site: str) -> str:
    """``<event id@voxelwatch.site>``: one Message-ID per alarm, the same on every delivery."""
    return f"<{event_id}@voxelwatch.{site}>"


def _refused(recipients: dict) -> Outcome:
    codes = {addr: code for addr, (code, _) in recipients.items()}
    kind = "give_up" if all(500 <= c < 600 for c in codes.values()) else "retry"
    return Outcome(kind, f"recipients refused: {', '.join(f'{a} ({c})' for a, c in codes.items())}")


def _text(raw: bytes | str) -> str:
    text = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
    return " ".join(text.split())[:200]
