"""The scenario suite: every synthetic-house scenario replayed and scored.

One row a scenario, a total row from summed counts, and the same again with
fewer cameras to show how accuracy degrades when cameras fail. Uses the same
:func:`fusion_server.replay.replay` as ``voxelwatch replay``.

With an enrolment (``voxelwatch enrol`` of one person of the house, e.g.
person 1 from ``walk``: a person's build and clothes depend only on the seed
and their id, so they look the same in every scenario), the suite's site
enrols that person and every scenario also scores the name
(:mod:`evaluation.residents`): frames in which someone else's track
carries it (the target is zero) and the share of the person's own matched
frames that do.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path

from evaluation import evaluate, suite_table, write_json
from evaluation import suite_totals

QUICK_SCENARIOS = ("walk", "sit_stand", "fall_forward", "two_pass")
QUICK_FRAMES = 675  # 45 s at 15 fps

CAMERA_ORDER = ("cam1", "cam3", "cam2", "cam4", "cam5")
"""Cameras kept as the count falls: two opposite corners last."""


def cameras_for(count: int, available: Sequence[str]) -> list[str]:
    """The first ``count`` cameras of :data:`CAMERA_ORDER` that the site has, in site order."""
    ordered = [c for c in CAMERA_ORDER if c in available] + [c for c in available if c not in CAMERA_ORDER]
    if not 1 <= count <= len(ordered):
        raise ValueError(f"camera count must lie in 1..{len(ordered)}, got {count}")
    keep = set(ordered[:count])
    return [c for c in available if c in keep]


def run_suite(
    *,
    out_dir: str | Path,
    scenarios: Sequence[str] | None = None,
    quick: bool = False,
    camera_counts: Sequence[int] = (5,),
    max_frames: int | None = None,
    seed: int = 0,
    json_path: str | Path | None = None,
    jobs: int = 1,
    mask_scale: float | None = None,
    enrolled: str | Path | None = None,
    enrolled_person: int = 1,
    settings: Sequence[str] = (),
    stream=sys.stdout,
) -> int:
    """Replay and score the scenarios; print one table per camera count. Returns 0.

    jobs: scenarios replayed at once, each in its own process.
    mask_scale: the masks' downscale factor (default: the synthetic site's).
    enrolled: an enrolment file (``voxelwatch enrol``) of the house's person
        ``enrolled_person``, made with the same seed; the site enrols it and the
        scores gain ``resident``.
    settings: ``SECTION.KEY=VALUE`` changes to the site (:func:`common.site.with_settings`).
    """
    import synth

    out = Path(out_dir)
    names = list(scenarios) if scenarios else (list(QUICK_SCENARIOS) if quick else synth.list_scenarios())
    if quick and max_frames is None:
        max_frames = QUICK_FRAMES
    site = synth.default_site(out / "site")
    resident = None
    if mask_scale is not None or enrolled is not None:
        raw = site.model_dump(mode="json", exclude={"base_dir"})
        if mask_scale is not None:
            raw["carving"]["mask_scale"] = mask_scale
        if enrolled is not None:
            name = _enrolled_name(Path(enrolled))
            raw["enrolled"] = [{"name": name, "model": str(Path(enrolled).resolve())}]
            raw["residents"] = max(int(raw["residents"]), 1)
            resident = (str(int(enrolled_person)), name)
        site = synth_site_with(raw, out / "site")
        site.load_residents()  # a bad enrolment file stops the suite before any replay
    if settings:
        from common.site import with_settings, write_site

        site = with_settings(site, settings)
        write_site(site, out / "site" / "site.toml")
    plans = []
    for count in camera_counts:
        cams = cameras_for(count, site.camera_ids)
        for name in names:
            plans.append((count, cams, name))
    results: dict[tuple[int, str], dict] = {}
    site_path = site.base_dir / "site.toml"
    tasks = [(str(site_path), str(out), count, cams, name, max_frames, seed, resident) for count, cams, name in plans]
    if jobs <= 1:
        for task in tasks:
            results[(task[2], task[4])] = _report(_run_one(*task))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(_run_one, *task): task for task in tasks}
            for future in as_completed(futures):
                task = futures[future]
                results[(task[2], task[4])] = _report(future.result())
    report: dict[str, dict] = {}
    for count in camera_counts:
        cams = cameras_for(count, site.camera_ids)
        rows = {name: results[(count, name)]["scores"] for name in names}
        print(f"\n{count} cameras ({', '.join(cams)}):", file=stream)
        print(suite_table(rows), file=stream, flush=True)
        report[f"{count}cam"] = {"cameras": cams, "scenarios": rows, "total": suite_totals(rows.values())}
    if json_path is not None:
        write_json(report, json_path)
    return 0


def synth_site_with(raw: dict, folder: Path):
    """The synthetic site with changed settings, written back to its folder."""
    from common.site import site_from_dict, write_site, load_site

    return load_site(write_site(site_from_dict(raw, base_dir=folder.resolve()), folder / "site.toml"))


def _enrolled_name(path: Path) -> str:
    """The name an enrolment file carries; ValueError naming the file when it has none."""
    import json

    try:
        name = json.loads(path.read_text(encoding="utf-8")).get("name")
    except (OSError, ValueError, AttributeError) as exc:
        raise ValueError(f"enrolment file {path}: cannot read its name: {exc}") from None
    if not isinstance(name, str) or not name.strip():
        raise ValueError(f"enrolment file {path}: no name (write it with voxelwatch enrol)")
    return name


def _run_one(site_path: str, out: str, count: int, cams: list[str], name: str, max_frames: int | None, seed: int,
             resident: tuple[str, str] | None = None) -> dict:
    """Replay and score one scenario with some cameras (runs in a worker process)."""
    import synth
    from common.site import load_site
    from fusion_server.replay import replay

    out_dir = Path(out)
    site = load_site(site_path)
    scenario = synth.get_scenario(name, seed, utc_offset_hours=site.utc_offset_hours)
    n_frames = scenario.n_frames if max_frames is None else min(max_frames, scenario.n_frames)
    truth_dir = out_dir / "truth" / name
    synth.write_truth(scenario, truth_dir, n_frames=n_frames)
    run_dir = out_dir / f"run-{count}cam" / name
    t0 = time.perf_counter()
    summary = replay(site, run_dir, synthetic=name, cameras=cams, max_frames=n_frames, seed=seed, cache_dir=out_dir / "cache")
    return {"count": count, "name": name, "frames": summary.frames, "seconds": time.perf_counter() - t0,
            "scores": evaluate(truth_dir, run_dir, resident=resident)}


def _report(result: dict) -> dict:
    print(f"  {result['count']} cameras, {result['name']}: {result['frames']} frames in {result['seconds']:.0f} s",
          file=sys.stderr, flush=True)
    return result
