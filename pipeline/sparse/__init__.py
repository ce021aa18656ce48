"""Layer 4: sparse voxel blocks aligned with OpenVDB's leaves (BlockGrid), their conversion to
OpenVDB grids, and the memory of the large block arrays."""
