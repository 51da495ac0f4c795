"""Frame sources: recorded stamps, natural image order, spec parsing, clear failures, and a
live MJPEG stream over real HTTP on loopback that drops and comes back."""

from __future__ import annotations

import http.server
import socket
import socketserver
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from camera_worker.sources import (
    CaptureSource,
    ImageFolderSource,
    LiveReader,
    SourceError,
    VideoFileSource,
    describe_source,
    open_source,
    recorded_stamp_ns,
)
from synth.source import SyntheticSource


def write_video(path: Path, n: int, fps: float = 10.0, size=(96, 64)) -> Path:
    """An MJPG clip whose frame i is uniformly grey level 10 * i."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    assert writer.isOpened()
    for i in range(n):
        writer.write(np.full((size[1], size[0], 3), 10 * i, np.uint8))
    writer.release()
    return path


# --- recorded sources ----------------------------------------------------------------------------


def test_recorded_stamp_is_start_plus_index_over_fps():
    assert recorded_stamp_ns(1_000, 0, 25.0) == 1_000
    assert recorded_stamp_ns(1_000, 3, 25.0) == 1_000 + 120_000_000
    assert recorded_stamp_ns(0, 1, 30.0) == 33_333_333


def test_video_file_yields_every_frame_with_recorded_stamps(tmp_path):
    path = write_video(tmp_path / "clip.avi", 12, fps=10.0)
    with VideoFileSource(path, start_ns=5_000) as src:
        assert src.fps == 10.0 and not src.live
        frames = []
        while (frame := src.read()) is not None:
            frames.append(frame)
    assert [f.index for f in frames] == list(range(12))
    assert [f.stamp_ns for f in frames] == [5_000 + i * 100_000_000 for i in range(12)]
    assert frames[0].image.shape == (64, 96, 3) and frames[0].image.dtype == np.uint8
    assert abs(int(frames[7].image.mean()) - 70) <= 3      # frame order kept
    assert frames[0].truth is None


def test_video_file_and_image_folder_seek_to_any_frame(tmp_path):
    path = write_video(tmp_path / "clip.avi", 20, fps=10.0)
    with VideoFileSource(path, start_ns=5_000) as src:
        assert src.n_frames == 20
        for index in (13, 4, 19, 0):
            src.seek(index)
            frame = src.read()
            assert frame.index == index and frame.stamp_ns == 5_000 + index * 100_000_000
            assert abs(int(frame.image.mean()) - 10 * index) <= 3
        src.seek(25)
        assert src.read() is None
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(5):
        cv2.imwrite(str(folder / f"f{i}.png"), np.full((8, 8, 3), 10 * i, np.uint8))
    with ImageFolderSource(folder, fps=5.0) as src:
        src.seek(3)
        frame = src.read()
        assert frame.index == 3 and frame.stamp_ns == 600_000_000 and int(frame.image.mean()) == 30


def test_video_file_fps_override(tmp_path):
    path = write_video(tmp_path / "clip.avi", 3, fps=10.0)
    with VideoFileSource(path, fps=50.0) as src:
        src.read()
        assert src.read().stamp_ns == 20_000_000


def test_missing_and_broken_files_name_themselves(tmp_path):
    with pytest.raises(SourceError, match=r"video file .*nope\.avi: not found"):
        VideoFileSource(tmp_path / "nope.avi").open()
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"not a video" * 100)
    with pytest.raises(SourceError, match=r"video file .*junk\.avi: OpenCV cannot open it"):
        VideoFileSource(junk).open()
    with pytest.raises(SourceError, match="not a regular file"):
        VideoFileSource(tmp_path).open()


def test_image_folder_in_natural_order(tmp_path):
    for i in (1, 2, 10, 3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((8, 8, 3), i * 20, np.uint8))
    (tmp_path / "notes.txt").write_text("ignored")
    cv2.imwrite(str(tmp_path / "grey.pgm"), np.full((8, 8), 250, np.uint8))   # grey images become BGR
    with ImageFolderSource(tmp_path, start_ns=7, fps=4.0) as src:
        assert src.n_frames == 5
        frames = []
        while (frame := src.read()) is not None:
            frames.append(frame)
    assert [int(f.image[0, 0, 0]) for f in frames] == [20, 40, 60, 200, 250]   # f1 f2 f3 f10 grey
    assert [f.stamp_ns for f in frames] == [7 + i * 250_000_000 for i in range(5)]
    assert all(f.image.shape == (8, 8, 3) for f in frames)


def test_image_folder_hands_sixteen_bit_images_over_unconverted(tmp_path):
    """Thermal (centi-kelvin) and range (millimetre) frames keep every bit; an 8-bit image beside
    them still becomes BGR; a 16-bit colour image is refused by name."""
    ramp = (np.arange(12 * 16, dtype=np.uint16).reshape(12, 16) * 311 + 29415).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "000000.png"), ramp)
    cv2.imwrite(str(tmp_path / "000001.tiff"), ramp[::-1].copy())
    cv2.imwrite(str(tmp_path / "000002.png"), np.full((12, 16), 9, np.uint8))
    with ImageFolderSource(tmp_path, fps=9.0) as src:
        a, b, c = src.read(), src.read(), src.read()
    assert a.image.dtype == np.uint16 and np.array_equal(a.image, ramp)
    assert np.array_equal(b.image, ramp[::-1])
    assert c.image.shape == (12, 16, 3) and c.image.dtype == np.uint8
    (tmp_path / "000003.png").unlink(missing_ok=True)
    cv2.imwrite(str(tmp_path / "000003.png"), np.zeros((12, 16, 3), np.uint16))
    with ImageFolderSource(tmp_path, fps=9.0) as src:
        for _ in range(3):
            src.read()
        with pytest.raises(SourceError, match="000003.png.*uint16 with 3 channels"):
            src.read()


def test_image_folder_failures(tmp_path):
    with pytest.raises(SourceError, match="holds no images"):
        ImageFolderSource(tmp_path).open()
    (tmp_path / "bad.png").write_bytes(b"\x89PNG garbage")
    src = ImageFolderSource(tmp_path)
    src.open()
    with pytest.raises(SourceError, match=r"image folder .*: cannot decode image bad\.png"):
        src.read()
    with pytest.raises(SourceError, match="not found"):
        ImageFolderSource(tmp_path / "absent").open()


# --- spec strings --------------------------------------------------------------------------------


def test_open_source_dispatches_on_the_spec(tmp_path):
    write_video(tmp_path / "clip.avi", 2)
    assert isinstance(open_source("0", cam_id="c"), CaptureSource)
    assert open_source(2, cam_id="c").live
    assert isinstance(open_source("rtsp://10.0.0.5/live", cam_id="c"), CaptureSource)
    assert isinstance(open_source("/dev/video3", cam_id="c"), CaptureSource)
    assert isinstance(open_source(str(tmp_path), cam_id="c"), ImageFolderSource)
    rel = open_source("clip.avi", cam_id="c", base_dir=tmp_path)
    assert isinstance(rel, VideoFileSource) and rel.path == tmp_path / "clip.avi"
    syn = open_source("synthetic:fall", cam_id="cam2", seed=3)
    assert isinstance(syn, SyntheticSource) and syn.scenario == "fall" and syn.seed == 3 and syn.cam_id == "cam2"
    assert open_source("synthetic", cam_id="cam1").scenario is None
    folder = open_source(str(tmp_path), cam_id="c", default_fps=6.0)
    assert folder.fps == 6.0
    with pytest.raises(SourceError, match="no source given"):
        open_source("  ", cam_id="c")
    with pytest.raises(SourceError, match="unsupported scheme 'ftp'"):
        open_source("ftp://host/x", cam_id="c")


def test_describe_source_hides_stream_passwords():
    assert describe_source("rtsp://admin:secret@10.0.0.5:554/live") == "stream rtsp://admin:***@10.0.0.5:554/live"
    assert describe_source(0) == "camera 0"
    assert describe_source("/dev/video1") == "camera /dev/video1"


def test_unreachable_camera_and_stream_name_themselves():
    with pytest.raises(SourceError, match=r"camera 57: cannot open"):
        CaptureSource(57).open()
    port = _free_port()
    with pytest.raises(SourceError, match=rf"stream http://127\.0\.0\.1:{port}/x\.mjpg: cannot open"):
        CaptureSource(f"http://127.0.0.1:{port}/x.mjpg", timeout_ms=1000).open()


# --- live sources --------------------------------------------------------------------------------


class MjpegServer:
    """A real multipart-JPEG HTTP stream on loopback; frame k is uniformly grey level (5 * k) % 250."""

    def __init__(self, port: int = 0, period_s: float = 0.02) -> None:
        outer = self
        self.stopping = False

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                k = 0
                try:
                    while not outer.stopping:
                        ok, buf = cv2.imencode(".jpg", np.full((48, 64, 3), (5 * k) % 250, np.uint8))
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                         % len(buf) + buf.tobytes() + b"\r\n")
                        k += 1
                        time.sleep(period_s)
                except (BrokenPipeError, ConnectionResetError):
                    pass

            def log_message(self, *args) -> None:
                pass

        class Server(socketserver.ThreadingMixIn, http.server.HTTPServer):
            daemon_threads = True
            allow_reuse_address = True

        self.server = Server(("127.0.0.1", port), Handler)
        self.port = self.server.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}/stream.mjpg"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stopping = True
        self.server.shutdown()
        self.server.server_close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(cond, timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_stream_frames_carry_host_clock_capture_stamps():
    server = MjpegServer()
    try:
        src = CaptureSource(server.url, timeout_ms=2000)
        before = time.time_ns()
        src.open()
        frames = [src.read() for _ in range(5)]
        after = time.time_ns()
        src.close()
    finally:
        server.close()
    assert src.live
    assert [f.index for f in frames] == list(range(5))
    assert all(before <= f.stamp_ns <= after for f in frames)
    assert all(a.stamp_ns < b.stamp_ns for a, b in zip(frames, frames[1:]))
    assert frames[0].image.shape == (48, 64, 3)


def test_live_reader_keeps_the_newest_frame_and_counts_drops():
    server = MjpegServer()
    reader = LiveReader(CaptureSource(server.url, timeout_ms=2000), backoff_s=0.1)
    try:
        reader.start()
        assert _wait(lambda: reader.read >= 10)        # nobody takes frames for a while
        frame = reader.get(timeout_s=2.0)
        assert frame is not None
        assert reader.dropped >= reader.read - 2       # all but the newest were dropped ...
        assert frame.index >= reader.read - 2          # ... and the newest one is what we got
        assert reader.state == "ok"
    finally:
        reader.stop()
        server.close()
    assert reader.state == "stopped"


def test_live_reader_reopens_a_dropped_stream_with_backoff():
    server = MjpegServer()
    events: list[str] = []
    reader = LiveReader(CaptureSource(server.url, timeout_ms=1000), backoff_s=0.1, max_backoff_s=0.4,
                        on_event=events.append)
    port = server.port
    try:
        reader.start()
        assert _wait(lambda: reader.read >= 3)
        server.close()                                  # the stream goes down
        assert _wait(lambda: reader.degraded and reader.failures >= 3)
        assert "cannot open" in reader.last_error or "stopped delivering" in reader.last_error
        read_while_down = reader.read
        server = MjpegServer(port)                      # and comes back on the same address
        assert _wait(lambda: reader.state == "ok" and reader.read > read_while_down + 3)
        assert reader.reconnects >= 1
        first = reader.get(timeout_s=2.0)
        second = reader.get(timeout_s=2.0)
        assert first is not None and second is not None and second.index > first.index
    finally:
        reader.stop()
        server.close()
    assert any("retrying in 0.2 s" in e or "retrying in 0.4 s" in e for e in events)
    assert any("delivering frames" in e for e in events)


def test_live_reader_waits_for_a_source_that_is_not_there_yet(tmp_path):
    """A capture target absent at start-up: degraded and retried, then picked up when it appears."""
    path = tmp_path / "late.avi"
    reader = LiveReader(CaptureSource(path), backoff_s=0.05, max_backoff_s=0.1)
    try:
        reader.start()
        assert _wait(lambda: reader.failures >= 2)
        assert reader.degraded and "late.avi" in reader.last_error
        write_video(path, 5)
        assert _wait(lambda: reader.read >= 5)
        assert reader.reconnects >= 1
    finally:
        reader.stop()


def test_live_reader_rejects_bad_backoff():
    with pytest.raises(ValueError, match="backoff"):
        LiveReader(CaptureSource(0), backoff_s=0.0)


# --- the synthetic house ---------------------------------------------------------------------------


def test_synthetic_source_gives_frames_truth_and_the_empty_room():
    pytest.importorskip("synth.source")
    src = open_source("synthetic:walk", cam_id="cam2", seed=1, start_ns=1_000, n_frames=3)
    with src:
        assert src.fps == 15.0 and src.n_frames == 3 and not src.live
        frames = [src.read() for _ in range(3)]
        assert src.read() is None
    assert [f.stamp_ns for f in frames] == [recorded_stamp_ns(1_000, i, 15.0) for i in range(3)]
    assert frames[0].image.shape == (480, 640, 3) and frames[0].truth.shape == (480, 640)
    assert set(np.unique(frames[0].truth)) <= {0, 255}
    bg = open_source("synthetic:walk", cam_id="cam2", seed=1, background=True)
    with bg:
        assert bg.n_frames == 45                    # 3 s of empty room at 15 fps
        empty = bg.read()
    assert empty.truth is None and empty.image.shape == (480, 640, 3)


def test_synthetic_source_names_an_unknown_scenario_or_camera():
    pytest.importorskip("synth.source")
    with pytest.raises(SourceError, match="synthetic:nowhere"):
        open_source("synthetic:nowhere", cam_id="cam1").open()
    with pytest.raises(SourceError, match="cam9"):
        open_source("synthetic", cam_id="cam9").open()


@pytest.mark.parametrize("modality", [pytest.param("thermal", marks=pytest.mark.slow), "depth"])
def test_synthetic_source_serves_a_thermal_or_depth_camera_its_segmenter_reads(modality):
    """The house's cam2 as a thermal or range camera: 16-bit frames, the true masks beside them,
    and the worker's own segmenter for that modality finds the person in them."""
    from camera_worker.segmenters import segmenter_for

    seg = segmenter_for(modality, mask_scale=0.5, window_frames=500)
    with open_source("synthetic:walk", cam_id="cam2", modality=modality, background=True, n_frames=30) as bg:
        while (frame := bg.read()) is not None:
            assert frame.image.dtype == np.uint16 and frame.image.ndim == 2
            seg.learn(frame.image)
    ious = []
    with open_source("synthetic:walk", cam_id="cam2", modality=modality, n_frames=120) as src:
        while (frame := src.read()) is not None:
            mask, _ = seg.apply(frame.image)
            truth = cv2.resize(frame.truth, (mask.shape[1], mask.shape[0]), interpolation=cv2.INTER_NEAREST) > 0
            if frame.index % 10 == 0 and truth.sum() > 200:
                m = mask > 0
                ious.append((m & truth).sum() / (m | truth).sum())
    assert len(ious) >= 5 and np.mean(ious) > 0.6
