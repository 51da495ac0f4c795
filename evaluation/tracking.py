"""Tracking measures on the floor plane: CLEAR-MOT, identity (IDF1) and per-frame MOTME/MOTV/MTPF/ATPF.

All positions are ``x``, ``y`` in metres, world frame; a truth person and a
run track can only match when their floor distance is at most the radius
(inclusive). Frames are integers; a frame without rows has nobody in it.

CLEAR-MOT (Bernardin & Stiefelhagen 2008), radius 0.5 m by default:

1. every truth person keeps the run track it was last matched to, if that track
   is present, not yet taken and within the radius (the correspondence survives
   frames in which either side was absent, as in py-motmetrics);
2. the remaining people and tracks are paired by a gated Hungarian assignment
   that first maximises the number of pairs and then minimises their summed
   distance; a pair that contradicts the person's last correspondence is an
   identity switch;
3. people left over are misses (FN), tracks left over are false positives (FP).

MOTA = 1 - (FN + FP + IDSW) / GT, MOTP = mean distance of the matched pairs in
metres (not squared, not an overlap). A fragmentation is a run of misses
between two tracked frames of the same person (frames where the person is
absent do not count). Mostly tracked: matched in >= 80 % of the frames the
person is present; mostly lost: < 20 %; partly tracked in between.

Identity measures (Ristani et al. 2016): a person and a track agree in a frame
when both are present and within the radius; the one-to-one person/track
assignment that maximises the agreeing frames over the whole recording gives
IDTP; IDFN = GT - IDTP, IDFP = predictions - IDTP, IDP = IDTP / predictions,
IDR = IDTP / GT, IDF1 = 2 IDTP / (GT + predictions).

Per-frame measures (the evaluation protocol of the multi-sensor fusion paper in
DESIGN.md: MOTME, MOTV, missed and artifact tracks per frame), radius 1 m: every frame is matched
on its own (no memory) with the same gated Hungarian; MOTME and MOTV are the
mean and the (population) variance of the matched distances, MTPF and ATPF the
unmatched truth people and unmatched run tracks per evaluated frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from evaluation.io import TrackTable

CLEAR_RADIUS_M = 0.5
PER_FRAME_RADIUS_M = 1.0
MOSTLY_TRACKED = 0.8
MOSTLY_LOST = 0.2


@dataclass(frozen=True)
class Matches:
    """Matched truth/run pairs, one row per pair and frame.

    ``frame`` (M,) int64; ``truth_row`` and ``run_row`` (M,) int64 row indices
    into the two :class:`TrackTable` s as they were passed in; ``distance_m`` (M,) float64 floor
    distance in metres; ``switch`` (M,) bool, True where the pair was an
    identity switch.
    """

    frame: np.ndarray
    truth_row: np.ndarray
    run_row: np.ndarray
    distance_m: np.ndarray
    switch: np.ndarray

    def __len__(self) -> int:
        return int(self.frame.shape[0])


@dataclass(frozen=True)
class TrackingResult:
    """CLEAR-MOT and identity counts for one recording; ratios are None when undefined."""

    radius_m: float
    gt: int
    gt_ids: int
    pred: int
    pred_ids: int
    matches: int
    fp: int
    fn: int
    id_switches: int
    fragmentations: int
    mostly_tracked: int
    partly_tracked: int
    mostly_lost: int
    distance_sum_m: float
    idtp: int
    pairs: Matches = field(repr=False)

    @property
    def idfp(self) -> int:
        return self.pred - self.idtp

    @property
    def idfn(self) -> int:
        return self.gt - self.idtp

    @property
    def mota(self) -> float | None:
        return None if self.gt == 0 else 1.0 - (self.fn + self.fp + self.id_switches) / self.gt

    @property
    def motp_m(self) -> float | None:
        return ratio(self.distance_sum_m, self.matches)

    @property
    def idp(self) -> float | None:
        return ratio(self.idtp, self.pred)

    @property
    def idr(self) -> float | None:
        return ratio(self.idtp, self.gt)

    @property
    def idf1(self) -> float | None:
        return ratio(2 * self.idtp, self.gt + self.pred)

    def summary(self) -> dict[str, Any]:
        """Counts and ratios as plain JSON values."""
        return {
            "radius_m": self.radius_m,
            "gt": self.gt,
            "gt_ids": self.gt_ids,
            "pred": self.pred,
            "pred_ids": self.pred_ids,
            "matches": self.matches,
            "fp": self.fp,
            "fn": self.fn,
            "id_switches": self.id_switches,
            "fragmentations": self.fragmentations,
            "mostly_tracked": self.mostly_tracked,
            "partly_tracked": self.partly_tracked,
            "mostly_lost": self.mostly_lost,
            "distance_sum_m": self.distance_sum_m,
            "idtp": self.idtp,
            "idfp": self.idfp,
            "idfn": self.idfn,
            "mota": self.mota,
            "motp_m": self.motp_m,
            "precision": ratio(self.matches, self.pred),
            "recall": ratio(self.matches, self.gt),
            "idp": self.idp,
            "idr": self.idr,
            "idf1": self.idf1,
        }


@dataclass(frozen=True)
class PerFrameResult:
    """MOTME, MOTV, MTPF and ATPF for one recording; ratios are None when undefined."""

    radius_m: float
    frames: int
    matches: int
    missed: int
    artifacts: int
    distance_sum_m: float
    distance_sq_sum_m2: float
    motme_m: float | None
    motv_m2: float | None

    @property
    def mtpf(self) -> float | None:
        return ratio(self.missed, self.frames)

    @property
    def atpf(self) -> float | None:
        return ratio(self.artifacts, self.frames)

    def summary(self) -> dict[str, Any]:
        return {
            "radius_m": self.radius_m,
            "frames": self.frames,
            "matches": self.matches,
            "missed": self.missed,
            "artifacts": self.artifacts,
            "distance_sum_m": self.distance_sum_m,
            "distance_sq_sum_m2": self.distance_sq_sum_m2,
            "motme_m": self.motme_m,
            "motv_m2": self.motv_m2,
            "mtpf": self.mtpf,
            "atpf": self.atpf,
        }


def clear_mot(truth: TrackTable, run: TrackTable, *, radius_m: float = CLEAR_RADIUS_M) -> TrackingResult:
    """CLEAR-MOT and identity measures of ``run`` against ``truth`` (see the module text).

    Frames are visited in increasing order; within a frame, people and tracks
    are taken in the tables' (frame, id) order.
    """
    radius_m = _radius(radius_m)
    t_order, r_order = truth.sort_order(), run.sort_order()
    truth, run = truth.take(t_order), run.take(r_order)
    t_codes, t_names = _codes(truth.track_id)
    r_codes, r_names = _codes(run.track_id)
    t_xy, r_xy = truth.xy_m, run.xy_m
    n_t = len(t_names)

    last_match = np.full(n_t, -1, dtype=np.int64)  # run code of each person's last correspondence
    present = np.zeros(n_t, dtype=np.int64)
    tracked = np.zeros(n_t, dtype=np.int64)
    seen_tracked = np.zeros(n_t, dtype=bool)
    pending_miss = np.zeros(n_t, dtype=bool)
    fragmentations = 0
    agree: dict[tuple[int, int], int] = {}
    out: list[tuple[int, int, int, float, bool]] = []  # frame, truth row, run row, distance, switch

    for frame, ts, rs in _frames(truth, run):
        oc = t_codes[ts]
        hc = r_codes[rs]
        present[oc] += 1
        o_done = np.zeros(oc.shape[0], dtype=bool)
        if oc.size and hc.size:
            dist = _distances(t_xy[ts], r_xy[rs])
            ok = dist <= radius_m
            for i, j in zip(*np.nonzero(ok)):
                key = (int(oc[i]), int(hc[j]))
                agree[key] = agree.get(key, 0) + 1
            h_done = np.zeros(hc.shape[0], dtype=bool)
            # 1. keep last correspondences that are still within the radius
            for i in range(oc.shape[0]):
                prev = last_match[oc[i]]
                if prev < 0:
                    continue
                js = np.nonzero((hc == prev) & ~h_done)[0]
                if js.size and ok[i, js[0]]:
                    j = int(js[0])
                    o_done[i] = h_done[j] = True
                    out.append((frame, ts.start + i, rs.start + j, float(dist[i, j]), False))
            # 2. Hungarian for the rest
            free_o = np.nonzero(~o_done)[0]
            free_h = np.nonzero(~h_done)[0]
            if free_o.size and free_h.size:
                sub = dist[np.ix_(free_o, free_h)]
                for a, b in zip(*gated_assignment(sub, radius_m)):
                    i, j = int(free_o[a]), int(free_h[b])
                    o, h = int(oc[i]), int(hc[j])
                    is_switch = last_match[o] >= 0 and last_match[o] != h
                    last_match[o] = h
                    o_done[i] = h_done[j] = True
                    out.append((frame, ts.start + i, rs.start + j, float(sub[a, b]), bool(is_switch)))
        # per-person bookkeeping for MT/PT/ML and fragmentations
        for i in range(oc.shape[0]):
            o = oc[i]
            if o_done[i]:
                tracked[o] += 1
                if pending_miss[o]:
                    fragmentations += 1
                    pending_miss[o] = False
                seen_tracked[o] = True
            elif seen_tracked[o]:
                pending_miss[o] = True

    cols = list(zip(*out)) if out else [(), (), (), (), ()]
    pairs = Matches(
        frame=np.asarray(cols[0], dtype=np.int64),
        truth_row=t_order[np.asarray(cols[1], dtype=np.int64)],
        run_row=r_order[np.asarray(cols[2], dtype=np.int64)],
        distance_m=np.asarray(cols[3], dtype=np.float64),
        switch=np.asarray(cols[4], dtype=bool),
    )
    ratios = np.divide(tracked, present, out=np.zeros(n_t), where=present > 0)
    n_matches = len(pairs)
    return TrackingResult(
        radius_m=radius_m,
        gt=len(truth),
        gt_ids=n_t,
        pred=len(run),
        pred_ids=len(r_names),
        matches=n_matches,
        fp=len(run) - n_matches,
        fn=len(truth) - n_matches,
        id_switches=int(pairs.switch.sum()),
        fragmentations=fragmentations,
        mostly_tracked=int(np.count_nonzero(ratios >= MOSTLY_TRACKED)),
        partly_tracked=int(np.count_nonzero((ratios >= MOSTLY_LOST) & (ratios < MOSTLY_TRACKED))),
        mostly_lost=int(np.count_nonzero(ratios < MOSTLY_LOST)),
        distance_sum_m=float(pairs.distance_m.sum()),
        idtp=identity_true_positives(agree),
        pairs=pairs,
    )


def per_frame_measures(
    truth: TrackTable, run: TrackTable, *, radius_m: float = PER_FRAME_RADIUS_M, n_frames: int | None = None
) -> PerFrameResult:
    """MOTME, MOTV, missed and artifact tracks per frame (see the module text).

    ``n_frames`` is the number of evaluated frames (empty frames included);
    default: every frame from the first to the last frame with a row.
    """
    radius_m = _radius(radius_m)
    truth, run = truth.sorted(), run.sorted()
    if n_frames is None:
        first, last = frame_span(truth, run)
        n_frames = 0 if first is None else last - first + 1
    if n_frames < 0:
        raise ValueError(f"n_frames must be >= 0, got {n_frames}")
    t_xy, r_xy = truth.xy_m, run.xy_m
    dists: list[np.ndarray] = []
    for _frame, ts, rs in _frames(truth, run):
        if ts.stop > ts.start and rs.stop > rs.start:
            dist = _distances(t_xy[ts], r_xy[rs])
            rows, cols = gated_assignment(dist, radius_m)
            dists.append(dist[rows, cols])
    d = np.concatenate(dists) if dists else np.zeros(0)
    n = int(d.size)
    return PerFrameResult(
        radius_m=radius_m,
        frames=int(n_frames),
        matches=n,
        missed=len(truth) - n,
        artifacts=len(run) - n,
        distance_sum_m=float(d.sum()),
        distance_sq_sum_m2=float(np.square(d).sum()),
        motme_m=float(d.mean()) if n else None,
        motv_m2=float(d.var()) if n else None,
    )


PEOPLE_BANDS = ((0, 0), (1, 1), (2, 3), (4, 7), (8, 12), (13, None))
"""People present per frame, in bands for :func:`by_people_present` (None: no upper bound)."""


def by_people_present(
    truth: TrackTable, run: TrackTable, pairs: Matches, first: int | None, last: int | None,
    bands=PEOPLE_BANDS,
) -> dict[str, dict[str, Any]]:
    """CLEAR-MOT counts of the frames ``first..last``, split by how many people the truth has in each
    frame (``bands`` of (low, high) inclusive), with the frames whose run counts as many people as
    the truth (``count_exact``). ``pairs``: the matches of :func:`clear_mot` on the same tables.

    Returns band label ('0', '1', '2-3', ..., '13+') -> frames, gt, pred, matches, fp, fn,
    id_switches, distance_sum_m, count_exact, and the ratios mota, motp_m, count_exact_ratio.
    Bands without frames are left out.
    """
    if first is None or last is None:
        return {}
    n = last - first + 1
    gt = np.bincount(truth.frame - first, minlength=n)[:n] if len(truth) else np.zeros(n, dtype=np.int64)
    pred = np.bincount(run.frame - first, minlength=n)[:n] if len(run) else np.zeros(n, dtype=np.int64)
    matched = np.bincount(pairs.frame - first, minlength=n)[:n] if len(pairs) else np.zeros(n, dtype=np.int64)
    switches = (np.bincount(pairs.frame - first, weights=pairs.switch.astype(float), minlength=n)[:n]
                if len(pairs) else np.zeros(n))
    dist = (np.bincount(pairs.frame - first, weights=pairs.distance_m, minlength=n)[:n]
            if len(pairs) else np.zeros(n))
    out: dict[str, dict[str, Any]] = {}
    for lo, hi in bands:
        sel = (gt >= lo) & (gt <= (hi if hi is not None else np.iinfo(np.int64).max))
        if not sel.any():
            continue
        label = f"{lo}" if hi == lo else (f"{lo}+" if hi is None else f"{lo}-{hi}")
        out[label] = band_summary({
            "frames": int(sel.sum()), "gt": int(gt[sel].sum()), "pred": int(pred[sel].sum()),
            "matches": int(matched[sel].sum()), "id_switches": int(round(switches[sel].sum())),
            "distance_sum_m": float(dist[sel].sum()), "count_exact": int(np.count_nonzero(gt[sel] == pred[sel])),
        })
    return out


def band_summary(c: dict[str, Any]) -> dict[str, Any]:
    """The counts of one band of :func:`by_people_present` with fp, fn and the ratios added."""
    fp, fn = c["pred"] - c["matches"], c["gt"] - c["matches"]
    return {
        **c, "fp": fp, "fn": fn,
        "mota": None if c["gt"] == 0 else 1.0 - (fn + fp + c["id_switches"]) / c["gt"],
        "motp_m": ratio(c["distance_sum_m"], c["matches"]),
        "count_exact_ratio": ratio(c["count_exact"], c["frames"]),
    }


def gated_assignment(cost: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(rows, cols)`` with ``cost <= gate``: as many pairs as possible, then the least summed cost.

    ``cost`` (N, M) float, NaN or inf meaning never pair. Pairs above the gate
    are replaced by one cost so large that taking it can never pay, solved with
    scipy's Hungarian solver, and dropped afterwards.
    """
    cost = np.asarray(cost, dtype=np.float64)
    valid = np.isfinite(cost) & (cost <= gate)
    if not valid.any():
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if cost.shape == (1, 1):
        return np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64)
    # one forbidden pair must cost more than any max-cardinality set of allowed ones
    big = 2.0 * min(cost.shape) * (float(np.abs(cost[valid]).max()) + 1.0) + 1.0
    rows, cols = linear_sum_assignment(np.where(valid, cost, big))
    keep = valid[rows, cols]
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64)


def identity_true_positives(agree: dict[tuple[int, int], int]) -> int:
    """IDTP: the most agreeing frames any one-to-one person/track assignment collects.

    ``agree[(person, track)]`` is the number of frames in which the two were
    within the radius. Minimising IDFN + IDFP over assignments, as Ristani et
    al. state it, is the same as maximising the summed agreement.
    """
    if not agree:
        return 0
    people = sorted({o for o, _ in agree})
    tracks = sorted({h for _, h in agree})
    p_idx = {o: i for i, o in enumerate(people)}
    t_idx = {h: j for j, h in enumerate(tracks)}
    weight = np.zeros((len(people), len(tracks)), dtype=np.float64)
    for (o, h), n in agree.items():
        weight[p_idx[o], t_idx[h]] = n
    rows, cols = linear_sum_assignment(weight, maximize=True)
    return int(round(weight[rows, cols].sum()))


def frame_span(*tables: TrackTable) -> tuple[int | None, int | None]:
    """First and last frame with a row in any table; (None, None) when all are empty."""
    firsts = [int(t.frame.min()) for t in tables if len(t)]
    lasts = [int(t.frame.max()) for t in tables if len(t)]
    return (min(firsts), max(lasts)) if firsts else (None, None)


def ratio(num: float, den: float) -> float | None:
    """``num / den`` as a float, None when ``den`` is 0."""
    return None if den == 0 else float(num) / float(den)


# ---------------------------------------------------------------- helpers


def _radius(radius_m: float) -> float:
    radius_m = float(radius_m)
    if not (np.isfinite(radius_m) and radius_m > 0):
        raise ValueError(f"radius_m must be a positive number of metres, got {radius_m}")
    return radius_m


def _codes(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    names, codes = np.unique(ids, return_inverse=True)
    return codes.astype(np.int64).reshape(-1), names


def _distances(a_xy: np.ndarray, b_xy: np.ndarray) -> np.ndarray:
    """(N, M) float64 Euclidean floor distances between (N, 2) and (M, 2) points, metres."""
    return np.sqrt(np.square(a_xy[:, None, :] - b_xy[None, :, :]).sum(axis=-1))


def _frames(truth: TrackTable, run: TrackTable):
    """Yield ``(frame, truth_slice, run_slice)`` for every frame with a row in either sorted table."""
    frames = np.union1d(truth.frame, run.frame)
    t_lo = np.searchsorted(truth.frame, frames, side="left")
    t_hi = np.searchsorted(truth.frame, frames, side="right")
    r_lo = np.searchsorted(run.frame, frames, side="left")
    r_hi = np.searchsorted(run.frame, frames, side="right")
    for k in range(frames.shape[0]):
        yield int(frames[k]), slice(int(t_lo[k]), int(t_hi[k])), slice(int(r_lo[k]), int(r_hi[k]))
