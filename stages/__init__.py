"""Pipeline stages: one small module per stage mapping config parameters onto library calls.

Each module follows the stage protocol of :mod:`stages.base`: ``Params``, ``REQUIRES``,
``PRODUCES``, ``grids(params)``, ``estimate_bytes(job, params, band)`` and ``run(ctx, params)``.
"""

from stages import components, export, hfrep, voxelise

REGISTRY = {
    "voxelise": voxelise,
    "components": components,
    "hfrep": hfrep,
    "export": export,
}
