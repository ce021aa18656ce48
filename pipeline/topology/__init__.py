"""Layer 8: connected components (components seed): Algorithm 1 on an adaptive octree, labelling,
separation, and the same on bricks."""
