"""Graph-cut occupancy: the camera vote smoothed by a Potts prior (seed paper 002, section 2.2).

The labelling ``f`` (1 occupied, 0 empty) of the voxels of a candidate region
minimises

    E(f) = sum_v D_v(f_v) + lambda * sum_{v ~ w} [f_v != f_w]

over 6-neighbour pairs. The data term is the paper's, centred on the vote's
threshold instead of 1/2: only the difference ``D_v(1) - D_v(0)`` matters, and
it is ``2 (c(v) - h(v))`` with the visibility ratio ``h(v) = found / seeing``.
With ``c = 1/2`` that is ``(1 - h) - h``, the paper's eq. 4 with occupied
costing ``1 - h`` (as printed, eq. 4 swaps the two labels), so ``lambda`` keeps
the paper's scale. The centre ``c = (need - 1/2) / seeing`` lies halfway between the last
count the vote rejects and the first it keeps (``need``:
:func:`fusion_server.carving.distance.needed_votes`, which holds ``min_ratio``
and ``min_cameras``), so

* with ``lambda = 0`` the cut labels every voxel exactly as the vote does;
* a voxel one camera short of the vote and one with just enough are equally
  uncertain: with ``min_ratio = 0.75`` and four cameras seeing, 3 of 4 finding
  it is ``+0.25`` and 2 of 4 ``-0.25``. Centring on ``min_ratio`` itself would
  make 3 of 4 (and 6 of 8) a tie that any neighbour decides, whatever ``lambda``;
* the ``min_cameras`` rule stays hard: a voxel fewer cameras find is fixed empty.

A voxel outside the region is fixed empty too, so a region voxel pays
``lambda`` for each in-grid 6-neighbour outside the region when occupied; the
volume's faces cost nothing. What ``lambda`` does, by the arithmetic: an
isolated occupied voxel is removed when ``6 lambda`` exceeds its
``2 (h - c)``; a one-voxel hole inside occupied voxels is filled when
``6 lambda`` exceeds ``2 (c - h)``. The smallest margins are one camera's:
``1 / seeing`` (0.125 with eight cameras seeing, 0.25 with four), so the
paper's ``lambda = 0.01`` (``6 lambda = 0.06``) changes nothing with up to
sixteen cameras; a voxel on a flat face (one empty neighbour, five
occupied) flips only when ``4 lambda`` exceeds its margin.

Energies are integers in units of ``1 / ENERGY_SCALE`` (max-flow needs integer
capacities); a data term never rounds to zero, so ties cannot arise from it.
Most voxels are far from the threshold and are fixed before the cut (see
:func:`_reduced_cut`); the minimum cut of the rest is found with
``scipy.sparse.csgraph.maximum_flow``. PyMaxflow's Boykov-Kolmogorov solver
cuts the same graphs (same energies) several times faster: at ``lambda = 0.1``
0.5 against 4.5 ms a frame set on tuning world 20 (4 cameras, 5 people) and
1.6 against 11.9 ms on world 27 (8 cameras, 7 people), of a fusion stage of
12 and 25 ms. It is not used: it is GPL-licensed, and voxelwatch is Apache-2.0.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

from fusion_server.carving.distance import needed_votes

__all__ = ["ENERGY_SCALE", "benefits", "graphcut_labels", "labelling_energy", "neighbour_pairs", "potts_cut"]

ENERGY_SCALE = 1000
_FIXING_ROUNDS = 6


def benefits(found: np.ndarray, seeing: np.ndarray, *, n_cameras: int, min_cameras: int,
             min_ratio: float) -> np.ndarray:
    """(M,) int64 energy saved by labelling each voxel occupied rather than empty,
    ``2 (found - need + 1/2) / seeing`` in units of ``1 / ENERGY_SCALE`` (``need`` from
    :func:`needed_votes`), at least 1 in magnitude, positive exactly where the hard vote
    keeps the voxel.

    found, seeing: (M,) int camera counts (:func:`fusion_server.carving.distance.tally`).
    n_cameras: the largest possible ``seeing`` (cameras present).
    """
    found = np.asarray(found, dtype=np.int64)
    seeing = np.asarray(seeing, dtype=np.int64)
    need = needed_votes(n_cameras, min_cameras, min_ratio)[seeing].astype(np.int64)
    margin = 2.0 * (found - need + 0.5) / np.maximum(seeing, 1)
    size = np.maximum(1, np.rint(np.abs(margin) * ENERGY_SCALE)).astype(np.int64)
    return np.where(found >= need, size, -size)


def neighbour_pairs(linear: np.ndarray, shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """6-neighbourhood of a region of a grid.

    linear: (M,) int64 distinct linear indices (C order over ``shape``) of the region's voxels.
    Returns ``pairs`` (E, 2) int64 positions in ``linear`` of each neighbouring pair once,
    and ``outside`` (M,) int64: each voxel's in-grid 6-neighbours not in the region.
    """
    linear = np.asarray(linear, dtype=np.int64)
    nx, ny, nz = shape
    where = np.full(nx * ny * nz, -1, dtype=np.int32)  # grid -> position in the region
    where[linear] = np.arange(linear.size, dtype=np.int32)
    i, rest = np.divmod(linear, ny * nz)
    j, k = np.divmod(rest, nz)
    outside = np.zeros(linear.size, dtype=np.int64)
    pairs = []
    for coord, size, step in ((i, nx, ny * nz), (j, ny, nz), (k, nz, 1)):
        for sign in (1, -1):
            src = np.flatnonzero((coord + sign < size) & (coord + sign >= 0))
            dst = where[linear[src] + sign * step]
            outside[src[dst < 0]] += 1
            if sign == 1:
                keep = dst >= 0
                pairs.append(np.stack([src[keep], dst[keep]], axis=1))
    return np.concatenate(pairs).astype(np.int64), outside


def potts_cut(unary: np.ndarray, pairs: np.ndarray, pair_cost: int) -> np.ndarray:
    """Minimum of ``sum_v [f_v = 0] max(u_v, 0) + [f_v = 1] max(-u_v, 0) + pair_cost *
    sum_{(v, w) in pairs} [f_v != f_w]`` over binary labellings: (M,) bool, True = 1.

    unary: (M,) int, the benefit of label 1 (:func:`benefits`, less any fixed neighbours).
    pairs: (E, 2) int positions of neighbouring voxels. pair_cost: int >= 0.
    Where labels tie, the voxel is 0.
    """
    unary = np.asarray(unary, dtype=np.int64)
    m = unary.size
    if m == 0:
        return np.zeros(0, dtype=bool)
    source, sink = m, m + 1
    nodes = np.arange(m)
    up, down = unary > 0, unary < 0
    rows = [np.full(int(up.sum()), source), nodes[down]]
    cols = [nodes[up], np.full(int(down.sum()), sink)]
    caps = [unary[up], -unary[down]]
    if pair_cost > 0 and len(pairs):
        rows += [pairs[:, 0], pairs[:, 1]]
        cols += [pairs[:, 1], pairs[:, 0]]
        caps += [np.full(len(pairs), pair_cost), np.full(len(pairs), pair_cost)]
    rows, cols, caps = np.concatenate(rows), np.concatenate(cols), np.concatenate(caps)
    if caps.size and caps.max() >= 2**31:
        raise ValueError("capacities exceed int32")
    graph = coo_matrix((caps.astype(np.int32), (rows, cols)), shape=(m + 2, m + 2)).tocsr()
    flow = maximum_flow(graph, source, sink, method="dinic").flow
    residual = (graph - flow).tocsr()
    residual.data[residual.data < 0] = 0
    residual.eliminate_zeros()
    reached = breadth_first_order(residual, source, directed=True, return_predecessors=False)
    labels = np.zeros(m + 2, dtype=bool)
    labels[reached] = True
    return labels[:m]


def graphcut_labels(linear: np.ndarray, found: np.ndarray, seeing: np.ndarray, shape: tuple[int, int, int], *,
                    n_cameras: int, min_cameras: int, min_ratio: float, smoothing: float) -> np.ndarray:
    """Occupancy of a candidate region by the graph cut.

    linear: (M,) int64 distinct linear indices of the region's voxels in a grid of ``shape``;
    found, seeing: (M,) their camera counts; smoothing: ``lambda`` >= 0.
    Voxels outside the region, and region voxels fewer than ``min_cameras`` cameras find,
    are fixed empty. Returns (M,) bool, True = occupied.
    """
    linear = np.asarray(linear, dtype=np.int64)
    found = np.asarray(found)
    free = found >= min_cameras
    labels = np.zeros(linear.size, dtype=bool)
    if not free.any():
        return labels
    unary = benefits(found[free], np.asarray(seeing)[free], n_cameras=n_cameras, min_cameras=min_cameras,
                     min_ratio=min_ratio)
    pair_cost = int(round(smoothing * ENERGY_SCALE))
    if pair_cost == 0:
        labels[free] = unary > 0
        return labels
    pairs, outside = neighbour_pairs(linear[free], shape)
    labels[free] = _reduced_cut(unary - pair_cost * outside, pairs, pair_cost)
    return labels


def _reduced_cut(unary: np.ndarray, pairs: np.ndarray, pair_cost: int) -> np.ndarray:
    """:func:`potts_cut` after fixing the voxels whose data term outweighs every neighbour.

    A voxel with ``unary + pull > pair_cost * open_neighbours`` (``pull``: ``+pair_cost``
    per neighbour fixed occupied, ``-pair_cost`` per neighbour fixed empty) is occupied in
    some minimum whatever its open neighbours are, since relabelling it occupied never raises
    the energy; likewise for empty. Fixing such voxels and repeating leaves only the voxels
    near the threshold or near a change of label to cut: most of a person's voxels are far
    from the threshold, so the cut is a small one.
    """
    m = unary.size
    a, b = pairs[:, 0], pairs[:, 1]
    label = np.zeros(m, dtype=np.int64)  # 0 open, 1 fixed occupied, -1 fixed empty
    open_ = np.ones(m, dtype=bool)
    for _ in range(_FIXING_ROUNDS + 1):
        # only pairs with an open end still matter; each round looks at fewer
        open_a, open_b = open_[a], open_[b]
        keep = open_a | open_b
        a, b, open_a, open_b = a[keep], b[keep], open_a[keep], open_b[keep]
        both = open_a & open_b
        only_a, only_b = open_a & ~open_b, open_b & ~open_a
        pull = (np.bincount(a[only_a], weights=label[b[only_a]], minlength=m)
                + np.bincount(b[only_b], weights=label[a[only_b]], minlength=m)).astype(np.int64)
        net = unary + pair_cost * pull
        if _ == _FIXING_ROUNDS:
            break
        degree = np.bincount(a[both], minlength=m) + np.bincount(b[both], minlength=m)
        fix = open_ & (np.abs(net) > pair_cost * degree)
        if not fix.any():
            break
        label[fix] = np.where(net[fix] > 0, 1, -1)
        open_ &= ~fix
    out = label > 0
    if open_.any():
        both = open_[a] & open_[b]
        position = np.cumsum(open_) - 1
        sub = np.stack([position[a[both]], position[b[both]]], axis=1)
        out[open_] = potts_cut(net[open_], sub, pair_cost)
    return out


def labelling_energy(labels: np.ndarray, unary: np.ndarray, pairs: np.ndarray, pair_cost: int) -> np.ndarray:
    """Energies of labellings, the objective of :func:`potts_cut`.

    labels: (..., M) bool; unary: (M,) int; pairs: (E, 2). Returns (...,) int64.
    """
    labels = np.asarray(labels, dtype=bool)
    unary = np.asarray(unary, dtype=np.int64)
    data = np.where(labels, np.maximum(-unary, 0), np.maximum(unary, 0)).sum(axis=-1)
    cut = (labels[..., pairs[:, 0]] != labels[..., pairs[:, 1]]).sum(axis=-1) if len(pairs) else 0
    return data + pair_cost * cut
