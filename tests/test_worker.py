"""Camera worker: the pure pieces (hold book, mask messages, step, look answers), the benchmark, and real
``voxelwatch-camera`` processes talking to a plain zenoh subscriber on loopback."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh

from camera_worker.looks import LookAnswerer
from camera_worker.segmentation import ForegroundSegmenter
from camera_worker.segmenters import segmenter_for
from camera_worker.sources import Frame
from camera_worker.worker import (
    HoldBook,
    WorkerSettings,
    build_mask_frame,
    step,
)
from camera_worker.worker import HoldRegionsRejected
from common import appearance, keys, maskcodec, messages
from common.messages import HoldRegions, LookRequest, MaskFrame, PersonRegion
from evaluation.worker_bench import looks_bytes, measure_worker
from common.transport import zenoh_config

CAMERA = Path(sys.executable).parent / "voxelwatch-camera"
W, H, FPS = 160, 120, 25.0
BOX_FROM = 20                       # the walker enters at this frame


def _box_x(i: int) -> int:
    """The walker's left edge in frame ``i`` of the clip: 2 px a frame, back to the left edge every 64
    frames, so it is whole in the 160 px frame whatever frame a late worker joins at."""
    return 10 + 2 * (i % 64)


# --- pure pieces ---------------------------------------------------------------------------------


def _hold(cam="cam1", stamp=1_000, boxes=((1, 2, 30, 40),), ttl_ms=500) -> HoldRegions:
    return HoldRegions(cam=cam, stamp_ns=stamp, boxes=list(boxes), ttl_ms=ttl_ms)


def test_hold_book_applies_boxes_for_their_ttl_in_camera_time():
    book = HoldBook("cam1")
    assert book.boxes(0) == []
    book.offer(_hold(stamp=10**18), now_ns=5_000_000_000)     # a fusion clock far from the camera's
    assert book.boxes(5_000_000_000) == [(1, 2, 30, 40)]
    assert book.boxes(5_500_000_000) == [(1, 2, 30, 40)]       # ttl counted from arrival, camera time
    assert book.boxes(5_500_000_001) == []


def test_hold_book_replaces_releases_and_rejects():
    book = HoldBook("cam1")
    book.offer(_hold(stamp=100, boxes=((0, 0, 5, 5), (6, 6, 9, 9))), now_ns=0)
    assert len(book.boxes(0)) == 2
    book.offer(_hold(stamp=200, boxes=()), now_ns=1)            # an empty list releases every hold
    assert book.boxes(1) == []
    with pytest.raises(HoldRegionsRejected, match="camera 'cam2'"):
        book.offer(_hold(cam="cam2", stamp=300), now_ns=2)
    with pytest.raises(HoldRegionsRejected, match="older"):
        book.offer(_hold(stamp=150), now_ns=2)


def test_hold_book_keeps_its_boxes_while_no_fusion_server_is_live_for_a_bound():
    s = 1_000_000_000
    book = HoldBook("cam1", orphan_s=60.0)
    book.offer(_hold(stamp=100, ttl_ms=2000), now_ns=10 * s)
    book.server_gone(11 * s)                      # the server crashed while the hold was in force
    assert book.boxes(40 * s) == [(1, 2, 30, 40)]  # long past its 2 s: nobody can release it
    assert book.boxes(71 * s) == [(1, 2, 30, 40)]  # 60 s after the server went ...
    assert book.boxes(71 * s + 1) == []            # ... and no longer
    # a server back in time: one time-to-live more, for it to send its own
    book.server_gone(11 * s)
    book.server_back(30 * s)
    assert book.boxes(32 * s) == [(1, 2, 30, 40)]
    assert book.boxes(32 * s + 1) == []
    # a hold that had lapsed before the server went is not revived; a release is final
    late = HoldBook("cam1", orphan_s=60.0)
    late.offer(_hold(stamp=100, ttl_ms=2000), now_ns=10 * s)
    late.server_gone(13 * s)
    assert late.boxes(13 * s) == []
    released = HoldBook("cam1", orphan_s=60.0)
    released.offer(_hold(stamp=100, ttl_ms=2000), now_ns=10 * s)
    released.offer(_hold(stamp=200, boxes=(), ttl_ms=2000), now_ns=10 * s + 1)
    released.server_gone(11 * s)
    assert released.boxes(12 * s) == []
    with pytest.raises(ValueError, match="orphan_s"):
        HoldBook("cam1", orphan_s=-1.0)


def test_build_mask_frame_round_trips_through_the_wire():
    mask = np.zeros((60, 80), np.uint8)
    mask[10:30, 20:35] = 255
    msg = build_mask_frame(mask, cam="cam3", seq=7, stamp_ns=123, src_size=(160, 120))
    back = messages.decode(messages.encode(msg), MaskFrame)
    assert (back.cam, back.seq, back.stamp_ns, back.width, back.height, back.src_width, back.src_height) == \
        ("cam3", 7, 123, 80, 60, 160, 120)
    assert back.codec == maskcodec.DEFAULT_CODEC
    assert back.fg_fraction == pytest.approx(300 / 4800)
    assert np.array_equal(maskcodec.decode_mask(back.data, back.codec, back.width, back.height), mask)


def _learnt_room_with_person():
    """A segmenter that learnt a noisy room, and the room with a green person at rows
    30..90, columns 60..80."""
    rng = np.random.default_rng(0)
    room = np.clip(rng.normal(120, 30, (H, W, 3)), 0, 255).astype(np.uint8)
    seg = ForegroundSegmenter(min_area_px=20, mask_scale=0.5)
    for _ in range(10):
        seg.learn(room)
    person = room.copy()
    person[30:90, 60:80] = (30, 200, 40)
    return seg, person


def test_step_segments_and_wraps_one_frame():
    seg, person = _learnt_room_with_person()
    msg, mask, stats = step(seg, Frame(4, 99, person), cam="cam1", seq=4)
    assert (msg.width, msg.height, msg.src_width, msg.src_height) == (W // 2, H // 2, W, H)
    assert msg.seq == 4 and msg.stamp_ns == 99 and msg.fg_fraction == stats.fg_fraction
    # the person's 30 x 10 mask pixels, less the four corners the elliptic opening rounds off
    assert np.count_nonzero(mask[15:45, 30:40]) >= 296 and np.count_nonzero(mask) == np.count_nonzero(mask[15:45, 30:40])


def test_step_runs_the_view_check_on_the_mask_and_times_each_stage():
    """The view check is handed the frame and the mask it was segmented into, and its shift goes
    out in the message; each stage's seconds are added to the caller's table (the worker's own
    counters and the benchmark read them so); the holds reach the segmenter."""
    seg, person = _learnt_room_with_person()
    seen = []

    def view(frame, mask, stats):
        seen.append((frame.index, mask.shape, stats.fg_fraction))
        return 2.345

    stage_s = {"read": 0.5, "segment": 0.0, "looks": 0.0, "view": 0.0, "encode": 0.0, "publish": 0.0}
    msg, mask, stats = step(seg, Frame(4, 99, person), cam="cam1", seq=4, view=view, stage_s=stage_s,
                            holds=[(60, 30, 70, 90)])
    assert seen == [(4, mask.shape, stats.fg_fraction)] and msg.view_shift_px == 2.35
    assert stage_s["read"] == 0.5 and stage_s["publish"] == 0.0
    assert all(stage_s[k] > 0 for k in ("segment", "looks", "view", "encode")), stage_s
    assert stats.holds == 1 and np.count_nonzero(mask[15:45, 30:40]) >= 296   # held, and still foreground


def test_step_of_a_depth_camera_ships_the_foreground_range_and_a_thermal_one_none():
    """A drawn range scene: a wall at 4 m, a person at 2.5 m (30 x 10 pixels at mask size);
    the message's range decodes to the person's readings. A thermal camera sends no range and
    leaves a colour look request unanswered."""
    wall = np.full((H, W), 4000, np.uint16)
    depth_seg = segmenter_for("depth", mask_scale=0.5, window_frames=50)
    for _ in range(10):
        depth_seg.learn(wall)
    scene = wall.copy()
    scene[30:90, 60:80] = 2500 + (np.arange(60, dtype=np.uint16)[:, None] % 7)
    scene[50, 70] = 0   # one missing reading inside the person
    msg, mask, _ = step(depth_seg, Frame(0, 5, scene), cam="cam1", seq=0)
    assert msg.depth
    back = maskcodec.decode_depth(msg.depth, mask)
    assert np.count_nonzero(mask[15:45, 30:40]) >= 296
    assert set(np.unique(back[mask > 0])) <= set(range(2500, 2507)) | {0}
    assert back[25, 35] == 0   # the missing reading is in the mask but ships no range
    assert np.count_nonzero(back) >= 290
    hot = np.full((H, W), 29415, np.uint16)
    thermal_seg = segmenter_for("thermal", mask_scale=0.5, window_frames=50)
    for _ in range(10):
        thermal_seg.learn(hot)
    warm = hot.copy()
    warm[30:90, 60:80] = 30215   # 8 K warmer
    answerer = LookAnswerer()
    answerer.ask(_person_request(5))
    msg, mask, _ = step(thermal_seg, Frame(0, 5, warm), cam="cam1", seq=0, answerer=answerer)
    assert msg.depth == b"" and msg.looks == []
    assert np.count_nonzero(mask[15:45, 30:40]) >= 296


def test_segmenter_for_names_a_bad_modality_and_keeps_colour_settings_to_colour():
    assert isinstance(segmenter_for("infrared", detect_shadows=False), ForegroundSegmenter)
    assert segmenter_for("thermal", var_threshold=9.0, mask_scale=0.5).mask_scale == 0.5
    with pytest.raises(ValueError, match="modality"):
        segmenter_for("sonar")
    with pytest.raises(ValueError, match="modality"):
        WorkerSettings(cam="cam1", prefix="voxelwatch/x", source="0", modality="sonar")


def _person_request(stamp_ns: int, track: int = 3, cam: str = "cam1") -> LookRequest:
    # head, torso and legs bands over the person drawn at rows 30..90, columns 60..80
    return LookRequest(cam=cam, stamp_ns=stamp_ns, ttl_ms=500, people=[PersonRegion(
        track=track, depth_m=2.0, boxes=[(60, 30, 80, 40), (60, 40, 80, 65), (60, 65, 80, 90)])])


def test_step_answers_a_pending_look_request_once_and_only_in_time():
    seg, person = _learnt_room_with_person()
    answerer = LookAnswerer()
    msg, _, _ = step(seg, Frame(4, 99, person), cam="cam1", seq=4, answerer=answerer)
    assert msg.looks == [] and not answerer.pending                     # nothing asked: nothing sent
    answerer.ask(_person_request(stamp_ns=0))
    msg, _, _ = step(seg, Frame(5, 100_000_000, person), cam="cam1", seq=5, answerer=answerer)
    (look,) = msg.looks
    assert look.track == 3 and all(p > 0 for p in look.pixels) and look.visible == [1.0, 1.0, 1.0]
    assert len(look.hist) == 3 * appearance.N_BINS
    torso = np.frombuffer(look.hist, np.uint8)[appearance.N_BINS:2 * appearance.N_BINS]
    green = appearance.colour_bins(np.array([[30, 200, 40]], np.uint8))[0]
    assert torso[green] >= 250                                          # the shirt's colour, nothing else
    back = messages.decode(messages.encode(msg), MaskFrame)
    assert back.looks == msg.looks
    assert looks_bytes(msg.looks) == len(messages.encode(msg)) - len(messages.encode(msg.model_copy(update={"looks": []}))) + 1
    msg, _, _ = step(seg, Frame(6, 200_000_000, person), cam="cam1", seq=6, answerer=answerer)
    assert msg.looks == [] and answerer.answered == 1                   # answered once
    answerer.ask(_person_request(stamp_ns=0))
    msg, _, _ = step(seg, Frame(7, 600_000_001, person), cam="cam1", seq=7, answerer=answerer)
    assert msg.looks == [] and answerer.expired == 1 and not answerer.pending  # older than its ttl


def test_worker_settings_name_bad_values():
    with pytest.raises(ValueError, match="camera id"):
        WorkerSettings(cam="a/b", prefix="voxelwatch/x", source="0")
    with pytest.raises(ValueError, match="codec"):
        WorkerSettings(cam="c", prefix="voxelwatch/x", source="0", codec="gif")
    with pytest.raises(ValueError, match="max_frames"):
        WorkerSettings(cam="c", prefix="voxelwatch/x", source="0", max_frames=0)
    with pytest.raises(ValueError, match="look_queue"):
        WorkerSettings(cam="c", prefix="voxelwatch/x", source="0", look_queue=0)


def test_measure_worker_reports_every_stage():
    result = measure_worker(n_frames=20, width=W, height=H)
    assert result["frames"] == 15 and (result["width"], result["height"]) == (W, H)
    assert set(result["ms"]) == {"read", "segment", "looks", "view", "encode", "publish", "total"}
    assert all(v > 0 for v in result["ms"].values())
    assert result["fps"]["total"] == pytest.approx(1e3 / result["ms"]["total"])
    assert 0 < result["mask_bytes_median"] <= result["message_bytes_median"]
    assert result["fg_fraction_median"] > 0
    assert result["look_bytes_per_person"] == 0


def test_measure_worker_answers_a_look_request_per_frame():
    quiet = measure_worker(n_frames=20, width=W, height=H, n_people=3)
    asked = measure_worker(n_frames=20, width=W, height=H, n_people=3, looks=True)
    assert asked["people"] == 3 and asked["looks"] is True
    assert asked["ms"]["looks"] > 10 * quiet["ms"]["looks"]     # describing costs; an idle check does not
    assert 100 < asked["look_bytes_per_person"] < 200
    assert asked["message_bytes_median"] > quiet["message_bytes_median"] + 3 * 100


# --- real processes on loopback ------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _write_clips(folder: Path, n: int = 60) -> None:
    """``bg.avi``: 15 frames of an empty textured room; ``clip.avi``: ``n`` frames, a walker from frame 20."""
    rng = np.random.default_rng(3)
    base = cv2.resize(rng.normal(0, 1, (H // 8, W // 8, 3)).astype(np.float32), (W, H))
    room = np.clip(120 + 60 * base, 0, 255).astype(np.uint8)
    for name, frames in (("bg.avi", 15), ("clip.avi", n)):
        writer = cv2.VideoWriter(str(folder / name), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
        for i in range(frames):
            img = room.copy()
            if name == "clip.avi" and i >= BOX_FROM:
                x = _box_x(i)
                img[30:100, x:x + 24] = (40, 40, 200)
            writer.write(img)
        writer.release()


def _write_site(folder: Path) -> Path:
    site = folder / "site.toml"
    site.write_text(
        'name = "worker-test"\n'
        "[zenoh]\nmulticast_scouting = false\nshared_memory = false\n"
        '[[cameras]]\nid = "cam1"\ncalibration = "none.toml"\n'
        f"resolution = [{W}, {H}]\nfps = {FPS}\n"
        'source = "clip.avi"\nbackground = "bg.avi"\n'
    )
    return site


class Listener:
    """A plain zenoh peer that collects masks and liveliness changes of ``voxelwatch/worker-test``."""

    prefix = "voxelwatch/worker-test"

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        self.session = zenoh.open(zenoh_config(mode="peer", listen=[self.endpoint]))
        self.lock = threading.Lock()
        self.payloads: list[bytes] = []
        self.stops: list[int] = []  # masks heard before each stop notice
        self.alive: list[tuple[str, str]] = []
        self.sub = self.session.declare_subscriber(keys.mask_key(self.prefix, "cam1"), self._on_mask)
        self.live = self.session.liveliness().declare_subscriber(
            keys.alive_cameras_wildcard(self.prefix), self._on_alive, history=True)
        self.hold_pub = self.session.declare_publisher(keys.hold_key(self.prefix, "cam1"))
        self.look_pub = self.session.declare_publisher(keys.look_key(self.prefix, "cam1"))

    def _on_mask(self, sample) -> None:
        with self.lock:
            if sample.kind == zenoh.SampleKind.DELETE:  # the worker's notice that it stops on purpose
                self.stops.append(len(self.payloads))
            else:
                self.payloads.append(sample.payload.to_bytes())

    def _on_alive(self, sample) -> None:
        with self.lock:
            self.alive.append((str(sample.kind), str(sample.key_expr)))

    def masks(self) -> list[MaskFrame]:
        with self.lock:
            payloads = list(self.payloads)
        return [messages.decode(p, MaskFrame) for p in payloads]

    def count(self) -> int:
        with self.lock:
            return len(self.payloads)

    def close(self) -> None:
        self.sub.undeclare()
        self.live.undeclare()
        self.hold_pub.undeclare()
        self.look_pub.undeclare()
        self.session.close()


@pytest.fixture
def listener():
    lst = Listener()
    yield lst
    lst.close()


def _start(site: Path, listener: Listener, *extra: str) -> subprocess.Popen:
    cmd = [str(CAMERA), "--site", str(site), "--camera", "cam1", "--connect", listener.endpoint,
           "--listen", f"tcp/127.0.0.1:{_free_port()}", "--stats-period", "60", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _wait(cond, timeout_s: float = 20.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


def _check_masks(masks: list[MaskFrame], start_ns: int | None, period_ns: int) -> None:
    seqs = [m.seq for m in masks]
    assert all(a < b for a, b in zip(seqs, seqs[1:])), seqs
    for m in masks:
        assert (m.cam, m.width, m.height, m.src_width, m.src_height) == ("cam1", W, H, W, H)
        mask = maskcodec.decode_mask(m.data, m.codec, m.width, m.height)
        assert mask.shape == (H, W)
        assert m.fg_fraction == pytest.approx(np.count_nonzero(mask) / mask.size)
        if start_ns is not None:
            assert m.stamp_ns == start_ns + m.seq * period_ns


def test_worker_process_publishes_decodable_masks_in_order(tmp_path, listener):
    """A recorded clip played at its own rate from a given start stamp: every mask decodes, seq
    increases, stamps are start + seq / fps, the walker is in the masks; holds over zenoh are taken (a broken one is
    counted and dropped); look requests are answered in the masks' ``looks`` with the walker's colours (a broken
    one and one for another camera are refused, counted, and each fault logged once with the key); the process exits 0 at the
    end of the clip and its liveliness goes."""
    _write_clips(tmp_path)
    site = _write_site(tmp_path)
    start_ns = time.time_ns() + 1_000_000_000     # a shared start: frames go out at their stamps
    proc = _start(site, listener, "--start-ns", str(start_ns))
    try:
        assert _wait(lambda: listener.count() >= BOX_FROM + 5), proc.stderr.read() if proc.poll() is not None else ""
        for k in range(5):     # a few times, in case the worker's subscription is still on its way
            hold = HoldRegions(cam="cam1", stamp_ns=start_ns + k, boxes=[(0, 0, 8, 8)], ttl_ms=200)
            listener.hold_pub.put(messages.encode(hold))
            listener.hold_pub.put(b"\x92broken")
            # the walker's bands along its whole path (rows 30..100)
            look = LookRequest(cam="cam1", stamp_ns=time.time_ns(), people=[PersonRegion(
                track=7, depth_m=3.0, boxes=[(0, 30, W, 45), (0, 45, W, 70), (0, 70, W, 100)])])
            listener.look_pub.put(messages.encode(look))
            listener.look_pub.put(messages.encode(look.model_copy(update={"cam": "cam2"})))
            listener.look_pub.put(b"\x93broken")
            time.sleep(0.05)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    masks = listener.masks()
    assert len(masks) >= 45, len(masks)                  # 60 frames; DROP may lose a few
    _check_masks(masks, start_ns, int(1e9 / FPS))
    late = [m for m in masks if m.seq >= BOX_FROM + 5]
    for m in late:
        mask = maskcodec.decode_mask(m.data, m.codec, m.width, m.height)
        x = _box_x(m.seq)
        assert np.count_nonzero(mask[30:100, x:x + 24]) >= 0.9 * 70 * 24
        assert m.fg_fraction <= 1.3 * 70 * 24 / (W * H)
    counted = re.search(r"stopped: .*holds (\d+) \(rejected (\d+)\)", err)
    assert counted and int(counted.group(1)) >= 1 and int(counted.group(2)) >= 1, err
    answered = [m for m in masks if m.looks]
    assert answered and all(len(m.looks) == 1 and m.looks[0].track == 7 for m in answered)
    red = appearance.colour_bins(np.array([[40, 40, 200]], np.uint8))[0]
    for m in answered:
        torso = np.frombuffer(m.looks[0].hist, np.uint8)[appearance.N_BINS:2 * appearance.N_BINS]
        assert m.looks[0].pixels[1] > 0 and torso[red] >= 200, m.looks[0]  # the walker's colour (MJPG shifts a few)
    looks = re.search(r"stopped: .*looks answered (\d+) \(expired (\d+), rejected (\d+)\)", err)
    assert looks and int(looks.group(1)) >= len(answered) and int(looks.group(3)) >= 2, err
    look_key = keys.look_key(Listener.prefix, "cam1")
    assert f"look request on {look_key} dropped" in err and "camera 'cam2'" in err and "Traceback" not in err, err
    assert "learned the background from 15 frames" in err
    alive_key = keys.alive_camera_key(Listener.prefix, "cam1")
    assert _wait(lambda: ("SampleKind.DELETE", alive_key) in listener.alive, 5.0), listener.alive
    assert listener.alive[0] == ("SampleKind.PUT", alive_key)


def test_a_worker_given_a_start_file_is_ready_first_and_starts_at_the_stamp_written_there(tmp_path, listener):
    """Started with ``--start-file`` and no file there, the worker learns the background, puts out
    its liveliness token and publishes nothing; once the file holds a stamp, its frame 0 carries
    that stamp and the rest follow on the lattice, none skipped."""
    from common import sharedstart

    _write_clips(tmp_path)
    site = _write_site(tmp_path)
    start_file = tmp_path / "start_ns"
    proc = _start(site, listener, "--start-file", str(start_file))
    try:
        alive_key = keys.alive_camera_key(Listener.prefix, "cam1")
        assert _wait(lambda: ("SampleKind.PUT", alive_key) in listener.alive), \
            proc.stderr.read() if proc.poll() is not None else "no liveliness token"
        time.sleep(1.0)             # ready, and waiting: nothing goes out
        assert listener.count() == 0 and proc.poll() is None
        start_ns = time.time_ns() + 300_000_000
        sharedstart.write_start(start_file, start_ns)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    masks = listener.masks()
    assert [m.seq for m in masks][:1] == [0] and len(masks) >= 55, [m.seq for m in masks]
    _check_masks(masks, start_ns, int(1e9 / FPS))
    assert f"waiting for the shared start in {start_file}" in err and "skipped 0" in err, err


def test_a_start_file_that_cannot_be_read_is_named():
    """Not there yet: None (the worker waits); a folder or bytes that are not text: one message
    naming the file; a negative stamp likewise."""
    import tempfile

    from common import sharedstart

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        assert sharedstart.read_start(folder / "start_ns") is None
        with pytest.raises(ValueError, match=rf"start file {re.escape(str(folder))}: cannot be read"):
            sharedstart.read_start(folder)
        (folder / "bytes").write_bytes(b"\xff\xfe1")
        with pytest.raises(ValueError, match="start file .*bytes: cannot be read"):
            sharedstart.read_start(folder / "bytes")
        sharedstart.write_start(folder / "start_ns", 5)
        assert sharedstart.read_start(folder / "start_ns") == 5 and not list(folder.glob(".*tmp"))
        (folder / "start_ns").write_text("-3\n")
        with pytest.raises(ValueError, match="must not be negative"):
            sharedstart.read_start(folder / "start_ns")


def test_a_broken_start_file_stops_the_worker_naming_the_file(tmp_path, listener):
    _write_clips(tmp_path)
    site = _write_site(tmp_path)
    start_file = tmp_path / "start_ns"
    start_file.write_text("soon\n")
    proc = _start(site, listener, "--start-file", str(start_file))
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    assert f"start file {start_file}: expected one integer" in err and "Traceback" not in err, err
    assert listener.count() == 0


def test_worker_process_sends_how_far_its_view_moved(tmp_path, listener):
    """The room's picture slides 6 px sideways at frame 50 of 150 (the camera panned): masks before
    say the view has not moved, masks from a second after the pan on say 6 px."""
    rng = np.random.default_rng(5)
    room = np.clip(120 + 60 * cv2.resize(rng.normal(0, 1, (H // 8, W // 8 + 5, 3)).astype(np.float32),
                                          (W + 40, H)), 0, 255).astype(np.uint8)
    turn, shift = 50, 6
    for name, frames in (("bg.avi", 15), ("clip.avi", 150)):
        writer = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
        for i in range(frames):
            x = 20 + (shift if name == "clip.avi" and i >= turn else 0)
            writer.write(np.ascontiguousarray(room[:, x:x + W]))
        writer.release()
    site = _write_site(tmp_path)
    proc = _start(site, listener, "--start-ns", str(time.time_ns() + 500_000_000))
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    masks = listener.masks()
    before = [m.view_shift_px for m in masks if m.seq < turn and m.view_shift_px is not None]
    after = [m.view_shift_px for m in masks if m.seq >= turn + FPS]
    assert before and max(before) < 0.5, before
    assert after and all(v == pytest.approx(shift, abs=1.0) for v in after), after
    assert "took the reference view of the room" in err


def test_worker_process_stops_cleanly_on_sigterm_while_looping(tmp_path, listener):
    _write_clips(tmp_path, n=30)
    site = _write_site(tmp_path)
    proc = _start(site, listener, "--loop", "--fast", "--no-background")
    try:
        assert _wait(lambda: listener.count() >= 80)       # more than the clip: it loops
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "SIGTERM received, stopping" in err
    masks = listener.masks()
    _check_masks(masks, None, 0)
    assert masks[-1].seq >= 80
    stamps = [m.stamp_ns for m in masks]
    assert all(a < b for a, b in zip(stamps, stamps[1:]))
    assert _wait(lambda: listener.stops) and listener.stops == [len(masks)]  # one stop notice, after the last mask


def test_worker_process_reads_a_live_stream(tmp_path, listener):
    from test_sources import MjpegServer

    server = MjpegServer()
    site = _write_site(tmp_path)
    before = time.time_ns()
    proc = _start(site, listener, "--source", server.url, "--no-background", "--min-area-px", "1")
    try:
        assert _wait(lambda: listener.count() >= 20), proc.stderr.read() if proc.poll() is not None else ""
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    finally:
        server.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    after = time.time_ns()
    assert proc.returncode == 0, err
    masks = listener.masks()
    seqs = [m.seq for m in masks]
    assert all(a < b for a, b in zip(seqs, seqs[1:]))
    assert all(before <= m.stamp_ns <= after for m in masks)      # capture time, host clock
    assert all((m.width, m.height, m.src_width, m.src_height) == (64, 48, 64, 48) for m in masks)
    assert "delivering frames" in err


def test_missing_source_file_is_named_and_exits_non_zero(tmp_path, listener):
    site = _write_site(tmp_path)
    proc = _start(site, listener, "--source", str(tmp_path / "absent.avi"))
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 1
    assert f"video file {tmp_path / 'absent.avi'}: not found" in err
    assert "Traceback" not in err


def test_bad_site_and_camera_exit_2_with_one_line(tmp_path):
    site = _write_site(tmp_path)
    proc = subprocess.run([str(CAMERA), "--site", str(site), "--camera", "cam7"], capture_output=True, text=True,
                          timeout=30)
    assert proc.returncode == 2
    assert "no camera 'cam7'" in proc.stderr and "Traceback" not in proc.stderr
    proc = subprocess.run([str(CAMERA), "--help"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and "--source" in proc.stdout and "rtsp://" in proc.stdout


def _play_walk(site: Path, listener: Listener) -> str:
    """Run the worker on 30 frames of the synthetic house's walk (background from the same walk),
    as fast as possible; its standard error once it has exited cleanly."""
    proc = _start(site, listener, "--source", "synthetic:walk", "--background", "synthetic:walk", "--fast",
                  "--max-frames", "30", "--start-ns", "0")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    return err


def test_worker_process_plays_the_synthetic_house(tmp_path, listener):
    """The synthetic house as source and background: masks of the walking person, as fast as possible."""
    pytest.importorskip("synth.source")
    site = _write_site(tmp_path)
    err = _play_walk(site, listener)
    masks = listener.masks()
    assert len(masks) >= 20
    assert all((m.width, m.height) == (640, 480) and m.stamp_ns == round(m.seq * 1e9 / 15.0) for m in masks)
    assert all(m.fg_fraction > 0.002 for m in masks)              # the person is in every mask
    assert "learned the background from 45 frames" in err
    assert "frames are 640x480 but the site file says 160x120" in err


@pytest.mark.slow  # the range's coding and the depth segmenter are held in process by faster tests
def test_worker_process_of_a_depth_camera_sends_the_range_with_its_masks(tmp_path, listener):
    """The site's camera is a range camera: the synthetic house renders it as one, the worker
    segments it with the range segmenter and every mask with a person carries its range."""
    pytest.importorskip("synth.source")
    site = _write_site(tmp_path)
    site.write_text(site.read_text().replace('source = "clip.avi"', 'modality = "depth"\nsource = "clip.avi"'))
    _play_walk(site, listener)
    masks = listener.masks()
    assert len(masks) >= 20
    ranged = 0
    for m in masks:
        mask = maskcodec.decode_mask(m.data, m.codec, m.width, m.height)
        if m.depth:
            depth = maskcodec.decode_depth(m.depth, mask)
            assert np.all(mask[depth > 0] > 0)
            # the walker is 2-7 m from the camera (a reading at an edge may fly a little beyond)
            v = depth[depth > 0]
            assert np.percentile(v, 1) > 1500 and v.max() < 8000, (v.min(), v.max())
            ranged += 1
    assert ranged >= 20


ROOT = Path(__file__).resolve().parents[1]


def _start_module(site: Path, listener: Listener, *extra: str) -> subprocess.Popen:
    """Like :func:`_start`, but this tree's worker (``python -m``), whichever is installed."""
    cmd = [sys.executable, "-m", "camera_worker.cli", "--site", str(site), "--camera", "cam1", "--connect",
           listener.endpoint, "--listen", f"tcp/127.0.0.1:{_free_port()}", "--stats-period", "60", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


@pytest.mark.parametrize("loop", [False, True])
def test_a_worker_restarted_after_the_shared_start_joins_at_the_frame_for_now(tmp_path, listener, loop):
    """A recorded-file worker started when the shared start is already 1.2 s past (5.3 s, looping a
    2.4 s clip), as a restarted worker is, publishes the frame for now on the shared lattice instead of
    replaying the file from frame 0."""
    n = 60 if loop else 200
    _write_clips(tmp_path, n=n)
    site = _write_site(tmp_path)
    late_s = 5.3 if loop else 1.2
    start_ns = time.time_ns() - int(late_s * 1e9)
    proc = _start_module(site, listener, "--start-ns", str(start_ns), "--max-frames", "15",
                         *(["--loop"] if loop else []))
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    masks = listener.masks()
    period_ns = int(1e9 / FPS)
    assert len(masks) >= 10, err
    assert masks[0].seq >= int(late_s * FPS), [m.seq for m in masks]    # never frame 0
    _check_masks(masks, start_ns, period_ns)                              # the shared lattice
    skipped = int(re.search(r"skipped (\d+)", err).group(1))
    assert skipped >= int(late_s * FPS) and "joining it at frame" in err
    for m in masks:                                                       # the file's frame for that time
        i = m.seq % n
        if i >= BOX_FROM + 3:
            mask = maskcodec.decode_mask(m.data, m.codec, m.width, m.height)
            x = _box_x(i)
            assert np.count_nonzero(mask[30:100, x:x + 24]) >= 0.8 * 70 * 24, m.seq


def test_a_worker_whose_router_is_unreachable_says_so_once_and_stops_on_sigint(tmp_path):
    _write_clips(tmp_path)
    site = _write_site(tmp_path)
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "camera_worker.cli", "--site", str(site), "--camera", "cam1",
                             "--mode", "client", "--connect", endpoint], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        time.sleep(4.0)
        assert proc.poll() is None
        asked = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=10)
        took = time.monotonic() - asked
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and took < 2.0, (proc.returncode, took, out)
    assert out.count("cannot reach zenoh") == 1 and endpoint in out and "Traceback" not in out, out
