"""Voxel carving: foreground masks of a frame set -> foreground voxels (seed paper 000, section 2.1).

* :mod:`.octree` - the levels of the octree and the descent;
* :mod:`.lut` - per-camera projection tables with a disk cache;
* :mod:`.distance` - distance images of the masks and the camera vote h(v);
* :mod:`.freespace` - depth cameras' verdicts: free space in front of a measured surface;
* :mod:`.graphcut` - occupancy by a graph cut with a Potts prior (seed paper 002);
* :mod:`.carver` - :class:`Carver`, the octree carve and the dense oracle;
* :mod:`.bench` - synthetic rigs and masks, and :func:`measure_carving`.
"""

from fusion_server.carving.carver import DEFAULT_CACHE_DIR, DEFAULT_VOXEL_SIZES_M, Carver
from fusion_server.carving.distance import DistanceImages, distance_images, needed_votes, observations, tally, vote
from fusion_server.carving.graphcut import graphcut_labels
from fusion_server.carving.lut import CacheReport, CameraLut, compute_lut, load_or_compute_lut, lut_key
from fusion_server.carving.octree import OctreeLayout, children, descend, level_ijk, octree_layout

__all__ = [
    "Carver",
    "DEFAULT_CACHE_DIR",
    "DEFAULT_VOXEL_SIZES_M",
    "DistanceImages",
    "distance_images",
    "vote",
    "observations",
    "tally",
    "needed_votes",
    "graphcut_labels",
    "CacheReport",
    "CameraLut",
    "compute_lut",
    "load_or_compute_lut",
    "lut_key",
    "OctreeLayout",
    "children",
    "descend",
    "level_ijk",
    "octree_layout",
]
