"""Offline replay: the live pipeline in one process, as fast as the machine allows.

Every camera's frames are read in lock step (frame ``i`` of every camera
forms frame set ``i``), segmented with the camera worker's own segmenter,
fused by the live server's own :class:`~fusion_server.node.FusionNode`
(which writes the tracks and events files as the live server does), and the hold
regions of still people go back to the segmenters for the next frame, as
the live server sends them over zenoh; so do its look requests, answered on
the next frame with the camera worker's own colour descriptors. Colour and
infrared cameras check their own view against the room as their workers do
(:mod:`camera_worker.viewcheck`), so a camera knocked during a recording
raises ``camera_moved`` in its replay too; against the camera's
``view_reference`` picture when the site names one that is there, else
against the room as its background model learns it.

Inputs per camera, under ``INPUT/<camera id>/``:

* ``video.*`` (or the only video file there): frames to segment;
  ``background.*`` beside it is learnt first when present;
* ``masks/``: a folder of recorded masks (one image per frame, 0 background,
  255 foreground), fused as they are; ``colour.avi`` beside it, when
  present, holds the colour frames the masks were made from (at the masks'
  size), for the people's colour descriptors;
* otherwise the folder itself as an image folder.

A camera whose site ``modality`` is ``thermal`` or ``depth`` is segmented with
the camera worker's own thermal or range segmenter: its frames are the 16-bit
images of ``thermal/`` or ``range/`` (else the folder itself, or a video), its
empty room ``background/`` when present. A depth camera's foreground range goes
to the pipeline with its mask (``depths``), as its worker would send it.

Or ``synthetic=SCENARIO``: every camera of the synthetic house rendered in
this process (the site must be the synthetic house's).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from camera_worker.looks import LookAnswerer
from camera_worker.segmentation import ForegroundSegmenter, window_frames_for
from camera_worker.segmenters import foreground_depth, segmenter_for
from camera_worker.sources import FrameSource, SourceError, open_source
from camera_worker.viewcheck import ViewCheck, load_reference
from camera_worker.viewsize import DEFAULT_MIN_AREA_PX, min_area_for_site
from common.messages import LookRequest
from common.site import Site
from fusion_server.node import FusionNode
from fusion_server.settings import FusionSettings
from fusion_server.outputs import RunOutputs
from fusion_server.pipeline import FusedFrame, FusionPipeline
from fusion_server.sync import FrameSet

SENSOR_FOLDERS = {"thermal": "thermal", "depth": "range"}
"""Where a thermal or depth camera's 16-bit frames lie under ``INPUT/<camera id>/``."""
VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".m4v", ".webm")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")
@dataclass
class ReplaySummary:
    """What a replay did; ``stage_s`` sums wall time per stage (``fuse`` includes writing the files)."""

    frames: int = 0
    events: int = 0
    track_rows: int = 0
    cameras: tuple[str, ...] = ()
    elapsed_s: float = 0.0
    stage_s: dict[str, float] = field(default_factory=lambda: {"read": 0.0, "segment": 0.0, "fuse": 0.0})

    @property
    def fps(self) -> float:
        return self.frames / self.elapsed_s if self.elapsed_s > 0 else 0.0


class _MaskFolder:
    """Recorded masks: one image per frame, sorted by name; the colour frames beside
    them when there are any."""

    def __init__(self, folder: Path, fps: float, colour: FrameSource | None = None, capture_width: int = 0) -> None:
        self.files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise SourceError(f"mask folder {folder}: no mask images ({', '.join(IMAGE_SUFFIXES)})")
        self.fps = fps
        self.index = 0
        self.colour = colour
        self.capture_width = capture_width  # the camera's full width: colour frames may be smaller
        if colour is not None:
            colour.open()

    def read_colour(self) -> tuple[np.ndarray | None, float]:
        """The colour frame of the mask last read, or None (none recorded, or ended), and
        its width over the camera's."""
        if self.colour is None:
            return None, 1.0
        frame = self.colour.read()
        if frame is None:
            return None, 1.0
        return frame.image, (frame.image.shape[1] / self.capture_width if self.capture_width else 1.0)

    def read(self) -> tuple[int, np.ndarray] | None:
        if self.index >= len(self.files):
            return None
        path = self.files[self.index]
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise SourceError(f"mask folder: cannot read {path}")
        self.index += 1
        return self.index - 1, np.where(mask > 127, 255, 0).astype(np.uint8)

    def close(self) -> None:
        if self.colour is not None:
            self.colour.close()


class _SegmentedCamera:
    """A frame source and its segmenter."""

    def __init__(self, source: FrameSource, background: FrameSource | None, *, mask_scale: float, default_fps: float,
                 modality: str = "colour", view_reference: np.ndarray | None = None,
                 min_area_px: int = DEFAULT_MIN_AREA_PX) -> None:
        self.source = source
        self.last_stamp_ns = 0
        source.open()
        fps = source.fps or default_fps
        self.segmenter = segmenter_for(modality, mask_scale=mask_scale, window_frames=window_frames_for(fps),
                                       min_area_px=min_area_px)
        # only a colour camera's frames can answer a look request
        self.colour = isinstance(self.segmenter, ForegroundSegmenter) and modality == "colour"
        # the worker's own check of its view (colour and infrared), as a live worker runs it
        self.view = ViewCheck(reference=view_reference) if isinstance(self.segmenter, ForegroundSegmenter) else None
        if background is not None:
            with background:
                while (frame := background.read()) is not None:
                    self.segmenter.learn(frame.image)

    def read_frame(self):
        return self.source.read()

    def close(self) -> None:
        self.source.close()


def replay(
    site: Site,
    out_dir: str | Path,
    *,
    input_dir: str | Path | None = None,
    synthetic: str | None = None,
    cameras: Sequence[str] | None = None,
    max_frames: int | None = None,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    background_frames: int = 45,
    progress: Callable[[int, int | None, FusedFrame], None] | None = None,
    pipeline: FusionPipeline | None = None,
    overlay_every: int | None = None,
) -> ReplaySummary:
    """Run the pipeline over recorded inputs and write ``tracks.csv`` and ``events.jsonl``.

    Exactly one of ``input_dir`` and ``synthetic`` names the input.
    overlay_every: every this many frames, write each camera's frame with its
        mask overlaid to ``OUT/overlays/<camera>-<frame>.png``.
    cameras: the subset of the site's cameras to use (default all).
    """
    if (input_dir is None) == (synthetic is None):
        raise ValueError("give exactly one of input_dir and synthetic")
    cam_ids = list(cameras) if cameras else site.camera_ids
    for cam in cam_ids:
        site.camera(cam)  # names the unknown camera
    all_cameras = site.load_cameras()
    used = {cam: all_cameras[cam] for cam in cam_ids}
    if pipeline is None:
        min_cameras = min(site.carving.min_cameras, len(used))
        pipeline = FusionPipeline.from_site(site, cameras=used, cache_dir=cache_dir, seed=seed, min_cameras=min_cameras)
        if min_cameras < site.carving.min_cameras:
            pipeline.carver.min_cameras = min_cameras
    inputs = _open_inputs(site, cam_ids, input_dir, synthetic, seed, background_frames)
    summary = ReplaySummary(cameras=tuple(cam_ids))
    holds: dict[str, list] = {}
    asked: dict[str, LookAnswerer] = {cam: LookAnswerer() for cam in inputs}
    total = _expected_frames(inputs, max_frames)
    start = time.perf_counter()
    try:
        with RunOutputs(out_dir, fresh=True) as outputs:
            node = FusionNode(FusionSettings(site=site, prefix=site.prefix), pipeline, outputs=outputs)
            while max_frames is None or summary.frames < max_frames:
                t0 = time.perf_counter()
                images: dict[str, np.ndarray] | None = {} if overlay_every else None
                depths: dict[str, np.ndarray] = {}
                views: dict[str, tuple[float, int, int]] = {}
                masks, stamp_ns, frame_index, t_segment = _next_masks(inputs, holds, images, asked, depths, views)
                if masks is None:
                    break
                t1 = time.perf_counter()
                for cam, answerer in asked.items():
                    if answerer.last:
                        node.add_looks(cam, stamp_ns, answerer.last)
                for cam, (shift, shift_ns, width) in views.items():
                    pipeline.consistency.report_view(cam, shift, shift_ns, width)
                frame_set = FrameSet(stamp_ns=stamp_ns, payloads=masks, stamps_ns={cam: stamp_ns for cam in masks},
                                     seqs={cam: frame_index for cam in masks})
                fused = node.fuse(frame_set, stamp_ns, t1, depths=depths or None)
                node.take()  # nothing is published offline
                holds = fused.holds
                for cam, people in fused.looks.items():
                    asked[cam].ask(LookRequest(cam=cam, stamp_ns=fused.stamp_ns, people=people))
                t2 = time.perf_counter()
                summary.frames += 1
                summary.track_rows += len(fused.tracks)
                summary.events += len(fused.events)
                summary.stage_s["read"] += t1 - t0 - t_segment
                summary.stage_s["segment"] += t_segment
                summary.stage_s["fuse"] += t2 - t1
                if images and summary.frames % overlay_every == 1:
                    _write_overlays(Path(out_dir) / "overlays", fused.frame, images, masks)
                if progress is not None:
                    progress(summary.frames, total, fused)
    finally:
        for item in inputs.values():
            item.close()
    summary.elapsed_s = time.perf_counter() - start
    return summary


def _open_inputs(site, cam_ids, input_dir, synthetic, seed, background_frames) -> dict:
    inputs: dict[str, object] = {}
    try:
        for cam in cam_ids:
            spec = site.camera(cam)
            if synthetic is not None:
                source = open_source(f"synthetic:{synthetic}", cam_id=cam, seed=seed, start_ns=None,
                                     utc_offset_hours=site.utc_offset_hours, modality=spec.modality)
                background = open_source(
                    f"synthetic:{synthetic}", cam_id=cam, seed=seed, background=True, n_frames=background_frames,
                    modality=spec.modality,
                )
                inputs[cam] = _SegmentedCamera(source, background, modality=spec.modality, **_segmenter_args(site, cam))
                continue
            folder = Path(input_dir) / cam
            if not folder.is_dir():
                raise SourceError(f"replay input {input_dir}: no folder for camera {cam!r} ({folder})")
            if spec.modality in SENSOR_FOLDERS:
                frames = folder / SENSOR_FOLDERS[spec.modality]
                video = None if frames.is_dir() else _find_video(folder, "video")
                source = open_source(str(video or (frames if frames.is_dir() else folder)), cam_id=cam,
                                     fps=None if video else spec.fps)
                back = folder / "background"
                back_source = open_source(str(back), cam_id=cam, fps=spec.fps) if back.is_dir() else None
                inputs[cam] = _SegmentedCamera(source, back_source, modality=spec.modality, **_segmenter_args(site, cam))
                continue
            if (folder / "masks").is_dir():
                colour = folder / "colour.avi"
                source = open_source(str(colour), cam_id=cam, fps=spec.fps) if colour.is_file() else None
                inputs[cam] = _MaskFolder(folder / "masks", spec.fps, source, site.load_camera(cam).width)
                continue
            video = _find_video(folder, "video")
            background = _find_video(folder, "background")
            source = open_source(str(video or folder), cam_id=cam, fps=None if video else spec.fps)
            back = open_source(str(background), cam_id=cam) if background else None
            inputs[cam] = _SegmentedCamera(source, back, modality=spec.modality,
                                           view_reference=_view_reference(site, spec), **_segmenter_args(site, cam))
    except BaseException:
        for item in inputs.values():
            item.close()
        raise
    return inputs


def _segmenter_args(site: Site, cam: str) -> dict:
    """The segmenter settings of a camera segmented here, its smallest blob sized as its worker sizes it
    (computed only for such cameras: a folder of masks needs none)."""
    return dict(mask_scale=site.carving.mask_scale, default_fps=site.camera(cam).fps,
                min_area_px=min_area_for_site(site, cam))


def _view_reference(site: Site, spec) -> np.ndarray | None:
    """The camera's reference picture of the room from the site (``view_reference``), when the file is
    there; ValueError when it is there but is not a picture."""
    if not spec.view_reference:
        return None
    return load_reference(site.resolve(spec.view_reference))


def _next_masks(inputs: dict, holds: dict, images: dict | None = None, asked: dict | None = None,
                depths: dict | None = None, views: dict | None = None):
    """The next frame set: (masks, stamp_ns, frame index, seconds spent segmenting),
    or (None, ...) when any camera's recording has ended. ``images`` receives
    each segmented camera's frame; ``asked`` (camera id -> LookAnswerer) has each
    camera answer its pending look request on its frame (into ``answerer.last``);
    ``depths`` receives each depth camera's foreground range (``(h, w) uint16`` mm); ``views``
    each checking camera's latest view shift ``(pixels, stamp_ns, capture width)``.
    The stamp given to the answerers is the frame's own (the set's is the median)."""
    masks: dict[str, np.ndarray] = {}
    stamps: list[int] = []
    indices: list[int] = []
    t_segment = 0.0
    for cam, item in inputs.items():
        if isinstance(item, _MaskFolder):
            got = item.read()
            if got is None:
                return None, 0, 0, t_segment
            index, mask = got
            masks[cam] = mask
            indices.append(index)
            stamps.append(int(round(index * 1e9 / item.fps)))
            if asked is not None:
                colour, scale = item.read_colour()
                asked[cam].answer(colour, mask, stamps[-1], scale=scale)
            continue
        frame = item.read_frame()
        if frame is None:
            return None, 0, 0, t_segment
        t = time.perf_counter()
        masks[cam], stats = item.segmenter.apply(frame.image, holds=holds.get(cam, ()))
        if item.view is not None and views is not None:
            shift = item.view.follow(item.segmenter, frame.image, masks[cam], stats.fg_fraction, stats.relearning,
                                     frame.stamp_ns)
            if shift is not None:
                views[cam] = (shift, frame.stamp_ns, frame.image.shape[1])
        depth = foreground_depth(item.segmenter)
        if depth is not None and depths is not None:
            depths[cam] = depth
        if asked is not None:
            asked[cam].answer(frame.image if item.colour else None, masks[cam], frame.stamp_ns)
        t_segment += time.perf_counter() - t
        if images is not None:
            images[cam] = frame.image if frame.image.dtype == np.uint8 else _view8(frame.image)
        indices.append(frame.index)
        stamps.append(frame.stamp_ns)
    return masks, int(np.median(stamps)), int(np.median(indices)), t_segment


def _write_overlays(folder: Path, frame: int, images: dict, masks: dict) -> None:
    from fusion_server.outputs import mask_overlay

    folder.mkdir(parents=True, exist_ok=True)
    for cam, image in images.items():
        mask_overlay(image, masks[cam], folder / f"{cam}-{frame:06d}.png")


def _view8(image: np.ndarray) -> np.ndarray:
    """An 8-bit view of a 16-bit thermal or range frame for the overlays (its own 1-99 % span)."""
    valid = image[image > 0]
    if valid.size == 0:
        return np.zeros(image.shape, np.uint8)
    lo, hi = (float(v) for v in np.percentile(valid, (1.0, 99.0)))
    scale = 255.0 / max(hi - lo, 1.0)
    return cv2.convertScaleAbs(image.astype(np.float32), alpha=scale, beta=-lo * scale)


def _expected_frames(inputs: dict, max_frames: int | None) -> int | None:
    counts = []
    for item in inputs.values():
        if isinstance(item, _MaskFolder):
            counts.append(len(item.files))
        else:
            n = getattr(item.source, "n_frames", None)
            if isinstance(n, int) and n > 0:
                counts.append(n)
    total = min(counts) if counts else None
    if max_frames is not None:
        total = max_frames if total is None else min(total, max_frames)
    return total


def _find_video(folder: Path, stem: str) -> Path | None:
    for suffix in VIDEO_SUFFIXES:
        path = folder / f"{stem}{suffix}"
        if path.is_file():
            return path
    if stem == "video":
        videos = [p for p in folder.iterdir()
                  if p.suffix.lower() in VIDEO_SUFFIXES and not p.stem.startswith(("background", "checkerboard"))]
        if len(videos) == 1:
            return videos[0]
    return None
