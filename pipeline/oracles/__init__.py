"""Layer 9: nodes whose field is computed by a lower layer rather than by a formula: ``mesh``
(BSP-field or ADF), ``grid`` (a .vdb), ``hfrep`` (a solved HFRep field) and ``component`` (one
separated piece). Importing this package registers every node type, the model's and these."""

from pipeline.model import am, expr, operations, primitives, transforms  # noqa: F401  (registers them)
from pipeline.model.base import REGISTRY, Node
from pipeline.oracles import component, gridnode, hfrepnode, mesh  # noqa: F401  (registers them)

__all__ = ["REGISTRY", "Node"]
