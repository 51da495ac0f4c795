"""Write a whole synthetic scenario to a folder, and measure the renderer's speed.

Layout written by :func:`write_scenario` into ``OUT``::

    OUT/site.toml                 site file (cameras' source = <cam>/video.avi, background = <cam>/background.avi)
    OUT/calib/<cam>.toml          calibrations, voxelwatch format
    OUT/<cam>/video.avi           the scenario as seen by the camera
    OUT/<cam>/background.avi      the empty room just before (3 s)
    OUT/<cam>/masks/000000.png    true person masks (255 = person), when masks=True
    OUT/truth/tracks.csv          ground truth tracks (see synth.truth)
    OUT/truth/events.jsonl        ground truth events
    OUT/truth/meta.json           fps, n_frames, scenario, seed, start time, people

Videos: 'MJPG' (OpenCV's own Motion-JPEG writer at quality 95: ~70 KB a
frame, any OpenCV reads it) by default; 'FFV1' is lossless but ~470 KB a
frame (the sensor noise does not compress).
"""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np

from synth.scenario import Scenario
from synth.scenarios import DEFAULT_SCENARIO, get_scenario
from synth.scene import CAMERA_IDS, default_cameras, default_site
from synth.source import BACKGROUND_S, SyntheticCamera
from synth.truth import derive_truth, write_truth

CODECS = ("MJPG", "FFV1")
MJPEG_QUALITY = 95


@dataclass(frozen=True)
class HouseOutput:
    """What :func:`write_scenario` wrote (absolute paths)."""

    out_dir: Path
    site: Path
    tracks: Path
    events: Path
    meta: Path
    n_frames: int
    videos: dict[str, Path] = field(default_factory=dict)
    backgrounds: dict[str, Path] = field(default_factory=dict)
    masks: dict[str, Path] = field(default_factory=dict)


def write_scenario(
    name: str = DEFAULT_SCENARIO,
    out_dir: str | Path = "synthetic",
    *,
    seed: int = 0,
    cameras: list[str] | tuple[str, ...] | None = None,
    frames: int | None = None,
    video: bool = True,
    masks: bool = False,
    codec: str = "MJPG",
    background_s: float = BACKGROUND_S,
    workers: int = 1,
) -> HouseOutput:
    """Render scenario ``name`` for ``seed`` into ``out_dir`` (layout in the module docstring).

    cameras: camera ids to render (default all five). frames: only the first ``frames``
    frames (the truth is cut to match). video: write the videos (False: site, calibrations and
    truth only). masks: also write true masks as PNG. codec: 'MJPG' or 'FFV1'.
    workers: processes rendering cameras in parallel (spawned).
    """
    if codec not in CODECS:
        raise ValueError(f"codec must be one of {CODECS}, got {codec!r}")
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive int, got {workers!r}")
    scenario = get_scenario(name, seed)
    all_cams = default_cameras()
    cam_ids = list(CAMERA_IDS if cameras is None else cameras)
    unknown = [c for c in cam_ids if c not in all_cams]
    if unknown or not cam_ids:
        raise ValueError(f"cameras must be a non-empty subset of {list(CAMERA_IDS)}, got {cam_ids}")
    n = scenario.n_frames if frames is None else int(frames)
    if not (1 <= n <= scenario.n_frames):
        raise ValueError(f"frames must lie in 1..{scenario.n_frames} for scenario {scenario.name}, got {frames!r}")
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    default_site(
        out,
        cameras={c: all_cams[c] for c in cam_ids},
        room=scenario.room,
        sources={c: f"{c}/video.avi" for c in cam_ids} if video else None,
        backgrounds={c: f"{c}/background.avi" for c in cam_ids} if video else None,
        fps=scenario.fps,
    )
    paths = write_truth(scenario, out / "truth", derive_truth(scenario), n_frames=n)
    videos, backgrounds, mask_dirs = {}, {}, {}
    if video or masks:
        jobs = [(scenario.spec, seed, c, str(out), n, video, masks, codec, background_s) for c in cam_ids]
        if workers == 1 or len(jobs) == 1:
            results = [_render_camera(*job) for job in jobs]
        else:
            with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=get_context("spawn")) as pool:
                results = list(pool.map(_render_camera_star, jobs))
        for cam_id, res in zip(cam_ids, results):
            if "video" in res:
                videos[cam_id] = Path(res["video"])
                backgrounds[cam_id] = Path(res["background"])
            if "masks" in res:
                mask_dirs[cam_id] = Path(res["masks"])
    return HouseOutput(out_dir=out, site=out / "site.toml", tracks=paths["tracks"], events=paths["events"],
                       meta=paths["meta"], n_frames=n, videos=videos, backgrounds=backgrounds, masks=mask_dirs)


def measure_render(
    scenario: str | Scenario = DEFAULT_SCENARIO,
    *,
    cameras: list[str] | tuple[str, ...] | None = None,
    frames: int = 30,
    seed: int = 0,
    cpu_time: bool = False,
) -> float:
    """Steady-state rendering speed on this process's core: camera-frames per second.

    Renders ``frames`` frames spread evenly over the scenario for each camera (default all
    five, 640x480) and returns (frames x cameras) / seconds; the one-off per-camera
    precomputation is excluded. ``cpu_time`` divides by this process's CPU time instead of
    wall-clock time (a fairer figure on a machine shared with other work).
    """
    sc = get_scenario(scenario, seed)
    cam_ids = list(CAMERA_IDS if cameras is None else cameras)
    sources = [SyntheticCamera(sc, c, seed) for c in cam_ids]
    idx = np.linspace(0, sc.n_frames - 1, max(int(frames), 1)).round().astype(int)
    for s in sources:
        s.frame(int(idx[0]))
    clock = time.process_time if cpu_time else time.perf_counter
    t0 = clock()
    for s in sources:
        for i in idx:
            s.frame(int(i))
    dt = clock() - t0
    return len(idx) * len(sources) / dt


# ---------------------------------------------------------------------- helpers


def _render_camera_star(args):
    return _render_camera(*args)


def _render_camera(spec, seed, cam_id, out_dir, n, video, masks, codec, background_s) -> dict:
    """Render one camera's clips (runs in a worker process too)."""
    out = Path(out_dir) / cam_id
    out.mkdir(parents=True, exist_ok=True)
    source = SyntheticCamera(get_scenario(spec, seed), cam_id, seed, background_s=background_s)
    size = (source.width, source.height)
    result: dict = {}
    mask_dir = out / "masks"
    if masks:
        mask_dir.mkdir(exist_ok=True)
        result["masks"] = str(mask_dir)
    if video:
        bg_path = out / "background.avi"
        writer = open_video_writer(bg_path, codec, source.fps, size)
        try:
            for i in range(source.n_background_frames):
                writer.write(source.background_frame(i))
        finally:
            writer.release()
        result["background"] = str(bg_path)
    writer = open_video_writer(out / "video.avi", codec, source.fps, size) if video else None
    try:
        for i in range(n):
            bgr, mask = source.frame(i)
            if writer is not None:
                writer.write(bgr)
            if masks:
                cv2.imwrite(str(mask_dir / f"{i:06d}.png"), mask)
    finally:
        if writer is not None:
            writer.release()
    if video:
        result["video"] = str(out / "video.avi")
    return result


def open_video_writer(path: Path, codec: str, fps: float, size: tuple[int, int]) -> cv2.VideoWriter:
    """An OpenCV video writer for ``codec`` ('MJPG' at quality 95, or 'FFV1'); RuntimeError when it cannot open."""
    if codec == "MJPG":
        writer = cv2.VideoWriter(str(path), cv2.CAP_OPENCV_MJPEG, cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
        if writer.isOpened():
            writer.set(cv2.VIDEOWRITER_PROP_QUALITY, MJPEG_QUALITY)
    else:
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), fps, size)
    if not writer.isOpened():
        raise RuntimeError(f"video file {path}: OpenCV cannot write codec {codec} here")
    return writer
