"""Tracking measures against hand-worked cases, a brute-force oracle and py-motmetrics."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from evaluation import io
from evaluation.io import TrackTable
from evaluation.posture import posture_from_labels, posture_scores
from evaluation.report import evaluate, suite_totals
from evaluation.tracking import by_people_present, clear_mot, gated_assignment, per_frame_measures

NS = 66_666_667  # one frame at 15 fps


def table(rows: list[tuple]) -> TrackTable:
    """Rows (frame, id, x, y[, posture]) -> TrackTable."""
    full = []
    for r in rows:
        frame, tid, x, y = r[:4]
        posture = r[4] if len(r) > 4 else "standing"
        full.append((frame, frame * NS, tid, x, y, 1.7, posture))
    return TrackTable.from_rows(full)


# ---------------------------------------------------------------- hand-worked cases


def test_perfect_run_scores_perfectly() -> None:
    truth = table([(f, p, 1.0 + p_i * 2, 0.5 * f) for f in range(3) for p_i, p in enumerate("AB")])
    run = table([(f, str(10 + p_i), 1.1 + p_i * 2, 0.5 * f) for f in range(3) for p_i in range(2)])
    r = clear_mot(truth, run)
    assert (r.gt, r.matches, r.fp, r.fn, r.id_switches, r.fragmentations) == (6, 6, 0, 0, 0, 0)
    assert r.mota == 1.0 and r.idf1 == 1.0
    assert r.motp_m == pytest.approx(0.1, abs=1e-12)
    assert (r.mostly_tracked, r.partly_tracked, r.mostly_lost) == (2, 0, 0)


def hand_case() -> tuple[TrackTable, TrackTable]:
    # truth: A stands at (0, 0), B at (3, 0), frames 0..3
    truth = table([(f, p, x, 0.0) for f in range(4) for p, x in (("A", 0.0), ("B", 3.0))])
    run = table(
        [
            (0, "1", 0.1, 0.0), (1, "1", 0.1, 0.0),   # track 1 on A, 0.1 m off, lost in frame 2
            (3, "2", 0.2, 0.0),                       # track 2 picks A up in frame 3, 0.2 m off
            *[(f, "3", 3.0, 0.3) for f in range(4)],  # track 3 on B all along, 0.3 m off
            (1, "9", 10.0, 10.0),                     # a false positive far away
        ]
    )
    return truth, run


def test_by_people_present_splits_the_hand_case_by_frame() -> None:
    # the hand case has two people in frames 0..3; add frame 4 with A alone (track 2 on it) and
    # frame 5 with nobody but a false track
    truth, run = hand_case()
    truth = table([*[(f, p, x, 0.0) for f in range(4) for p, x in (("A", 0.0), ("B", 3.0))], (4, "A", 0.0, 0.0)])
    run = table([(0, "1", 0.1, 0.0), (1, "1", 0.1, 0.0), (3, "2", 0.2, 0.0), *[(f, "3", 3.0, 0.3) for f in range(4)],
                 (1, "9", 10.0, 10.0), (4, "2", 0.1, 0.0), (5, "7", 1.0, 1.0)])
    r = clear_mot(truth, run)
    bands = by_people_present(truth, run, r.pairs, 0, 5)
    assert list(bands) == ["0", "1", "2-3"]
    two = bands["2-3"]
    # frames 0-3: GT 8; matches 7 (A missed in frame 2); FP 1 (track 9); one switch (A: 1 -> 2 in frame 3)
    assert (two["frames"], two["gt"], two["pred"], two["matches"], two["fp"], two["fn"], two["id_switches"]) == (
        4, 8, 8, 7, 1, 1, 1)
    # the count is right in frames 0 and 3 (frame 1 has 3 tracks, frame 2 one)
    assert two["count_exact"] == 2 and two["count_exact_ratio"] == 0.5
    assert two["mota"] == pytest.approx(1 - 3 / 8)
    one = bands["1"]
    assert (one["frames"], one["gt"], one["matches"], one["fp"], one["count_exact"]) == (1, 1, 1, 0, 1)
    assert one["motp_m"] == pytest.approx(0.1)
    empty = bands["0"]
    assert (empty["frames"], empty["gt"], empty["fp"], empty["count_exact"], empty["mota"]) == (1, 0, 1, 0, None)
    # the bands add up to the whole
    assert sum(b["gt"] for b in bands.values()) == r.gt and sum(b["fp"] for b in bands.values()) == r.fp
    assert sum(b["id_switches"] for b in bands.values()) == r.id_switches


def test_hand_worked_clear_mot_and_identity() -> None:
    truth, run = hand_case()
    r = clear_mot(truth, run)
    # frame 0: A-1 0.1, B-3 0.3 | frame 1: A-1 0.1, B-3 0.3, 9 is FP | frame 2: A missed, B-3 0.3
    # frame 3: A-2 0.2 (A was last with 1: switch), B-3 0.3
    # GT 8, matches 7, FN 1, FP 1, IDSW 1 -> MOTA = 1 - 3/8 = 0.625
    # MOTP = (0.1 + 0.3 + 0.1 + 0.3 + 0.3 + 0.2 + 0.3) / 7 = 1.6 / 7
    assert (r.gt, r.pred, r.matches, r.fn, r.fp, r.id_switches) == (8, 8, 7, 1, 1, 1)
    assert r.mota == pytest.approx(0.625, abs=1e-12)
    assert r.motp_m == pytest.approx(1.6 / 7, abs=1e-12)
    # A: tracked, tracked, missed, tracked -> one fragmentation; 3/4 = 0.75 -> partly tracked
    # B: 4/4 -> mostly tracked
    assert r.fragmentations == 1
    assert (r.mostly_tracked, r.partly_tracked, r.mostly_lost) == (1, 1, 0)
    # agreeing frames: (A,1)=2, (A,2)=1, (B,3)=4; best one-to-one: A-1 + B-3 = 6
    # IDP = 6/8, IDR = 6/8, IDF1 = 12/16 = 0.75
    assert (r.idtp, r.idfp, r.idfn) == (6, 2, 2)
    assert r.idp == pytest.approx(0.75) and r.idr == pytest.approx(0.75) and r.idf1 == pytest.approx(0.75)
    assert r.pairs.switch.sum() == 1 and int(r.pairs.frame[r.pairs.switch][0]) == 3


def test_hand_worked_per_frame_measures() -> None:
    truth, run = hand_case()
    s = per_frame_measures(truth, run, n_frames=4)
    # same 7 pairs (all within 1 m): d = 0.1 0.3 0.1 0.3 0.3 0.2 0.3
    # MOTME = 1.6/7; mean d^2 = 0.42/7 = 0.06; MOTV = 0.06 - (1.6/7)^2 = 0.0077551...
    assert s.matches == 7
    assert s.motme_m == pytest.approx(1.6 / 7, abs=1e-12)
    assert s.motv_m2 == pytest.approx(0.06 - (1.6 / 7) ** 2, abs=1e-12)
    # one missed person (A, frame 2) and one artifact (9, frame 1) over 4 frames
    assert (s.missed, s.artifacts, s.mtpf, s.atpf) == (1, 1, 0.25, 0.25)
    # empty frames count: the same errors over 8 frames halve the rates
    assert per_frame_measures(truth, run, n_frames=8).mtpf == 0.125


def test_previous_correspondence_is_kept_over_a_cheaper_hungarian_swap() -> None:
    # frame 0: A(0,0)-1(0,0), B(0.6,0)-2(0.6,0)
    # frame 1: 1 at (0.45,0): d(A)=0.45, d(B)=0.15; 2 at (0.2,0): d(A)=0.2, d(B)=0.4
    # fresh Hungarian would swap (0.2 + 0.15 = 0.35 < 0.45 + 0.4 = 0.85): two switches;
    # CLEAR-MOT keeps A-1 and B-2 (both still within 0.5 m): no switch, MOTP = 0.85/4
    truth = table([(f, p, x, 0.0) for f in range(2) for p, x in (("A", 0.0), ("B", 0.6))])
    run = table([(0, "1", 0.0, 0.0), (0, "2", 0.6, 0.0), (1, "1", 0.45, 0.0), (1, "2", 0.2, 0.0)])
    r = clear_mot(truth, run)
    assert r.id_switches == 0
    assert r.motp_m == pytest.approx(0.85 / 4, abs=1e-12)
    # the per-frame measures have no memory: frame 1 is matched fresh, MOTME = (0.2 + 0.15) / 4
    assert per_frame_measures(truth, run).motme_m == pytest.approx(0.35 / 4, abs=1e-12)


def test_correspondence_survives_absence_and_then_switches() -> None:
    # A-1 in frame 0; A absent in frame 1; in frame 2 track 1 is out of reach and 2 takes A: a switch
    truth = table([(0, "A", 0.0, 0.0), (2, "A", 0.0, 0.0)])
    run = table([(0, "1", 0.0, 0.0), (2, "1", 2.0, 0.0), (2, "2", 0.1, 0.0)])
    r = clear_mot(truth, run)
    assert (r.matches, r.id_switches, r.fp, r.fragmentations) == (2, 1, 1, 0)


def test_gate_keeps_most_pairs_then_least_distance() -> None:
    # A(0,0), B(0.8,0); 1 at (0.4,0): 0.4 to both; 2 at (-0.45,0): 0.45 to A, 1.25 to B
    # cheapest single pair is A-1 (0.4) but A-2 + B-1 keeps two pairs within 0.5 m
    truth = table([(0, "A", 0.0, 0.0), (0, "B", 0.8, 0.0)])
    run = table([(0, "1", 0.4, 0.0), (0, "2", -0.45, 0.0)])
    r = clear_mot(truth, run)
    assert (r.matches, r.fn, r.fp) == (2, 0, 0)
    assert r.motp_m == pytest.approx((0.45 + 0.4) / 2)


def test_match_radius_is_inclusive() -> None:
    truth = table([(0, "A", 0.0, 0.0)])
    assert clear_mot(truth, table([(0, "1", 0.5, 0.0)])).matches == 1
    assert clear_mot(truth, table([(0, "1", 0.5001, 0.0)])).matches == 0
    assert per_frame_measures(truth, table([(0, "1", 0.0, 1.0)])).matches == 1
    assert per_frame_measures(truth, table([(0, "1", 0.0, 1.0001)])).matches == 0


def test_mostly_tracked_boundaries_and_absence_is_not_fragmentation() -> None:
    # P present in 5 frames, tracked in 4 (0.8 -> MT); Q tracked 1 of 5 (0.2 -> PT); R never (ML)
    rows, runs = [], []
    for f in range(5):
        rows += [(f, "P", 0.0, 0.0), (f, "Q", 5.0, 0.0), (f, "R", 9.0, 0.0)]
        if f != 4:
            runs.append((f, "p", 0.0, 0.0))
        if f == 2:
            runs.append((f, "q", 5.0, 0.0))
    # S is present in frames 0, 1 and 4, tracked each time: its absence in 2-3 is no fragmentation
    rows += [(f, "S", 2.0, 2.0) for f in (0, 1, 4)]
    runs += [(f, "s", 2.0, 2.0) for f in (0, 1, 4)]
    r = clear_mot(table(rows), table(runs))
    assert (r.mostly_tracked, r.partly_tracked, r.mostly_lost) == (2, 1, 1)
    assert r.fragmentations == 0


def test_empty_inputs_have_undefined_ratios() -> None:
    empty = TrackTable.empty()
    r = clear_mot(empty, empty)
    assert (r.gt, r.pred, r.mota, r.motp_m, r.idf1) == (0, 0, None, None, None)
    only_run = clear_mot(empty, table([(0, "1", 0.0, 0.0)]))
    assert (only_run.fp, only_run.mota, only_run.idp, only_run.idf1) == (1, None, 0.0, 0.0)
    s = per_frame_measures(empty, empty)
    assert (s.frames, s.motme_m, s.mtpf) == (0, None, None)


def test_row_indices_refer_to_the_tables_as_passed() -> None:
    # rows deliberately out of (frame, id) order
    truth = TrackTable(
        frame=np.array([1, 0]), stamp_ns=np.array([NS, 0]), track_id=np.array(["A", "A"]),
        x=np.array([1.0, 0.0]), y=np.zeros(2), z_top=np.full(2, 1.7), posture=np.array(["lying", "standing"]),
    )
    run = table([(0, "1", 0.0, 0.1), (1, "1", 1.0, 0.1)])
    pairs = clear_mot(truth, run).pairs
    for f, t, r in zip(pairs.frame, pairs.truth_row, pairs.run_row):
        assert truth.frame[t] == f and run.frame[r] == f


# ---------------------------------------------------------------- oracle: brute-force matching


def brute_force_pairs(cost: np.ndarray, gate: float) -> tuple[int, float]:
    """(most pairs within the gate, least summed cost among those) by trying every assignment."""
    n, m = cost.shape
    best = (0, 0.0)
    for k in range(min(n, m), 0, -1):
        sums = [
            sum(cost[i, j] for i, j in zip(rows, cols))
            for rows in itertools.combinations(range(n), k)
            for cols in itertools.permutations(range(m), k)
            if all(cost[i, j] <= gate for i, j in zip(rows, cols))
        ]
        if sums:
            return k, min(sums)
    return best


def test_gated_assignment_equals_brute_force() -> None:
    rng = np.random.default_rng(7)
    for _ in range(300):
        n, m = rng.integers(1, 5, size=2)
        cost = rng.uniform(0.0, 1.6, size=(n, m))
        rows, cols = gated_assignment(cost, 1.0)
        k, total = brute_force_pairs(cost, 1.0)
        assert len(rows) == k
        assert cost[rows, cols].sum() == pytest.approx(total, abs=1e-9)
        assert len(set(rows.tolist())) == len(rows) and len(set(cols.tolist())) == len(cols)


# ---------------------------------------------------------------- py-motmetrics cross-check


def random_scene(rng: np.random.Generator, *, n_people: int = 5, n_frames: int = 240) -> tuple[TrackTable, TrackTable]:
    """People walking (some crossing), a run with noise, outliers, misses, new ids, swaps and clutter."""
    truth_rows, run_rows = [], []
    pos = rng.uniform(0.0, 6.0, size=(n_people, 2))
    vel = rng.normal(0.0, 0.04, size=(n_people, 2))
    # two people walk towards each other to force ambiguous frames
    pos[0], pos[1] = (1.0, 3.0), (5.0, 3.2)
    vel[0], vel[1] = (0.03, 0.0), (-0.03, 0.0)
    spans = [(int(rng.integers(0, n_frames // 6)), int(rng.integers(2 * n_frames // 3, n_frames))) for _ in range(n_people)]
    run_of = {p: str(100 + p) for p in range(n_people)}
    next_id = 200
    for f in range(n_frames):
        pos += vel + rng.normal(0.0, 0.01, size=pos.shape)
        if rng.random() < 0.03:  # the run swaps two identities
            a, b = rng.choice(n_people, size=2, replace=False)
            run_of[a], run_of[b] = run_of[b], run_of[a]
        for p in range(n_people):
            lo, hi = spans[p]
            if not lo <= f <= hi:
                continue
            truth_rows.append((f, f"p{p}", pos[p, 0], pos[p, 1]))
            if rng.random() < 0.01:  # the run re-initialises the track under a new id
                run_of[p] = str(next_id)
                next_id += 1
            if rng.random() < 0.08:  # missed
                continue
            noise = rng.normal(0.0, 0.15, size=2) if rng.random() > 0.06 else rng.normal(0.0, 0.6, size=2)
            run_rows.append((f, run_of[p], pos[p, 0] + noise[0], pos[p, 1] + noise[1]))
        if rng.random() < 0.12:  # clutter
            x, y = rng.uniform(0.0, 6.0, size=2)
            run_rows.append((f, str(9000 + f // 25), x, y))
    # ids in the same frame must be unique: keep the first row of any repeat
    seen, unique = set(), []
    for row in run_rows:
        if (row[0], row[1]) not in seen:
            seen.add((row[0], row[1]))
            unique.append(row)
    return table(truth_rows), table(unique)


def motmetrics_summary(truth: TrackTable, run: TrackTable, radius_m: float = 0.5) -> dict:
    """py-motmetrics on the same frames, same order, with linear distances (NaN beyond the radius)."""
    mm = pytest.importorskip("motmetrics", reason="py-motmetrics is a test dependency")
    _, t_codes = np.unique(truth.track_id, return_inverse=True)
    _, r_codes = np.unique(run.track_id, return_inverse=True)
    acc = mm.MOTAccumulator(auto_id=False)
    for f in np.union1d(truth.frame, run.frame):
        ts, rs = truth.frame == f, run.frame == f
        t_xy, r_xy = truth.xy_m[ts], run.xy_m[rs]
        # norm2squared_matrix gives squared distances; take the root so MOTP is in metres
        d2 = mm.distances.norm2squared_matrix(t_xy, r_xy, max_d2=radius_m**2)
        dist = np.sqrt(d2) if d2.size else np.empty((t_xy.shape[0], r_xy.shape[0]))
        acc.update(t_codes[ts], r_codes[rs] + 100_000, dist, frameid=int(f))
    names = ["mota", "motp", "idf1", "idp", "idr", "idtp", "idfp", "idfn", "num_switches", "num_fragmentations",
             "mostly_tracked", "partially_tracked", "mostly_lost", "num_false_positives", "num_misses",
             "num_objects", "num_detections", "num_unique_objects"]
    row = mm.metrics.create().compute(acc, metrics=names, name="run")
    return {k: float(row.loc["run", k]) for k in names}


MINE_VS_MM = {
    "mota": "mota", "motp_m": "motp", "idf1": "idf1", "idp": "idp", "idr": "idr", "idtp": "idtp", "idfp": "idfp",
    "idfn": "idfn", "id_switches": "num_switches", "fragmentations": "num_fragmentations",
    "mostly_tracked": "mostly_tracked", "partly_tracked": "partially_tracked", "mostly_lost": "mostly_lost",
    "fp": "num_false_positives", "fn": "num_misses", "gt": "num_objects", "matches": "num_detections",
    "gt_ids": "num_unique_objects",
}


@pytest.mark.parametrize("seed", range(6))
def test_clear_mot_and_identity_equal_motmetrics(seed: int) -> None:
    truth, run = random_scene(np.random.default_rng(seed))
    mine = clear_mot(truth, run).summary()
    ref = motmetrics_summary(truth, run)
    assert mine["id_switches"] > 0 and mine["fp"] > 0 and mine["fn"] > 0  # the scene exercises every count
    for ours, theirs in MINE_VS_MM.items():
        assert mine[ours] == pytest.approx(ref[theirs], abs=1e-6), ours


def test_hand_case_equals_motmetrics() -> None:
    truth, run = hand_case()
    mine = clear_mot(truth, run).summary()
    ref = motmetrics_summary(truth, run)
    for ours, theirs in MINE_VS_MM.items():
        assert mine[ours] == pytest.approx(ref[theirs], abs=1e-6), ours


def test_suite_totals_equal_motmetrics_overall(tmp_path) -> None:
    mm = pytest.importorskip("motmetrics", reason="py-motmetrics is a test dependency")
    results, accs = [], []
    for seed in (11, 12):
        truth, run = random_scene(np.random.default_rng(seed), n_frames=120)
        io.write_tracks(tmp_path / f"t{seed}" / "truth" / "tracks.csv", truth)
        io.write_tracks(tmp_path / f"r{seed}" / "tracks.csv", run)
        results.append(evaluate(tmp_path / f"t{seed}", tmp_path / f"r{seed}"))
        # re-read so both sides see the 4-decimal positions that were written
        truth = io.read_tracks(tmp_path / f"t{seed}" / "truth" / "tracks.csv")
        run = io.read_tracks(tmp_path / f"r{seed}" / "tracks.csv")
        acc = mm.MOTAccumulator(auto_id=False)
        _, tc = np.unique(truth.track_id, return_inverse=True)
        _, rc = np.unique(run.track_id, return_inverse=True)
        for f in np.union1d(truth.frame, run.frame):
            ts, rs = truth.frame == f, run.frame == f
            d2 = mm.distances.norm2squared_matrix(truth.xy_m[ts], run.xy_m[rs], max_d2=0.25)
            dist = np.sqrt(d2) if d2.size else np.empty((int(ts.sum()), int(rs.sum())))
            acc.update(tc[ts], rc[rs] + 100_000, dist, frameid=int(f))
        accs.append(acc)
    overall = mm.metrics.create().compute_many(
        accs, metrics=["mota", "motp", "idf1", "num_switches"], names=["a", "b"], generate_overall=True
    ).loc["OVERALL"]
    total = suite_totals(results)["tracking"]
    assert total["mota"] == pytest.approx(overall["mota"], abs=1e-6)
    assert total["motp_m"] == pytest.approx(overall["motp"], abs=1e-6)
    assert total["idf1"] == pytest.approx(overall["idf1"], abs=1e-6)
    assert total["id_switches"] == overall["num_switches"]
    # and a total is not the mean of the two ratios
    mean_mota = (results[0]["tracking"]["mota"] + results[1]["tracking"]["mota"]) / 2
    expected = 1 - sum(r["tracking"]["fn"] + r["tracking"]["fp"] + r["tracking"]["id_switches"] for r in results) / sum(
        r["tracking"]["gt"] for r in results
    )
    assert total["mota"] == pytest.approx(expected, abs=1e-12)
    assert not math.isclose(total["mota"], mean_mota, abs_tol=1e-9)


def test_pooled_motv_equals_variance_of_all_distances() -> None:
    a = per_frame_measures(*random_scene(np.random.default_rng(3), n_frames=80))
    b = per_frame_measures(*random_scene(np.random.default_rng(4), n_frames=80))
    fake = [{"tracking": _zero_tracking(), "per_frame": s.summary(), "posture": _zero_posture(), "frames": {"count": 1},
             "duration_s": None} for s in (a, b)]
    pooled = suite_totals(fake)["per_frame"]
    n = a.matches + b.matches
    mean = (a.distance_sum_m + b.distance_sum_m) / n
    var = (a.distance_sq_sum_m2 + b.distance_sq_sum_m2) / n - mean**2
    assert pooled["motme_m"] == pytest.approx(mean, abs=1e-12)
    assert pooled["motv_m2"] == pytest.approx(var, abs=1e-12)


def _zero_tracking() -> dict:
    keys = ["gt", "gt_ids", "pred", "pred_ids", "matches", "fp", "fn", "id_switches", "fragmentations",
            "mostly_tracked", "partly_tracked", "mostly_lost", "distance_sum_m", "idtp", "idfp", "idfn"]
    return {**{k: 0 for k in keys}, "radius_m": 0.5}


def _zero_posture() -> dict:
    return {"pairs": 0, "scored": 0, "strict_correct": 0, "lenient_correct": 0, "labels": list(io.POSTURES),
            "confusion": np.zeros((5, 5), dtype=int).tolist()}


# ---------------------------------------------------------------- posture over matched pairs


def test_posture_strict_lenient_and_confusion() -> None:
    # 6 pairs: standing/standing, bending/standing, sitting/sitting, lying/sitting, standing/unknown,
    # unknown/standing (not scored). scored 5; strict right: 2; lenient also counts bending=standing: 3
    r = posture_from_labels(
        np.array(["standing", "bending", "sitting", "lying", "standing", "unknown"]),
        np.array(["standing", "standing", "sitting", "sitting", "unknown", "standing"]),
    )
    assert (r.pairs, r.scored, r.strict_correct, r.lenient_correct) == (6, 5, 2, 3)
    assert r.strict_accuracy == pytest.approx(0.4) and r.lenient_accuracy == pytest.approx(0.6)
    k = {label: i for i, label in enumerate(r.labels)}
    assert r.confusion[k["bending"], k["standing"]] == 1
    assert r.confusion[k["lying"], k["sitting"]] == 1
    assert r.confusion.sum() == 6
    assert r.recall_by_truth()["standing"] == pytest.approx(0.5)


def test_posture_uses_the_tracking_pairs_only() -> None:
    truth = table([(0, "A", 0.0, 0.0, "lying"), (1, "A", 0.0, 0.0, "lying"), (2, "A", 0.0, 0.0, "lying")])
    # frame 0 right, frame 1 wrong, frame 2 the run is 2 m away: no pair, no posture judgement
    run = table([(0, "1", 0.1, 0.0, "lying"), (1, "1", 0.1, 0.0, "sitting"), (2, "1", 2.0, 0.0, "lying")])
    r = posture_scores(truth, run, clear_mot(truth, run).pairs)
    assert (r.pairs, r.strict_correct) == (2, 1)


def test_false_lying_markers_are_spells_over_two_seconds_on_people_not_lying() -> None:
    # A sits for frames 0..99 and lies on 100..139; B stands throughout, 3 m away. The run reads
    # A lying on 10..49 (40 frames: 39 frame periods, 2.6 s, a false marker), again on 60..69 (0.6 s:
    # too short to count), and from 95 on (95..99 false but short, then right); B lying on 0..30,
    # interrupted at frame 20 by a frame it is 2 m off (no pair there): 0..19 is 1.27 s and 21..30
    # 0.6 s, neither counts.
    truth, run = [], []
    for f in range(140):
        truth.append((f, "A", 0.0, 0.0, "sitting" if f < 100 else "lying"))
        truth.append((f, "B", 3.0, 0.0, "standing"))
        a = "lying" if 10 <= f < 50 or 60 <= f < 70 or f >= 95 else "sitting"
        run.append((f, "1", 0.1, 0.0, a))
        run.append((f, "2", 5.0 if f == 20 else 3.1, 0.0, "lying" if f <= 30 else "standing"))
    truth, run = table(truth), table(run)
    r = posture_scores(truth, run, clear_mot(truth, run).pairs)
    assert r.false_lying_spells == 1
    assert r.false_lying_s == pytest.approx(39 * NS * 1e-9, abs=1e-3)
    assert r.summary()["false_lying_spells"] == 1
