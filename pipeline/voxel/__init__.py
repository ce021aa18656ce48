"""Layer 6: voxelisation: the model (its tape) sampled on the sparse blocks around its surface,
with affine-arithmetic cell culling (voxelise seed)."""
