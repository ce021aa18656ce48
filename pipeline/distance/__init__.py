"""Layer 7: distance fields on the sparse grid: block FIM kernels, the eikonal solve (also across
bricks), the hierarchical FIM, the HFRep field and its attributes, the C2 spline, the field-quality
report (hfrep seed, steps 2-3)."""
