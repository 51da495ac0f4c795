"""voxelwatch: fusion_server."""
