"""The moved-camera alarm on randomised worlds: false alarms of untouched cameras, time to alarm of moved ones.

``python -m evaluation.moved_suite --seeds 1000-1011 --out DIR`` takes each
world of :mod:`synth.world` at ``duration_s`` (people do more in the
same room with the same rig), knocks one camera (drawn from the seed) out of
place ``move_at_s`` into the run -- turned by 2 degrees about an axis in its
image plane, or shifted by 10 cm along the floor, alternately by seed, or not
at all with ``--move none`` -- renders every camera's masks (the world's own
mask faults included; the site keeps the old calibration), and fuses them
through the live server's own :class:`~fusion_server.node.FusionNode` as the
offline replay does, in memory (no files but the site). Each colour or
infrared camera's worker-side view check (:mod:`camera_worker.viewcheck`)
runs on its colour frames, rendered once a second through the camera as it
stands, against the empty room's picture, and reports to the node as a
worker's masks would (``--no-view``: the people's evidence alone).
It reports per world the ``camera_moved`` events, and in total:

* false alarms per hour of untouched cameras (every camera but the moved one,
  over the whole run, after the move too);
* for the moved cameras, the share alarmed within 60 s of the move and the
  time to alarm.

Seeds below 1000 are for tuning; figures are reported on 1000 and up.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

MOVES = ("rotate", "shift", "alternate", "none")
ROTATION_DEG = 2.0
SHIFT_M = 0.1


def run_moved_world(seed: int, out_dir: str | Path, *, duration_s: float = 120.0, move_at_s: float = 60.0,
                    move: str = "rotate", faults: bool = True, cache_dir: str | Path | None = None,
                    sideways: bool = False, view: bool = True) -> dict[str, Any]:
    """One world: ``move`` is 'rotate', 'shift' or 'none'; a shift goes along the floor in a direction
    drawn from the seed, or with ``sideways`` across the camera's view (a shift along its axis only
    scales people by a few per cent); ``view``: run the cameras' own view checks. Returns what
    happened (module text)."""
    from camera_worker.viewcheck import ViewCheck
    from synth.source import SyntheticCamera
    from common.site import load_site
    from synth.degrade import CameraMove
    from synth.world import _bodies_at, iter_masks, random_world, with_camera_moved, write_world_site
    from fusion_server.node import FusionNode
    from fusion_server.settings import FusionSettings
    from fusion_server.pipeline import FusionPipeline
    from fusion_server.sync import FrameSet

    if move not in ("rotate", "shift", "none"):
        raise ValueError(f"move must be rotate, shift or none, got {move!r}")
    world = random_world(seed, duration_s=duration_s)
    cams = list(world.cameras)
    rng = np.random.default_rng([seed, 41])
    moved_cam = cams[int(rng.integers(len(cams)))] if move != "none" else None
    first = int(round(move_at_s * 15.0))
    if moved_cam is not None:
        angle = float(rng.uniform(0, 2 * np.pi))
        if move == "rotate":
            change = CameraMove(first=first, rotation_deg=ROTATION_DEG, axis=(np.sin(angle), np.cos(angle), 0.0))
        else:
            if sideways:
                fwd = world.cameras[moved_cam].forward
                angle = float(np.arctan2(fwd[1], fwd[0])) + np.pi / 2
            change = CameraMove(first=first, shift_m=(SHIFT_M * np.cos(angle), SHIFT_M * np.sin(angle), 0.0))
        world = with_camera_moved(world, moved_cam, change)
    written = write_world_site(world, Path(out_dir) / world.name)
    site = load_site(written.site)
    pipeline = FusionPipeline.from_site(site, cache_dir=cache_dir)
    node = FusionNode(FusionSettings(site=site, prefix=site.prefix), pipeline)
    sc = world.scenario
    n = sc.n_frames
    bodies = [_bodies_at(sc, i) for i in range(n)]
    masks = {c: iter_masks(world, c, range(n), faults=faults, bodies=bodies) for c in cams}
    sources, checks = {}, {}
    if view:
        for c in cams:
            if world.modality(c) in ("colour", "infrared"):
                sources[c] = SyntheticCamera(sc, c, world.seed, camera=world.cameras[c], modality=world.modality(c),
                                             moved=world.faults[c].moved if c in world.faults else None)
                checks[c] = ViewCheck(reference=sources[c].background_frame(0))
    every = int(round(15.0 * checks[next(iter(checks))].params.every_s)) if checks else 0
    shifts: dict[str, list[float]] = {c: [] for c in checks}  # the turn read at each report, degrees
    alarms = []
    t0 = time.perf_counter()
    for i in range(n):
        stamp = sc.stamp_ns(i)
        payloads = {c: next(masks[c]) for c in cams}
        if every and i % every == 0:
            for c, check in checks.items():
                shift = check.observe(sources[c].frame(i)[0], payloads[c], stamp)
                if shift is not None:
                    node.pipeline.consistency.report_view(c, shift, stamp, sources[c].width)
                    shifts[c].append(node.pipeline.consistency.view_deg(c))
        fs = FrameSet(stamp_ns=stamp, payloads=payloads, stamps_ns={c: stamp for c in cams},
                      seqs={c: i for c in cams})
        node.fuse(fs, stamp, time.perf_counter())
        for _, text in node.take().events:
            if '"camera_moved"' in text:
                import json

                ev = json.loads(text)
                alarms.append({"cam": ev["details"]["camera"], "t_s": (ev["stamp_ns"] - sc.stamp_ns(0)) / 1e9,
                               **{k: v for k, v in ev["details"].items() if k != "camera"}})
    mon = pipeline.consistency
    status = {cs.cam: cs.consistency for cs in node.status(sc.stamp_ns(n - 1), time.perf_counter()).cameras}
    return {
        "seed": seed, "rig": world.rig, "cameras": len(cams), "people": len(world.cast.scripts),
        "duration_s": n / 15.0, "moved": moved_cam, "move": move, "move_at_s": first / 15.0 if moved_cam else None,
        "alarms": alarms, "fuse_s": time.perf_counter() - t0,
        "figures": {c: [status[c], mon.baseline(c)] for c in cams},
        "view_deg_max": {c: [max((v for k, v in enumerate(shifts[c]) if k * every < first), default=None),
                             max((v for k, v in enumerate(shifts[c]) if k * every >= first), default=None)]
                         for c in shifts},
    }


def summarise(results: list[dict]) -> dict[str, Any]:
    """False alarms per hour of untouched cameras; detections of moved ones (within 60 s, delays)."""
    untouched_h = sum((r["cameras"] - (1 if r["moved"] else 0)) * r["duration_s"] for r in results) / 3600.0
    false = [a for r in results for a in r["alarms"] if a["cam"] != r["moved"]]
    delays = []
    missed = 0
    for r in results:
        if not r["moved"]:
            continue
        own = [a["t_s"] - r["move_at_s"] for a in r["alarms"] if a["cam"] == r["moved"] and a["t_s"] >= r["move_at_s"]]
        if own and own[0] <= 60.0:
            delays.append(own[0])
        else:
            missed += 1
    moved = sum(1 for r in results if r["moved"])
    return {
        "worlds": len(results), "untouched_camera_hours": untouched_h, "false_alarms": len(false),
        "false_alarms_per_camera_hour": len(false) / untouched_h if untouched_h else None,
        "moved": moved, "detected_within_60s": len(delays), "missed": missed,
        "delay_s_median": statistics.median(delays) if delays else None,
        "delay_s_max": max(delays) if delays else None,
    }


def main(argv: list[str] | None = None) -> int:
    from evaluation.world_suite import parse_seeds

    p = argparse.ArgumentParser(prog="python -m evaluation.moved_suite", description=__doc__.split("\n")[0])
    p.add_argument("--seeds", required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--move", choices=MOVES, default="alternate")
    p.add_argument("--duration", type=float, default=120.0)
    p.add_argument("--move-at", type=float, default=60.0)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--no-view", action="store_true", help="leave the cameras' own view checks out")
    args = p.parse_args(argv)
    seeds = parse_seeds(args.seeds)
    kinds = {s: (("rotate", "shift")[k % 2] if args.move == "alternate" else args.move) for k, s in enumerate(seeds)}
    tasks = [dict(seed=s, out_dir=args.out, duration_s=args.duration, move_at_s=args.move_at, move=kinds[s],
                  cache_dir=args.out / "cache", view=not args.no_view) for s in seeds]
    results = []
    if args.jobs <= 1:
        for t in tasks:
            results.append(_report(run_moved_world(**t)))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            for future in as_completed([pool.submit(_run, t) for t in tasks]):
                results.append(_report(future.result()))
    results.sort(key=lambda r: r["seed"])
    total = summarise(results)
    print(f"moved-camera alarm, seeds {args.seeds}: {total}")
    if args.json is not None:
        import json

        args.json.write_text(json.dumps({"worlds": results, "total": total}, indent=1) + "\n", encoding="utf-8")
    return 0


def _run(task: dict) -> dict:
    return run_moved_world(**task)


def _report(r: dict) -> dict:
    own = [(round(a["t_s"], 1), a.get("evidence")) for a in r["alarms"] if a["cam"] == r["moved"]]
    other = [(a["cam"], round(a["t_s"], 1), a.get("evidence")) for a in r["alarms"] if a["cam"] != r["moved"]]
    print(f"  world {r['seed']}: {r['rig']}, {r['cameras']} cameras, {r['people']} people, {r['move']} "
          f"{r['moved']} at {r['move_at_s']} s: alarmed at {own}; other alarms {other}; fused in {r['fuse_s']:.0f} s",
          file=sys.stderr, flush=True)
    return r


if __name__ == "__main__":
    sys.exit(main())
