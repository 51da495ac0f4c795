"""Wire messages: round trips, version/type checks, validation, corruption and size bombs."""

from __future__ import annotations

import json
import re
import struct
import typing

import msgpack
import numpy as np
import pytest

from common import maskcodec, messages
from common.messages import (
    CameraStatus,
    Event,
    HoldRegions,
    MaskFrame,
    Status,
    TrackFrame,
    TrackState,
    WireError,
    WorkerStats,
    decode,
    decode_any,
    decode_event,
    encode,
)


def _mask_frame(n_people: int = 2, codec: str = maskcodec.DEFAULT_CODEC) -> MaskFrame:
    mask = maskcodec.sample_room_mask(n_people, np.random.default_rng(n_people))
    return MaskFrame(cam="cam1", seq=41, stamp_ns=1_700_000_000_123_456_789, width=640, height=480,
                     src_width=1280, src_height=960, codec=codec, data=maskcodec.encode_mask(mask, codec),
                     fg_fraction=float(np.count_nonzero(mask)) / mask.size)


def _track(i: int) -> TrackState:
    return TrackState(id=i, x=1.5 + i, y=-2.25, z_top=1.72, volume_m3=0.071, posture="standing",
                      reliability=0.9, vx=0.3, vy=-0.1, still=False)


def _samples() -> list[messages.Message]:
    return [
        _mask_frame(),
        HoldRegions(cam="cam1", stamp_ns=10, boxes=[(0, 0, 10, 20), (100, 50, 160, 230)], ttl_ms=2000),
        HoldRegions(cam="cam2", stamp_ns=11, boxes=[], ttl_ms=0),
        TrackFrame(frame=7, stamp_ns=12, tracks=[_track(1), _track(4)], cameras=["cam1", "cam2"]),
        TrackFrame(frame=0, stamp_ns=0, tracks=[], cameras=[]),
        Event(id="e-000017", kind="fall", track=4, stamp_ns=13, frame=7, x=1.25, y=-0.5,
              details={"from": "standing", "drop_m": 0.9, "frames": 6, "confirmed": True, "zone": None}),
        Event(id="e-000018", kind="camera_lost", track=-1, stamp_ns=14, frame=-1, x=0.0, y=0.0,
              details={"cam": "cam3"}),
        Status(stamp_ns=15, frame_sets=1000, frame_sets_dropped=3, cameras=[
            CameraStatus(cam="cam1", state="ok", received=1000, dropped=2, late=1, undecodable=0, rate_hz=15.0,
                         latency_ms=4.5, last_seen_ns=14, clock_offset_ms=-0.8),
            CameraStatus(cam="cam2", state="lost", received=10, dropped=0, late=0, undecodable=3, rate_hz=0.0,
                         latency_ms=0.0, last_seen_ns=0, clock_offset_ms=0.0)]),
        WorkerStats(cam="cam1", stamp_ns=16, read=500, dropped=1, published=499,
                    stage_ms={"segment": 2.5, "encode": 0.2}),
    ]


def _fields(msg) -> dict:
    return msgpack.unpackb(encode(msg), raw=False)


def _pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


# --- round trips ---------------------------------------------------------------


@pytest.mark.parametrize("msg", _samples(), ids=lambda m: type(m).__name__)
def test_round_trip(msg):
    data = encode(msg)
    assert decode(data, type(msg)) == msg
    assert decode_any(data) == msg
    obj = msgpack.unpackb(data, raw=False)
    assert list(obj)[:2] == ["v", "type"]
    assert obj["v"] == messages.SCHEMA_VERSION and obj["type"] == type(msg).TYPE


@pytest.mark.parametrize("codec", maskcodec.CODECS)
def test_mask_frame_carries_a_decodable_mask(codec):
    msg = decode(encode(_mask_frame(2, codec)), MaskFrame)
    mask = maskcodec.decode_mask(msg.data, msg.codec, msg.width, msg.height)
    expected = maskcodec.sample_room_mask(2, np.random.default_rng(2))
    assert np.array_equal(mask, expected)
    assert msg.fg_fraction == pytest.approx(np.count_nonzero(expected) / expected.size)


def test_mask_frame_for_two_people_stays_small():
    assert len(encode(_mask_frame(2))) <= 4096


def test_event_json_is_readable_text_and_round_trips():
    ev = _samples()[5]
    text = ev.to_json()
    assert "\n" not in text
    obj = json.loads(text)
    assert obj["v"] == 1 and obj["type"] == "event" and obj["kind"] == "fall" and obj["track"] == 4
    assert obj["details"] == {"from": "standing", "drop_m": 0.9, "frames": 6, "confirmed": True, "zone": None}
    assert Event.from_json(text) == ev
    assert Event.from_json(text.encode()) == ev
    assert decode_event(text.encode()) == ev
    assert decode_event(encode(ev)) == ev


def test_event_detail_types_survive_both_forms():
    ev = Event(id="x", kind="visit", track=1, stamp_ns=1, frame=1, x=0.5, y=0.5,
               details={"b": True, "i": 1, "f": 1.0, "s": "1", "n": None})
    for back in (Event.from_json(ev.to_json()), decode(encode(ev), Event)):
        assert [type(v) for v in back.details.values()] == [bool, int, float, str, type(None)]


def test_literals_match_public_tuples():
    assert typing.get_args(Event.model_fields["kind"].annotation) == messages.EVENT_KINDS
    assert typing.get_args(TrackState.model_fields["posture"].annotation) == messages.POSTURES
    assert typing.get_args(CameraStatus.model_fields["state"].annotation) == messages.CAMERA_STATES


def test_messages_are_frozen():
    msg = _samples()[1]
    with pytest.raises(Exception):
        msg.ttl_ms = 5  # type: ignore[misc]


def test_type_tags_are_unique():
    assert len(messages.MESSAGE_TYPES) == 7
    assert all(cls.TYPE == tag for tag, cls in messages.MESSAGE_TYPES.items())


def test_encode_refuses_nested_models():
    with pytest.raises(TypeError):
        encode(_track(1))  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        decode(encode(_samples()[1]), TrackState)  # type: ignore[type-var]


# --- envelope errors -----------------------------------------------------------


def test_wrong_version_is_named():
    obj = _fields(_samples()[1])
    obj["v"] = 2
    with pytest.raises(WireError, match=r"HoldRegions: schema version 2 received, this build supports 1"):
        decode(_pack(obj), HoldRegions)
    del obj["v"]
    with pytest.raises(WireError, match="'v' is missing"):
        decode(_pack(obj), HoldRegions)
    for bad in ("1", True, 1.0, None, [1]):
        obj["v"] = bad
        with pytest.raises(WireError, match="version"):
            decode(_pack(obj), HoldRegions)


def test_wrong_type_is_named():
    data = encode(_samples()[1])
    with pytest.raises(WireError, match=r"TrackFrame: message type 'hold' received, expected 'tracks'"):
        decode(data, TrackFrame)
    obj = _fields(_samples()[1])
    del obj["type"]
    with pytest.raises(WireError, match="message type None"):
        decode(_pack(obj), HoldRegions)
    obj["type"] = "nonsense"
    with pytest.raises(WireError, match="unknown type 'nonsense'"):
        decode_any(_pack(obj))


@pytest.mark.parametrize("payload, match", [
    (b"", "empty"),
    (b"\xc1", "not a msgpack"),
    (_pack([1, 2, 3]), "expected a msgpack map"),
    (_pack(7), "expected a msgpack map"),
    (_pack({"v": 1, "type": "hold"}) + b"\x00", "not a msgpack"),  # trailing data
    (_pack({1: 2}), "not a msgpack"),  # non-string map key
    (b"\x81\xa1v\xa2\xff\xfe", "not a msgpack"),  # invalid UTF-8
    (msgpack.packb({"v": 1, "x": msgpack.ExtType(5, b"abc")}), "not a msgpack"),
])
def test_not_a_message(payload, match):
    with pytest.raises(WireError, match=match):
        decode(payload, HoldRegions)


def test_non_bytes_payload():
    with pytest.raises(WireError, match="must be bytes"):
        decode("hello", HoldRegions)  # type: ignore[arg-type]


def test_extra_and_missing_fields_are_named():
    obj = _fields(_samples()[1])
    obj["colour"] = "red"
    with pytest.raises(WireError, match="'colour'"):
        decode(_pack(obj), HoldRegions)
    obj = _fields(_samples()[1])
    del obj["ttl_ms"]
    with pytest.raises(WireError, match="'ttl_ms'"):
        decode(_pack(obj), HoldRegions)
    obj = _fields(_samples()[3])
    obj["tracks"][1]["speed"] = 1.0
    with pytest.raises(WireError, match=r"'tracks\.1\.speed'"):
        decode(_pack(obj), TrackFrame)


# --- field validation ----------------------------------------------------------


BAD_FIELDS = [
    # (sample index, path, value, field named in the error)
    (0, ("seq",), -1, "seq"),
    (0, ("stamp_ns",), -5, "stamp_ns"),
    (0, ("stamp_ns",), 2**64 - 1, "stamp_ns"),
    (0, ("stamp_ns",), 1.5, "stamp_ns"),
    (0, ("seq",), True, "seq"),
    (0, ("seq",), "3", "seq"),
    (0, ("width",), 0, "width"),
    (0, ("width",), 8193, "width"),
    (0, ("height",), -480, "height"),
    (0, ("fg_fraction",), 1.5, "fg_fraction"),
    (0, ("fg_fraction",), float("nan"), "fg_fraction"),
    (0, ("fg_fraction",), -0.1, "fg_fraction"),
    (0, ("codec",), "jpeg", "codec"),
    (0, ("cam",), "cam/1", "cam"),
    (0, ("cam",), "*", "cam"),
    (0, ("cam",), "", "cam"),
    (0, ("cam",), "c" * 65, "cam"),
    (0, ("data",), "text", "data"),
    (1, ("ttl_ms",), -1, "ttl_ms"),
    (1, ("boxes",), [[0, 0, 10]], "boxes.0"),
    (1, ("boxes",), [[0, 0, 10, 20, 30]], "boxes.0"),
    (1, ("boxes",), [[-1, 0, 10, 20]], "boxes.0.0"),
    (1, ("boxes",), [[0, 0, 10.0, 20]], "boxes.0.2"),
    (1, ("boxes",), [[0, 0, 10, 9000]], "boxes.0.3"),
    (1, ("boxes",), [[0, 0, 10, 20]] * 65, "boxes"),
    (3, ("tracks", 0, "reliability"), float("nan"), "tracks.0.reliability"),
    (3, ("tracks", 0, "reliability"), 1.01, "tracks.0.reliability"),
    (3, ("tracks", 0, "x"), float("inf"), "tracks.0.x"),
    (3, ("tracks", 0, "vy"), float("-inf"), "tracks.0.vy"),
    (3, ("tracks", 0, "z_top"), -0.1, "tracks.0.z_top"),
    (3, ("tracks", 0, "volume_m3"), -1.0, "tracks.0.volume_m3"),
    (3, ("tracks", 0, "posture"), "flying", "tracks.0.posture"),
    (3, ("tracks", 0, "still"), 1, "tracks.0.still"),
    (3, ("tracks", 0, "id"), -2, "tracks.0.id"),
    (3, ("frame",), -1, "frame"),
    (3, ("cameras",), ["ok", "a b"], "cameras.1"),
    (5, ("kind",), "party", "kind"),
    (5, ("track",), -2, "track"),
    (5, ("id",), "", "id"),
    (5, ("x",), float("nan"), "x"),
    (5, ("details",), {"k": [1, 2]}, "details.k"),
    (5, ("details",), {"k": {"a": 1}}, "details.k"),
    (5, ("details",), {"k": float("inf")}, "details.k"),
    (5, ("details",), {"": 1}, "details"),
    (5, ("details",), {f"k{i}": i for i in range(33)}, "details"),
    (7, ("cameras", 0, "state"), "fine", "cameras.0.state"),
    (7, ("cameras", 0, "rate_hz"), -1.0, "cameras.0.rate_hz"),
    (7, ("cameras", 0, "latency_ms"), float("nan"), "cameras.0.latency_ms"),
    (7, ("frame_sets_dropped",), -1, "frame_sets_dropped"),
    (8, ("stage_ms",), {"segment": -1.0}, "stage_ms.segment"),
]


@pytest.mark.parametrize("index, path, value, field", BAD_FIELDS,
                         ids=[f"{i}-{'.'.join(map(str, p))}-{v!r:.12}" for i, p, v, _ in BAD_FIELDS])
def test_bad_field_is_refused_and_named(index, path, value, field):
    msg = _samples()[index]
    obj = _fields(msg)
    target = obj
    for p in path[:-1]:
        target = target[p]
    target[path[-1]] = value
    with pytest.raises(WireError) as info:
        decode(_pack(obj), type(msg))
    text = str(info.value)
    assert text.startswith(type(msg).__name__ + ":")
    assert re.search(rf"'{re.escape(field)}(\.[^']*)?'", text), text


def test_detail_ints_beyond_int64_become_floats_and_still_encode():
    obj = _fields(_samples()[5])
    obj["details"] = {"big": 2**64 - 1, "small": -(2**63)}
    ev = decode(_pack(obj), Event)
    assert isinstance(ev.details["big"], float) and ev.details["small"] == -(2**63)
    assert decode(encode(ev), Event) == ev
    ev = Event(id="a", kind="visit", track=1, stamp_ns=0, frame=0, x=0.0, y=0.0, details={"n": 2**70})
    assert decode(encode(ev), Event) == ev


def test_cross_field_checks():
    obj = _fields(_samples()[1])
    obj["boxes"] = [[10, 0, 10, 20]]
    with pytest.raises(WireError, match=r"boxes\[0\].*empty"):
        decode(_pack(obj), HoldRegions)
    obj = _fields(_samples()[3])
    obj["tracks"][1]["id"] = obj["tracks"][0]["id"]
    with pytest.raises(WireError, match="track ids repeat"):
        decode(_pack(obj), TrackFrame)
    obj = _fields(_samples()[3])
    obj["cameras"] = ["cam1", "cam1"]
    with pytest.raises(WireError, match="cameras repeat"):
        decode(_pack(obj), TrackFrame)
    obj = _fields(_samples()[7])
    obj["cameras"][1]["cam"] = "cam1"
    with pytest.raises(WireError, match="cameras repeat"):
        decode(_pack(obj), Status)


def test_mask_frame_consistency():
    base = _fields(_mask_frame())
    obj = dict(base, src_width=320)
    with pytest.raises(WireError, match="larger than its capture"):
        decode(_pack(obj), MaskFrame)
    obj = dict(base, data=b"")
    with pytest.raises(WireError, match="implausible"):
        decode(_pack(obj), MaskFrame)
    obj = dict(base, width=8, height=8, src_width=8, src_height=8)  # 2 KB cannot be an 8x8 mask
    with pytest.raises(WireError, match="implausible"):
        decode(_pack(obj), MaskFrame)
    obj = dict(base, width=8192, height=8192, src_width=8192, src_height=8192)
    with pytest.raises(WireError, match="pixels"):
        decode(_pack(obj), MaskFrame)


def test_constructing_an_invalid_message_raises_value_error():
    with pytest.raises(ValueError, match="reliability"):
        TrackState(id=1, x=0.0, y=0.0, z_top=1.0, volume_m3=0.1, posture="standing", reliability=2.0,
                   vx=0.0, vy=0.0, still=False)


# --- corruption, fuzz and bombs ------------------------------------------------


@pytest.mark.parametrize("index", [0, 3, 5, 7], ids=["MaskFrame", "TrackFrame", "Event", "Status"])
def test_truncation_at_every_offset(index):
    msg = _samples()[index]
    data = encode(msg)
    for cut in range(len(data)):
        with pytest.raises(WireError):
            decode(data[:cut], type(msg))


def test_random_bytes_fuzz():
    rng = np.random.default_rng(2024)
    kinds = list(messages.MESSAGE_TYPES.values())
    for i in range(5000):
        n = int(rng.integers(0, 64 if i % 2 else 600))
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        if i % 3 == 0:
            data = b"\x8a" + data  # start as a 10-entry map to get deeper into the parser
        with pytest.raises(WireError):
            decode(data, kinds[i % len(kinds)])


def test_mutation_fuzz_gives_wire_error_or_a_valid_message():
    rng = np.random.default_rng(7)
    samples = [m for m in _samples() if not isinstance(m, MaskFrame)] + [_mask_frame(1)]
    accepted = 0
    for i in range(3000):
        msg = samples[i % len(samples)]
        data = bytearray(encode(msg))
        for pos in rng.integers(0, len(data), int(rng.integers(1, 4))):
            data[pos] = int(rng.integers(0, 256))
        try:
            out = decode(bytes(data), type(msg))
        except WireError:
            continue
        accepted += 1
        assert type(out) is type(msg)
    assert accepted < 3000


def test_event_json_errors():
    for bad in ["", "not json", "[1, 2]", '{"v": 1}', '{"v":1,"type":"event","x":NaN}', "[" * 100_000,
                Event.from_json.__doc__]:
        with pytest.raises(WireError):
            Event.from_json(bad)
    with pytest.raises(WireError, match="UTF-8"):
        Event.from_json(b"{\xff}")
    with pytest.raises(WireError, match="limit"):
        Event.from_json("{" + " " * messages.MAX_SMALL_MESSAGE_BYTES + "}")
    with pytest.raises(WireError, match="JSON text"):
        Event.from_json(5)  # type: ignore[arg-type]
    obj = json.loads(_samples()[5].to_json())
    obj["v"] = 3
    with pytest.raises(WireError, match="version 3 received"):
        decode_event(json.dumps(obj).encode())


def _map_with(value_header: bytes) -> bytes:
    """A msgpack map {"v": 1, "type": "mask", "data": <header only>} declaring a huge value."""
    return b"\x83" + _pack("v") + _pack(1) + _pack("type") + _pack("mask") + _pack("data") + value_header


@pytest.mark.parametrize("header", [
    b"\xc6" + struct.pack(">I", 100_000_000),  # bin32 of 100 MB
    b"\xc6" + struct.pack(">I", 2**32 - 1),
    b"\xdb" + struct.pack(">I", 2**32 - 1),  # str32
    b"\xdd" + struct.pack(">I", 2**32 - 1),  # array32
    b"\xdf" + struct.pack(">I", 2**32 - 1),  # map32
    b"\xc9" + struct.pack(">I", 2**31) + b"\x01",  # ext32
])
def test_declared_size_bombs_fail_fast(header):
    with pytest.raises(WireError, match="not a msgpack"):
        decode(_map_with(header), MaskFrame)


def test_declared_limits_are_enforced_even_when_the_bytes_are_there():
    big_array = b"\xdd" + struct.pack(">I", 5000) + b"\x00" * 5000
    with pytest.raises(WireError, match="not a msgpack"):
        decode(_map_with(big_array), MaskFrame)
    big_str = b"\xdb" + struct.pack(">I", 70_000) + b"a" * 70_000
    with pytest.raises(WireError, match="not a msgpack"):
        decode(_map_with(big_str), MaskFrame)


def test_oversize_payload_is_refused_before_unpacking():
    huge = bytes(100 * 1024 * 1024)
    with pytest.raises(WireError, match="exceeds the 4194304-byte limit"):
        decode(huge, MaskFrame)
    small_limit = messages.MAX_SMALL_MESSAGE_BYTES
    with pytest.raises(WireError, match=f"TrackFrame: payload of {small_limit + 1} bytes exceeds"):
        decode(bytes(small_limit + 1), TrackFrame)
    with pytest.raises(WireError, match="exceeds"):
        decode_any(bytes(messages.MAX_MESSAGE_BYTES + 1))


def test_decode_any_applies_the_per_type_limit():
    obj = _fields(_samples()[5])
    obj["padding"] = bytes(messages.MAX_SMALL_MESSAGE_BYTES)
    with pytest.raises(WireError, match="Event: payload of .* exceeds"):
        decode_any(_pack(obj))


def test_encode_refuses_what_a_receiver_would_refuse():
    msg = MaskFrame(cam="c", seq=0, stamp_ns=0, width=4096, height=4096, src_width=4096, src_height=4096,
                    codec="rle-zlib", data=bytes(messages.MAX_MESSAGE_BYTES), fg_fraction=0.5)
    with pytest.raises(WireError, match="MaskFrame: payload of .* exceeds"):
        encode(msg)


def test_deep_nesting_is_refused():
    deep = b"\x81" + _pack("details") + b"\x91" * 100_000 + b"\xc0"
    with pytest.raises(WireError):
        decode(deep, Event)


def test_wire_error_is_a_value_error():
    assert issubclass(WireError, ValueError)


# --- over real zenoh -----------------------------------------------------------


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _peer(listen: list[str], connect: list[str]):
    import zenoh

    from common.transport import zenoh_config

    return zenoh.open(zenoh_config(mode="peer", listen=listen, connect=connect))


def test_messages_over_zenoh_loopback_and_events_readable_as_text():
    import time

    import zenoh

    from common import keys

    prefix = keys.default_prefix("testsite")
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    mask, event = _mask_frame(2), _samples()[5]
    with _peer([endpoint], []) as pub_side, _peer([f"tcp/127.0.0.1:{_free_port()}"], [endpoint]) as sub_side:
        masks = sub_side.declare_subscriber(keys.mask_wildcard(prefix), zenoh.handlers.FifoChannel(16))
        events = sub_side.declare_subscriber(keys.events_wildcard(prefix), zenoh.handlers.FifoChannel(16))
        mask_key, event_key = keys.mask_key(prefix, mask.cam), keys.event_key(prefix, event.kind, event.track)
        got_mask = got_event = None
        deadline = time.monotonic() + 10.0
        while (got_mask is None or got_event is None) and time.monotonic() < deadline:
            pub_side.put(mask_key, encode(mask), encoding=zenoh.Encoding(messages.MSGPACK_ENCODING))
            pub_side.put(event_key, event.to_json(), encoding=zenoh.Encoding.APPLICATION_JSON)
            time.sleep(0.05)
            while (sample := masks.try_recv()) is not None:
                assert keys.camera_of(sample.key_expr, prefix) == "cam1"
                got_mask = decode(sample.payload.to_bytes(), MaskFrame)
            while (sample := events.try_recv()) is not None:
                assert keys.event_of(sample.key_expr, prefix) == ("fall", 4)
                text = sample.payload.to_string()  # what stock zenoh clients print
                assert json.loads(text)["kind"] == "fall"
                got_event = decode_event(sample.payload.to_bytes())
        masks.undeclare()
        events.undeclare()
    assert got_mask == mask
    assert got_event == event
