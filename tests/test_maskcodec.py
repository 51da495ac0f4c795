"""Mask codecs: lossless round trips, oracles for the run-length format, hostile input."""

from __future__ import annotations

import itertools
import struct
import zlib

import cv2
import numpy as np
import pytest

from common import maskcodec as mc
from common.maskcodec import CODECS, MaskCodecError, decode_mask, encode_mask


def _room(n_people: int, seed: int = 0, width: int = 640, height: int = 480) -> np.ndarray:
    return mc.sample_room_mask(n_people, np.random.default_rng(seed), width=width, height=height)


def _roundtrip(mask: np.ndarray, codec: str) -> np.ndarray:
    h, w = mask.shape
    out = decode_mask(encode_mask(mask, codec), codec, w, h)
    assert out.shape == (h, w) and out.dtype == np.uint8
    assert set(np.unique(out)) <= {0, 255}
    return out


def _leb128(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _rle_payload(runs: list[int]) -> bytes:
    return zlib.compress(b"".join(_leb128(r) for r in runs))


# --- round trips ---------------------------------------------------------------


@pytest.mark.parametrize("codec", CODECS)
@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (7, 13), (3, 641), (480, 640), (486, 644)])
@pytest.mark.parametrize("density", [0.0, 0.02, 0.5, 1.0])
def test_round_trip_random(codec, shape, density):
    rng = np.random.default_rng(hash((shape, density)) % 2**32)
    mask = (rng.random(shape) < density).astype(np.uint8) * 255
    assert np.array_equal(_roundtrip(mask, codec), mask)


@pytest.mark.parametrize("codec", CODECS)
@pytest.mark.parametrize("n_people", [0, 1, 2, 4])
def test_round_trip_structured(codec, n_people):
    mask = _room(n_people, seed=n_people)
    assert np.array_equal(_roundtrip(mask, codec), mask)


@pytest.mark.parametrize("codec", CODECS)
def test_bool_and_nonzero_inputs_mean_foreground(codec):
    rng = np.random.default_rng(3)
    values = rng.integers(0, 4, (37, 29)).astype(np.uint8) * 60  # 0, 60, 120, 180
    expected = np.where(values > 0, 255, 0).astype(np.uint8)
    assert np.array_equal(_roundtrip(values, codec), expected)
    assert np.array_equal(_roundtrip(values > 0, codec), expected)
    assert np.array_equal(_roundtrip((values > 0).astype(np.uint8), codec), expected)


@pytest.mark.parametrize("codec", CODECS)
def test_non_contiguous_input(codec):
    mask = _room(2)[::2, ::3]
    assert not mask.flags.c_contiguous
    assert np.array_equal(_roundtrip(mask, codec), mask)


@pytest.mark.parametrize("codec", CODECS)
@pytest.mark.parametrize("level", [0, 1, 6, 9])
def test_zlib_level_changes_size_not_format(codec, level):
    mask = _room(2)
    data = encode_mask(mask, codec, zlib_level=level)
    assert np.array_equal(decode_mask(data, codec, 640, 480), mask)


# --- format oracles ------------------------------------------------------------


def test_rle_zlib_format_matches_hand_written_oracle():
    rng = np.random.default_rng(5)
    for mask in [_room(2), (rng.random((31, 17)) < 0.3), np.ones((4, 4), bool), np.zeros((2, 3), bool)]:
        flat = (np.asarray(mask) != 0).ravel().tolist()
        runs = [len(list(g)) for _, g in itertools.groupby(flat)]
        if flat[0]:
            runs = [0] + runs
        raw = zlib.decompress(encode_mask(np.asarray(mask), "rle-zlib"))
        assert raw == b"".join(_leb128(r) for r in runs)


def test_rle_decoder_accepts_hand_built_payload():
    # 2x5: . # # . .  / . . . # #  -> runs 1,2,4,2,1? no: stream .##.....## -> 1,2,5,2
    data = _rle_payload([1, 2, 5, 2])
    out = decode_mask(data, "rle-zlib", 5, 2)
    expected = np.array([[0, 255, 255, 0, 0], [0, 0, 0, 255, 255]], np.uint8)
    assert np.array_equal(out, expected)
    # leading zero run: the stream starts with foreground; long runs need multi-byte varints
    out = decode_mask(_rle_payload([0, 300, 100]), "rle-zlib", 100, 4)
    assert out.ravel()[:300].all() and not out.ravel()[300:].any()


def test_bits_zlib_format_is_packbits_msb_first():
    mask = np.array([[1, 0, 0, 0, 0, 0, 0, 1, 1, 0, 1]], np.uint8)
    assert zlib.decompress(encode_mask(mask, "bits-zlib")) == bytes([0b10000001, 0b10100000])


def test_png_is_a_one_bit_greyscale_png_readable_by_opencv():
    mask = _room(1)
    data = encode_mask(mask, "png")
    assert data.startswith(b"\x89PNG\r\n\x1a\n")
    w, h, depth, colour = struct.unpack(">IIBB", data[16:26])
    assert (w, h, depth, colour) == (640, 480, 1, 0)
    assert np.array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE), mask)


@pytest.mark.parametrize("shape", [(480, 640), (97, 101)])
def test_toggle_path_equals_repeat_path(shape):
    rng = np.random.default_rng(11)
    for mask in [(rng.random(shape) < 0.4).astype(np.uint8) * 255,
                 cv2.resize(_room(4), shape[::-1], interpolation=cv2.INTER_NEAREST)]:
        raw = zlib.decompress(encode_mask(mask, "rle-zlib"))
        h, w = shape
        fast = mc._runs_to_mask(raw, w, h, repeat_max_runs=1 << 30)
        blocked = mc._runs_to_mask(raw, w, h, repeat_max_runs=0, block_bytes=64)
        assert np.array_equal(fast, mask) and np.array_equal(blocked, mask)


def test_random_mask_takes_the_toggle_path_and_round_trips():
    mask = (np.random.default_rng(2).random((480, 640)) < 0.5).astype(np.uint8) * 255
    raw = zlib.decompress(encode_mask(mask, "rle-zlib"))
    assert np.count_nonzero(np.frombuffer(raw, np.uint8) < 0x80) > mc._REPEAT_MAX_RUNS
    assert np.array_equal(decode_mask(encode_mask(mask, "rle-zlib"), "rle-zlib", 640, 480), mask)


# --- hostile and wrong input ---------------------------------------------------


@pytest.mark.parametrize("codec", CODECS)
def test_truncation_at_every_offset_is_refused(codec):
    mask = cv2.resize(_room(2), (96, 72), interpolation=cv2.INTER_NEAREST)
    data = encode_mask(mask, codec)
    for cut in range(len(data)):
        with pytest.raises(MaskCodecError):
            decode_mask(data[:cut], codec, 96, 72)


@pytest.mark.parametrize("codec", CODECS)
def test_trailing_bytes_are_refused(codec):
    data = encode_mask(_room(1), codec)
    with pytest.raises(MaskCodecError):
        decode_mask(data + b"\x00junk", codec, 640, 480)


@pytest.mark.parametrize("codec", CODECS)
def test_bit_flips_give_error_or_a_mask_of_the_declared_size(codec):
    mask = cv2.resize(_room(2), (96, 72), interpolation=cv2.INTER_NEAREST)
    data = bytearray(encode_mask(mask, codec))
    rng = np.random.default_rng(9)
    for _ in range(400):
        bad = bytearray(data)
        for pos in rng.integers(0, len(bad), rng.integers(1, 4)):
            bad[pos] ^= 1 << int(rng.integers(0, 8))
        try:
            out = decode_mask(bytes(bad), codec, 96, 72)
        except MaskCodecError:
            continue
        assert out.shape == (72, 96) and out.dtype == np.uint8


@pytest.mark.parametrize("codec", CODECS)
def test_random_bytes_are_refused(codec):
    rng = np.random.default_rng(13)
    prefixes = {"rle-zlib": b"x\x01", "bits-zlib": b"x\x01", "png": b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR"}
    for i in range(1000):
        body = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
        data = prefixes[codec] + body if i % 2 else body
        with pytest.raises(MaskCodecError):
            decode_mask(data, codec, 64, 48)


@pytest.mark.parametrize("codec", CODECS)
@pytest.mark.parametrize("size", [(641, 480), (640, 479), (1, 1), (960, 320)])
def test_wrong_declared_size_is_refused(codec, size):
    data = encode_mask(_room(2), codec)
    if codec != "png" and size[0] * size[1] == 640 * 480:
        # the zlib codecs carry no shape: only the pixel count can be checked
        assert decode_mask(data, codec, *size).size == 640 * 480
        return
    with pytest.raises(MaskCodecError):
        decode_mask(data, codec, *size)


def test_png_also_catches_a_swapped_shape():
    with pytest.raises(MaskCodecError, match="640x480"):
        decode_mask(encode_mask(_room(2), "png"), "png", 480, 640)


@pytest.mark.parametrize("codec", CODECS)
@pytest.mark.parametrize("size", [(0, 10), (10, 0), (-1, 10), (8193, 1), (1, 8193), (8192, 8192), (10.0, 10),
                                  (True, 10), ("10", 10)])
def test_bad_declared_size_is_refused_before_decoding(codec, size):
    with pytest.raises(MaskCodecError):
        decode_mask(b"\x00" * 64, codec, *size)


def test_zip_bombs_never_inflate_past_the_declared_size():
    # 30 MB of zeros packs into ~30 KB: refused after inflating just past 38 400 bytes
    bomb = zlib.compress(b"\x00" * 30_000_000, 9)
    assert len(bomb) <= mc.encoded_size_bounds("bits-zlib", 640, 480)[1]
    with pytest.raises(MaskCodecError, match="more than"):
        decode_mask(bomb, "bits-zlib", 640, 480)
    with pytest.raises(MaskCodecError, match="implausible"):
        decode_mask(zlib.compress(b"\x00" * 100_000_000, 9), "bits-zlib", 640, 480)
    runs_bomb = zlib.compress(b"\x01" * 10_000_000, 9)
    with pytest.raises(MaskCodecError, match="more than"):
        decode_mask(runs_bomb, "rle-zlib", 640, 480)


def test_oversized_data_is_refused_before_inflating():
    lo, hi = mc.encoded_size_bounds("rle-zlib", 64, 48)
    assert lo >= 1 and hi < 64 * 48 * 2
    with pytest.raises(MaskCodecError, match="implausible"):
        decode_mask(b"\x00" * (hi + 1), "rle-zlib", 64, 48)
    with pytest.raises(MaskCodecError, match="implausible"):
        decode_mask(b"", "bits-zlib", 64, 48)


@pytest.mark.parametrize("runs, match", [
    ([10, 10, 9], "cover"),  # one short of 30
    ([10, 10, 11], "cover"),  # one too many
    ([10, 0, 20], "empty run"),
    ([0, 0, 30], "empty run"),
    ([31], "exceeds|cover"),
])
def test_rle_runs_must_tile_the_mask_exactly(runs, match):
    with pytest.raises(MaskCodecError, match=match):
        decode_mask(_rle_payload(runs), "rle-zlib", 10, 3)


def test_rle_malformed_varints_are_refused():
    with pytest.raises(MaskCodecError, match="truncated"):
        decode_mask(zlib.compress(bytes([30, 0x80])), "rle-zlib", 10, 3)
    with pytest.raises(MaskCodecError, match="longer than"):
        decode_mask(zlib.compress(bytes([0x9E, 0x80, 0x80, 0x80, 0x00])), "rle-zlib", 10, 3)
    with pytest.raises(MaskCodecError, match="no runs"):
        decode_mask(zlib.compress(b""), "rle-zlib", 10, 3)


def test_rle_huge_run_value_is_refused():
    with pytest.raises(MaskCodecError):
        decode_mask(_rle_payload([(1 << 28) - 1]), "rle-zlib", 10, 3)


def test_png_of_other_size_or_depth_is_refused():
    mask = _room(1, width=64, height=48)
    with pytest.raises(MaskCodecError, match="64x48"):
        decode_mask(encode_mask(mask, "png"), "png", 48, 64)
    ok, grey8 = cv2.imencode(".png", mask)
    assert ok
    with pytest.raises(MaskCodecError, match="1-bit"):
        decode_mask(grey8.tobytes(), "png", 64, 48)
    with pytest.raises(MaskCodecError, match="signature"):
        decode_mask(encode_mask(mask, "bits-zlib") + b"\x00" * 64, "png", 64, 48)


def test_png_declaring_a_huge_image_is_refused_before_decoding():
    ihdr = struct.pack(">IIBBBBB", 100000, 100000, 1, 0, 0, 0, 0)
    header = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr
    data = header + b"\x00" * 64
    with pytest.raises(MaskCodecError):
        decode_mask(data, "png", 640, 480)


def test_unknown_codec_is_refused():
    with pytest.raises(MaskCodecError, match="unknown mask codec"):
        encode_mask(np.zeros((4, 4), np.uint8), "jpeg")
    with pytest.raises(MaskCodecError, match="unknown mask codec"):
        decode_mask(b"\x00" * 16, "jpeg", 4, 4)


@pytest.mark.parametrize("bad, match", [
    (np.zeros((4, 4, 3), np.uint8), "2-D"),
    (np.zeros((4,), np.uint8), "2-D"),
    (np.zeros((4, 4), np.float32), "dtype"),
    (np.zeros((0, 4), np.uint8), "height"),
    ([[0, 1], [1, 0]], "numpy array"),
])
def test_encode_refuses_bad_masks(bad, match):
    with pytest.raises(MaskCodecError, match=match):
        encode_mask(bad)


def test_encode_refuses_bad_level_and_decode_refuses_non_bytes():
    with pytest.raises(MaskCodecError, match="zlib_level"):
        encode_mask(np.zeros((4, 4), np.uint8), "rle-zlib", zlib_level=10)
    with pytest.raises(MaskCodecError, match="bytes"):
        decode_mask(10**9, "rle-zlib", 4, 4)  # type: ignore[arg-type]


def test_decode_accepts_bytearray_and_memoryview():
    mask = _room(1, width=64, height=48)
    data = encode_mask(mask)
    assert np.array_equal(decode_mask(bytearray(data), mc.DEFAULT_CODEC, 64, 48), mask)
    assert np.array_equal(decode_mask(memoryview(data), mc.DEFAULT_CODEC, 64, 48), mask)


# --- measurement ---------------------------------------------------------------


def test_measure_codecs_reports_every_codec_losslessly():
    masks = [_room(2, seed=s) for s in range(5)]
    rows = mc.measure_codecs(masks, repeats=1)
    assert [r["codec"] for r in rows] == list(CODECS)
    for r in rows:
        assert r["lossless"] and r["masks"] == 5
        assert r["max_bytes"] >= r["median_bytes"] > 0
        assert r["median_total_ms"] > 0
    sizes = {r["codec"]: r["median_bytes"] for r in rows}
    # the default is the smallest on rooms with people, and within the 4 KB budget
    assert min(sizes, key=sizes.get) == mc.DEFAULT_CODEC
    assert sizes[mc.DEFAULT_CODEC] <= 4096


def test_measure_codecs_refuses_empty_input():
    with pytest.raises(ValueError):
        mc.measure_codecs([])


def test_sample_room_mask_grows_with_people():
    fg = [np.count_nonzero(_room(n, seed=1)) for n in (0, 1, 2, 4)]
    assert fg[0] <= 6 * 21 < fg[1] < fg[2] < fg[3]  # an empty room holds only six speckles
    one = _room(1, seed=1)
    _, _, stats, _ = cv2.connectedComponentsWithStats(one)
    body = stats[1:][np.argmax(stats[1:, cv2.CC_STAT_AREA])]
    assert 150 <= body[cv2.CC_STAT_HEIGHT] <= 210 and 40 <= body[cv2.CC_STAT_WIDTH] <= 90


# ---------------------------------------------------------------------- foreground depth


def test_depth_round_trip_keeps_foreground_values_exactly():
    rng = np.random.default_rng(5)
    mask = np.zeros((48, 64), np.uint8)
    mask[10:40, 20:35] = 255
    depth = rng.integers(0, 65536, size=mask.shape, dtype=np.uint16)  # any value, wrap-around deltas
    depth[12, 22] = 0  # a missing measurement stays missing
    out = mc.decode_depth(mc.encode_depth(depth, mask), mask)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out[mask > 0], depth[mask > 0])
    assert not out[mask == 0].any()


def test_depth_of_a_smooth_person_compresses_well():
    mask = np.zeros((240, 320), np.uint8)
    mask[60:220, 140:180] = 255
    yy, xx = np.mgrid[0:240, 0:320]
    depth = (3000 + 2 * (xx - 160) ** 2 // 40 + yy // 8).astype(np.uint16)
    data = mc.encode_depth(depth, mask)
    assert len(data) < 0.25 * 2 * np.count_nonzero(mask)


def test_depth_decode_refuses_a_payload_for_another_mask():
    mask = np.zeros((20, 20), np.uint8)
    mask[5:10, 5:10] = 255
    data = mc.encode_depth(np.full((20, 20), 1500, np.uint16), mask)
    other = mask.copy()
    other[0, 0] = 255
    with pytest.raises(mc.MaskCodecError, match="26 foreground pixels"):
        mc.decode_depth(data, other)
    with pytest.raises(mc.MaskCodecError, match="not a valid zlib stream"):
        mc.decode_depth(b"\x00" * 12, mask)
    with pytest.raises(mc.MaskCodecError, match="uint16"):
        mc.encode_depth(np.zeros((20, 20), np.float32), mask)
