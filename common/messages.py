"""Wire messages: versioned msgpack maps validated by pydantic at decode.

Every message is one msgpack map holding ``v`` (schema version, int,
currently :data:`SCHEMA_VERSION`), ``type`` (a short tag, below) and the
model's fields. Binary fields are msgpack ``bin``, strings UTF-8 ``str``.

| model          | ``type``        | key (see ``common.keys``)    |
|----------------|-----------------|------------------------------|
| MaskFrame      | ``mask``        | ``<p>/cam/<cam>/mask``       |
| HoldRegions    | ``hold``        | ``<p>/cam/<cam>/hold``       |
| LookRequest    | ``look``        | ``<p>/cam/<cam>/look``       |
| TrackFrame     | ``tracks``      | ``<p>/tracks``               |
| Event          | ``event``       | ``<p>/events/<kind>/<track>``, ``<p>/history/events`` |
| Status         | ``status``      | ``<p>/status``               |
| WorkerStats    | ``worker_stats``| (optional diagnostics)       |

Events are published as JSON text (:meth:`Event.to_json`, encoding
:data:`JSON_ENCODING`) rather than msgpack, so that any zenoh client --
including the stock examples, which print ``payload.to_string()`` -- shows
them readably. The JSON object carries the same ``v``/``type``/fields as the
msgpack form; :func:`decode_event` reads either form.

Decoding never raises anything but :class:`WireError` (a ``ValueError``)
whose message names the expected message type and the problem: oversize
payload (checked before unpacking), not msgpack, not a map, wrong or missing
``v``/``type``, a bad field (named by its path), or an inconsistent mask.
Unpacking uses msgpack's length limits so that a hostile header that
declares a huge string, binary, array or map fails at once instead of
allocating it.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import msgpack
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    StrictInt,
    StringConstraints,
    ValidationError,
    model_validator,
)

from common import appearance, keys, maskcodec
from common.postures import POSTURES  # the wire's posture names (TrackState.posture)

SCHEMA_VERSION = 1
"""The only schema version this build reads and writes."""

MAX_MESSAGE_BYTES = 4 * 1024 * 1024
"""Largest accepted message of any type (a mask of pure noise at 1920x1080 fits)."""
MAX_SMALL_MESSAGE_BYTES = 256 * 1024
"""Largest accepted message of every type other than MaskFrame."""
MAX_HOLD_BOXES = 64
MAX_TRACKS = 256
MAX_CAMERAS = 64
MAX_DETAILS = 32
MAX_STAGES = 32

MSGPACK_ENCODING = "application/msgpack"
"""Zenoh encoding string for msgpack payloads."""
JSON_ENCODING = "application/json"
"""Zenoh encoding string for JSON payloads (events)."""

PERSON_EVENT_KINDS = ("fall", "long_lie", "sit_down", "stand_up", "enter", "exit", "dwell_start", "dwell_end",
                      "visit", "inactivity")
"""Events about people: what the reasoner decides and the evaluation scores."""
CAMERA_EVENT_KINDS = ("camera_lost", "camera_back", "clock_skew", "camera_stopped", "camera_moved")
"""Events about the system's health (``camera_stopped``: a worker that stopped on purpose said so;
``camera_moved``: a camera's masks stopped agreeing with what the other cameras carve)."""
ACK_EVENT_KINDS = ("alarm_ack",)
"""Someone acknowledged an alarm: ``details`` name the ``event`` (its id), the ``alarm`` (its kind)
and who acknowledged it (``by``)."""
EVENT_KINDS = PERSON_EVENT_KINDS + CAMERA_EVENT_KINDS + ACK_EVENT_KINDS
CAMERA_STATES = ("ok", "degraded", "lost", "skewed", "stopped")

_I64_MAX = 2**63 - 1
_MAX_ARRAY_LEN = 4096
_MAX_MAP_LEN = 64
_MAX_STR_LEN = 64 * 1024


class WireError(ValueError):
    """A payload is not a valid message of the expected type."""


def _camera_id(value: str) -> str:
    return keys.validate_chunk(value, "camera id")


def _codec(value: str) -> str:
    if value not in maskcodec.CODECS:
        raise ValueError(f"codec {value!r} is not one of {', '.join(maskcodec.CODECS)}")
    return value


CamId = Annotated[str, StringConstraints(max_length=64), AfterValidator(_camera_id)]
"""Camera id: one zenoh key chunk, at most 64 characters."""
NonNegInt = Annotated[int, Field(ge=0, le=_I64_MAX)]
StampNs = Annotated[int, Field(ge=0, le=_I64_MAX)]
"""Nanoseconds since the Unix epoch (or since the start of a recording)."""
Side = Annotated[int, Field(ge=1, le=maskcodec.MAX_MASK_SIDE)]
Coord = Annotated[StrictInt, Field(ge=0, le=maskcodec.MAX_MASK_SIDE)]
Fraction = Annotated[float, Field(ge=0.0, le=1.0)]
Box = Annotated[tuple[Coord, Coord, Coord, Coord], Strict(False)]
"""``(x0, y0, x1, y1)`` pixels, full-resolution capture frame, ``x1``/``y1`` exclusive."""
DetailValue = (Annotated[str, StringConstraints(max_length=1024)] | Annotated[int, Field(ge=-_I64_MAX - 1, le=_I64_MAX)]
               | float | bool | None)
DetailKey = Annotated[str, StringConstraints(min_length=1, max_length=64)]

_CONFIG = ConfigDict(strict=True, frozen=True, extra="forbid", allow_inf_nan=False)
_N_BANDS = len(appearance.BANDS)


class Appearance(BaseModel):
    """Colour descriptor of one person in one camera frame (:mod:`common.appearance`).

    ``hist`` holds one histogram per body band (head, torso, legs), each
    ``appearance.N_BINS`` bytes summing to about 255 (all zero when the band
    showed no foreground); ``pixels`` the foreground pixels each counts;
    ``visible`` the share of each band's box that no nearer person hides.
    """

    model_config = _CONFIG

    track: NonNegInt
    hist: Annotated[bytes, Field(min_length=_N_BANDS * appearance.N_BINS, max_length=_N_BANDS * appearance.N_BINS)]
    pixels: Annotated[list[NonNegInt], Field(min_length=_N_BANDS, max_length=_N_BANDS)]
    visible: Annotated[list[Fraction], Field(min_length=_N_BANDS, max_length=_N_BANDS)]


class _Message(BaseModel):
    """Base of the top-level messages: ``TYPE`` is the wire tag, ``MAX_BYTES`` the size cap."""

    model_config = _CONFIG
    TYPE: ClassVar[str] = ""
    MAX_BYTES: ClassVar[int] = MAX_SMALL_MESSAGE_BYTES


class MaskFrame(_Message):
    """One camera's encoded foreground mask for one captured frame.

    The mask is ``height x width`` pixels (possibly downscaled from the
    ``src_width x src_height`` capture), compressed with ``codec`` (one of
    ``maskcodec.CODECS``); ``maskcodec.decode_mask(data, codec, width, height)``
    restores it. ``seq`` counts captured frames (gaps are drops),
    ``stamp_ns`` is the capture time, ``fg_fraction`` the share of
    foreground pixels. ``looks``: the colour descriptors of the people the
    fusion server last asked about (:class:`LookRequest`), measured on this
    frame; empty when nobody was asked about. ``depth``: a depth camera's
    range at the mask's foreground pixels (``maskcodec.decode_depth(depth,
    mask)``: uint16 millimetres from the camera centre along each pixel's
    ray, 0 where nothing was measured); empty for other cameras.
    ``view_shift_px``: how far the camera's view of the room has moved since the
    worker took its reference picture, in pixels of the capture frame (root
    mean square over the image, :mod:`camera_worker.viewcheck`); None until
    measured, and from cameras that do not check (thermal, depth).
    """

    TYPE: ClassVar[str] = "mask"
    MAX_BYTES: ClassVar[int] = MAX_MESSAGE_BYTES

    cam: CamId
    seq: NonNegInt
    stamp_ns: StampNs
    width: Side
    height: Side
    src_width: Side
    src_height: Side
    codec: Annotated[str, AfterValidator(_codec)]
    data: bytes
    fg_fraction: Fraction
    looks: list[Appearance] = Field(default_factory=list, max_length=MAX_TRACKS)
    depth: bytes = b""
    view_shift_px: Annotated[float, Field(ge=0.0, le=float(maskcodec.MAX_MASK_SIDE))] | None = None

    @model_validator(mode="after")
    def _consistent(self) -> MaskFrame:
        if self.width > self.src_width or self.height > self.src_height:
            raise ValueError(f"mask {self.width}x{self.height} is larger than its capture "
                             f"{self.src_width}x{self.src_height}")
        try:
            lo, hi = maskcodec.encoded_size_bounds(self.codec, self.width, self.height)
        except maskcodec.MaskCodecError as exc:
            raise ValueError(str(exc)) from None
        if not lo <= len(self.data) <= hi:
            raise ValueError(f"data of {len(self.data)} bytes is implausible for a {self.codec} "
                             f"{self.width}x{self.height} mask (expected {lo}..{hi})")
        if self.depth:
            lo, hi = maskcodec.depth_size_bounds(self.width, self.height)
            if not lo <= len(self.depth) <= hi:
                raise ValueError(f"depth of {len(self.depth)} bytes is implausible for a "
                                 f"{self.width}x{self.height} mask (expected {lo}..{hi})")
        return self


class HoldRegions(_Message):
    """Regions a camera must not learn into its background (tracked people keeping still).

    ``boxes`` are ``(x0, y0, x1, y1)`` in the camera's full-resolution capture
    pixels, ``x1``/``y1`` exclusive. The hold lapses ``ttl_ms`` after
    ``stamp_ns`` unless renewed; an empty list releases every hold.
    """

    TYPE: ClassVar[str] = "hold"

    cam: CamId
    stamp_ns: StampNs
    boxes: list[Box] = Field(max_length=MAX_HOLD_BOXES)
    ttl_ms: Annotated[int, Field(ge=0, le=3_600_000)]

    @model_validator(mode="after")
    def _ordered(self) -> HoldRegions:
        for i, (x0, y0, x1, y1) in enumerate(self.boxes):
            if x0 >= x1 or y0 >= y1:
                raise ValueError(f"boxes[{i}] = {(x0, y0, x1, y1)} is empty: need x0 < x1 and y0 < y1")
        return self


class PersonRegion(BaseModel):
    """Where one tracked person lies in a camera's image: one box per body band
    (head, torso, legs; full-resolution pixels, exclusive ends; ``(0, 0, 0, 0)``
    for a band out of view) and the person's distance from the camera, metres."""

    model_config = _CONFIG

    track: NonNegInt
    depth_m: Annotated[float, Field(ge=0.0, le=1e4)]
    boxes: Annotated[list[Box], Field(min_length=_N_BANDS, max_length=_N_BANDS)]


class LookRequest(_Message):
    """The people whose colours a camera should describe on its next frame.

    The worker answers once, in the ``looks`` of the next :class:`MaskFrame`
    it sends, unless the request is older than ``ttl_ms`` by then.
    """

    TYPE: ClassVar[str] = "look"

    cam: CamId
    stamp_ns: StampNs
    people: list[PersonRegion] = Field(max_length=MAX_TRACKS)
    ttl_ms: Annotated[int, Field(ge=0, le=60_000)] = 1000

    @model_validator(mode="after")
    def _unique(self) -> LookRequest:
        ids = [p.track for p in self.people]
        if len(set(ids)) != len(ids):
            raise ValueError(f"people repeat: tracks {sorted(i for i in set(ids) if ids.count(i) > 1)}")
        return self


class TrackState(BaseModel):
    """One tracked person in one fused frame; world frame, metres, Z up.

    ``(x, y)`` is the floor position, ``z_top`` the top of the body,
    ``volume_m3`` the occupied volume, ``(vx, vy)`` the floor velocity in m/s,
    ``still`` whether the person has not moved for a while, ``person`` the
    name of the enrolled resident this is (None for anyone else).
    """

    model_config = _CONFIG

    id: NonNegInt
    x: float
    y: float
    z_top: Annotated[float, Field(ge=0.0)]
    volume_m3: Annotated[float, Field(ge=0.0)]
    posture: Literal[POSTURES]  # type: ignore[valid-type]
    reliability: Fraction
    vx: float
    vy: float
    still: bool
    person: Annotated[str, StringConstraints(min_length=1, max_length=64)] | None = None


class TrackFrame(_Message):
    """All tracks of one fused frame set, and the cameras whose masks were fused."""

    TYPE: ClassVar[str] = "tracks"

    frame: NonNegInt
    stamp_ns: StampNs
    tracks: list[TrackState] = Field(max_length=MAX_TRACKS)
    cameras: list[CamId] = Field(max_length=MAX_CAMERAS)

    @model_validator(mode="after")
    def _unique(self) -> TrackFrame:
        ids = [t.id for t in self.tracks]
        if len(set(ids)) != len(ids):
            raise ValueError(f"track ids repeat: {sorted(i for i in set(ids) if ids.count(i) > 1)}")
        if len(set(self.cameras)) != len(self.cameras):
            raise ValueError("cameras repeat")
        return self


class Event(_Message):
    """One event: a fall, a sit-down, an entry, a lost camera ...

    The one event type of the system: the reasoner makes it, the store keeps
    it, the run files and the ground truth hold it (:meth:`to_dict`,
    :meth:`from_dict`), the wire carries it and the evaluation scores it.

    ``id`` is unique across the site's history (:func:`event_id`: the stamp,
    kind and track); ``track`` is the track (or, in ground truth, the person)
    and -1 when no single one is involved (camera events); ``frame`` is the
    fused frame number (-1 when the event is tied to none); ``(x, y)`` is the
    world floor position in metres (0, 0 for events without a place).
    ``details`` holds kind-specific scalars (``duration_s``, ``door``,
    ``camera`` ...).

    Published as JSON text (:meth:`to_json`), so stock zenoh clients print it.
    """

    TYPE: ClassVar[str] = "event"

    id: Annotated[str, StringConstraints(min_length=1, max_length=128)]
    kind: Literal[EVENT_KINDS]
    track: Annotated[int, Field(ge=-1, le=_I64_MAX)]
    stamp_ns: StampNs
    frame: Annotated[int, Field(ge=-1, le=_I64_MAX)]
    x: float
    y: float
    details: dict[DetailKey, DetailValue] = Field(default_factory=dict, max_length=MAX_DETAILS)

    def to_json(self) -> str:
        """One-line JSON object with ``v``, ``type`` and every field (readable by any client)."""
        return json.dumps(_tagged(self), ensure_ascii=False, allow_nan=False, separators=(",", ":"))

    def to_dict(self) -> dict[str, Any]:
        """The fields as a plain dict, in the order of an events-file line (a copy)."""
        return {"id": self.id, "kind": self.kind, "track": self.track, "frame": self.frame,
                "stamp_ns": self.stamp_ns, "x": self.x, "y": self.y, "details": dict(self.details)}

    @classmethod
    def from_dict(cls, obj: Any) -> Event:
        """An event from a dict of its fields (an events-file line, a store row, ...).

        ``id`` may be left out (it is then :func:`event_id` of the stamp, kind
        and track), ``track`` null for none (-1), ``x``/``y`` null for no place
        (0, 0). WireError (a ValueError) naming the field on anything else.
        """
        if not isinstance(obj, dict):
            raise WireError(f"{cls.__name__}: expected a map, got {type(obj).__name__}")
        fields = dict(obj)
        if fields.get("track") is None:
            fields["track"] = -1
        for name in ("x", "y"):
            if fields.get(name) is None:
                fields[name] = 0.0
        if fields.get("details") is None:
            fields["details"] = {}
        if fields.get("id") is None:
            try:
                fields["id"] = event_id(fields["stamp_ns"], fields["kind"], fields["track"])
            except (KeyError, TypeError, ValueError):
                fields["id"] = "?"  # the missing or bad field is named below
        try:
            return cls.model_validate(fields)
        except ValidationError as exc:
            raise WireError(f"{cls.__name__}: {_describe(exc)}") from None

    @classmethod
    def from_json(cls, text: str | bytes) -> Event:
        """Parse :meth:`to_json` output; raises WireError like :func:`decode`."""
        if isinstance(text, (bytes, bytearray, memoryview)):
            if len(text) > cls.MAX_BYTES:
                raise WireError(_oversize(cls, len(text)))
            try:
                text = bytes(text).decode("utf-8")
            except UnicodeDecodeError as exc:
                raise WireError(f"{cls.__name__}: JSON text is not UTF-8 ({exc})") from None
        if not isinstance(text, str):
            raise WireError(f"{cls.__name__}: expected JSON text, got {type(text).__name__}")
        if len(text) > cls.MAX_BYTES:
            raise WireError(_oversize(cls, len(text)))
        try:
            obj = json.loads(text, parse_constant=_refuse_constant)
        except Exception as exc:  # noqa: BLE001 - ValueError, RecursionError: all mean "not JSON"
            raise WireError(f"{cls.__name__}: not valid JSON ({type(exc).__name__}: {exc})") from None
        return _validate(obj, cls)


class CameraStatus(BaseModel):
    """Health of one camera as the fusion server sees it.

    Counters run since the server started: ``received`` masks, ``dropped``
    (sequence gaps and overflow), ``late`` (missed their frame set),
    ``undecodable``. ``refused``: masks the server's time and sequence checks
    turned away (stamped ahead of the server's clock, older than what it
    already took from the camera, or repeating a sequence number; also
    counted in ``late`` or ``dropped``). ``rate_hz`` and ``latency_ms``
    (capture to arrival, after clock-offset correction) are recent averages;
    ``last_seen_ns`` is 0 before the first mask; ``clock_offset_ms`` is the
    estimated camera clock minus server clock. ``consistency``: how well the
    camera's recent masks agree with the people the other cameras carve (0..1;
    None until it has been measured); a camera that was moved or bumped drops.
    ``view_deg``: how far the camera's view has turned against its worker's
    reference picture of the room, in degrees (None until it reports one).
    ``reason``: in a few words why the camera is not ``ok`` (None when it is):
    ``undecodable masks (...)``, ``no mask for 2 s``, ``clock off by 900 ms``...
    """

    model_config = _CONFIG

    cam: CamId
    state: Literal[CAMERA_STATES]  # type: ignore[valid-type]
    received: NonNegInt
    dropped: NonNegInt
    late: NonNegInt
    undecodable: NonNegInt
    rate_hz: Annotated[float, Field(ge=0.0)]
    latency_ms: float
    last_seen_ns: StampNs
    clock_offset_ms: float
    refused: NonNegInt = 0
    consistency: Fraction | None = None
    view_deg: Annotated[float, Field(ge=0.0)] | None = None
    reason: Annotated[str, StringConstraints(max_length=200)] | None = None


class Status(_Message):
    """Periodic health report of the fusion server: cameras and frame-set counters.

    ``events_not_stored``: events the store could not write since the server
    started (each was published anyway and kept in the store's fallback file);
    ``events_pending``: those still waiting in the fallback file to be merged
    back into the store. ``state``: ``overloaded`` while the server cannot keep up
    (its masks wait in its own queue: late masks are then not taken for clocks
    that lag), else ``ok``; ``load``: the share of its recent time the server
    spent working (1.0: all of it).
    """

    TYPE: ClassVar[str] = "status"

    stamp_ns: StampNs
    cameras: list[CameraStatus] = Field(max_length=MAX_CAMERAS)
    frame_sets: NonNegInt
    frame_sets_dropped: NonNegInt
    events_not_stored: NonNegInt = 0
    events_pending: NonNegInt = 0
    state: Literal["ok", "overloaded"] = "ok"
    load: Annotated[float, Field(ge=0.0)] = 0.0

    @model_validator(mode="after")
    def _unique(self) -> Status:
        names = [c.cam for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError("cameras repeat")
        return self


class WorkerStats(_Message):
    """Counters of one camera worker: frames ``read``, ``dropped``, masks ``published``,
    and the recent mean time per stage in milliseconds (``{"segment": 2.1, ...}``)."""

    TYPE: ClassVar[str] = "worker_stats"

    cam: CamId
    stamp_ns: StampNs
    read: NonNegInt
    dropped: NonNegInt
    published: NonNegInt
    stage_ms: dict[DetailKey, Annotated[float, Field(ge=0.0)]] = Field(default_factory=dict,
                                                                        max_length=MAX_STAGES)


Message = MaskFrame | HoldRegions | LookRequest | TrackFrame | Event | Status | WorkerStats
MESSAGE_TYPES: dict[str, type[_Message]] = {m.TYPE: m for m in (MaskFrame, HoldRegions, LookRequest, TrackFrame, Event,
                                                                Status, WorkerStats)}
"""Wire tag -> model, for tools that record or replay any message."""

M = TypeVar("M", bound=_Message)


def encode(msg: _Message) -> bytes:
    """The msgpack bytes of a message (``v`` and ``type`` first, then its fields).

    Raises WireError if the result is larger than a receiver accepts.
    """
    if not isinstance(msg, _Message) or not msg.TYPE:
        raise TypeError(f"cannot encode {type(msg).__name__}: not a top-level message")
    data = msgpack.packb(_tagged(msg), use_bin_type=True)
    if len(data) > msg.MAX_BYTES:
        raise WireError(_oversize(type(msg), len(data)))
    return data


def decode(data: bytes, expected: type[M]) -> M:
    """Validate ``data`` as one msgpack message of type ``expected``; raise WireError otherwise."""
    if not isinstance(expected, type) or not issubclass(expected, _Message) or not expected.TYPE:
        raise TypeError(f"expected must be a message class, got {expected!r}")
    return _validate(_unpack(data, expected.__name__, expected.MAX_BYTES), expected)


def decode_any(data: bytes) -> Message:
    """Decode a message of whichever type its ``type`` tag names; raise WireError otherwise."""
    obj = _unpack(data, "message", MAX_MESSAGE_BYTES)
    tag = obj.get("type")
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise WireError(f"message: unknown type {tag!r}; known: {', '.join(MESSAGE_TYPES)}")
    if len(data) > cls.MAX_BYTES:
        raise WireError(_oversize(cls, len(data)))
    return _validate(obj, cls)


def event_id(stamp_ns: int, kind: str, track: int) -> str:
    """The deterministic event id ``f"{stamp_ns}-{kind}-{track}"``."""
    return f"{int(stamp_ns)}-{kind}-{int(track)}"


def decode_event(data: bytes) -> Event:
    """An Event from either of its wire forms: JSON text (``{...}``) or msgpack."""
    if isinstance(data, (bytes, bytearray, memoryview)) and bytes(data[:1]) == b"{":
        return Event.from_json(data)
    return decode(data, Event)


# --- helpers -----------------------------------------------------------------


def _tagged(msg: _Message) -> dict[str, Any]:
    return {"v": SCHEMA_VERSION, "type": msg.TYPE, **msg.model_dump(mode="python")}


def _oversize(cls: type[_Message], n: int) -> str:
    return f"{cls.__name__}: payload of {n} bytes exceeds the {cls.MAX_BYTES}-byte limit"


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not allowed")


def _unpack(data: bytes, name: str, max_bytes: int) -> dict:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(f"{name}: payload must be bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise WireError(f"{name}: payload of {len(data)} bytes exceeds the {max_bytes}-byte limit")
    if len(data) == 0:
        raise WireError(f"{name}: empty payload")
    try:
        obj = msgpack.unpackb(
            data, raw=False, strict_map_key=True, use_list=True,
            max_bin_len=max_bytes, max_str_len=_MAX_STR_LEN, max_array_len=_MAX_ARRAY_LEN,
            max_map_len=_MAX_MAP_LEN, max_ext_len=0,
        )
    except Exception as exc:  # noqa: BLE001 - msgpack raises several unrelated types for bad input
        detail = str(exc) or "bad format byte"
        raise WireError(f"{name}: not a msgpack message ({type(exc).__name__}: {detail})") from None
    if not isinstance(obj, dict):
        raise WireError(f"{name}: expected a msgpack map, got {type(obj).__name__}")
    return obj


def _validate(obj: Any, cls: type[M]) -> M:
    name = cls.__name__
    if not isinstance(obj, dict):
        raise WireError(f"{name}: expected a map, got {type(obj).__name__}")
    fields = dict(obj)
    version = fields.pop("v", None)
    if version is None:
        raise WireError(f"{name}: schema version 'v' is missing (supported: {SCHEMA_VERSION})")
    if isinstance(version, bool) or not isinstance(version, int):
        raise WireError(f"{name}: schema version 'v' must be an int, got {version!r:.40}")
    if version != SCHEMA_VERSION:
        raise WireError(f"{name}: schema version {version} received, this build supports {SCHEMA_VERSION}")
    tag = fields.pop("type", None)
    if tag != cls.TYPE:
        raise WireError(f"{name}: message type {tag!r:.40} received, expected {cls.TYPE!r}")
    try:
        return cls.model_validate(fields)
    except ValidationError as exc:
        raise WireError(f"{name}: {_describe(exc)}") from None


def _describe(exc: ValidationError) -> str:
    """``field 'path': problem`` for each failing field, one line, no input values."""
    seen: dict[str, str] = {}
    unions: dict[str, list[str]] = {}
    for err in exc.errors(include_url=False, include_input=False):
        # a union reports one error per member: gather them into one line per field
        members = [p for p in err["loc"] if isinstance(p, str) and p in _UNION_MEMBERS]
        path = ".".join(str(p) for p in err["loc"] if not (isinstance(p, str) and p in _UNION_MEMBERS))
        if members:
            unions.setdefault(path, []).append(members[-1].replace("constrained-", ""))
            seen.setdefault(path, "")
        else:
            seen.setdefault(path, err["msg"].removeprefix("Value error, "))
    for path, members in unions.items():
        if not seen[path]:
            # the only union on the wire is DetailValue, which also allows null
            seen[path] = f"must be {', '.join(dict.fromkeys(members))} or null (finite, within length limits)"
    parts = [f"field {path!r}: {msg}" if path else msg for path, msg in list(seen.items())[:5]]
    if len(seen) > 5:
        parts.append(f"and {len(seen) - 5} more")
    return "; ".join(parts)


_UNION_MEMBERS = frozenset({"str", "int", "float", "bool", "none", "constrained-str"})

