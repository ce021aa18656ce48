"""Pipeline stages: one small module per stage mapping config parameters onto library calls.

Each module has ``Params`` (pydantic, unknown keys forbidden), optional ``REQUIRES`` (stages
that must run before it) and ``run(ctx, params) -> dict`` (stats for the manifest).
"""

from stages import components, export, hfrep, voxelise

REGISTRY = {
    "voxelise": voxelise,
    "components": components,
    "hfrep": hfrep,
    "export": export,
}
