"""The data structures and tools every stage shares: the point cloud, coordinate frames and
geodesy, voxel grids, worker processes, the stage cache and the optional extras."""
