"""The randomised-world suite: many worlds written, replayed and scored, with totals by people and rig.

``voxelwatch eval --suite --world random --seeds 1000-1049 --jobs 2`` writes
each world (:mod:`synth.world`), replays it exactly as ``voxelwatch
replay --input`` does, scores it as ``voxelwatch eval`` does, and prints:

* what the worlds hold: rooms, rigs, cameras, people, behaviours, dress, faults;
* one row per world, and a total row from summed counts;
* totals by the number of people present in a frame (tracking figures: a
  frame belongs to the band of its own truth count);
* totals by rig kind (whole worlds): high corners, level walls, with and
  without a ceiling fisheye (drawn rigs), the real rigs;
* totals by dress (whole worlds): everyone dressed alike or not.

``IDSW`` counts identity switches (CLEAR-MOT); ``re-ID`` the truth re-entries
(an exit and the person's return within 10 minutes) whose run track id after
the return is the one before it, as same/re-entries
(:mod:`evaluation.reentry`). ``fused/s`` is frame sets through the fusion pipeline (carving, detection,
tracking, posture, events) per second of that stage's wall time, in a process
that shares the machine with the suite's other jobs. The worlds' media are
deleted once scored unless ``keep_media``.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from evaluation import evaluate, suite_totals, write_json
from evaluation.report import event_cells, fmt_num, fmt_pct, identity_cell, people_table, text_table


def parse_seeds(text: str) -> list[int]:
    """'1000-1049' or '3,7,20-22' -> the seeds, in order, without repeats; ValueError naming the bad part."""
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        try:
            if "-" in part:
                lo, hi = (int(v) for v in part.split("-", 1))
                if hi < lo:
                    raise ValueError
                seeds += range(lo, hi + 1)
            else:
                seeds.append(int(part))
        except ValueError:
            raise ValueError(f"--seeds: {part!r} is not a seed or a range like 1000-1049") from None
    if not seeds or min(seeds) < 0:
        raise ValueError(f"--seeds: give non-negative seeds, got {text!r}")
    return list(dict.fromkeys(seeds))


def run_world_suite(
    *,
    seeds: Sequence[int],
    out_dir: str | Path,
    jobs: int = 1,
    frames: int | None = None,
    json_path: str | Path | None = None,
    keep_media: bool = False,
    settings: Sequence[str] = (),
    sensors: str = "colour",
    stream=sys.stdout,
) -> dict[str, Any]:
    """Write, replay and score the worlds of ``seeds``; print the tables; return the report (also as JSON
    at ``json_path``). ``frames``: only the first N frames of each world. ``settings``: ``SECTION.KEY=VALUE``
    changes to every world's site before its replay (:func:`common.site.with_settings`). ``sensors``:
    'colour' rigs, or 'mixed' (one depth and one thermal camera in each world; the same worlds
    otherwise, so the two reports compare the rigs)."""
    from synth.world import seed_set

    sets = sorted({seed_set(s) for s in seeds})
    out = Path(out_dir)
    if sensors not in ("colour", "mixed"):
        raise ValueError(f"sensors must be 'colour' or 'mixed', got {sensors!r}")
    tasks = [(int(s), str(out), frames, keep_media, tuple(settings), sensors) for s in seeds]
    results: dict[int, dict] = {}
    if jobs <= 1:
        for task in tasks:
            results[task[0]] = _report(_run_world(*task))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(_run_world, *task): task[0] for task in tasks}
            for future in as_completed(futures):
                results[futures[future]] = _report(future.result())
    ordered = [results[int(s)] for s in seeds]
    rigs = ", mixed rigs (a depth and a thermal camera in each)" if sensors == "mixed" else ""
    print(f"\nrandom worlds, {' and '.join(sets)} seeds {_seed_text(seeds)}{rigs}"
          + (f"; site settings {', '.join(settings)}" if settings else ""), file=stream)
    print(composition(ordered), file=stream)
    print("", file=stream)
    print(worlds_table(ordered), file=stream)
    total = suite_totals(r["scores"] for r in ordered)
    print("\n" + posture_line(total["posture"]), file=stream)
    print("\nby people present in the frame (tracking only; each frame in the band of its truth count):", file=stream)
    print("\n".join(people_table(total["by_people"])), file=stream)
    print("\nby rig (whole worlds):", file=stream)
    print(groups_table(ordered), file=stream)
    print("\nby dress (whole worlds; 'alike': every adult in the same clothes):", file=stream)
    print(groups_table(ordered, dress_groups(ordered)), file=stream, flush=True)
    report = {
        "seeds": list(seeds), "seed_sets": sets, "settings": list(settings), "sensors": sensors,
        "worlds": [{k: r[k] for k in ("seed", "world", "frames", "fuse_s", "replay_s", "scores")} for r in ordered],
        "total": total,
        "groups": {label: suite_totals(r["scores"] for r in rs) for label, rs in rig_groups(ordered).items()},
        "dress": {label: suite_totals(r["scores"] for r in rs) for label, rs in dress_groups(ordered).items()},
    }
    if json_path is not None:
        write_json(report, json_path)
    return report


def posture_line(p: dict) -> str:
    """Strict posture, seated frames read lying, and false lying markers, of summed posture scores."""
    labels, conf = p["labels"], p["confusion"]
    seated = conf[labels.index("sitting")]
    known = sum(seated[labels.index(k)] for k in labels if k != "unknown")
    lying = seated[labels.index("lying")]
    share = f"{100.0 * lying / known:.2f} %" if known else "-"
    return (f"posture strict {fmt_pct(p['strict_accuracy'])}; seated frames read lying {lying} of {known} ({share}); "
            f"false lying markers over 2 s: {p.get('false_lying_spells', 0)} "
            f"({fmt_num(p.get('false_lying_s', 0.0), 1)} s)")


def composition(results: Sequence[dict]) -> str:
    """What the worlds hold, in a few lines."""
    worlds = [r["world"] for r in results]
    n = len(worlds)
    rigs = Counter(w["rig_label"] + (" + fisheye" if w["fisheye"] else "") for w in worlds)
    shapes = Counter(w["room"]["shape"] for w in worlds)
    areas = sorted(w["room"]["floor_area_m2"] for w in worlds if not w["rig"].startswith("real"))
    cams = Counter(w["cameras"] for w in worlds)
    res = Counter(r for w in worlds for r in w["resolutions"])
    lenses = Counter(lens for w in worlds for lens in w["lenses"])
    people = Counter(_band(w["people_per_frame_max"]) for w in worlds)
    band_order = lambda label: int(label.split("-")[0].rstrip("+"))  # noqa: E731
    behaviours = Counter(b for w in worlds for b in w["behaviours"])
    faults = Counter(f.split()[0] for w in worlds for fs in w["faults"].values() for f in set(fs))
    media = Counter(w["media"] for w in worlds)
    dress = Counter(w.get("dress", "distinct") for w in worlds)
    stepping = [w.get("step_outs", 0) for w in worlds]
    frames = sum(r["frames"] for r in results)
    lines = [
        f"{n} worlds, {frames} frame sets ({frames / 15.0 / 60:.1f} min at 15 fps); media: {_counts(media)}",
        f"rigs: {_counts(rigs)}",
        f"cameras per world: {_counts(cams, key=int)}; lenses: {_counts(lenses)}; sizes: {_counts(res)}",
        f"rooms: {_counts(shapes)}" + (f", drawn floors {areas[0]:.0f}-{areas[-1]:.0f} m2 (median {areas[len(areas) // 2]:.0f})"
                                       if areas else ""),
        f"most people at once: {_counts(people, key=band_order)} worlds; children in "
        f"{sum(1 for w in worlds if w['children'])} worlds; mean people per frame "
        f"{sum(w['people_per_frame_mean'] * r['frames'] for w, r in zip(worlds, results)) / max(frames, 1):.2f}",
        f"behaviours (worlds with it): {_counts(behaviours)}",
        f"dress: {_counts(dress)}; people stepping out and back: {sum(stepping)} in "
        f"{sum(1 for k in stepping if k)} worlds",
        f"mask faults (worlds with a camera showing it): {_counts(faults)}",
    ]
    return "\n".join(lines)


def worlds_table(results: Sequence[dict]) -> str:
    """One row per world and a total row."""
    header = ["world", "rig", "cams", "people", "media", "frames", *_SCORE_HEADER]
    rows = []
    for r in results:
        w = r["world"]
        rig = w["rig_label"] + (" +fe" if w["fisheye"] else "")
        rows.append([str(r["seed"]), rig, w["cameras"], w["people_per_frame_max"], w["media"], r["frames"],
                     *_score_cells(r["scores"], r["frames"], r["fuse_s"])])
    total = suite_totals(r["scores"] for r in results)
    rows.append(["total", "", "", "", "", sum(r["frames"] for r in results),
                 *_score_cells(total, sum(r["frames"] for r in results), sum(r["fuse_s"] for r in results))])
    return "\n".join(text_table(header, rows, rule_before_last=True))


def rig_groups(results: Sequence[dict]) -> dict[str, list[dict]]:
    """Worlds by rig: each kind, drawn rigs with and without a fisheye, and the real rigs together
    (groups without worlds left out)."""
    from synth.world import RIG_LABELS

    order = [RIG_LABELS["high-corners"], RIG_LABELS["level-walls"], "drawn, with fisheye", "drawn, no fisheye",
             RIG_LABELS["real-lab"], RIG_LABELS["real-pets"], "real rigs"]
    groups: dict[str, list[dict]] = {label: [] for label in order}
    for r in results:
        w = r["world"]
        groups[w["rig_label"]].append(r)
        if w["rig"].startswith("real"):
            groups["real rigs"].append(r)
        else:
            groups["drawn, with fisheye" if w["fisheye"] else "drawn, no fisheye"].append(r)
    return {label: rs for label, rs in groups.items() if rs}


def dress_groups(results: Sequence[dict]) -> dict[str, list[dict]]:
    """Worlds by dress: 'alike' and 'distinct' (groups without worlds left out)."""
    groups: dict[str, list[dict]] = {"alike": [], "distinct": []}
    for r in results:
        groups[r["world"].get("dress", "distinct")].append(r)
    return {label: rs for label, rs in groups.items() if rs}


def groups_table(results: Sequence[dict], groups: dict[str, list[dict]] | None = None) -> str:
    """One row per group of worlds (default: :func:`rig_groups`)."""
    header = ["rig" if groups is None else "group", "worlds", "frames", *_SCORE_HEADER]
    rows = []
    for label, rs in (rig_groups(results) if groups is None else groups).items():
        frames = sum(r["frames"] for r in rs)
        rows.append([label, len(rs), frames, *_score_cells(suite_totals(r["scores"] for r in rs), frames,
                                                           sum(r["fuse_s"] for r in rs))])
    return "\n".join(text_table(header, rows))


# ---------------------------------------------------------------------- helpers

_SCORE_HEADER = ["MOTA", "IDF1", "IDSW", "re-ID", "count", "posture", "fall P", "fall R", "false falls/h",
                 "sit/stand F1", "enter/exit F1", "fused/s"]


def _score_cells(s: dict, frames: int, fuse_s: float) -> list[str]:
    t, p, ev = s["tracking"], s["posture"], s.get("events")
    bands = (s.get("by_people") or {}).values()
    exact = sum(b["count_exact"] for b in bands)
    n = sum(b["frames"] for b in bands)
    fall_p, fall_r, ss, ee = event_cells(ev)
    hours = (s.get("duration_s") or 0.0) / 3600.0
    ff = fmt_num(ev["per_kind"].get("fall", {}).get("fp", 0) / hours, 1) if ev is not None and hours else "-"
    return [fmt_pct(t["mota"]), fmt_pct(t["idf1"]), t["id_switches"], identity_cell(s.get("identity")),
            fmt_pct(exact / n if n else None), fmt_pct(p["strict_accuracy"]),
            fall_p, fall_r, ff, ss, ee, fmt_num(frames / fuse_s if fuse_s > 0 else None, 1)]


def _run_world(seed: int, out: str, frames: int | None, keep_media: bool, settings: tuple[str, ...] = (),
               sensors: str = "colour") -> dict:
    """Write, replay and score one world (runs in a worker process)."""
    from common.site import load_site, with_settings
    from synth.world import random_world, write_world
    from fusion_server.replay import replay

    out_dir = Path(out)
    t0 = time.perf_counter()
    world = random_world(seed, sensors=sensors)
    written = write_world(world, out_dir / "worlds" / world.name, frames=frames)
    t1 = time.perf_counter()
    run_dir = out_dir / "runs" / world.name
    summary = replay(with_settings(load_site(written.site), settings), run_dir, input_dir=written.out_dir, cache_dir=out_dir / "cache")
    t2 = time.perf_counter()
    scores = evaluate(written.truth_dir, run_dir)
    if not keep_media:
        for cam in world.cameras:
            shutil.rmtree(written.out_dir / cam, ignore_errors=True)
    return {"seed": seed, "world": world.summary(), "frames": summary.frames, "fuse_s": summary.stage_s["fuse"],
            "write_s": t1 - t0, "replay_s": t2 - t1, "scores": scores}


def _report(result: dict) -> dict:
    w = result["world"]
    print(f"  world {result['seed']}: {w['rig_label']}, {w['cameras']} cameras, {w['people']} people, "
          f"{result['frames']} frames: written in {result['write_s']:.0f} s, replayed in {result['replay_s']:.0f} s",
          file=sys.stderr, flush=True)
    return result


def _band(n: int) -> str:
    for lo, hi in ((0, 0), (1, 1), (2, 3), (4, 7), (8, 12)):
        if lo <= n <= hi:
            return f"{lo}" if lo == hi else f"{lo}-{hi}"
    return "13+"


def _counts(counter: Counter, key=None) -> str:
    items = sorted(counter.items(), key=(lambda kv: key(kv[0])) if key else (lambda kv: (-kv[1], kv[0])))
    return ", ".join(f"{k} {v}" for k, v in items) or "none"


def _seed_text(seeds: Sequence[int]) -> str:
    s = sorted(seeds)
    if s == list(range(s[0], s[-1] + 1)):
        return f"{s[0]}-{s[-1]}" if len(s) > 1 else str(s[0])
    return ",".join(str(v) for v in seeds)
