"""Key expressions: exact strings, zenoh validity, wildcard matching and parsing."""

from __future__ import annotations

import pytest
import zenoh

from common import keys

P = "voxelwatch/home"


def test_default_prefix():
    assert keys.default_prefix("home") == P
    with pytest.raises(ValueError, match="site"):
        keys.default_prefix("care/home")


def test_exact_keys():
    assert keys.mask_key(P, "cam1") == "voxelwatch/home/cam/cam1/mask"
    assert keys.mask_wildcard(P) == "voxelwatch/home/cam/*/mask"
    assert keys.hold_key(P, "cam1") == "voxelwatch/home/cam/cam1/hold"
    assert keys.alive_camera_key(P, "cam1") == "voxelwatch/home/alive/cam/cam1"
    assert keys.alive_cameras_wildcard(P) == "voxelwatch/home/alive/cam/*"
    assert keys.alive_fusion_key(P) == "voxelwatch/home/alive/fusion"
    assert keys.tracks_key(P) == "voxelwatch/home/tracks"
    assert keys.event_key(P, "fall", 7) == "voxelwatch/home/events/fall/7"
    assert keys.event_key(P, "camera_lost", -1) == "voxelwatch/home/events/camera_lost/-1"
    assert keys.events_wildcard(P) == "voxelwatch/home/events/**"
    assert keys.history_key(P) == "voxelwatch/home/history/events"
    assert keys.status_key(P) == "voxelwatch/home/status"


def _all_keys(prefix: str) -> list[str]:
    return [
        keys.mask_key(prefix, "c-1"), keys.mask_wildcard(prefix), keys.hold_key(prefix, "c-1"),
        keys.alive_camera_key(prefix, "c-1"), keys.alive_cameras_wildcard(prefix),
        keys.alive_fusion_key(prefix), keys.tracks_key(prefix), keys.event_key(prefix, "fall", 3),
        keys.events_wildcard(prefix), keys.history_key(prefix), keys.status_key(prefix),
    ]


@pytest.mark.parametrize("prefix", [P, "care/home-12/wing_b", "x"])
def test_every_key_is_a_valid_zenoh_key_expression(prefix):
    for key in _all_keys(prefix):
        assert str(zenoh.KeyExpr(key)) == key


def test_wildcards_match_their_concrete_keys_and_nothing_else():
    masks = zenoh.KeyExpr(keys.mask_wildcard(P))
    assert masks.intersects(zenoh.KeyExpr(keys.mask_key(P, "cam7")))
    assert not masks.intersects(zenoh.KeyExpr(keys.hold_key(P, "cam7")))
    assert not masks.intersects(zenoh.KeyExpr(keys.mask_key("voxelwatch/other", "cam7")))
    alive = zenoh.KeyExpr(keys.alive_cameras_wildcard(P))
    assert alive.intersects(zenoh.KeyExpr(keys.alive_camera_key(P, "cam7")))
    assert not alive.intersects(zenoh.KeyExpr(keys.alive_fusion_key(P)))
    events = zenoh.KeyExpr(keys.events_wildcard(P))
    assert events.intersects(zenoh.KeyExpr(keys.event_key(P, "long_lie", 12)))
    assert not events.intersects(zenoh.KeyExpr(keys.history_key(P)))
    assert not events.intersects(zenoh.KeyExpr(keys.tracks_key(P)))


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "a*", "$*", "a?b", "a#b", "a b", "a\tb", "a\nb", "a\x00b"])
def test_validate_chunk_refuses(bad):
    with pytest.raises(ValueError, match="camera id"):
        keys.validate_chunk(bad, "camera id")
    with pytest.raises(ValueError):
        keys.mask_key(P, bad)


def test_validate_chunk_refuses_non_string():
    with pytest.raises(ValueError, match="must be a string"):
        keys.validate_chunk(3, "camera id")  # type: ignore[arg-type]


@pytest.mark.parametrize("good", ["cam1", "Cam_02", "kitchen-north", "cámara", "1"])
def test_validate_chunk_accepts(good):
    assert keys.validate_chunk(good, "camera id") == good
    zenoh.KeyExpr(keys.mask_key(P, good))


@pytest.mark.parametrize("bad", ["", "/voxelwatch", "voxelwatch/", "a//b", "voxelwatch/*", "a/**/b", "a b/c"])
def test_bad_prefix_refused(bad):
    with pytest.raises(ValueError, match="prefix"):
        keys.tracks_key(bad)


def test_event_key_refuses_bad_kind_and_track():
    with pytest.raises(ValueError, match="event kind"):
        keys.event_key(P, "fall/x", 1)
    with pytest.raises(ValueError, match="track"):
        keys.event_key(P, "fall", "1")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="track"):
        keys.event_key(P, "fall", True)


@pytest.mark.parametrize("builder", [keys.mask_key, keys.hold_key, keys.alive_camera_key])
@pytest.mark.parametrize("prefix", [P, "care/home-12/wing_b"])
def test_camera_of_round_trip(builder, prefix):
    assert keys.camera_of(builder(prefix, "cam-3"), prefix) == "cam-3"


@pytest.mark.parametrize("key", [
    "voxelwatch/home/cam/cam1",
    "voxelwatch/home/cam/cam1/mask/extra",
    "voxelwatch/home/cam/cam1/other",
    "voxelwatch/home/alive/fusion",
    "voxelwatch/home/tracks",
    "voxelwatch/other/cam/cam1/mask",
    "voxelwatch/homeX/cam/cam1/mask",
    "voxelwatch/home/cam/*/mask",
    "voxelwatch/home/cam//mask",
    "",
])
def test_camera_of_refuses(key):
    with pytest.raises(ValueError):
        keys.camera_of(key, P)


def test_camera_of_accepts_zenoh_keyexpr():
    assert keys.camera_of(zenoh.KeyExpr(keys.mask_key(P, "c9")), P) == "c9"


def test_event_of():
    assert keys.event_of(keys.event_key(P, "fall", 4), P) == ("fall", 4)
    assert keys.event_of(keys.event_key(P, "camera_lost", -1), P) == ("camera_lost", -1)
    for bad in ["voxelwatch/home/events/fall", "voxelwatch/home/events/fall/x",
                "voxelwatch/home/events/fall/1_0", "voxelwatch/home/events/fall/1/2",
                "voxelwatch/home/tracks"]:
        with pytest.raises(ValueError):
            keys.event_of(bad, P)


def test_the_acknowledgement_selector_percent_encodes_the_name():
    assert keys.ack_key(P, "17-fall-2") == "voxelwatch/home/ack/17-fall-2"
    assert keys.ack_selector(P, "17-fall-2", "night nurse; Ann") == "voxelwatch/home/ack/17-fall-2?by=night%20nurse%3B%20Ann"
    with pytest.raises(ValueError, match="event id"):
        keys.ack_key(P, "a/b")
