"""Read an FBX with ufbx (independent of Blender) and print what the tests check as JSON.

    python tests/ufbx_reader.py file.fbx

ufbx 0.0.5's Python binding crashes the interpreter when a proxy object it handed out is freed while the
scene lives (a list indexed twice, an element read and dropped), so every proxy is kept until the process
ends with ``os._exit``, and the tests run this file in a process of its own.
"""
import json
import os
import sys

import ufbx

scene = ufbx.load_file(sys.argv[1])
keep = []
def items(lst):
    got = [lst[i] for i in range(len(lst))]
    keep.append(got)
    return got
settings = scene.settings
axes = settings.axes
out = {"unit_meters": settings.unit_meters, "fps": settings.frames_per_second,
       "axes": [axes.right.name, axes.up.name, axes.front.name]}
out["stacks"] = [[s.name, s.time_begin, s.time_end] for s in items(scene.anim_stacks)]
out["channels"] = [c.name for c in items(scene.blend_channels)]
nodes = [c.bone_node for c in items(scene.skin_clusters)]
keep.append(nodes)
out["clusters"] = [n.name for n in nodes]
meshes = items(scene.meshes)
instances = items(meshes[0].instances)
out["mesh_visible"] = [node.visible for node in instances]
attribute = meshes[0].vertex_position
keep.append(attribute)
values = attribute.values
keep.append(values)
points = items(values)
out["extent"] = [max(getattr(p, a) for p in points) - min(getattr(p, a) for p in points) for a in "xyz"]
print(json.dumps(out), flush=True)
os._exit(0)
