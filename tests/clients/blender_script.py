"""Blender script: import the .vdb as a volume object and the .ply/.obj meshes; write a JSON summary.

Usage: blender -b --factory-startup --python blender_script.py -- FILE.vdb FILE.ply FILE.obj RESULT.json
"""

import json
import os
import sys

import bpy
from mathutils import Vector


def world_bounds(ob) -> list:
    ev = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
    corners = [ev.matrix_world @ Vector(c) for c in ev.bound_box]
    return [[min(v[i] for v in corners) for i in range(3)], [max(v[i] for v in corners) for i in range(3)]]


def import_volume(path: str) -> dict:
    bpy.ops.object.volume_import(filepath=path, directory=os.path.dirname(path),
                                 files=[{"name": os.path.basename(path)}])
    ob = bpy.context.active_object
    grids = ob.data.grids
    grids.load()
    listed = {}
    for g in grids:
        g.load()
        listed[g.name] = {"type": g.data_type, "channels": g.channels, "loaded": g.is_loaded}
    return {"object_type": ob.type, "loaded": grids.is_loaded, "error": grids.error_message,
            "grids": listed, "bounds": world_bounds(ob)}


def mesh_summary(ob) -> dict:
    polys = ob.data.polygons
    return {"type": ob.type, "vertices": len(ob.data.vertices), "polygons": len(polys),
            "triangles": sum(1 for p in polys if len(p.vertices) == 3), "bounds": world_bounds(ob)}


def main(vdb_path: str, ply_path: str, obj_path: str, result: str) -> None:
    res = {"version": bpy.app.version_string, "volume": import_volume(vdb_path)}
    bpy.ops.import_mesh.ply(filepath=ply_path)
    res["ply"] = mesh_summary(bpy.context.selected_objects[0])
    bpy.ops.wm.obj_import(filepath=obj_path, forward_axis="Y", up_axis="Z")  # keep the .vdb's world axes
    res["obj"] = mesh_summary(bpy.context.selected_objects[0])
    with open(result, "w") as f:
        json.dump(res, f)


if __name__ == "__main__":
    main(*sys.argv[sys.argv.index("--") + 1:])
