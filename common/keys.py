"""Zenoh key expressions: the one place where voxelwatch builds and parses them.

Every key lives under a prefix, ``voxelwatch/<site>`` by default, which a
site may replace with any valid multi-chunk key (``care/home-12`` ...).

| key                          | direction        | payload                         |
|------------------------------|------------------|---------------------------------|
| ``<p>/cam/<cam>/mask``       | worker -> fusion | ``messages.MaskFrame``          |
| ``<p>/cam/<cam>/hold``       | fusion -> worker | ``messages.HoldRegions``        |
| ``<p>/cam/<cam>/look``       | fusion -> worker | ``messages.LookRequest``        |
| ``<p>/alive/cam/<cam>``      | liveliness token | none                            |
| ``<p>/alive/fusion``         | liveliness token | none                            |
| ``<p>/tracks``               | fusion -> users  | ``messages.TrackFrame``         |
| ``<p>/events/<kind>/<track>``| fusion -> users  | ``messages.Event`` (JSON text)  |
| ``<p>/history/events``       | queryable        | ``messages.Event`` per reply    |
| ``<p>/ack/<event id>``       | queryable        | the ``alarm_ack`` ``Event``     |
| ``<p>/status``               | fusion -> users  | ``messages.Status``             |

Who may do what (the site's access control, :mod:`common.access`): camera ``<cam>`` publishes
``<p>/cam/<cam>/mask`` and declares ``<p>/alive/cam/<cam>``, and subscribes
to ``<p>/cam/<cam>/hold`` and ``<p>/cam/<cam>/look``; the fusion server
subscribes to ``<p>/cam/*/mask`` and ``<p>/alive/**``, publishes
``<p>/cam/*/hold``, ``<p>/cam/*/look``, ``<p>/tracks``, ``<p>/events/**``
and ``<p>/status``, declares ``<p>/alive/fusion``, the history
queryable and the acknowledgement queryable; readers subscribe to tracks,
events and status, query the history, and acknowledge an alarm by querying
``<p>/ack/<event id>?by=<name>`` (:func:`ack_selector`): the fusion server stores and publishes an
``alarm_ack`` event and answers with it (an error reply when there is no
such alarm). An acknowledgement is a query so that readers never publish. The answers to look requests travel inside the masks
(``MaskFrame.looks``): colour histograms, never pixels.

Chunks that come from configuration (site, camera ids, event kinds) are
checked by :func:`validate_chunk` so that a camera called ``a/b`` or ``*``
can never publish onto, or subscribe to, someone else's keys.
"""

from __future__ import annotations

import re

DEFAULT_ROOT = "voxelwatch"

_FORBIDDEN = frozenset("/*$?#")
_TRACK_RE = re.compile(r"-?[0-9]+")


def default_prefix(site: str) -> str:
    """The default prefix ``voxelwatch/<site>`` for a site id."""
    validate_chunk(site, "site")
    return f"{DEFAULT_ROOT}/{site}"


def validate_chunk(name: str, what: str = "chunk") -> str:
    """Return ``name`` if it is usable as one key chunk, else raise ValueError.

    Refused: non-strings, the empty string, ``/``, the wildcard and reserved
    characters ``* $ ? #``, whitespace and other non-printable characters.
    ``what`` names the value in the error (``"camera id"``, ``"site"`` ...).
    """
    if not isinstance(name, str):
        raise ValueError(f"{what} must be a string, got {type(name).__name__}")
    if not name:
        raise ValueError(f"{what} must not be empty")
    bad = sorted({c for c in name if c in _FORBIDDEN or c.isspace() or not c.isprintable()})
    if bad:
        raise ValueError(f"{what} {name!r} contains forbidden character(s) {''.join(bad)!r} "
                         "(not allowed: '/', '*', '$', '?', '#', whitespace, control characters)")
    return name


def validate_prefix(prefix: str) -> str:
    """Return ``prefix`` if every ``/``-separated chunk passes :func:`validate_chunk`."""
    if not isinstance(prefix, str) or not prefix:
        raise ValueError("key prefix must be a non-empty string")
    for chunk in prefix.split("/"):
        validate_chunk(chunk, f"key prefix {prefix!r} chunk")
    return prefix


def mask_key(prefix: str, cam: str) -> str:
    """``<p>/cam/<cam>/mask``: one camera's encoded foreground masks."""
    return f"{validate_prefix(prefix)}/cam/{validate_chunk(cam, 'camera id')}/mask"


def mask_wildcard(prefix: str) -> str:
    """``<p>/cam/*/mask``: masks of every camera."""
    return f"{validate_prefix(prefix)}/cam/*/mask"


def hold_key(prefix: str, cam: str) -> str:
    """``<p>/cam/<cam>/hold``: regions a camera must not learn into its background."""
    return f"{validate_prefix(prefix)}/cam/{validate_chunk(cam, 'camera id')}/hold"


def look_key(prefix: str, cam: str) -> str:
    """``<p>/cam/<cam>/look``: the people whose colours camera ``cam`` should describe."""
    return f"{validate_prefix(prefix)}/cam/{validate_chunk(cam, 'camera id')}/look"


def alive_camera_key(prefix: str, cam: str) -> str:
    """``<p>/alive/cam/<cam>``: liveliness token of one camera worker."""
    return f"{validate_prefix(prefix)}/alive/cam/{validate_chunk(cam, 'camera id')}"


def alive_cameras_wildcard(prefix: str) -> str:
    """``<p>/alive/cam/*``: liveliness tokens of every camera worker."""
    return f"{validate_prefix(prefix)}/alive/cam/*"


def alive_fusion_key(prefix: str) -> str:
    """``<p>/alive/fusion``: liveliness token of the fusion server."""
    return f"{validate_prefix(prefix)}/alive/fusion"


def tracks_key(prefix: str) -> str:
    """``<p>/tracks``: every fused frame's tracks."""
    return f"{validate_prefix(prefix)}/tracks"


def event_key(prefix: str, kind: str, track: int) -> str:
    """``<p>/events/<kind>/<track>``: one event; ``track`` is -1 when no track is involved."""
    if isinstance(track, bool) or not isinstance(track, int):
        raise ValueError(f"event track must be an int, got {track!r}")
    return f"{validate_prefix(prefix)}/events/{validate_chunk(kind, 'event kind')}/{track}"


def events_wildcard(prefix: str) -> str:
    """``<p>/events/**``: every event of every kind and track."""
    return f"{validate_prefix(prefix)}/events/**"


def history_key(prefix: str) -> str:
    """``<p>/history/events``: the queryable event store."""
    return f"{validate_prefix(prefix)}/history/events"


def ack_key(prefix: str, event_id: str) -> str:
    """``<p>/ack/<event id>``: query it (``?by=<name>``) to acknowledge the alarm ``event_id``."""
    return f"{validate_prefix(prefix)}/ack/{validate_chunk(event_id, 'event id')}"


def ack_selector(prefix: str, event_id: str, by: str) -> str:
    """The selector that acknowledges alarm ``event_id`` on behalf of ``by``:
    ``<p>/ack/<event id>?by=<name, percent-encoded>`` (``session.get`` it)."""
    from urllib.parse import quote

    return f"{ack_key(prefix, event_id)}?by={quote(str(by), safe='')}"


def ack_wildcard(prefix: str) -> str:
    """``<p>/ack/*``: the acknowledgement queryable."""
    return f"{validate_prefix(prefix)}/ack/*"


def status_key(prefix: str) -> str:
    """``<p>/status``: per-camera health reports."""
    return f"{validate_prefix(prefix)}/status"


def camera_of(key: str, prefix: str) -> str:
    """The camera id in a mask, hold or camera-liveliness key under ``prefix``.

    Accepts ``<p>/cam/<cam>/mask``, ``<p>/cam/<cam>/hold`` and
    ``<p>/alive/cam/<cam>``; raises ValueError for anything else.
    """
    validate_prefix(prefix)
    key = str(key)
    head = prefix + "/"
    if not key.startswith(head):
        raise ValueError(f"key {key!r} is not under prefix {prefix!r}")
    rest = key[len(head):].split("/")
    if len(rest) == 3 and rest[0] == "cam" and rest[2] in ("mask", "hold", "look"):
        cam = rest[1]
    elif len(rest) == 3 and rest[0] == "alive" and rest[1] == "cam":
        cam = rest[2]
    else:
        raise ValueError(f"key {key!r} is not a camera mask, hold, look or liveliness key under {prefix!r}")
    try:
        return validate_chunk(cam, "camera id")
    except ValueError as exc:
        raise ValueError(f"key {key!r}: {exc}") from None


def event_of(key: str, prefix: str) -> tuple[str, int]:
    """``(kind, track)`` parsed from an ``<p>/events/<kind>/<track>`` key; ValueError otherwise."""
    validate_prefix(prefix)
    key = str(key)
    head = prefix + "/events/"
    parts = key[len(head):].split("/") if key.startswith(head) else []
    if len(parts) != 2:
        raise ValueError(f"key {key!r} is not an event key under {prefix!r}")
    kind, track = parts
    if not _TRACK_RE.fullmatch(track):
        raise ValueError(f"key {key!r}: event track {track!r} is not an integer")
    try:
        validate_chunk(kind, "event kind")
    except ValueError as exc:
        raise ValueError(f"key {key!r}: {exc}") from None
    return kind, int(track)
