"""``voxelwatch bench``: speed and size of every stage, measured in one run on this machine.

Each section calls the ``measure_*`` function of the stage it measures (the
stages themselves stay free of clocks). Comparisons are ratios taken in the
same run; every figure carries the machine it was measured on. Single-core
figures pin this process to one core and OpenCV to one thread.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import json
import os
import platform
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from common.transport import free_port

if TYPE_CHECKING:
    from common.camera import Camera
    from common.site import Site
    from evaluation.carving_bench import Cylinder
    from fusion_server.pipeline import FusionPipeline

SECTIONS = ("codec", "worker", "render", "carving", "tracking", "pipeline", "looks", "latency")

_FPS = 15.0
"""Frame rate of the synthetic frame sets, frames per second."""
LOOK_BUDGET_B = 1024.0
"""Most descriptor bytes per person per second per camera the looks may cost on the wire."""


@dataclass(frozen=True)
class PipelineRow:
    """One configuration of the ``pipeline`` section: ``cameras`` of ``width`` x ``height``
    around a room of floor ``room_m`` (x, y metres, 2.5 m high) with ``people`` walking;
    ``target_fps``, the frame sets per second the pipeline must reach (None: no target)."""

    cameras: int
    width: int
    height: int
    room_m: tuple[float, float]
    people: int
    target_fps: float | None = None


PIPELINE_ROWS: tuple[PipelineRow, ...] = (
    PipelineRow(5, 640, 480, (8.0, 6.0), 1),
    PipelineRow(5, 640, 480, (8.0, 6.0), 4, target_fps=60.0),
    PipelineRow(5, 640, 480, (8.0, 6.0), 8),
    PipelineRow(7, 960, 540, (12.0, 36.0), 20, target_fps=20.0),
)


def machine() -> dict[str, Any]:
    """What this machine is: CPU model, cores, Python and library versions, date."""
    import cv2

    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "date": _dt.date.today().isoformat(),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "platform": platform.platform(terse=True),
    }


def run_bench(
    *,
    sections: Sequence[str] = SECTIONS,
    quick: bool = False,
    json_path: str | Path | None = None,
    stream=sys.stdout,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the chosen sections, print their tables, return (and optionally write) the figures."""
    import cv2

    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        raise ValueError(f"unknown bench sections {unknown}; sections are {list(SECTIONS)}")
    results: dict[str, Any] = {"machine": machine()}
    m = results["machine"]
    print(f"voxelwatch bench, {m['date']}, {m['cpu']}, {m['cores']} cores, Python {m['python']}, OpenCV {m['opencv']}", file=stream)
    pinned = _pin_one_core()
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for name in SECTIONS:
            if name not in sections or name == "latency":
                continue
            log(f"bench: {name} ...")
            results[name] = _SECTION_FUNCS[name](quick)
            print(_SECTION_TABLES[name](results[name]), file=stream, flush=True)
    finally:
        cv2.setNumThreads(threads)
        _unpin(pinned)
    if "latency" in sections:
        log("bench: latency over zenoh (real processes, all cores) ...")
        results["latency"] = measure_latency(seconds=8.0 if quick else 20.0)
        print(_latency_table(results["latency"]), file=stream, flush=True)
    if json_path is not None:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(results, indent=2, default=float) + "\n")
    return results


# ---------------------------------------------------------------- sections


def bench_codec(quick: bool) -> list[dict[str, Any]]:
    from common import maskcodec

    rng = np.random.default_rng(0)
    rows = []
    for people in (0, 1, 2, 4):
        masks = [maskcodec.sample_room_mask(people, rng) for _ in range(11 if quick else 31)]
        for row in maskcodec.measure_codecs(masks):
            rows.append({"people": people, **row})
    return rows


def bench_worker(quick: bool) -> list[dict[str, Any]]:
    from evaluation.worker_bench import measure_worker

    n = 100 if quick else 300
    rows = []
    for scale in (1.0, 0.5):
        rows.append({"mask_scale": scale, **measure_worker(n_frames=n, mask_scale=scale)})
    return rows


def bench_render(quick: bool) -> dict[str, Any]:
    from synth import measure_render

    frames = 10 if quick else 30
    fps = measure_render(frames=frames, cpu_time=True)
    return {"camera_frames_per_s": fps, "cameras": 5, "width": 640, "height": 480, "realtime_need": 5 * 15.0}


GRAPHCUT_BENCH_SMOOTHING = 0.1
"""The graph cut's lambda in the carving bench: large enough that the cut has work (at the
paper's 0.01 every voxel is settled before it)."""


def bench_carving(quick: bool) -> list[dict[str, Any]]:
    """Octree against dense carving, and the vote against the graph cut (lambda
    ``GRAPHCUT_BENCH_SMOOTHING``), over people, cameras and voxel size, 8 x 6 x 2.5 m."""
    import tempfile

    from fusion_server.carving import Carver
    from evaluation.carving_bench import MaskRenderer, measure_carving, random_people, room_rig

    rows = []
    configs: list[tuple[int, float, tuple[int, ...]]] = [(5, 0.05, (0, 1, 2, 4)), (8, 0.05, (2,)), (16, 0.05, (2,))]
    if not quick:
        configs.append((5, 0.025, (2,)))
    with tempfile.TemporaryDirectory() as cache:
        for n_cams, voxel_m, people_counts in configs:
            cams = room_rig(n_cameras=n_cams)
            sizes = [0.4 * voxel_m / 0.05 / (2**i) for i in range(4)] if voxel_m == 0.05 else [0.4, 0.2, 0.1, 0.05, 0.025]
            t0 = time.perf_counter()
            carver = Carver(cameras=cams, volume_min_m=(0, 0, 0), volume_max_m=(8, 6, 2.5), voxel_sizes_m=sizes, cache_dir=cache)
            build_s = time.perf_counter() - t0
            renderer = MaskRenderer(cams)
            rng = np.random.default_rng(1)
            for people in people_counts:
                sets = [renderer.render(random_people(people, rng)) for _ in range(3 if quick else 6)]
                fig = measure_carving(carver, sets, repeats=2 if quick else 3, dense=not (quick and voxel_m < 0.05),
                                      graphcut_smoothing=GRAPHCUT_BENCH_SMOOTHING)
                rows.append({"cameras": n_cams, "voxel_m": voxel_m, "people": people, "lut_build_s": build_s,
                             "graphcut_smoothing": GRAPHCUT_BENCH_SMOOTHING, **fig})
            del carver, renderer
    return rows


def bench_tracking(quick: bool) -> list[dict[str, Any]]:
    """Cost per frame of detection (the blobs and the explanation that keeps the people among
    them), association + filtering, posture and reasoning for 1, 4, 8 people, with the stages
    of a :class:`FusionPipeline` built as the pipeline builds them, in an 8 x 6 x 2.5 m room."""
    import tempfile

    from evaluation.carving_bench import MaskRenderer, room_rig
    from fusion_server.pipeline import FusionPipeline, build_carver, build_reasoner

    volume_max_m = (8.0, 6.0, 2.5)
    cams = room_rig(n_cameras=5, volume_max_m=volume_max_m)
    site = _room_site(cams, volume_max_m)
    frames = 20 if quick else 45
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        carver = build_carver(site, cams, cache_dir=cache)
        renderer = MaskRenderer({c: cam.scaled(site.carving.mask_scale) for c, cam in cams.items()})
        for people in (1, 4, 8):
            walk = _walk(people, np.random.default_rng(people), frames, volume_max_m=volume_max_m)
            mask_sets = [renderer.render(bodies) for bodies in walk]
            carves = [carver.carve(masks, _stamp_ns(f)) for f, masks in enumerate(mask_sets)]
            pipeline = FusionPipeline(carver=carver, cameras=cams, reasoner=build_reasoner(site), rng=np.random.default_rng(0))
            t = {"detect": 0.0, "track": 0.0, "posture": 0.0, "reason": 0.0}
            for f, (carve, masks) in enumerate(zip(carves, mask_sets)):
                t0 = time.perf_counter()
                blobs = pipeline.detect_people(carve, masks)
                t1 = time.perf_counter()
                estimates = pipeline.tracker.step(carve, blobs, carve.stamp_ns, hidden=pipeline.refused_blobs)
                t2 = time.perf_counter()
                readings = pipeline.update_postures(estimates, carve.stamp_ns)
                t3 = time.perf_counter()
                pipeline.reasoner.step(carve.stamp_ns, f, estimates, readings)
                t4 = time.perf_counter()
                for key, dt in zip(t, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                    t[key] += dt
            ms = {k: 1e3 * v / frames for k, v in t.items()}
            ms["total"] = sum(ms.values())
            rows.append({"people": people, "frames": frames, "tracks_at_end": len(estimates), "ms": ms})
    return rows


def bench_pipeline(quick: bool, rows: Sequence[PipelineRow] = PIPELINE_ROWS) -> list[dict[str, Any]]:
    """The whole fused path of one frame set on one core: decode its masks, then
    ``FusionPipeline.step`` (carve, detect, explain, track, posture, events), every stage
    built as the pipeline builds it from a site file that gives the room and its cameras
    and leaves every other setting at its default (:class:`common.site.Carving`)."""
    import tempfile

    from evaluation.carving_bench import MaskRenderer, room_rig
    from fusion_server.pipeline import FusionPipeline, build_carver, build_reasoner

    poses, frames = (10, 30) if quick else (16, 90)
    out = []
    with tempfile.TemporaryDirectory() as cache:
        for (n_cams, width, height, room_m), group in itertools.groupby(
            rows, key=lambda r: (r.cameras, r.width, r.height, r.room_m)
        ):
            volume_max_m = (*room_m, 2.5)
            cams = room_rig(n_cameras=n_cams, volume_max_m=volume_max_m, width=width, height=height)
            site = _room_site(cams, volume_max_m)
            carving = site.carving
            t0 = time.perf_counter()
            carver = build_carver(site, cams, cache_dir=cache)
            build_s = time.perf_counter() - t0
            renderer = MaskRenderer({c: cam.scaled(carving.mask_scale) for c, cam in cams.items()})
            for row in group:
                pipeline = FusionPipeline(
                    carver=carver, cameras=cams, reasoner=build_reasoner(site), rng=np.random.default_rng(0)
                )
                fig = measure_pipeline(
                    pipeline, renderer, people=row.people, rng=np.random.default_rng(row.people),
                    volume_max_m=volume_max_m, poses=poses, frames=frames,
                )
                met = None if row.target_fps is None else bool(fig["fps"] >= row.target_fps)
                out.append({
                    "cameras": n_cams, "width": width, "height": height, "room_m": list(room_m), "people": row.people,
                    "voxel_sizes_m": list(carving.voxel_sizes_m), "min_cameras": carving.min_cameras,
                    "min_ratio": carving.min_ratio, "mask_scale": carving.mask_scale, "lut_build_s": build_s,
                    "lut_bytes": carver.lut_nbytes, **fig, "target_fps": row.target_fps, "met": met,
                })
            del carver, renderer, pipeline
    return out


def measure_pipeline(pipeline: FusionPipeline, renderer, *, people: int, rng: np.random.Generator,
                     volume_max_m: Sequence[float], poses: int, frames: int, warmup: int = 5) -> dict[str, Any]:
    """Time decode + ``pipeline.step`` over ``frames`` frame sets after ``warmup`` untimed ones
    (``pipeline`` fresh: it keeps its tracks from one frame set to the next).

    ``people`` walk from random places at 0.5 m/s; ``renderer`` draws their true
    silhouettes at ``poses`` successive places, encoded once, and the frame sets walk
    them to and fro (rendering costs seconds a frame set, carving milliseconds).
    Returns ``frames``, mean ``ms`` per frame set of ``decode``, ``step`` and ``total``
    (and ``total_median``), ``fps`` (frame sets per second, from the mean),
    ``tracks_at_end`` (confirmed tracks after the last frame set) and ``tracks_mean``.
    """
    from common import maskcodec

    if poses < 2 or frames < 1 or warmup < 0:
        raise ValueError(f"need poses >= 2, frames >= 1, warmup >= 0; got {poses}, {frames}, {warmup}")
    codec = maskcodec.DEFAULT_CODEC
    encoded = [
        {c: (maskcodec.encode_mask(m, codec), m.shape[1], m.shape[0]) for c, m in renderer.render(bodies).items()}
        for bodies in _walk(people, rng, poses, volume_max_m=volume_max_m)
    ]
    decode_s, step_s, tracks = [], [], []
    period = 2 * (poses - 1)
    for f in range(warmup + frames):
        k = f % period
        payloads = encoded[k if k < poses else period - k]
        t0 = time.perf_counter()
        masks = {c: maskcodec.decode_mask(data, codec, w, h) for c, (data, w, h) in payloads.items()}
        t1 = time.perf_counter()
        fused = pipeline.step(masks, _stamp_ns(f), f)
        t2 = time.perf_counter()
        if f >= warmup:
            decode_s.append(t1 - t0)
            step_s.append(t2 - t1)
            tracks.append(len(fused.tracks))
    total = np.add(decode_s, step_s)
    ms = {"decode": 1e3 * float(np.mean(decode_s)), "step": 1e3 * float(np.mean(step_s)),
          "total": 1e3 * float(np.mean(total)), "total_median": 1e3 * float(np.median(total))}
    return {"frames": frames, "ms": ms, "fps": 1e3 / ms["total"], "tracks_at_end": tracks[-1],
            "tracks_mean": float(np.mean(tracks))}


def bench_looks(quick: bool, *, cameras: int = 5, width: int = 640, height: int = 480,
                room_m: tuple[float, float] = (8.0, 6.0), people: Sequence[int] | None = None,
                describe_people: int = 4) -> dict[str, Any]:
    """What appearance costs: the descriptor bytes on the wire per person per second per
    camera, at the identity keeper's default request rate, for 1, 4 and 8 people (``quick``: 1
    and 4, for 2 s instead of 10) walking in a
    room seen by ``cameras`` (the requests are the pipeline's own, answered from the rendered
    frames); and a camera worker's time to answer a request naming ``describe_people``
    people, per frame at ``width`` x ``height``."""
    import tempfile

    from evaluation.worker_bench import measure_worker
    from evaluation.carving_bench import MaskRenderer, room_rig
    from fusion_server.identity import IdentityParams
    from fusion_server.pipeline import FusionPipeline, build_carver, build_reasoner

    poses, frames = (4, 30) if quick else (16, 150)  # rendering a pose costs more than fusing it
    if people is None:
        people = (1, 4) if quick else (1, 4, 8)
    volume_max_m = (*room_m, 2.5)
    cams = room_rig(n_cameras=cameras, volume_max_m=volume_max_m, width=width, height=height)
    site = _room_site(cams, volume_max_m)
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        carver = build_carver(site, cams, cache_dir=cache)
        renderer = MaskRenderer({c: cam.scaled(site.carving.mask_scale) for c, cam in cams.items()})
        for n in people:
            pipeline = FusionPipeline(carver=carver, cameras=cams, reasoner=build_reasoner(site),
                                      rng=np.random.default_rng(0))
            fig = measure_look_budget(pipeline, renderer, people=n, rng=np.random.default_rng(n),
                                      volume_max_m=volume_max_m, poses=poses, frames=frames,
                                      capture_size=(width, height))
            rows.append({"cameras": cameras, "width": width, "height": height, "room_m": list(room_m), "people": n,
                         **fig, "budget_B": LOOK_BUDGET_B, "met": bool(fig["B_per_person_s_camera"] < LOOK_BUDGET_B)})
        del carver, renderer
    worker = measure_worker(n_frames=60 if quick else 300, width=width, height=height, n_people=describe_people,
                            looks=True)
    return {
        "rate_hz": IdentityParams().rate_hz,
        "budget": rows,
        "describe": {"people": describe_people, "width": width, "height": height, "frames": worker["frames"],
                     "ms": worker["ms"]["looks"], "ms_per_person": worker["ms"]["looks"] / describe_people,
                     "worker_total_ms": worker["ms"]["total"],
                     "look_bytes_per_person": worker["look_bytes_per_person"]},
    }


def measure_look_budget(pipeline: FusionPipeline, renderer, *, people: int, rng: np.random.Generator,
                        volume_max_m: Sequence[float], poses: int, frames: int, capture_size: tuple[int, int],
                        warmup: int = 15) -> dict[str, Any]:
    """The wire cost of the look answers over ``frames`` frame sets after ``warmup`` ones (the
    tracker confirming the people, and their first requests, which go out at once).

    ``people`` walk as in :func:`measure_pipeline` (``poses`` rendered places walked to and
    fro); each frame set, every camera answers the request the previous one made of it
    (:func:`camera_worker.looks.describe` on a frame whose foreground is one colour) and its
    MaskFrame is encoded with and without the answer. Returns ``frames``, ``seconds``,
    ``descriptors`` (answered people, all cameras), ``answers_per_person_s_camera``,
    ``B_per_descriptor`` and ``B_per_person_s_camera`` (the extra MaskFrame bytes).
    """
    import cv2

    from camera_worker.looks import describe
    from common import maskcodec, messages
    from common.messages import MaskFrame

    if poses < 2 or frames < 1 or warmup < 0:
        raise ValueError(f"need poses >= 2, frames >= 1, warmup >= 0; got {poses}, {frames}, {warmup}")
    width, height = capture_size
    codec = maskcodec.DEFAULT_CODEC
    rendered = [renderer.render(bodies) for bodies in _walk(people, rng, poses, volume_max_m=volume_max_m)]
    encoded = [{c: maskcodec.encode_mask(m, codec) for c, m in masks.items()} for masks in rendered]
    images = []
    for masks in rendered:
        per_cam = {}
        for c, m in masks.items():
            fg = cv2.resize(m, (width, height), interpolation=cv2.INTER_NEAREST) > 0
            img = np.full((height, width, 3), 128, np.uint8)
            img[fg] = (40, 60, 190)
            per_cam[c] = img
        images.append(per_cam)
    period = 2 * (poses - 1)
    asked: dict[str, list] = {}
    extra_bytes = 0
    descriptors = 0
    for f in range(warmup + frames):
        k = f % period
        k = k if k < poses else period - k
        masks = rendered[k]
        looks = {c: describe(regions, images[k][c], masks[c]) for c, regions in asked.items() if c in masks}
        if f >= warmup:
            for c, answer in looks.items():
                if not answer:
                    continue
                m = masks[c]
                plain = MaskFrame(cam=c, seq=f, stamp_ns=_stamp_ns(f), width=m.shape[1], height=m.shape[0],
                                  src_width=width, src_height=height, codec=codec, data=encoded[k][c],
                                  fg_fraction=float(np.count_nonzero(m)) / m.size)
                extra_bytes += (len(messages.encode(plain.model_copy(update={"looks": answer})))
                                - len(messages.encode(plain)))
                descriptors += len(answer)
        fused = pipeline.step(masks, _stamp_ns(f), f, looks)
        asked = fused.looks
    seconds = frames / _FPS
    n_cams = len(rendered[0])
    return {
        "frames": frames, "seconds": seconds, "descriptors": descriptors,
        "answers_per_person_s_camera": descriptors / people / seconds / n_cams,
        "B_per_descriptor": extra_bytes / descriptors if descriptors else 0.0,
        "B_per_person_s_camera": extra_bytes / people / seconds / n_cams,
    }


def measure_latency(*, seconds: float = 20.0, fps: float = 15.0, n_cameras: int = 5) -> dict[str, Any]:
    """Capture-to-track and capture-to-event latency over zenoh on loopback.

    A real ``voxelwatch-fusion`` process serves the synthetic house; this
    process publishes the five cameras' true silhouettes of the demo scenario
    as encoded masks, stamped with the host clock at the moment of capture,
    at ``fps``; a subscriber in this process notes when each track frame and
    event arrives. Latency = arrival time - capture stamp of its frame set.
    """
    import subprocess
    import tempfile
    import threading

    import zenoh

    import synth
    from common import keys, maskcodec, messages
    from common.transport import zenoh_config

    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        site = synth.default_site(tmp_path / "site")
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        scenario = synth.get_scenario("fall_forward", 0)
        cams = site.camera_ids[:n_cameras]
        n_frames = int(seconds * fps)
        sources = {c: synth.SyntheticCamera(scenario, c, 0) for c in cams}
        payloads = []  # pre-rendered so publishing costs only the encode and the put
        for i in range(min(n_frames, scenario.n_frames)):
            payloads.append({c: maskcodec.encode_mask(sources[c].frame(i)[1]) for c in cams})
        server = subprocess.Popen(
            [sys.executable, "-m", "fusion_server.cli", "--site", str(site.base_dir / "site.toml"), "--listen", endpoint,
             "--store", str(tmp_path / "events.sqlite"), "--cache-dir", str(tmp_path / "cache"), "--exit-after-idle", "3"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )
        track_lat: list[float] = []
        event_lat: list[float] = []
        sent: dict[int, int] = {}
        lock = threading.Lock()

        def on_tracks(sample) -> None:
            now = time.time_ns()
            try:
                msg = messages.decode(sample.payload.to_bytes(), messages.TrackFrame)
            except messages.WireError:
                return
            with lock:
                track_lat.append((now - msg.stamp_ns) / 1e6)

        def on_event(sample) -> None:
            now = time.time_ns()
            try:
                event = messages.decode_event(sample.payload.to_bytes())
            except messages.WireError:
                return
            if event.kind in ("camera_lost", "camera_back", "clock_skew"):
                return
            with lock:
                event_lat.append((now - event.stamp_ns) / 1e6)

        conf = zenoh_config(site.zenoh, mode="peer", listen=[], connect=[endpoint])
        try:
            with zenoh.open(conf) as session:
                _wait_for(session, keys.alive_fusion_key(site.prefix), timeout_s=120)
                subs = [
                    session.declare_subscriber(keys.tracks_key(site.prefix), on_tracks),
                    session.declare_subscriber(keys.events_wildcard(site.prefix), on_event),
                ]
                pubs = {c: session.declare_publisher(keys.mask_key(site.prefix, c)) for c in cams}
                tokens = [session.liveliness().declare_token(keys.alive_camera_key(site.prefix, c)) for c in cams]
                period_ns = int(1e9 / fps)
                t0 = time.time_ns()
                for i, frame in enumerate(payloads):
                    due = t0 + i * period_ns
                    wait = (due - time.time_ns()) / 1e9
                    if wait > 0:
                        time.sleep(wait)
                    stamp = time.time_ns()
                    for c in cams:
                        cam = site.camera(c)
                        width, height = cam.resolution or (640, 480)
                        msg = messages.MaskFrame(
                            cam=c, seq=i, stamp_ns=stamp, width=width, height=height, src_width=width, src_height=height,
                            codec=maskcodec.DEFAULT_CODEC, data=frame[c], fg_fraction=0.01,
                        )
                        pubs[c].put(messages.encode(msg))
                    sent[i] = stamp
                time.sleep(1.0)
                for token in tokens:
                    token.undeclare()
                for sub in subs:
                    sub.undeclare()
        finally:
            server.terminate()
            try:
                server.wait(timeout=20)
            except subprocess.TimeoutExpired:
                server.kill()
    return {
        "cameras": len(cams),
        "fps": fps,
        "frames_sent": len(payloads),
        "track_frames": len(track_lat),
        "track_ms": _percentiles(track_lat),
        "events": len(event_lat),
        "event_ms": _percentiles(event_lat),
    }


# ---------------------------------------------------------------- tables


def _codec_table(rows) -> str:
    lines = ["\nmask codec (640x480, zlib level 1)", "people  codec      median B  max B  enc+dec ms"]
    for r in rows:
        lines.append(f"{r['people']:>6}  {r['codec']:<9}  {r['median_bytes']:>8.0f}  {r['max_bytes']:>5.0f}  {r['median_total_ms']:>10.3f}")
    return "\n".join(lines)


def _worker_table(rows) -> str:
    lines = ["\ncamera worker, one core (frames per second per stage; 640x480 capture)"]
    stages = list(rows[0]["fps"])
    lines.append("mask scale  " + "  ".join(f"{s:>9}" for s in stages) + "  mask B (median)")
    for r in rows:
        lines.append(f"{r['mask_scale']:>10}  " + "  ".join(f"{r['fps'][s]:>9.0f}" for s in stages) + f"  {r['mask_bytes_median']:>15.0f}")
    return "\n".join(lines)


def _render_table(r) -> str:
    return (
        f"\nsynthetic house rendering, one core: {r['camera_frames_per_s']:.0f} camera-frames/s at 640x480 "
        f"(five cameras at 15 fps need {r['realtime_need']:.0f}/s; {r['camera_frames_per_s'] / r['realtime_need']:.2f}x real time per core)"
    )


def _carving_table(rows) -> str:
    lines = [
        "\nfusion carving, one core, 8 x 6 x 2.5 m (frame sets per second; dense = brute-force oracle;"
        f" cut = the octree's vote then the graph cut, lambda {rows[0].get('graphcut_smoothing', '-')})",
        "cameras  voxel cm  people  distance ms  octree ms  octree /s  dense /s  octree/dense  missed %  cut ms  cut /s  LUT MB",
    ]
    for r in rows:
        dense = r.get("dense_fps")
        ratio = f"{r['octree_fps'] / dense:>12.1f}" if dense else f"{'-':>12}"
        dense_s = f"{dense:>8.1f}" if dense else f"{'-':>8}"
        missed = f"{100 * r['missed_fraction']:>8.2f}" if dense else f"{'-':>8}"
        cut = r.get("graphcut_fps")
        cut_s = f"{1e3 * r['graphcut_s']:>6.2f}  {cut:>6.1f}" if cut else f"{'-':>6}  {'-':>6}"
        lines.append(
            f"{int(r['cameras']):>7}  {100 * r['voxel_m']:>8.1f}  {int(r['people']):>6}  {1e3 * r['distance_s']:>11.2f}  "
            f"{1e3 * r['octree_s']:>9.2f}  {r['octree_fps']:>9.1f}  {dense_s}  {ratio}  {missed}  {cut_s}  {r['lut_bytes'] / 1e6:>6.1f}"
        )
    return "\n".join(lines)


def _tracking_table(rows) -> str:
    lines = ["\ntracking and reasoning, one core (ms per frame)", "people  detect  associate+filter  posture  reason  total"]
    for r in rows:
        ms = r["ms"]
        lines.append(f"{r['people']:>6}  {ms['detect']:>6.2f}  {ms['track']:>16.2f}  {ms['posture']:>7.2f}  "
                     f"{ms['reason']:>6.2f}  {ms['total']:>5.2f}")
    return "\n".join(lines)


def _pipeline_table(rows) -> str:
    r0 = rows[0]
    voxels = "/".join(f"{100 * v:g}" for v in r0["voxel_sizes_m"])
    lines = [
        "\nfused pipeline, one core: decode masks + FusionPipeline.step (carve, detect, explain, track, posture, events)",
        f"voxels {voxels} cm, min {r0['min_cameras']} cameras, ratio {r0['min_ratio']}, mask scale {r0['mask_scale']}",
        "cameras  size      room m   people  frames  decode ms  step ms  frame sets/s  target  met  tracks",
    ]
    for r in rows:
        room = "x".join(f"{v:g}" for v in r["room_m"])
        target = f">= {r['target_fps']:g}" if r["target_fps"] is not None else "-"
        met = {None: "-", True: "yes", False: "no"}[r["met"]]
        lines.append(
            f"{r['cameras']:>7}  {r['width']}x{r['height']:<4}  {room:>6}  {r['people']:>6}  {r['frames']:>6}  "
            f"{r['ms']['decode']:>9.2f}  {r['ms']['step']:>7.2f}  {r['fps']:>12.1f}  {target:>6}  {met:>3}  "
            f"{r['tracks_at_end']:>6}"
        )
    return "\n".join(lines)


def _looks_table(r) -> str:
    rows = r["budget"]
    r0 = rows[0]
    lines = [
        f"\nappearance descriptors on the wire: {r0['cameras']} cameras {r0['width']}x{r0['height']}, "
        f"requests at {r['rate_hz']:g} Hz per person (the identity keeper's default), {r0['seconds']:.0f} s walked",
        "people  answers/person/s/camera  B/descriptor  B/person/s/camera  budget  met",
    ]
    for row in rows:
        lines.append(
            f"{row['people']:>6}  {row['answers_per_person_s_camera']:>23.2f}  {row['B_per_descriptor']:>12.1f}  "
            f"{row['B_per_person_s_camera']:>17.1f}  {row['budget_B']:>6.0f}  {'yes' if row['met'] else 'no':>3}"
        )
    d = r["describe"]
    lines.append(
        f"camera worker answering a request for {d['people']} people at {d['width']}x{d['height']}, one core: "
        f"{d['ms']:.2f} ms per frame ({d['ms_per_person']:.2f} ms a person; the whole frame {d['worker_total_ms']:.2f} ms), "
        f"{d['look_bytes_per_person']:.0f} B a person"
    )
    return "\n".join(lines)


def _latency_table(r) -> str:
    t, e = r["track_ms"], r["event_ms"]
    line = (
        f"\ncapture-to-track latency over zenoh on loopback, {r['cameras']} cameras x {r['fps']:.0f} fps: "
        f"median {t['median']:.1f} ms, p99 {t['p99']:.1f} ms over {r['track_frames']} of {r['frames_sent']} frame sets"
    )
    if r["events"]:
        line += f"\ncapture-to-event latency: median {e['median']:.1f} ms, p99 {e['p99']:.1f} ms over {r['events']} events"
    return line


_SECTION_FUNCS = {
    "codec": bench_codec, "worker": bench_worker, "render": bench_render, "carving": bench_carving, "tracking": bench_tracking,
    "pipeline": bench_pipeline, "looks": bench_looks,
}
_SECTION_TABLES = {
    "codec": _codec_table, "worker": _worker_table, "render": _render_table, "carving": _carving_table, "tracking": _tracking_table,
    "pipeline": _pipeline_table, "looks": _looks_table,
}


# ---------------------------------------------------------------- helpers


def _walk(people: int, rng: np.random.Generator, frames: int, *, volume_max_m: Sequence[float] = (8.0, 6.0, 2.5),
          speed_m_s: float = 0.5) -> list[list[Cylinder]]:
    """Per frame (15 fps) the bodies of ``people`` standing people who start at random places of the room
    from the origin to ``volume_max_m`` and walk straight in random directions at ``speed_m_s``."""
    from evaluation.carving_bench import Cylinder, random_people

    start = random_people(people, rng, volume_max_m=volume_max_m)
    heading = rng.uniform(0, 2 * np.pi, size=people)
    step_m = speed_m_s / _FPS
    return [
        [Cylinder(p.x_m + f * step_m * np.cos(h), p.y_m + f * step_m * np.sin(h), p.radius_m, p.height_m)
         for p, h in zip(start, heading)]
        for f in range(frames)
    ]


def _room_site(cameras: Mapping[str, Camera], volume_max_m: Sequence[float]) -> Site:
    """A site file of the room from the origin to ``volume_max_m`` seen by ``cameras``, every
    other setting its default (no hot spots, no doors: people come and go across the edges),
    but carved no further than the room (``margin_m`` 0: the bench's people never stand beyond
    it, and the rows name the floor they carve). Its calibration files are never read: the
    pipeline is given the cameras."""
    from common.site import CameraSpec, Site, Volume

    return Site(
        name="bench",
        volume=Volume(max_m=tuple(volume_max_m), margin_m=0.0),
        cameras=[CameraSpec(id=c, calibration=f"{c}.yaml") for c in cameras],
    )


def _stamp_ns(frame: int) -> int:
    return int(frame * 1e9 / _FPS)


def _percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"median": float("nan"), "p99": float("nan"), "max": float("nan")}
    arr = np.asarray(values)
    return {"median": float(np.median(arr)), "p99": float(np.percentile(arr, 99)), "max": float(arr.max())}


def _pin_one_core():
    if not hasattr(os, "sched_setaffinity"):
        return None
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(before)})
    return before


def _unpin(before) -> None:
    if before is not None:
        os.sched_setaffinity(0, before)


def _wait_for(session, key: str, *, timeout_s: float) -> None:
    """Wait until a liveliness token on ``key`` exists."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        replies = list(session.liveliness().get(key, timeout=1.0))
        if any(r.ok is not None for r in replies):
            return
        time.sleep(0.2)
    raise RuntimeError(f"no fusion server appeared on {key} within {timeout_s:.0f} s")


__all__ = ["LOOK_BUDGET_B", "PIPELINE_ROWS", "SECTIONS", "PipelineRow", "machine", "measure_latency",
           "measure_look_budget", "measure_pipeline", "run_bench"]
