"""Blender's half of the FBX tools: run inside Blender's own Python, never imported by the project.

    blender -b --factory-startup --python scene/fbx/blender_side.py -- convert in.glb out.fbx FPS UNITS TAKE
    blender -b --factory-startup --python scene/fbx/blender_side.py -- sample in.fbx|in.glb out.npz FPS FRAMES

``convert`` imports the project's GLB and writes one FBX take holding the skeleton's and the shape keys'
animation together (Blender's glTF importer gives each its own action and an NLA strip that starts at
frame 1; the strips are dropped and the actions played from frame 0, so the take's keys start at time 0:
Blender's FBX importer shifts a take that starts at frame 1 by one frame).  Every frame is keyed
(no curve simplification).  ``UNITS``: ``cm`` writes centimetres with the file's unit scale 1 cm (Unreal,
Maya); ``m`` writes metres with the file's unit scale 1 m.  Axes: y up, the face towards +z, as glTF.

``sample`` imports a GLB or FBX and writes the skinned, shape-keyed mesh at each frame index of
``FRAMES`` (comma-separated; frame k at time k / FPS) to an .npz: ``vertices [F,V,3]`` in Blender's world
(metres, z up), for the project's tests and benchmarks to compare with the rig (``tests/blender_sampling.py``).

Blender's Python has numpy but not the project's packages, so this file imports nothing of the project.
"""
import sys
from pathlib import Path

import numpy as np

# Debian's Blender 3.4 glTF importer still uses np.bool, which numpy 1.24 removed; the alias is the
# builtin bool, as numpy's own deprecation note says.
if "bool" not in np.__dict__:
    np.bool = bool

import bpy  # noqa: E402  (after the alias the importer needs)


def fresh_scene(fps: float) -> bpy.types.Scene:
    """An empty scene at ``fps`` (integer rates exactly; others through ``fps_base``)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    rounded = max(1, int(round(fps)))
    scene.render.fps, scene.render.fps_base = rounded, rounded / fps
    return scene


def the_rig(scene: bpy.types.Scene) -> tuple:
    """The scene's one mesh and one armature (SystemExit naming what was found otherwise)."""
    meshes = [o for o in scene.objects if o.type == "MESH"]
    armatures = [o for o in scene.objects if o.type == "ARMATURE"]
    if len(meshes) != 1 or len(armatures) != 1:
        raise SystemExit(f"expected one mesh and one armature, found {len(meshes)} and {len(armatures)}")
    return meshes[0], armatures[0]


def play_actions_from_zero(owners) -> int:
    """Make each owner's clip its active action with no NLA strips; the last keyed frame."""
    last = 0
    for owner in owners:
        data = owner.animation_data if owner is not None else None
        if data is None:
            continue
        if data.action is None and data.nla_tracks and data.nla_tracks[0].strips:
            data.action = data.nla_tracks[0].strips[0].action
        for track in list(data.nla_tracks):
            data.nla_tracks.remove(track)
        if data.action is not None:
            last = max(last, int(round(data.action.frame_range[1])))
    return last


def scale_to_centimetres(scene: bpy.types.Scene, armature, mesh) -> None:
    """Scale the rig by 100 into its data (bones, vertices, shape keys) and make the scene's unit 1 cm,
    so the FBX stores centimetres with unit scale 1 and no object scale (the glTF holds metres)."""
    armature.scale = (100.0, 100.0, 100.0)
    bpy.ops.object.select_all(action="DESELECT")
    armature.select_set(True)
    mesh.select_set(True)
    bpy.context.view_layer.objects.active = armature
    bpy.ops.object.transform_apply(location=False, rotation=False, scale=True)
    scene.unit_settings.scale_length = 0.01


def widen_sliders(mesh) -> None:
    """Let each shape key take the weights its animation holds: Blender clamps a key's value to its
    slider range, [0, 1] after either importer, and the larynx targets' weight ``eta * hat(tau)`` exceeds
    1 for a larynx larger than the generic one (Blender allows -10 .. 10)."""
    keys = mesh.data.shape_keys
    if keys is None:
        return
    action = keys.animation_data.action if keys.animation_data else None
    for curve in (action.fcurves if action else []):
        block = keys.path_resolve(curve.data_path.rsplit(".", 1)[0])
        values = [point.co[1] for point in curve.keyframe_points]
        block.slider_min = max(-10.0, min([0.0, *values]))
        block.slider_max = min(10.0, max([1.0, *values]))


def bake_keys_without_the_mesh(scene, mesh) -> None:
    """Spare the exporter's bake the deformed mesh (about 20 ms a frame on HACK's 14k vertices): it steps
    through every frame only to read the bones' transforms and the shape keys' values, but the depsgraph
    re-evaluates the whole mesh each time.  The mesh leaves the viewport (and so the depsgraph; the file
    still marks it visible), and a frame handler sets each key's value from its own animation curve, which
    is what the depsgraph would have done.  The mesh itself is written undeformed either way
    (``use_mesh_modifiers=False``)."""
    keys = mesh.data.shape_keys
    if keys is None or keys.animation_data is None or keys.animation_data.action is None:
        return
    curves = [(keys.path_resolve(curve.data_path.rsplit(".", 1)[0]), curve)
              for curve in keys.animation_data.action.fcurves]

    def set_key_values(scene, *_):
        frame = scene.frame_current + scene.frame_subframe
        for block, curve in curves:
            block.value = curve.evaluate(frame)

    bpy.app.handlers.frame_change_pre.append(set_key_values)
    mesh.hide_viewport = True
    # The exporter writes an object's Visibility from hide_viewport; the mesh is to be visible in the file.
    from io_scene_fbx import fbx_utils

    hidden = fbx_utils.ObjectWrapper.hide
    fbx_utils.ObjectWrapper.hide = property(
        lambda wrapper: False if wrapper.bdata == mesh else hidden.fget(wrapper))


def convert(glb: str, fbx: str, fps: float, units: str, take: str) -> None:
    scene = fresh_scene(fps)
    bpy.ops.import_scene.gltf(filepath=str(Path(glb).resolve()))
    mesh, armature = the_rig(scene)
    last = play_actions_from_zero([armature, mesh.data.shape_keys])
    widen_sliders(mesh)
    scene.frame_start, scene.frame_end = 0, last
    if units == "cm":  # the data itself in centimetres, one Blender unit = 1 cm, no scale on the objects
        scale_to_centimetres(scene, armature, mesh)
    scene.name = take  # the take's name in the FBX
    bake_keys_without_the_mesh(scene, mesh)
    bpy.ops.export_scene.fbx(
        filepath=str(Path(fbx).resolve()), check_existing=False, use_selection=False,
        object_types={"ARMATURE", "MESH"}, use_mesh_modifiers=False, mesh_smooth_type="OFF",
        add_leaf_bones=False, use_armature_deform_only=False, armature_nodetype="NULL",
        primary_bone_axis="Y", secondary_bone_axis="X",
        axis_forward="-Z", axis_up="Y", global_scale=1.0, apply_unit_scale=True,
        apply_scale_options="FBX_SCALE_NONE" if units == "cm" else "FBX_SCALE_UNITS",
        bake_anim=True, bake_anim_use_all_bones=True, bake_anim_use_nla_strips=False,
        bake_anim_use_all_actions=False, bake_anim_force_startend_keying=True, bake_anim_step=1.0,
        bake_anim_simplify_factor=0.0, path_mode="STRIP")
    print(f"fbx: {fbx}: frames 0..{last} at {fps:g} fps, units {units}")


def sample(path: str, out: str, fps: float, frames: list[int]) -> None:
    scene = fresh_scene(fps)
    if path.lower().endswith(".fbx"):
        bpy.ops.import_scene.fbx(filepath=str(Path(path).resolve()), anim_offset=0.0)
    else:
        bpy.ops.import_scene.gltf(filepath=str(Path(path).resolve()))
    mesh, armature = the_rig(scene)
    play_actions_from_zero([armature, mesh.data.shape_keys])
    widen_sliders(mesh)
    vertices = []
    for frame in frames:
        scene.frame_set(frame)
        evaluated = mesh.evaluated_get(bpy.context.evaluated_depsgraph_get())
        data = evaluated.to_mesh()
        local = np.empty(len(data.vertices) * 3)
        data.vertices.foreach_get("co", local)
        evaluated.to_mesh_clear()
        matrix = np.array(mesh.matrix_world)
        vertices.append(local.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3])
    keys = mesh.data.shape_keys
    np.savez(out, vertices=np.asarray(vertices), frames=np.asarray(frames),
             shape_keys=np.asarray([k.name for k in keys.key_blocks[1:]] if keys else []),
             bones=np.asarray([b.name for b in armature.data.bones]))


def main() -> None:
    argv = sys.argv[sys.argv.index("--") + 1:]
    if argv[0] == "convert":
        convert(argv[1], argv[2], float(argv[3]), argv[4], argv[5])
    elif argv[0] == "sample":
        sample(argv[1], argv[2], float(argv[3]), [int(f) for f in argv[4].split(",")])
    else:
        raise SystemExit(f"{argv[0]}: expected convert or sample")


main()
