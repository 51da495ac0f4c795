"""The octree over the voxel grid: which voxels exist on each level, and the descent.

Level ``0`` is the coarsest. A voxel of level ``L`` is a block of
``factor[L]^3`` finest voxels, ``factor[L] = 2 ** (n_levels - 1 - L)``; its
integer indices ``(I, J, K)`` cover finest indices ``[I f, (I + 1) f)`` along
each axis. A level holds only *full* blocks, those lying entirely inside the
finest grid, so ``dims[L] = grid_shape // factor[L]`` per axis.

Where the coarse blocks do not tile the volume (a 2.5 m tall room with 0.4 m
voxels leaves a 0.1 m slab under the ceiling), the border is filled with the
largest finer blocks that fit, as the seed paper does: a block of level ``L``
is a *root* (tested without a parent) when it is full and its parent block on
level ``L - 1`` is not. Roots of all levels plus the descendants of roots
partition the finest grid exactly, so every finest voxel has exactly one
chain of ancestors, and the descent tests each voxel at most once.

Linear index of ``(I, J, K)`` on a level with dims ``(nx, ny, nz)``:
``(I * ny + J) * nz + K`` (C order over X, Y, Z).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["OctreeLayout", "octree_layout", "children", "level_ijk", "descend"]


@dataclass(frozen=True, eq=False)
class OctreeLayout:
    """Levels of the octree over a finest grid of ``grid_shape`` voxels.

    grid_shape: (nx, ny, nz) finest voxels.
    factors: finest voxels per edge of a voxel of each level, coarse to fine (last is 1).
    dims: per level, the number of full blocks along X, Y, Z.
    roots: per level, (R,) int64 sorted linear indices of the level's voxels that have no
        parent block (all of level 0; the border fill on finer levels).
    """

    grid_shape: tuple[int, int, int]
    factors: tuple[int, ...]
    dims: tuple[tuple[int, int, int], ...]
    roots: tuple[np.ndarray, ...]

    @property
    def n_levels(self) -> int:
        return len(self.factors)

    def count(self, level: int) -> int:
        """Number of voxels on ``level``."""
        nx, ny, nz = self.dims[level]
        return nx * ny * nz


def octree_layout(grid_shape: tuple[int, int, int], n_levels: int) -> OctreeLayout:
    """The octree layout for a finest grid of ``grid_shape`` voxels with ``n_levels`` levels."""
    shape = tuple(int(n) for n in grid_shape)
    if len(shape) != 3 or min(shape) <= 0:
        raise ValueError(f"grid_shape must be three positive ints, got {grid_shape!r}")
    if isinstance(n_levels, bool) or not isinstance(n_levels, (int, np.integer)) or n_levels < 1:
        raise ValueError(f"n_levels must be a positive int, got {n_levels!r}")
    factors = tuple(2 ** (n_levels - 1 - level) for level in range(n_levels))
    dims = tuple(tuple(n // f for n in shape) for f in factors)
    roots = []
    for level, (nx, ny, nz) in enumerate(dims):
        if level == 0:
            roots.append(np.arange(nx * ny * nz, dtype=np.int64))
            continue
        px, py, pz = dims[level - 1]
        i = np.arange(nx)[:, None, None] // 2 < px
        j = np.arange(ny)[None, :, None] // 2 < py
        k = np.arange(nz)[None, None, :] // 2 < pz
        has_parent = i & j & k
        roots.append(np.flatnonzero(~has_parent).astype(np.int64))
    return OctreeLayout(grid_shape=shape, factors=factors, dims=dims, roots=tuple(roots))


def children(parent: np.ndarray, parent_dims: tuple[int, int, int], child_dims: tuple[int, int, int]) -> np.ndarray:
    """(M,) linear indices of parents -> (8 M,) linear indices of their children on the next level.

    Children of one parent are consecutive in the output, ordered by (a, b, c) in {0, 1}^3.
    """
    _, py, pz = parent_dims
    _, cy, cz = child_dims
    parent = np.asarray(parent, dtype=np.int64)
    ij, k = np.divmod(parent, pz)
    i, j = np.divmod(ij, py)
    base = ((2 * i) * cy + 2 * j) * cz + 2 * k
    a, b, c = np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")
    offsets = ((a * cy + b) * cz + c).ravel().astype(np.int64)
    return (base[:, None] + offsets[None, :]).ravel()


def level_ijk(index: np.ndarray, dims: tuple[int, int, int]) -> np.ndarray:
    """(M,) linear indices on a level with ``dims`` -> (M, 3) int32 ``(I, J, K)``."""
    _, ny, nz = dims
    ij, k = np.divmod(np.asarray(index, dtype=np.int64), nz)
    i, j = np.divmod(ij, ny)
    out = np.empty((len(k), 3), dtype=np.int32)
    out[:, 0], out[:, 1], out[:, 2] = i, j, k
    return out


def descend(layout: OctreeLayout, test: Callable[[int, np.ndarray], np.ndarray]) -> np.ndarray:
    """The seed paper's Figure 1 over all levels at once.

    test(level, index) -> (M,) bool: whether the voxels ``index`` (M,) int64 of ``level``
    hold foreground. Starting from the level-0 voxels, only voxels that pass are split
    into their 8 children; roots of finer levels join the candidates of their level.
    Returns the (N,) int64 linear indices of the finest voxels that pass.
    """
    kept = np.zeros(0, dtype=np.int64)
    for level in range(layout.n_levels):
        candidates = layout.roots[level]
        if level > 0 and kept.size:
            below = children(kept, layout.dims[level - 1], layout.dims[level])
            candidates = np.concatenate([candidates, below]) if candidates.size else below
        if candidates.size == 0:
            kept = candidates
            continue
        kept = candidates[test(level, candidates)]
    return kept
