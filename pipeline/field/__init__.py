"""Layer 1: field arithmetic without a model: revised affine forms (bounds over boxes), the R-functions
(set operations on FRep fields, on arrays and as compiled kernels) and the small LP of the BSP
special cases."""
