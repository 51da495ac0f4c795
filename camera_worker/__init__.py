"""voxelwatch: camera_worker."""
