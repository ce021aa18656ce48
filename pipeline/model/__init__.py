"""Layer 3: the model tree (node registry, primitives, set operations, transforms, ``expr``, AM
nodes; each node writes its formula once in :mod:`pipeline.model.ops`) and its lowering to one
compiled tape with evaluators for values, affine bounds and gradients (issue 13).

Importing :mod:`pipeline.oracles` registers every node type, this layer's and the oracles'."""
