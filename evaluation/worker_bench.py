"""The camera worker's benchmark: its stages timed on one core over a synthetic clip.

:func:`measure_worker` runs the worker's own frame loop (:class:`camera_worker.worker._Loop`, timed by
stage as the worker times it: :data:`camera_worker.worker.STAGES`) with stand-in subscribers on a clip of
walking figures it writes to a temporary MJPG video; ``voxelwatch bench --sections worker`` reports it.
"""

from __future__ import annotations

import statistics
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import msgpack
import numpy as np

from camera_worker.segmentation import Box, ForegroundSegmenter
from camera_worker.sources import VideoFileSource, recorded_stamp_ns
from camera_worker.viewcheck import ViewCheck
from camera_worker.worker import STAGES, WorkerCounters, WorkerSettings, _Loop
from common import keys, maskcodec, messages
from common.messages import Appearance, HoldRegions, LookRequest, MaskFrame, PersonRegion


def measure_worker(
    *,
    n_frames: int = 300,
    width: int = 640,
    height: int = 480,
    codec: str = maskcodec.DEFAULT_CODEC,
    mask_scale: float = 1.0,
    holds: bool = False,
    looks: bool = False,
    n_people: int = 2,
    seed: int = 0,
    session: Any = None,
) -> dict[str, Any]:
    """Time the worker's stages on one core; return figures (nothing is printed).

    A synthetic clip of a room with ``n_people`` walking figures (``seed``) is
    written to a temporary MJPG video; the worker's own frame loop
    (:class:`camera_worker.worker._Loop`, as :func:`camera_worker.worker.run` runs it, unpaced)
    reads it back, so ``read`` is a real decode, after the empty room is learned (untimed).
    Before each frame the loop's subscribers hand it a hold box over the first figure when
    ``holds``, and a look request naming every figure when ``looks`` (the worst case: the
    fusion server asks about each person a few times a second, not every frame); the view is
    checked against the empty room (a registration once a second of the clip's 15 frames/s,
    so ``view`` is that cost spread over the frames); each MaskFrame is put on a zenoh
    publisher (``session``, or a private peer session with no network). The first 5 frames
    (the model and the codec warming up) are not timed. OpenCV runs with one thread for the
    measurement.

    Returns ``{"frames", "people", "looks", "width", "height", "mask_width", "mask_height",
    "ms": {stage: mean ms, "total": ...}, "fps": {stage: frames/s, "total": ...},
    "mask_bytes_median", "mask_bytes_p95", "message_bytes_median", "fg_fraction_median",
    "look_bytes_per_person"}`` (the last: encoded descriptor bytes per person answered, median
    over frames; 0 without ``looks``).
    """
    import zenoh

    from common.transport import private_config

    if n_frames < 10:
        raise ValueError(f"n_frames must be >= 10, got {n_frames!r}")
    rng = np.random.default_rng(seed)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    own_session = None
    try:
        if session is None:
            own_session = session = zenoh.open(private_config())
        prefix = "voxelwatch/bench"
        publisher = _Recording(session.declare_publisher(keys.mask_key(prefix, CAM),
                                                         congestion_control=zenoh.CongestionControl.DROP, express=True))
        segmenter = ForegroundSegmenter(window_frames=500, mask_scale=mask_scale)
        with tempfile.TemporaryDirectory(prefix="vw-bench-") as tmp:
            path = Path(tmp) / "clip.avi"
            room, figures = _write_clip(path, n_frames, width, height, n_people, rng)
            for _ in range(30):   # the empty room first, as a background clip would give it (not timed)
                segmenter.learn(np.clip(room + rng.normal(0, 2.0, room.shape), 0, 255).astype(np.uint8))
            view = ViewCheck(reference=segmenter.background_image())
            with VideoFileSource(path, fps=15.0, start_ns=0) as source:
                stamp = lambda i: recorded_stamp_ns(0, i, source.fps)  # noqa: E731 - the frame the loop reads next
                hold_sub = _PerFrame(lambda i: HoldRegions(cam=CAM, stamp_ns=stamp(i),
                                                           boxes=[figures[i][0].box(width, height)], ttl_ms=500)
                                     if holds else None)
                look_sub = _PerFrame(lambda i: LookRequest(cam=CAM, stamp_ns=stamp(i),
                                                           people=[f.region(width, height) for f in figures[i]])
                                     if looks else None)
                timed = None
                for frames in (5, n_frames - 5):   # warming up, then timed
                    settings = WorkerSettings(cam=CAM, prefix=prefix, source=str(path), paced=False, codec=codec,
                                              max_frames=frames, stats_period_s=3600.0)
                    counters = WorkerCounters()
                    loop = _Loop(settings, segmenter, source, publisher, hold_sub, look_sub, counters,
                                 threading.Event(), view=view)
                    publisher.sent.clear()
                    loop.run()
                    timed = counters
            payloads = list(publisher.sent)
        publisher.undeclare()
    finally:
        cv2.setNumThreads(threads)
        if own_session is not None:
            own_session.close()
    sent = [messages.decode(p, MaskFrame) for p in payloads]
    n = timed.timed
    ms = {s: 1e3 * timed.stage_s[s] / n for s in STAGES}
    ms["total"] = sum(ms.values())
    look_sizes = [looks_bytes(m.looks) / len(m.looks) for m in sent if m.looks]
    return {
        "frames": n,
        "people": n_people,
        "looks": looks,
        "width": width,
        "height": height,
        "mask_width": sent[-1].width,
        "mask_height": sent[-1].height,
        "ms": ms,
        "fps": {k: (1e3 / v if v > 0 else float("inf")) for k, v in ms.items()},
        "mask_bytes_median": float(statistics.median(len(m.data) for m in sent)),
        "mask_bytes_p95": float(np.percentile([len(m.data) for m in sent], 95)),
        "message_bytes_median": float(statistics.median(len(p) for p in payloads)),
        "fg_fraction_median": float(statistics.median(m.fg_fraction for m in sent)),
        "look_bytes_per_person": float(statistics.median(look_sizes)) if look_sizes else 0.0,
    }


CAM = "bench"


class _Recording:
    """The loop's publisher: puts each payload on the real one and keeps it (read after the run)."""

    def __init__(self, publisher: Any) -> None:
        self.publisher = publisher
        self.sent: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.publisher.put(payload)
        self.sent.append(payload)

    def undeclare(self) -> None:
        self.publisher.undeclare()


class _Payload(bytes):
    def to_bytes(self) -> bytes:
        return bytes(self)


@dataclass
class _Sample:
    payload: _Payload


class _PerFrame:
    """A subscriber stand-in the loop polls before each frame: the message ``make(i)`` for frame
    ``i`` (None: nothing), then nothing until the next frame."""

    def __init__(self, make: Any) -> None:
        self.make, self.frame, self.given = make, 0, False

    def try_recv(self) -> _Sample | None:
        if self.given:
            self.given = False
            self.frame += 1
            return None
        self.given = True
        msg = self.make(self.frame)
        if msg is None:
            self.given = False
            self.frame += 1
            return None
        return _Sample(_Payload(messages.encode(msg)))


def looks_bytes(looks: Sequence[Appearance]) -> int:
    """What ``looks`` add to an encoded MaskFrame, bytes (the msgpack of the list)."""
    return len(msgpack.packb([a.model_dump(mode="python") for a in looks], use_bin_type=True))


@dataclass(frozen=True)
class _Figure:
    """One walking figure of the benchmark clip: an ellipse body centred at ``(cx, top + bh / 2)``
    of ``bw`` x ``bh`` pixels, a head circle of radius ``bw / 3`` above it; ``depth_m`` orders them."""

    cx: int
    top: int
    bw: int
    bh: int
    depth_m: float
    track: int

    def box(self, width: int, height: int) -> Box:
        """The whole figure, with a margin (a hold box)."""
        return (max(self.cx - self.bw, 0), self.top - self.bw, min(self.cx + self.bw, width), self.top + self.bh + 4)

    def region(self, width: int, height: int) -> PersonRegion:
        """Head, torso and legs boxes as the fusion server would send them."""
        r = self.bw // 3
        half = self.bw // 2
        clip = lambda x0, y0, x1, y1: (max(x0, 0), max(y0, 0), min(x1, width), min(y1, height))  # noqa: E731
        head = clip(self.cx - r, self.top - self.bw // 3 - r, self.cx + r + 1, self.top)
        torso = clip(self.cx - half, self.top, self.cx + half + 1, self.top + self.bh // 2)
        legs = clip(self.cx - half, self.top + self.bh // 2, self.cx + half + 1, self.top + self.bh + 1)
        boxes = [b if b[0] < b[2] and b[1] < b[3] else (0, 0, 0, 0) for b in (head, torso, legs)]
        return PersonRegion(track=self.track, depth_m=self.depth_m, boxes=boxes)


def _write_clip(path: Path, n_frames: int, width: int, height: int, n_people: int,
                rng: np.random.Generator) -> tuple[np.ndarray, list[list[_Figure]]]:
    """A room (smooth textured walls, floor) with figures walking across.

    Returns the empty room ``(H, W, 3) uint8`` and every figure in every frame.
    """
    base = rng.normal(0, 1, (height // 8, width // 8, 3)).astype(np.float32)
    room = cv2.resize(cv2.GaussianBlur(base, (0, 0), 2), (width, height), interpolation=cv2.INTER_LINEAR)
    room = np.clip(128 + 40 * room / (np.abs(room).max() + 1e-6), 0, 255).astype(np.uint8)
    room[height * 2 // 3:] = (60, 110, 40)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write an MJPG video to {path}")
    starts = rng.uniform(0.1, 0.9, n_people) * width
    speeds = rng.uniform(0.5, 2.0, n_people) * rng.choice([-1, 1], n_people)
    colours = rng.integers(20, 235, (n_people, 3))
    figures: list[list[_Figure]] = []
    try:
        for i in range(n_frames):
            img = room.copy()
            figures.append([])
            for k in range(n_people):
                cx = int((starts[k] + speeds[k] * i) % width)
                bw, bh = width // 14, height // 3
                top = height // 3
                cv2.ellipse(img, (cx, top + bh // 2), (bw // 2, bh // 2), 0, 0, 360, colours[k].tolist(), -1)
                cv2.circle(img, (cx, top - bw // 3), bw // 3, (90, 120, 170), -1)
                figures[-1].append(_Figure(cx, top, bw, bh, depth_m=2.0 + 0.5 * k, track=k + 1))
            noise = rng.normal(0, 2.0, img.shape).astype(np.float32)
            writer.write(np.clip(img + noise, 0, 255).astype(np.uint8))
    finally:
        writer.release()
    return room, figures
