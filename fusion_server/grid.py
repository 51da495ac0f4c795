"""The voxel grid of the monitored volume and what one carve produces.

These types are the contract between carving (``fusion_server.carving``) and
everything downstream (detection, tracking, posture). Pure data: no I/O.

Index convention: a finest-level voxel has integer indices ``(i, j, k)`` along
world X, Y, Z; its centre is ``origin_m + (ijk + 0.5) * voxel_m``. Floor maps
are indexed ``[j, i]`` (rows follow Y, columns follow X) like an image seen
from above with Y growing downward in array order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VoxelGrid:
    """The finest-level grid over the monitored volume.

    origin_m: (3,) float64, world frame, the volume's minimum corner.
    voxel_m: edge of a finest voxel, metres.
    shape: (nx, ny, nz) number of finest voxels along X, Y, Z.
    """

    origin_m: np.ndarray
    voxel_m: float
    shape: tuple[int, int, int]

    @classmethod
    def from_bounds(cls, min_m, max_m, voxel_m: float) -> "VoxelGrid":
        lo = np.asarray(min_m, dtype=np.float64)
        hi = np.asarray(max_m, dtype=np.float64)
        if voxel_m <= 0:
            raise ValueError(f"voxel_m must be positive, got {voxel_m}")
        if np.any(hi <= lo):
            raise ValueError(f"volume max {hi.tolist()} must exceed min {lo.tolist()}")
        n = np.ceil((hi - lo) / voxel_m - 1e-9).astype(int)
        return cls(origin_m=lo, voxel_m=float(voxel_m), shape=(int(n[0]), int(n[1]), int(n[2])))

    def centres(self, ijk: np.ndarray) -> np.ndarray:
        """(N, 3) int indices -> (N, 3) float64 world centres, metres."""
        return self.origin_m + (np.asarray(ijk, dtype=np.float64) + 0.5) * self.voxel_m

    def index_of(self, xyz_m: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 3) int64 indices (not clipped)."""
        return np.floor((np.asarray(xyz_m, dtype=np.float64) - self.origin_m) / self.voxel_m).astype(np.int64)

    def floor_xy(self, ji: np.ndarray) -> np.ndarray:
        """(N, 2) floor cell indices ``(j, i)`` -> (N, 2) world ``(x, y)`` centres."""
        ji = np.asarray(ji, dtype=np.float64)
        return np.stack(
            [self.origin_m[0] + (ji[:, 1] + 0.5) * self.voxel_m, self.origin_m[1] + (ji[:, 0] + 0.5) * self.voxel_m],
            axis=1,
        )


@dataclass(frozen=True)
class FloorMaps:
    """2.5D projection of the foreground voxels onto the floor.

    count: (ny, nx) int32, number of foreground voxels in each column.
    top_m: (ny, nx) float32, height above the floor of the top face of the
        highest foreground voxel in the column, 0 where the column is empty.
    """

    count: np.ndarray
    top_m: np.ndarray


@dataclass(frozen=True)
class CarveResult:
    """The foreground voxels of one frame set.

    ijk: (N, 3) int32 finest-level indices of foreground voxels.
    grid: the grid they index.
    floor: floor maps derived from ``ijk``.
    stamp_ns: capture time of the frame set.
    cameras: ids of the cameras that voted.
    """

    ijk: np.ndarray
    grid: VoxelGrid
    floor: FloorMaps
    stamp_ns: int
    cameras: tuple[str, ...]

    @property
    def centres_m(self) -> np.ndarray:
        """(N, 3) float64 world centres of the foreground voxels."""
        return self.grid.centres(self.ijk)

    def occupancy(self) -> np.ndarray:
        """(nx, ny, nz) bool dense occupancy."""
        occ = np.zeros(self.grid.shape, dtype=bool)
        if len(self.ijk):
            occ[self.ijk[:, 0], self.ijk[:, 1], self.ijk[:, 2]] = True
        return occ


def floor_maps(ijk: np.ndarray, grid: VoxelGrid) -> FloorMaps:
    """Project finest-level voxel indices (N, 3) onto the floor grid."""
    nx, ny, _ = grid.shape
    count = np.zeros((ny, nx), dtype=np.int32)
    top = np.zeros((ny, nx), dtype=np.float32)
    if len(ijk):
        ijk = np.asarray(ijk)
        # Flat column indices: ufunc.at and bincount are an order of magnitude faster on 1-D indices.
        col = ijk[:, 1].astype(np.int64) * nx + ijk[:, 0]
        count = np.bincount(col, minlength=nx * ny).astype(np.int32).reshape(ny, nx)
        np.maximum.at(top.ravel(), col, ((ijk[:, 2] + 1) * grid.voxel_m + grid.origin_m[2]).astype(np.float32))
    return FloorMaps(count=count, top_m=top)
