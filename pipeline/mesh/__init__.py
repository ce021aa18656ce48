"""Layer 2: polygon meshes as fields: loading and checking, the compiled BSP-tree build, BSP-fields
(bsp-fields seed, section 3) with their exact min_max kernels, and approximate distance fields."""
