"""Scoring a run folder against a truth folder, and showing the scores.

:func:`evaluate` reads the files and returns one JSON-ready dict holding every
count and ratio; :func:`format_table` prints it for the console;
:func:`suite_table` prints one row per scenario and a total row.

Frames: when the frame count is known (argument, or ``n_frames`` in the truth
``meta.json``) the evaluated frames are ``0 .. n_frames - 1``, widened with a
note if a file has rows outside; otherwise they run from the first to the
last frame that has a row in either tracks file. Frames without rows count as
frames with nobody in them.

Frame rate (for durations and false alarms per hour): the ``fps`` argument,
else ``fps`` in ``meta.json``, else estimated from the frame numbers and
stamps of the truth tracks (then the run's); unknown leaves rates at None.

Totals over scenarios are computed from summed counts, never by averaging
ratios: MOTA = 1 - sum(FN + FP + IDSW) / sum(GT); MOTP and MOTME = summed
distance / summed matches; MOTV pooled from summed distances and squared
distances; IDF1 = 2 sum(IDTP) / (sum(GT) + sum(predictions)) (each scenario
keeps its own identity assignment, as identities do not cross recordings);
MTPF and ATPF per summed frame; event precision/recall/F1 from summed
TP/FP/FN; posture accuracy from summed correct/scored pairs; false alarms per
summed hour; fall delays pooled; re-entry identity from summed re-entries and
same ids (:mod:`~evaluation.reentry`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evaluation import io
from evaluation.events import ALARM_KINDS, WINDOW_FRAMES, TrackLinks, f1_score, score_events
from evaluation.posture import FALSE_LYING_MIN_S, posture_scores
from evaluation.reentry import reentry_identity
from evaluation.residents import resident_scores
from evaluation.residents import totals as resident_totals
from evaluation.tracking import (
    CLEAR_RADIUS_M, PER_FRAME_RADIUS_M, band_summary, by_people_present, clear_mot, frame_span, per_frame_measures, ratio,
)
from common.plain import plain_value


def evaluate(
    truth_dir: str | Path,
    run_dir: str | Path,
    *,
    fps: float | None = None,
    n_frames: int | None = None,
    clear_radius_m: float = CLEAR_RADIUS_M,
    per_frame_radius_m: float = PER_FRAME_RADIUS_M,
    window_frames: int = WINDOW_FRAMES,
    position_gate_m: Mapping[str, float] | None = None,
    require_track: bool = False,
    alarm_kinds: Sequence[str] = ALARM_KINDS,
    resident: tuple[str, str] | None = None,
) -> dict[str, Any]:
    """Score ``run_dir`` (tracks.csv, events.jsonl) against ``truth_dir`` (truth/ or flat).

    Returns a dict of plain JSON values with the keys ``truth_dir``,
    ``run_dir``, ``frames`` {first, last, count}, ``fps``, ``fps_source``,
    ``duration_s``, ``tracking`` (CLEAR-MOT and identity), ``per_frame`` (MOTME,
    MOTV, MTPF, ATPF), ``events`` (None when the truth has no events file),
    ``posture``, ``identity`` (re-entries that keep their track id; None without truth
    events or frame rate), ``notes`` and, when ``resident`` gives ``(truth person id,
    enrolled name)``, ``resident`` (:func:`~evaluation.residents.resident_scores`).
    Raises :class:`~evaluation.io.EvalFormatError` naming the file, line and
    field of any bad input.
    """
    if fps is not None and not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    if n_frames is not None and (isinstance(n_frames, bool) or not isinstance(n_frames, int) or n_frames < 0):
        raise ValueError(f"n_frames must be a non-negative integer, got {n_frames!r}")
    notes: list[str] = []
    truth = io.read_truth_tracks(truth_dir)
    run = io.read_run_tracks(run_dir)
    meta = io.read_truth_meta(truth_dir)
    truth_events = io.read_truth_events(truth_dir)
    run_events = io.read_run_events(run_dir, required=truth_events is not None)

    offset_ns = clock_offset_ns(truth, run)
    if offset_ns is not None and abs(offset_ns) >= CLOCK_OFFSET_LIMIT_NS:
        # a replay of a recording without its capture times (mask folders, video files) stamps
        # frames from 0: delays are measured on the truth's clock, through the shared frames
        run_events = [e.model_copy(update={"stamp_ns": e.stamp_ns - offset_ns}) for e in run_events]
        notes.append(f"the run's clock differs from the truth's by {offset_ns / 1e9:.3f} s over the frames both have: "
                     "run event stamps shifted by that much for delays")
    fps_value, fps_source = _frame_rate(fps, meta, truth, run)
    if fps_value is None:
        notes.append("frame rate unknown (no fps argument, no meta.json fps, stamps unusable): rates per hour left out")
    first, last = _frame_range(n_frames if n_frames is not None else meta.n_frames, truth, run, truth_events, run_events, notes)
    count = 0 if first is None else last - first + 1
    duration_s = None if fps_value is None else count / fps_value

    mot = clear_mot(truth, run, radius_m=clear_radius_m)
    per_frame = per_frame_measures(truth, run, radius_m=per_frame_radius_m, n_frames=count)
    events = None
    if truth_events is None:
        notes.append("the truth has no events.jsonl: events not scored")
    else:
        links = TrackLinks.from_matches(truth, run, mot.pairs) if require_track else None
        scores = score_events(
            truth_events, run_events, window_frames=window_frames, position_gate_m=position_gate_m, track_links=links
        )
        events = scores.summary(duration_s=duration_s, alarm_kinds=alarm_kinds)
    identity = None
    if truth_events is not None and fps_value is not None:
        identity = reentry_identity(truth, run, mot.pairs, truth_events, fps_value).summary()
    elif truth_events is not None:
        notes.append("frame rate unknown: re-entry identity not scored")
    return {
        "truth_dir": str(truth_dir),
        "run_dir": str(run_dir),
        "frames": {"first": first, "last": last, "count": count},
        "fps": fps_value,
        "fps_source": fps_source,
        "duration_s": duration_s,
        "tracking": mot.summary(),
        "per_frame": per_frame.summary(),
        "events": events,
        "posture": posture_scores(truth, run, mot.pairs).summary(),
        "identity": identity,
        "by_people": by_people_present(truth, run, mot.pairs, first, last),
        "notes": notes,
        **({} if resident is None else
           {"resident": resident_scores(truth, run, mot.pairs, person=resident[0], name=resident[1])}),
    }


CLOCK_OFFSET_LIMIT_NS = 1_000_000_000
"""A run whose stamps differ from the truth's by this much or more, frame for frame, runs on another clock."""


def clock_offset_ns(truth: io.TrackTable, run: io.TrackTable) -> int | None:
    """Median of (run stamp - truth stamp) over the frames both track tables have (the stamp of
    each frame's first row); None when they share no frame."""
    if not len(truth) or not len(run):
        return None
    t, r = truth.sorted(), run.sorted()
    tf, ti = np.unique(t.frame, return_index=True)
    rf, ri = np.unique(r.frame, return_index=True)
    common, a, b = np.intersect1d(tf, rf, return_indices=True)
    if not common.size:
        return None
    return int(np.median(r.stamp_ns[ri[b]] - t.stamp_ns[ti[a]]))


def format_table(results: Mapping[str, Any]) -> str:
    """The results of :func:`evaluate` as aligned plain-text tables for the console."""
    t, s, p = results["tracking"], results["per_frame"], results["posture"]
    fr = results["frames"]
    lines = [
        f"truth {results['truth_dir']}  run {results['run_dir']}",
        f"frames {fr['first']}..{fr['last']} ({fr['count']})  fps {fmt_num(results['fps'], 3)} ({results['fps_source']})"
        f"  duration {fmt_num(results['duration_s'], 1)} s",
        "",
        f"tracking (CLEAR-MOT, match radius {t['radius_m']} m)",
    ]
    lines += text_table(
        ["MOTA", "MOTP m", "IDF1", "IDP", "IDR", "IDSW", "FRAG", "MT", "PT", "ML", "FP", "FN", "GT", "GT ids", "run ids"],
        [[fmt_pct(t["mota"]), fmt_num(t["motp_m"], 3), fmt_pct(t["idf1"]), fmt_pct(t["idp"]), fmt_pct(t["idr"]), t["id_switches"],
          t["fragmentations"], t["mostly_tracked"], t["partly_tracked"], t["mostly_lost"], t["fp"], t["fn"], t["gt"],
          t["gt_ids"], t["pred_ids"]]],
        label_column=False,
    )
    bands = results.get("by_people") or {}
    if bands:
        lines += ["", "by people present in the frame (count exact: frames where the run counts as many people)"]
        lines += people_table(bands)
    lines += ["", f"per-frame measures (MOTME, MOTV, MTPF, ATPF: fresh Hungarian in every frame, radius {s['radius_m']} m)"]
    lines += text_table(
        ["MOTME m", "MOTV m2", "MTPF", "ATPF", "matches", "missed", "artifacts"],
        [[fmt_num(s["motme_m"], 3), fmt_num(s["motv_m2"], 4), fmt_num(s["mtpf"], 4), fmt_num(s["atpf"], 4), s["matches"],
          s["missed"], s["artifacts"]]],
        label_column=False,
    )
    ev = results.get("events")
    if ev is not None:
        gate = ", ".join(f"{k} {v} m" for k, v in ev["position_gate_m"].items()) or "none"
        lines += ["", f"events (window +-{ev['window_frames']} frames; position gate: {gate};"
                      f" same track required: {'yes' if ev['track_required'] else 'no'})"]
        rows = [
            [kind, k["truth"], k["run"], k["tp"], k["fp"], k["fn"], fmt_pct(k["precision"]), fmt_pct(k["recall"]), fmt_pct(k["f1"])]
            for kind, k in ev["per_kind"].items()
            if k["truth"] or k["run"]
        ]
        o = ev["overall"]
        rows.append(["all", o["truth"], o["run"], o["tp"], o["fp"], o["fn"],
                     fmt_pct(o["precision"]), fmt_pct(o["recall"]), fmt_pct(o["f1"])])
        lines += text_table(["kind", "truth", "run", "TP", "FP", "FN", "precision", "recall", "F1"], rows)
        lines.append(
            f"fall delay s: mean {fmt_num(ev['fall_delay_mean_s'], 2)}  median {fmt_num(ev['fall_delay_median_s'], 2)}"
            f"  max {fmt_num(ev['fall_delay_max_s'], 2)}  ({len(ev['fall_delays_s'])} detected)"
        )
        lines.append(
            f"false alarms ({'/'.join(ev['alarm_kinds'])}): {ev['false_alarms']}"
            f"  per hour {fmt_num(ev['false_alarms_per_hour'], 2)}"
        )
    ident = results.get("identity")
    if ident is not None:
        lines += ["", f"identity across re-entries (exit and back within {ident['within_s']:.0f} s; run id of the last "
                      f"{ident['before_s']:g} s matched before against the first {ident['after_s']:g} s matched after)",
                  f"re-entries {ident['reentries']}  same id {ident['same_id']}  rate {fmt_pct(ident['rate'])}"]
    lines += ["", f"posture over {p['pairs']} matched pairs ({p['scored']} with a known truth posture)"]
    lines.append(f"accuracy strict {fmt_pct(p['strict_accuracy'])}  lenient (bending = standing) {fmt_pct(p['lenient_accuracy'])}")
    if "false_lying_spells" in p:
        lines.append(f"false lying markers (read lying over {FALSE_LYING_MIN_S:g} s while not lying): "
                     f"{p['false_lying_spells']}, {fmt_num(p['false_lying_s'], 1)} s in all")
    labels = p["labels"]
    conf = p["confusion"]
    rows = [[lab, *row] for lab, row in zip(labels, conf) if any(row)] or [["-"] * (len(labels) + 1)]
    lines += text_table(["truth \\ run", *labels], rows)
    res = results.get("resident")
    if res is not None:
        lines += ["", f"enrolled resident {res['name']} (truth person {res['person']}): "
                      f"named on {fmt_pct(res['named_ratio'])} of their {res['resident_matched']} matched frames; "
                      f"someone else named {res['false_named']} times, a named track matching nobody "
                      f"{res['named_unmatched']} times"]
    for note in results.get("notes", []):
        lines.append(f"note: {note}")
    return "\n".join(lines)


def suite_totals(results: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Totals over scenarios from summed counts (see the module text), in :func:`evaluate`'s layout."""
    results = list(results)
    if not results:
        raise ValueError("suite_totals needs at least one result")
    add = lambda section, key: sum(r[section][key] for r in results)  # noqa: E731
    t_keys = ["gt", "gt_ids", "pred", "pred_ids", "matches", "fp", "fn", "id_switches", "fragmentations",
              "mostly_tracked", "partly_tracked", "mostly_lost", "distance_sum_m", "idtp", "idfp", "idfn"]
    t = {k: add("tracking", k) for k in t_keys}
    t["radius_m"] = results[0]["tracking"]["radius_m"]
    t["mota"] = None if t["gt"] == 0 else 1.0 - (t["fn"] + t["fp"] + t["id_switches"]) / t["gt"]
    t["motp_m"] = ratio(t["distance_sum_m"], t["matches"])
    t["precision"] = ratio(t["matches"], t["pred"])
    t["recall"] = ratio(t["matches"], t["gt"])
    t["idp"] = ratio(t["idtp"], t["pred"])
    t["idr"] = ratio(t["idtp"], t["gt"])
    t["idf1"] = ratio(2 * t["idtp"], t["gt"] + t["pred"])

    s = {k: add("per_frame", k) for k in ["frames", "matches", "missed", "artifacts", "distance_sum_m", "distance_sq_sum_m2"]}
    s["radius_m"] = results[0]["per_frame"]["radius_m"]
    s["motme_m"] = ratio(s["distance_sum_m"], s["matches"])
    s["motv_m2"] = None if not s["matches"] else max(0.0, s["distance_sq_sum_m2"] / s["matches"] - s["motme_m"] ** 2)
    s["mtpf"] = ratio(s["missed"], s["frames"])
    s["atpf"] = ratio(s["artifacts"], s["frames"])

    p_counts = {k: add("posture", k) for k in ["pairs", "scored", "strict_correct", "lenient_correct"]}
    confusion = np.sum([np.asarray(r["posture"]["confusion"]) for r in results], axis=0).astype(int)
    p = {
        **p_counts,
        "strict_accuracy": ratio(p_counts["strict_correct"], p_counts["scored"]),
        "lenient_accuracy": ratio(p_counts["lenient_correct"], p_counts["scored"]),
        "labels": results[0]["posture"]["labels"],
        "confusion": confusion.tolist(),
        "false_lying_spells": int(sum(r["posture"].get("false_lying_spells", 0) for r in results)),
        "false_lying_s": round(float(sum(r["posture"].get("false_lying_s", 0.0) for r in results)), 3),
    }
    bands: dict[str, dict[str, Any]] = {}
    for r in results:
        for label, c in (r.get("by_people") or {}).items():
            acc = bands.setdefault(label, dict.fromkeys(_BAND_COUNTS, 0))
            for k in _BAND_COUNTS:
                acc[k] += c[k]
    durations = [r["duration_s"] for r in results]
    duration_s = None if any(d is None for d in durations) else float(sum(durations))
    return {
        "truth_dir": "(suite)",
        "run_dir": "(suite)",
        "frames": {"first": None, "last": None, "count": add("frames", "count")},
        "fps": None,
        "fps_source": "suite",
        "duration_s": duration_s,
        "tracking": t,
        "per_frame": s,
        "events": _sum_events([r["events"] for r in results if r.get("events") is not None], duration_s),
        "posture": p,
        "identity": _sum_identity([r.get("identity") for r in results]),
        "by_people": {label: band_summary(bands[label]) for label in sorted(bands, key=_band_low)},
        "notes": [],
        **({"resident": resident_totals([r["resident"] for r in results])}
           if all(r.get("resident") is not None for r in results) else {}),
    }


def identity_cell(ident: Mapping[str, Any] | None) -> str:
    """Re-entries keeping their id, as 'same/re-entries', '-' when not scored or none."""
    if not ident or not ident["reentries"]:
        return "-"
    return f"{ident['same_id']}/{ident['reentries']}"


def people_table(bands: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """Text rows of :func:`~evaluation.tracking.by_people_present` bands and their total."""
    total = band_summary({k: sum(b[k] for b in bands.values()) for k in _BAND_COUNTS})
    rows = [[label, b["frames"], b["gt"], fmt_pct(b["mota"]), fmt_num(b["motp_m"], 3), fmt_pct(b["count_exact_ratio"]),
             b["fp"], b["fn"], b["id_switches"]] for label, b in [*bands.items(), ("all", total)]]
    return text_table(["people", "frames", "GT", "MOTA", "MOTP m", "count exact", "FP", "FN", "IDSW"], rows,
                  rule_before_last=True)


def _band_low(label: str) -> int:
    """'2-3' -> 2, '13+' -> 13: the order of the bands."""
    return int(label.split("-")[0].rstrip("+"))


_BAND_COUNTS = ("frames", "gt", "pred", "matches", "id_switches", "distance_sum_m", "count_exact")


def suite_table(rows: Mapping[str, Mapping[str, Any]] | Iterable[tuple[str, Mapping[str, Any]]]) -> str:
    """One line per scenario and a ``total`` line from :func:`suite_totals`.

    ``rows``: scenario name -> :func:`evaluate` result (a mapping or pairs).
    Columns: frames, GT, MOTA, MOTP, IDF1, IDSW, FRAG, FP, FN, MOTME, MTPF,
    ATPF, fall P and R, sit/stand F1 (sit_down + stand_up counts), enter/exit
    F1 (enter + exit counts), strict posture accuracy, false alarms per hour; when
    every result scores an enrolled resident, also the frames someone else was
    named as the resident (``false res``) and the share of the resident's
    matched frames that carry the name (``res named``).
    """
    items = list(rows.items()) if isinstance(rows, Mapping) else list(rows)
    if not items:
        return "(no scenarios)"
    header = ["scenario", "frames", "GT", "MOTA", "MOTP m", "IDF1", "IDSW", "FRAG", "FP", "FN", "MOTME m", "MTPF",
              "ATPF", "fall P", "fall R", "sit/stand F1", "enter/exit F1", "posture", "FA/h"]
    with_resident = all(r.get("resident") is not None for _, r in items)
    if with_resident:
        header += ["false res", "res named"]
    body = [_suite_row(name, r, with_resident) for name, r in items]
    total = _suite_row("total", suite_totals(r for _, r in items), with_resident)
    return "\n".join(text_table(header, body + [total], rule_before_last=True))


def to_json(results: Mapping[str, Any]) -> str:
    """The results as indented JSON text (None becomes null)."""
    return json.dumps(plain_value(results), indent=2, allow_nan=False)


def write_json(results: Mapping[str, Any], path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(to_json(results) + "\n", encoding="utf-8")
    return path


# ---------------------------------------------------------------- helpers


def _frame_rate(fps: float | None, meta: io.Meta, truth: io.TrackTable, run: io.TrackTable) -> tuple[float | None, str]:
    if fps is not None:
        return float(fps), "argument"
    if meta.fps is not None:
        return meta.fps, "meta.json"
    for name, table in (("truth", truth), ("run", run)):
        est = table.fps_from_stamps()
        if est is not None:
            return est, f"{name} stamps"
    return None, "unknown"


def _frame_range(
    n_frames: int | None,
    truth: io.TrackTable,
    run: io.TrackTable,
    truth_events: list[io.Event] | None,
    run_events: list[io.Event],
    notes: list[str],
) -> tuple[int | None, int | None]:
    """First and last evaluated frame (see the module text); appends a note when the range is widened."""
    first, last = frame_span(truth, run)
    ev_frames = [e.frame for e in (truth_events or []) + (run_events or [])]
    if ev_frames and first is None:
        first, last = min(ev_frames), max(ev_frames)
    elif ev_frames:
        first, last = min(first, min(ev_frames)), max(last, max(ev_frames))
    if n_frames is None:
        return first, last
    if n_frames == 0 and first is None:
        return None, None
    if first is not None and (first < 0 or last > n_frames - 1):
        notes.append(f"rows or events lie outside frames 0..{n_frames - 1}: the evaluated range is widened to "
                     f"{min(first, 0)}..{max(last, n_frames - 1)}")
        return min(first, 0), max(last, n_frames - 1)
    return 0, n_frames - 1


def _sum_events(events: list[Mapping[str, Any]], duration_s: float | None) -> dict[str, Any] | None:
    if not events:
        return None
    kinds = list(dict.fromkeys(k for e in events for k in e["per_kind"]))
    per_kind = {}
    for kind in kinds:
        c = {n: sum(e["per_kind"].get(kind, {}).get(n, 0) for e in events) for n in ("truth", "run", "tp", "fp", "fn")}
        per_kind[kind] = _kind_summary(c)
    overall = _kind_summary({n: sum(k[n] for k in per_kind.values()) for n in ("truth", "run", "tp", "fp", "fn")})
    delays = [d for e in events for d in e["fall_delays_s"]]
    n_false = sum(e["false_alarms"] for e in events)
    return {
        "window_frames": events[0]["window_frames"],
        "position_gate_m": events[0]["position_gate_m"],
        "track_required": events[0]["track_required"],
        "per_kind": per_kind,
        "overall": overall,
        "fall_delays_s": delays,
        "fall_delay_mean_s": float(np.mean(delays)) if delays else None,
        "fall_delay_median_s": float(np.median(delays)) if delays else None,
        "fall_delay_max_s": max(delays) if delays else None,
        "alarm_kinds": events[0]["alarm_kinds"],
        "false_alarms": n_false,
        "duration_s": duration_s,
        "false_alarms_per_hour": None if not duration_s else n_false / (duration_s / 3600.0),
        "unscored_run_events": sum(e["unscored_run_events"] for e in events),
    }


def _sum_identity(parts: Sequence[Mapping[str, Any] | None]) -> dict[str, Any] | None:
    """Re-entry identity summed over recordings (None when none was scored)."""
    parts = [p for p in parts if p is not None]
    if not parts:
        return None
    n, k = sum(p["reentries"] for p in parts), sum(p["same_id"] for p in parts)
    return {**{key: parts[0][key] for key in ("within_s", "before_s", "after_s")}, "reentries": n, "same_id": k,
            "rate": ratio(k, n)}


def _kind_summary(c: Mapping[str, int]) -> dict[str, Any]:
    return {
        **c,
        "precision": ratio(c["tp"], c["run"]),
        "recall": ratio(c["tp"], c["truth"]),
        "f1": f1_score(c["tp"], c["fp"], c["fn"]),
    }


def _suite_row(name: str, r: Mapping[str, Any], with_resident: bool = False) -> list[Any]:
    t, s, p, ev = r["tracking"], r["per_frame"], r["posture"], r.get("events")
    fall, fall_r, sit, door = event_cells(ev)
    fa = "-" if ev is None else fmt_num(ev["false_alarms_per_hour"], 2)
    row = [name, r["frames"]["count"], t["gt"], fmt_pct(t["mota"]), fmt_num(t["motp_m"], 3), fmt_pct(t["idf1"]),
           t["id_switches"], t["fragmentations"], t["fp"], t["fn"], fmt_num(s["motme_m"], 3), fmt_num(s["mtpf"], 3),
           fmt_num(s["atpf"], 3), fall, fall_r, sit, door, fmt_pct(p["strict_accuracy"]), fa]
    if with_resident:
        res = r["resident"]
        row += [res["false_named"], fmt_pct(res["named_ratio"])]
    return row


def event_cells(ev: Mapping[str, Any] | None) -> list[str]:
    """Fall precision, fall recall, sit/stand F1 (sit_down + stand_up counts) and enter/exit F1
    (enter + exit counts) of an events summary, formatted; '-' where there is nothing to score."""
    if ev is None:
        return ["-"] * 4
    k = ev["per_kind"]
    fall = k.get("fall")
    return [fmt_pct(fall["precision"]) if fall else "-", fmt_pct(fall["recall"]) if fall else "-",
            fmt_pct(pooled_f1(k, ("sit_down", "stand_up"))), fmt_pct(pooled_f1(k, ("enter", "exit")))]


def pooled_f1(per_kind: Mapping[str, Mapping[str, int]], kinds: Sequence[str]) -> float | None:
    tp = sum(per_kind.get(k, {}).get("tp", 0) for k in kinds)
    fp = sum(per_kind.get(k, {}).get("fp", 0) for k in kinds)
    fn = sum(per_kind.get(k, {}).get("fn", 0) for k in kinds)
    return f1_score(tp, fp, fn)


def text_table(
    header: Sequence[str], rows: Sequence[Sequence[Any]], *, rule_before_last: bool = False, label_column: bool = True
) -> list[str]:
    """Aligned text rows: the first column left-aligned when it holds labels, numbers right-aligned."""
    cells = [[str(h) for h in header]] + [[str(c) for c in row] for row in rows]
    widths = [max(len(row[k]) for row in cells) for k in range(len(header))]

    def line(row: Sequence[str]) -> str:
        first = row[0].ljust(widths[0]) if label_column else row[0].rjust(widths[0])
        return "  ".join([first] + [c.rjust(w) for c, w in zip(row[1:], widths[1:])]).rstrip()

    rule = "  ".join("-" * w for w in widths)
    out = [line(cells[0]), rule]
    for k, row in enumerate(cells[1:]):
        if rule_before_last and k == len(cells) - 2 and k > 0:
            out.append(rule)
        out.append(line(row))
    return out


def fmt_pct(value: float | None) -> str:
    return "-" if value is None else f"{100.0 * value:.1f}%"


def fmt_num(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"
