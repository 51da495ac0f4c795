"""voxelwatch: common."""
