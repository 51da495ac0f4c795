"""What travels on the wire of a live run: every message, recorded and checked.

The synthetic house runs as real processes on loopback (the test process is
the zenoh router, multicast scouting off; the fusion server and five camera
workers are clients), playing 'two_pass' (two people walking past each
other) on the host clock. A subscriber on ``<p>/**`` records every sample's
key and payload. Then:

* every payload decodes as the message its key carries (events as JSON
  text), and the run carried masks, holds or looks, look answers inside the
  masks, tracks and status;
* nothing but a MaskFrame is larger than :data:`SMALL_BOUND` bytes;
* the only binary fields of any message are a MaskFrame's mask ``data``
  (which decodes to a 0/255 mask of the declared size) and the ``hist`` of
  each of its looks (exactly ``3 * N_BINS`` bytes): no image content;
* the descriptors cost less than :data:`BUDGET_B` bytes per person per
  second per camera.

The default run plays a few seconds; a longer one is marked slow.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field

import msgpack
import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from procs import Listener, Proc, Router, start_camera, start_fusion, start_in_step, stop_all, wait_for  # noqa: E402

from evaluation.worker_bench import looks_bytes  # noqa: E402
from common import appearance, keys, maskcodec, messages  # noqa: E402

SCENARIO = "two_pass"
PEOPLE = 2
"""People in the scenario, both in the room from its first frame."""
SMALL_BOUND = 4096
"""Largest payload, bytes, of any message but a MaskFrame."""
BUDGET_B = 1024
"""Most descriptor bytes per person per second per camera."""


@dataclass
class Recorder:
    """Every sample under ``<p>/**``: ``(key, payload bytes)``, and apart the keys of DELETE samples
    (a worker's notice that it stops on purpose); the callback only appends."""

    session: object
    prefix: str
    lock: threading.Lock = field(default_factory=threading.Lock)
    samples: list[tuple[str, bytes]] = field(default_factory=list)
    deletes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.sub = self.session.declare_subscriber(f"{self.prefix}/**", self._on)

    def _on(self, sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            with self.lock:
                self.deletes.append(str(sample.key_expr))
            return
        item = (str(sample.key_expr), sample.payload.to_bytes())
        with self.lock:
            self.samples.append(item)

    def taken(self) -> list[tuple[str, bytes]]:
        with self.lock:
            return list(self.samples)

    def close(self) -> None:
        self.sub.undeclare()


def expected_type(key: str, prefix: str) -> str:
    """The wire tag the key must carry (``event`` for event keys, which carry JSON text)."""
    rest = key[len(prefix) + 1:].split("/")
    if rest[0] == "cam" and len(rest) == 3:
        return {"mask": "mask", "hold": "hold", "look": "look"}[rest[2]]
    if rest == ["tracks"]:
        return "tracks"
    if rest == ["status"]:
        return "status"
    if rest[0] == "events":
        keys.event_of(key, prefix)
        return "event"
    raise AssertionError(f"a message on a key the system does not use: {key}")


def binary_fields(obj, path: str = "") -> list[str]:
    """The paths of every binary value in a msgpack-decoded object (list items as ``[]``)."""
    if isinstance(obj, (bytes, bytearray)):
        return [path]
    if isinstance(obj, dict):
        return [p for k, v in obj.items() for p in binary_fields(v, f"{path}.{k}" if path else str(k))]
    if isinstance(obj, (list, tuple)):
        return [p for v in obj for p in binary_fields(v, f"{path}[]")]
    return []


def check_wire(samples: list[tuple[str, bytes]], prefix: str, n_cameras: int) -> dict:
    """Decode and check every recorded sample; return the measured figures."""
    sizes: dict[str, list[int]] = defaultdict(list)
    descriptor_bytes: dict[str, int] = Counter()
    stamps: dict[str, list[int]] = defaultdict(list)
    looks_per_cam: Counter = Counter()
    for key, payload in samples:
        kind = expected_type(key, prefix)
        sizes[kind].append(len(payload))
        if kind == "event":
            event = messages.decode_event(payload)
            assert (event.kind, event.track) == keys.event_of(key, prefix), key
            assert bytes(payload[:1]) == b"{", "events travel as JSON text"
            continue
        msg = messages.decode_any(payload)
        assert msg.TYPE == kind, (key, msg.TYPE)
        raw = msgpack.unpackb(payload, raw=False)
        found = binary_fields(raw)
        if kind != "mask":
            assert found == [], (key, found)
            assert len(payload) <= SMALL_BOUND, (key, len(payload))
            if kind in ("hold", "look"):
                assert keys.camera_of(key, prefix) == msg.cam
            continue
        assert keys.camera_of(key, prefix) == msg.cam
        assert set(found) <= {"data", "looks[].hist", "depth"} and found.count("data") == 1, found
        assert msg.depth == b"", "colour cameras ship no depth"
        mask = maskcodec.decode_mask(msg.data, msg.codec, msg.width, msg.height)
        assert mask.shape == (msg.height, msg.width) and mask.dtype == np.uint8
        assert set(np.unique(mask).tolist()) <= {0, 255}
        for look in msg.looks:
            assert len(look.hist) == 3 * appearance.N_BINS
        stamps[msg.cam].append(msg.stamp_ns)
        if msg.looks:
            looks_per_cam[msg.cam] += 1
            descriptor_bytes[msg.cam] += looks_bytes(msg.looks)
            sizes["mask looks"].append(looks_bytes(msg.looks))
    seen = set(sizes)
    assert {"mask", "tracks", "status", "mask looks"} <= seen and seen & {"hold", "look"}, sorted(seen)
    assert "look" in seen, "the fusion server asked no camera for looks"
    seconds = {cam: (max(s) - min(s)) / 1e9 + 1 / 15 for cam, s in stamps.items()}
    per_person = {cam: descriptor_bytes[cam] / PEOPLE / seconds[cam] for cam in stamps}
    assert len(stamps) == n_cameras
    overall = sum(descriptor_bytes.values()) / PEOPLE / (sum(seconds.values()) / len(seconds)) / n_cameras
    return {
        "messages": {kind: len(v) for kind, v in sorted(sizes.items())},
        "bytes_median": {kind: float(np.median(v)) for kind, v in sorted(sizes.items())},
        "bytes_max": {kind: int(max(v)) for kind, v in sorted(sizes.items())},
        "masks_with_looks": dict(sorted(looks_per_cam.items())),
        "descriptor_B_per_person_s_camera": round(overall, 1),
        "descriptor_B_per_person_s_by_camera": {cam: round(v, 1) for cam, v in sorted(per_person.items())},
    }


def run_house(house, tmp_path, n_frames: int) -> tuple[list[tuple[str, bytes]], object]:
    """Play ``n_frames`` of the scenario with every camera; return the recorded samples and the site."""
    site, site_file, cache = house
    logs = tmp_path / "logs"
    logs.mkdir()
    procs: list[Proc] = []
    with Router() as router:
        listener = Listener(router.session, site.prefix)
        recorder = Recorder(router.session, site.prefix)
        try:
            fusion = start_fusion(site_file, endpoint=router.endpoint, store=tmp_path / "events.sqlite", out=None,
                                  cache_dir=cache, log_dir=logs)
            procs.append(fusion)
            listener.wait_fusion(fusion)
            start_file = tmp_path / "start_ns"
            workers = [start_camera(site_file, cam, endpoint=router.endpoint, scenario=SCENARIO,
                                    start_file=start_file, max_frames=n_frames, log_dir=logs)
                       for cam in site.camera_ids]
            procs.extend(workers)
            start_in_step(router.session, site.prefix, dict(zip(site.camera_ids, workers)), start_file)
            for worker in workers:
                assert worker.popen.wait(timeout=n_frames / 15 + 120) == 0, worker.tail()
            # the workers say they stop on purpose: camera_stopped, not camera_lost
            wait_for(lambda: len(listener.events_of("camera_stopped")) >= len(workers), 30,
                     "camera_stopped events as the workers end", procs=[fusion])
            time.sleep(0.5)
            assert listener.events_of("camera_lost") == []
            assert sorted(recorder.deletes) == sorted(keys.mask_key(site.prefix, c) for c in site.camera_ids)
            time.sleep(1.0)
            assert fusion.stop() == 0, fusion.tail()
            for worker in workers:
                assert "Traceback" not in worker.output(), worker.tail()
            assert "Traceback" not in fusion.output(), fusion.tail()
        finally:
            stop_all(procs)
            recorder.close()
            listener.close()
    return recorder.taken(), site


def _check_run(house, tmp_path, n_frames: int) -> None:
    samples, site = run_house(house, tmp_path, n_frames)
    measured = check_wire(samples, site.prefix, len(site.camera_ids))
    print("wire:", measured)
    assert measured["descriptor_B_per_person_s_camera"] < BUDGET_B, measured
    assert all(v < BUDGET_B for v in measured["descriptor_B_per_person_s_by_camera"].values()), measured


def test_nothing_on_the_wire_of_a_live_run_carries_image_content(house, tmp_path):
    _check_run(house, tmp_path, n_frames=75)


@pytest.mark.slow
def test_nothing_on_the_wire_of_a_whole_crossing_carries_image_content(house, tmp_path):
    _check_run(house, tmp_path, n_frames=330)
