"""Blender's USD importer as an independent consumer, run by a Python that has the ``bpy`` wheel:

    python tests/blender_usd_reader.py anim.usdc out.npz FRAME [FRAME ...]

Imports the file into an empty scene with the importer's defaults and writes ``vertices`` [F,N,3]: the
evaluated mesh (armature modifier and shape keys, as Blender plays the file) in the mesh object's own
coordinates (the file's units; the importer puts the metre conversion and the y-up to z-up turn on the
objects' transforms), at Blender frames FRAME (the importer maps time code t to frame t), and the shape
keys' slider ranges ``slider_min``/``slider_max`` [K].
"""
import sys

import bpy
import numpy as np


def main(path: str, out: str, frames: list[int]) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if "FINISHED" not in bpy.ops.wm.usd_import(filepath=path):
        raise SystemExit(f"{path}: Blender's USD importer failed")
    mesh = next(o for o in bpy.data.objects if o.type == "MESH")
    scene = bpy.context.scene
    vertices = []
    for frame in frames:
        scene.frame_set(frame)
        evaluated = mesh.evaluated_get(bpy.context.evaluated_depsgraph_get())
        data = evaluated.to_mesh()
        flat = np.zeros(len(data.vertices) * 3)
        data.vertices.foreach_get("co", flat)
        vertices.append(flat.reshape(-1, 3))
        evaluated.to_mesh_clear()
    keys = mesh.data.shape_keys.key_blocks[1:] if mesh.data.shape_keys else []
    np.savez(out, vertices=np.array(vertices), slider_min=np.array([k.slider_min for k in keys]),
             slider_max=np.array([k.slider_max for k in keys]), frame_start=scene.frame_start,
             frame_end=scene.frame_end)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], [int(f) for f in sys.argv[3:]])
