"""Gated optimal assignment of tracks to detections (Hungarian method)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from fusion_server.detection import Blob

__all__ = ["associate", "floor_distance_cost"]


def associate(cost: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match tracks (rows) to detections (columns) at least total cost.

    cost: (T, D) float, any unit (the tracker uses metres). NaN and +inf mean
        "cannot match". The caller's array is never modified.
    gate: pairs costing more than this are never matched.

    The gated pairs are given a cost larger than any set of admissible pairs
    can add up to, so the solver first makes as many admissible matches as
    possible and, among those, picks the cheapest; any gated pair it still
    had to use is then dropped.

    Returns ``(matches, unmatched_tracks, unmatched_detections)``:
    matches (K, 2) intp rows ``[track, detection]`` sorted by track;
    unmatched_tracks (T - K,) intp and unmatched_detections (D - K,) intp,
    ascending.
    """
    c = np.array(cost, dtype=np.float64, copy=True)
    if c.ndim != 2:
        raise ValueError(f"cost must be a 2-D (tracks, detections) matrix, got shape {c.shape}")
    if np.isnan(gate) or gate == -np.inf:
        raise ValueError(f"gate must be a number or +inf, got {gate}")
    if np.any(c == -np.inf):
        raise ValueError("cost must not contain -inf")
    n_tracks, n_dets = c.shape
    admissible = np.isfinite(c) & (c <= gate)
    if n_tracks == 0 or n_dets == 0 or not admissible.any():
        return (
            np.zeros((0, 2), dtype=np.intp),
            np.arange(n_tracks, dtype=np.intp),
            np.arange(n_dets, dtype=np.intp),
        )
    valid = c[admissible]
    spread = float(valid.max() - valid.min())
    c[~admissible] = float(valid.max()) + (spread + 1.0) * (min(n_tracks, n_dets) + 1)
    rows, cols = linear_sum_assignment(c)
    keep = admissible[rows, cols]
    matches = np.stack([rows[keep], cols[keep]], axis=1).astype(np.intp)
    unmatched_tracks = np.setdiff1d(np.arange(n_tracks), matches[:, 0]).astype(np.intp)
    unmatched_dets = np.setdiff1d(np.arange(n_dets), matches[:, 1]).astype(np.intp)
    return matches, unmatched_tracks, unmatched_dets


def floor_distance_cost(target_xy: np.ndarray, blobs: Sequence[Blob]) -> np.ndarray:
    """Floor distance from each target to each blob's centroid, the tracker's default cost.

    target_xy: (T, 2) float64 floor positions, world frame, metres.
    blobs: D blobs (their ``x``, ``y`` centroid, world metres).
    Returns (T, D) float64 metres.
    """
    positions = np.asarray(target_xy, dtype=np.float64).reshape(-1, 2)
    blob_xy = np.array([[b.x, b.y] for b in blobs]).reshape(-1, 2)
    return np.linalg.norm(positions[:, None, :] - blob_xy[None, :, :], axis=2)
