"""Frame sources of a camera worker: files, folders, cameras, streams, the synthetic house.

Every source yields :class:`Frame` objects: a BGR image, its index and its
``stamp_ns``. Two kinds:

* **Recorded** (video file, image folder, synthetic house): frame ``i`` is
  stamped ``start_ns + round(i * 1e9 / fps)``; :meth:`FrameSource.read`
  returns None at the end. Sources never sleep: pacing at the recording's
  rate is the caller's business (the worker's adapter).
* **Live** (camera index, device path, RTSP/HTTP/... URL): each frame is
  stamped with the host clock when it was captured (``clock()``, by default
  ``time.time_ns``). A live source that stops delivering raises
  :class:`SourceError`; :class:`LiveReader` runs one in a thread, keeps only
  the newest frame, and reopens a dropped source with exponential back-off.

Spec strings (command line, site file), see :func:`open_source`::

    /path/clip.avi            video file (anything OpenCV/FFmpeg reads)
    /path/frames/             image folder: images sorted by name (natural order)
    0, 1, ...                 camera index (V4L2 on Linux)
    /dev/video0               camera device
    rtsp://host/stream        stream URL (rtsp, rtsps, http, https, udp, tcp, rtp, srt, rtmp)
    synthetic[:scenario]      the synthetic house, this camera's view
    world:SEED                this camera's view of the randomised world of SEED

The last two are not the worker's own: another installed package provides
them through the entry-point group ``voxelwatch.sources`` (the synthetic
worlds register ``synthetic`` and ``world``, :mod:`synth.source`), so a
camera host needs nothing of the simulator. A plugin is
``factory(rest, *, cam_id, seed, start_ns, background, n_frames, fps,
modality, utc_offset_hours) -> FrameSource`` where ``rest`` is the spec after
``scheme:``; a ValueError it raises becomes a :class:`SourceError`.

Every failure is a :class:`SourceError` whose message names the source and
the problem (``video file /x/y.avi: not found``).
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

__all__ = [
    "CaptureSource",
    "Frame",
    "FrameSource",
    "IMAGE_SUFFIXES",
    "ImageFolderSource",
    "LiveReader",
    "SourceError",
    "URL_SCHEMES",
    "VideoFileSource",
    "describe_source",
    "open_source",
    "plugin_schemes",
    "recorded_stamp_ns",
]

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".pnm", ".webp"})
_DEEP_SUFFIXES = frozenset({".png", ".tif", ".tiff", ".pgm"})   # can hold 16-bit images
URL_SCHEMES = ("rtsp", "rtsps", "http", "https", "udp", "tcp", "rtp", "srt", "rtmp")
STREAM_TIMEOUT_MS = 5000
SOURCE_PLUGINS = "voxelwatch.sources"
"""Open and read time-out given to FFmpeg for stream URLs."""

_URL_RE = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://")


class SourceError(RuntimeError):
    """A source that cannot deliver frames; the message names the source and the problem."""


@dataclass(frozen=True)
class Frame:
    """One captured frame.

    ``image``: ``(H, W, 3) uint8`` BGR, or ``(H, W) uint16`` as a thermal or range camera
    records it (16-bit single-channel images of a folder, the synthetic house's
    thermal and range cameras), never converted. ``index``: 0-based position in a
    recording, or count of frames captured by a live source. ``stamp_ns``:
    capture time, nanoseconds. ``truth``: ``(H, W) uint8`` 0/255 true
    silhouette mask when the source knows it (synthetic house), else None.
    """

    index: int
    stamp_ns: int
    image: np.ndarray
    truth: np.ndarray | None = None


def recorded_stamp_ns(start_ns: int, index: int, fps: float) -> int:
    """Stamp of frame ``index`` of a recording played from ``start_ns`` at ``fps``."""
    return int(start_ns) + int(round(index * 1e9 / fps))


class FrameSource:
    """Base of all sources: ``open()``, ``read()``, ``close()``; a context manager.

    ``name`` describes the source for messages; ``live`` tells recorded from
    live; ``fps`` is the nominal frame rate (None when unknown).
    """

    name: str = "source"
    live: bool = False
    fps: float | None = None

    def open(self) -> None:
        """Open the source; raise :class:`SourceError` if it cannot deliver frames."""

    def read(self) -> Frame | None:
        """The next frame; None at the end of a recording; SourceError if the source failed."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the device or file; safe to call twice."""

    def __enter__(self) -> FrameSource:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class VideoFileSource(FrameSource):
    """A video file read through OpenCV (FFmpeg); recorded stamps.

    ``fps`` overrides the file's own rate; ``default_fps`` is used when the
    file states none (without either, such a file is refused).
    """

    live = False

    def __init__(self, path: str | Path, *, start_ns: int = 0, fps: float | None = None,
                 default_fps: float | None = None) -> None:
        self.path = Path(path)
        self.name = f"video file {self.path}"
        self.start_ns = int(start_ns)
        self._fps_override = check_fps(fps)
        self._default_fps = check_fps(default_fps)
        self.fps = self._fps_override
        self._cap: cv2.VideoCapture | None = None
        self._index = 0

    def open(self) -> None:
        if not self.path.exists():
            raise SourceError(f"{self.name}: not found")
        if not self.path.is_file():
            raise SourceError(f"{self.name}: not a regular file")
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"{self.name}: OpenCV cannot open it as a video (unknown or damaged format)")
        if self._fps_override is None:
            rate = cap.get(cv2.CAP_PROP_FPS)
            if rate and np.isfinite(rate) and 0 < rate <= 1000:
                self.fps = float(rate)
            elif self._default_fps is not None:
                self.fps = self._default_fps
            else:
                cap.release()
                raise SourceError(f"{self.name}: the file states no frame rate; give one (--fps)")
        self._cap = cap
        self._index = 0

    def read(self) -> Frame | None:
        if self._cap is None:
            raise SourceError(f"{self.name}: read before open")
        ok, image = self._cap.read()
        if not ok or image is None:
            if self._index == 0:
                raise SourceError(f"{self.name}: no frame could be decoded")
            return None
        frame = Frame(self._index, recorded_stamp_ns(self.start_ns, self._index, self.fps), _bgr(image))
        self._index += 1
        return frame

    @property
    def n_frames(self) -> int | None:
        """Frames in the file as its container states them (None when it does not)."""
        if self._cap is None:
            return None
        n = self._cap.get(cv2.CAP_PROP_FRAME_COUNT)
        return int(n) if n and np.isfinite(n) and n > 0 else None

    def seek(self, index: int) -> None:
        """Make frame ``index`` the next one read (past the end: the next read ends the file).

        Tries the container's own seek, and checks where it landed; otherwise (or
        when it cannot go back) reopens the file and skips frames without converting them."""
        if self._cap is None:
            raise SourceError(f"{self.name}: seek before open")
        index = max(0, int(index))
        if index == self._index:
            return
        if self._cap.set(cv2.CAP_PROP_POS_FRAMES, index) and int(self._cap.get(cv2.CAP_PROP_POS_FRAMES)) == index:
            self._index = index
            return
        if index < self._index:
            self._cap.release()
            self._cap = cv2.VideoCapture(str(self.path))
            self._index = 0
        while self._index < index and self._cap.grab():
            self._index += 1
        self._index = index

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class ImageFolderSource(FrameSource):
    """The images of a folder in natural name order (``f2.png`` before ``f10.png``); recorded stamps."""

    live = False

    def __init__(self, path: str | Path, *, start_ns: int = 0, fps: float = 15.0) -> None:
        self.path = Path(path)
        self.name = f"image folder {self.path}"
        self.start_ns = int(start_ns)
        self.fps = check_fps(fps) or 15.0
        self._files: list[Path] = []
        self._index = 0

    def open(self) -> None:
        if not self.path.exists():
            raise SourceError(f"{self.name}: not found")
        if not self.path.is_dir():
            raise SourceError(f"{self.name}: not a folder")
        files = [p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()]
        if not files:
            raise SourceError(f"{self.name}: holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        self._files = sorted(files, key=_natural_key)
        self._index = 0

    @property
    def n_frames(self) -> int:
        return len(self._files)

    def seek(self, index: int) -> None:
        """Make image ``index`` the next one read."""
        self._index = max(0, int(index))

    def read(self) -> Frame | None:
        if self._index >= len(self._files):
            return None
        path = self._files[self._index]
        if path.suffix.lower() in _DEEP_SUFFIXES:
            # 16-bit single-channel images (thermal, range) reach the segmenter as they are
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is not None and image.dtype == np.uint8:
                image = _bgr(image)
            elif image is not None and not (image.dtype == np.uint16 and image.ndim == 2):
                raise SourceError(f"{self.name}: image {path.name} is {image.dtype} with "
                                  f"{1 if image.ndim == 2 else image.shape[2]} channels; only 8-bit images and "
                                  "16-bit single-channel ones (thermal, range) are read")
        else:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise SourceError(f"{self.name}: cannot decode image {path.name}")
        frame = Frame(self._index, recorded_stamp_ns(self.start_ns, self._index, self.fps), image)
        self._index += 1
        return frame


class CaptureSource(FrameSource):
    """A live OpenCV capture: camera index, device path or stream URL; host-clock stamps.

    ``clock`` returns nanoseconds (``time.time_ns`` by default); the stamp is
    taken right after the frame is grabbed. Any OpenCV-readable target works,
    a video file too (then its end counts as the stream dropping).
    """

    live = True

    def __init__(self, target: int | str | Path, *, fps: float | None = None,
                 clock: Callable[[], int] = time.time_ns,
                 timeout_ms: int = STREAM_TIMEOUT_MS) -> None:
        self.target = target if isinstance(target, int) else str(target)
        self.name = describe_source(target)
        self.fps = check_fps(fps)
        self._clock = clock
        self._timeout_ms = int(timeout_ms)
        self._cap: cv2.VideoCapture | None = None
        self._index = 0

    def open(self) -> None:
        self.close()
        if isinstance(self.target, str) and _URL_RE.match(self.target):
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, self._timeout_ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, self._timeout_ms]
            cap = cv2.VideoCapture(self.target, cv2.CAP_FFMPEG, params)
        else:
            cap = cv2.VideoCapture(self.target)
        if not cap.isOpened():
            cap.release()
            what = "unplugged or busy?" if isinstance(self.target, int) or str(self.target).startswith("/dev/") \
                else "down or unreachable?"
            raise SourceError(f"{self.name}: cannot open ({what})")
        if self.fps is None:
            rate = cap.get(cv2.CAP_PROP_FPS)
            self.fps = float(rate) if rate and np.isfinite(rate) and 0 < rate <= 1000 else None
        self._cap = cap

    def read(self) -> Frame:
        if self._cap is None:
            raise SourceError(f"{self.name}: not open")
        ok = self._cap.grab()
        stamp = self._clock()
        image = self._cap.retrieve()[1] if ok else None
        if image is None:
            raise SourceError(f"{self.name}: stopped delivering frames")
        frame = Frame(self._index, int(stamp), _bgr(image))
        self._index += 1
        return frame

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def describe_source(spec: int | str | Path) -> str:
    """How messages name a source spec: ``camera 0``, ``stream rtsp://...``, ``video file /x.avi``."""
    if isinstance(spec, int):
        return f"camera {spec}"
    text = str(spec)
    if text.isdigit():
        return f"camera {int(text)}"
    if text.startswith("/dev/"):
        return f"camera {text}"
    if _URL_RE.match(text):
        return f"stream {_redact(text)}"
    if _plugin_of(text) is not None:
        return text
    path = Path(text)
    if path.is_dir():
        return f"image folder {path}"
    return f"video file {path}"


def open_source(
    spec: str | int,
    *,
    cam_id: str,
    start_ns: int | None = 0,
    fps: float | None = None,
    seed: int = 0,
    base_dir: str | Path | None = None,
    background: bool = False,
    n_frames: int | None = None,
    default_fps: float = 15.0,
    clock: Callable[[], int] = time.time_ns,
    modality: str = "colour",
    utc_offset_hours: float = 0.0,
) -> FrameSource:
    """Build (not open) the source a spec string names; see the module docstring for the forms.

    Relative paths are resolved against ``base_dir`` (the site file's folder)
    when given. ``background=True`` asks for the empty room of the synthetic
    house; other specs are the clip itself. ``fps`` overrides a recording's
    own rate; ``default_fps`` (the site's camera fps) applies to image
    folders and to files that state no rate. ``modality`` (the site camera's) makes
    the synthetic house render that kind of camera. ``start_ns=None`` stamps a
    plugin's recording from its own start (a synthetic scenario's clock in the
    site's time zone, ``utc_offset_hours``); other sources take it as 0.
    Raises SourceError for an empty or unknown spec.
    """
    if isinstance(spec, int):
        return CaptureSource(spec, fps=fps, clock=clock)
    text = str(spec).strip()
    if not text:
        raise SourceError("no source given (a path, folder, camera index, URL or 'synthetic')")
    if text.isdigit():
        return CaptureSource(int(text), fps=fps, clock=clock)
    scheme = _plugin_of(text)
    if scheme is not None:
        factory = plugin_schemes()[scheme].load()
        try:
            return factory(text.partition(":")[2], cam_id=cam_id, seed=seed, start_ns=start_ns, background=background,
                           n_frames=n_frames, fps=fps, modality=modality, utc_offset_hours=utc_offset_hours)
        except ValueError as exc:
            raise SourceError(f"{text}: {exc}") from None
    match = _URL_RE.match(text)
    if match:
        if match.group(1).lower() not in URL_SCHEMES:
            raise SourceError(f"stream {_redact(text)}: unsupported scheme {match.group(1)!r} "
                              f"(supported: {', '.join(URL_SCHEMES)})")
        return CaptureSource(text, fps=fps, clock=clock)
    if text.startswith("/dev/"):
        return CaptureSource(text, fps=fps, clock=clock)
    path = Path(text).expanduser()
    if base_dir is not None and not path.is_absolute():
        path = Path(base_dir) / path
    if path.is_dir():
        return ImageFolderSource(path, start_ns=start_ns or 0, fps=fps or default_fps)
    return VideoFileSource(path, start_ns=start_ns or 0, fps=fps, default_fps=default_fps)


class LiveReader:
    """Reads a live source on a thread into a one-slot, newest-wins buffer.

    A frame not taken before the next one arrives is dropped and counted
    (``dropped``). When the source fails, the reader closes it and reopens it
    after ``backoff_s``, doubling the wait up to ``max_backoff_s`` after each
    failed attempt; meanwhile ``state`` is ``"degraded"`` and ``last_error``
    holds the message. ``on_event(text)`` (optional) is called once per state
    change and per failed reopen, from the reader thread.
    """

    def __init__(self, source: FrameSource, *, backoff_s: float = 0.5, max_backoff_s: float = 30.0,
                 on_event: Callable[[str], None] | None = None) -> None:
        if not backoff_s > 0 or not max_backoff_s >= backoff_s:
            raise ValueError(f"need 0 < backoff_s <= max_backoff_s, got {backoff_s!r}, {max_backoff_s!r}")
        self.source = source
        self.backoff_s = float(backoff_s)
        self.max_backoff_s = float(max_backoff_s)
        self._on_event = on_event
        self._cond = threading.Condition()
        self._slot: Frame | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.read = 0
        self.dropped = 0
        self.failures = 0
        self.reconnects = 0
        self.state = "starting"
        self.last_error = ""

    def start(self, *, opened: bool = False) -> LiveReader:
        """Start the thread; ``opened=True`` when the caller already opened the source."""
        self._thread = threading.Thread(target=self._run, args=(opened,), name=f"reader {self.source.name}",
                                        daemon=True)
        self._thread.start()
        return self

    def get(self, timeout_s: float | None = None) -> Frame | None:
        """Take the newest frame, waiting up to ``timeout_s``; None if none came or the reader stopped."""
        with self._cond:
            if self._slot is None and not self._stop.is_set():
                self._cond.wait(timeout_s)
            frame, self._slot = self._slot, None
            return frame

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread and close the source."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self.state = "stopped"

    @property
    def degraded(self) -> bool:
        return self.state == "degraded"

    def __enter__(self) -> LiveReader:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- thread ---------------------------------------------------------------

    def _run(self, opened: bool) -> None:
        wait = self.backoff_s
        try:
            while not self._stop.is_set():
                if not opened:
                    try:
                        self.source.open()
                    except SourceError as exc:
                        self._fail(str(exc), f"retrying in {wait:g} s")
                        if self._stop.wait(wait):
                            break
                        wait = min(wait * 2.0, self.max_backoff_s)
                        continue
                    if self.state == "degraded":
                        self.reconnects += 1
                    opened = True
                self._set_state("ok", f"{self.source.name}: delivering frames")
                wait = self.backoff_s
                try:
                    while not self._stop.is_set():
                        frame = self.source.read()
                        if frame is None:
                            raise SourceError(f"{self.source.name}: ended")
                        self._put(frame)
                except SourceError as exc:
                    self.source.close()
                    opened = False
                    self._fail(str(exc), f"reopening in {wait:g} s")
                    if self._stop.wait(wait):
                        break
                    wait = min(wait * 2.0, self.max_backoff_s)
        finally:
            self.source.close()
            with self._cond:
                self._cond.notify_all()

    def _put(self, frame: Frame) -> None:
        with self._cond:
            if self._slot is not None:
                self.dropped += 1
            self._slot = frame
            self.read += 1
            self._cond.notify()

    def _fail(self, message: str, then: str) -> None:
        self.failures += 1
        self.last_error = message
        self.state = "degraded"
        if self._on_event is not None:
            self._on_event(f"{message}; {then}")

    def _set_state(self, state: str, message: str) -> None:
        if state != self.state:
            self.state = state
            if self._on_event is not None:
                self._on_event(message)


def check_fps(fps: float | None) -> float | None:
    if fps is None:
        return None
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not 0 < fps <= 1000 or not np.isfinite(fps):
        raise ValueError(f"fps must be a number in (0, 1000], got {fps!r}")
    return float(fps)


def plugin_schemes() -> dict:
    """The source schemes other installed packages provide: name -> entry point (group ``voxelwatch.sources``)."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=SOURCE_PLUGINS)}


def _plugin_of(text: str) -> str | None:
    """The plugin scheme ``text`` names (``scheme`` or ``scheme:rest``), or None."""
    scheme = text.partition(":")[0]
    if _URL_RE.match(text) or scheme not in plugin_schemes():
        return None
    return scheme


def _bgr(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def _natural_key(path: Path) -> list:
    return [(0, int(part), "") if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", path.name)]


def _redact(url: str) -> str:
    """A URL without its password, for messages and logs."""
    return re.sub(r"^([A-Za-z][A-Za-z0-9+.-]*://[^/@:]*):[^/@]*@", r"\1:***@", url)
