"""Model-tree node types; importing this package registers all of them."""

from pipeline.nodes import am, component, expr, gridnode, hfrepnode, mesh, operations, primitives, transforms  # noqa: F401
from pipeline.nodes.base import REGISTRY, Node

__all__ = ["REGISTRY", "Node"]
