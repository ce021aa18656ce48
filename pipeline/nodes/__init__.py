"""Model-tree node types; importing this package registers all of them."""

from pipeline.nodes import expr, gridnode, mesh, operations, primitives, transforms  # noqa: F401
from pipeline.nodes import component  # noqa: F401  (components seed, section 4.3)
from pipeline.nodes.base import REGISTRY, Node

__all__ = ["REGISTRY", "Node"]
