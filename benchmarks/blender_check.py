"""Import an exported GLB into Blender with its animation and compare the deformed mesh with the rig's.

    blender -b --python benchmarks/blender_check.py -- anim.glb params.npz [--frames 0,10,20] [--rig rig.npz]

(Debian: ``apt-get install blender python3-numpy``; the glTF importer needs numpy in Blender's Python.)
Inside Blender the script imports the file (``bpy.ops.import_scene.gltf``, the scene's frame rate set to
the clip's so keyframe k sits on frame k), evaluates the skinned, shape-keyed mesh at each frame of
``--frames`` (default: first, middle, last) and prints the largest and mean vertex distance (cm) from
the rig's own mesh at the same frame.  Blender's Python has no torch, so the rig's mesh is computed by
this file run with the project's Python (``$HACKNECK_PYTHON``, else ``python3`` on the PATH) in
``--reference`` mode, which writes the expected glTF-vertex positions (metres, glTF axes) to an .npz.
Blender turns glTF's y-up into its z-up: Blender (x, y, z) = glTF (x, -z, y).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("glb")
    parser.add_argument("params")
    parser.add_argument("--frames", default=None, help="comma-separated frame indices (default: first, middle, last)")
    parser.add_argument("--rig", default=None, help="rig file overriding the one recorded in params")
    parser.add_argument("--reference", default=None, help="(internal) write the rig's vertices to this .npz")
    return parser.parse_args(argv)


def glb_json(path: str) -> dict:
    """The JSON chunk of a GLB."""
    raw = Path(path).read_bytes()
    length = int.from_bytes(raw[12:16], "little")
    return json.loads(raw[20:20 + length])


# ----------------------------------------------------------------------------- reference (project Python)


def write_reference(args: argparse.Namespace) -> None:
    """The rig's posed mesh at the requested frames, in glTF vertex order, metres."""
    sys.path.insert(0, str(REPO))
    import torch

    from data.params import load_params
    from scene.gltf import METRES_PER_CM, resolve_rig, rig_vertices

    torch.set_num_threads(1)
    params = load_params(args.params)
    rig = resolve_rig(params, args.params, args.rig)
    frames = choose_frames(args.frames, len(params))
    index = np.asarray(glb_json(args.glb)["meshes"][0]["extras"]["rig_vertex_index"])
    vertices = rig_vertices(rig, params, frames)[:, index] * METRES_PER_CM
    with torch.no_grad():
        rest = rig(rig.neutral(1))[0].double().numpy()[index] * METRES_PER_CM
    np.savez(args.reference, frames=frames, times=params.time[frames], fps=params.fps, vertices=vertices, rest=rest)


def choose_frames(spec: str | None, count: int) -> np.ndarray:
    if spec:
        frames = np.array([int(f) for f in spec.split(",")])
        if (frames < 0).any() or (frames >= count).any():
            raise SystemExit(f"--frames {spec}: the clip has frames 0..{count - 1}")
        return frames
    return np.unique([0, count // 2, count - 1])


# ----------------------------------------------------------------------------- Blender side


def blender_check(args: argparse.Namespace) -> None:
    import bpy

    python = os.environ.get("HACKNECK_PYTHON") or shutil.which("python3") or "python"
    with tempfile.TemporaryDirectory() as folder:
        reference = Path(folder) / "reference.npz"
        command = [python, __file__, args.glb, args.params, "--reference", str(reference)]
        command += ["--frames", args.frames] if args.frames else []
        command += ["--rig", args.rig] if args.rig else []
        subprocess.run(command, check=True, cwd=REPO)
        with np.load(reference) as z:
            frames, times, fps, expected, rest = z["frames"], z["times"], float(z["fps"]), z["vertices"], z["rest"]

    # Debian's Blender 3.4 glTF importer (3.4.50) still uses np.bool, which numpy 1.24 (Debian 12's
    # python3-numpy) removed; the alias is the builtin bool, as numpy's own deprecation note says.
    if "bool" not in np.__dict__:
        np.bool = bool
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = int(round(fps)), 1.0
    bpy.ops.import_scene.gltf(filepath=str(Path(args.glb).resolve()))
    meshes = [o for o in scene.objects if o.type == "MESH"]
    armatures = [o for o in scene.objects if o.type == "ARMATURE"]
    if len(meshes) != 1 or len(armatures) != 1:
        raise SystemExit(f"expected one mesh and one armature, got {len(meshes)} and {len(armatures)}")
    mesh, armature = meshes[0], armatures[0]
    # The importer stashes each glTF animation in an NLA track; make the clip the active action.
    for owner in (armature, mesh.data.shape_keys):
        data = owner.animation_data
        if data is not None and data.action is None and data.nla_tracks:
            strips = data.nla_tracks[0].strips
            if strips:
                data.action = strips[0].action
                data.nla_tracks[0].mute = True
    print(f"blender {bpy.app.version_string}; glTF importer "
          f"{'.'.join(map(str, __import__('io_scene_gltf2').bl_info['version']))}; "
          f"{len(mesh.data.vertices)} vertices, {len(mesh.data.shape_keys.key_blocks) - 1} shape keys, "
          f"{len(armature.data.bones)} bones")
    if len(mesh.data.vertices) != expected.shape[1]:
        raise SystemExit(f"Blender has {len(mesh.data.vertices)} vertices, the file {expected.shape[1]}")
    worst = 0.0
    for frame, t, target in zip(frames, times, expected):
        position = t * scene.render.fps / scene.render.fps_base
        scene.frame_set(int(np.floor(position)), subframe=float(position - np.floor(position)))
        evaluated = mesh.evaluated_get(bpy.context.evaluated_depsgraph_get())
        data = evaluated.to_mesh()
        local = np.empty(len(data.vertices) * 3)
        data.vertices.foreach_get("co", local)
        evaluated.to_mesh_clear()
        local = local.reshape(-1, 3)
        matrix = np.array(mesh.matrix_world)
        world = local @ matrix[:3, :3].T + matrix[:3, 3]
        gltf_axes = np.stack([world[:, 0], world[:, 2], -world[:, 1]], axis=1)
        error = np.linalg.norm(gltf_axes - target, axis=1) * 100.0
        worst = max(worst, float(error.max()))
        moved = np.linalg.norm(gltf_axes - rest, axis=1).max() * 100.0
        print(f"frame {int(frame)} (t = {t:.4f} s, Blender frame {position:.2f}): vertex error max "
              f"{error.max():.5f} cm, mean {error.mean():.5f} cm (the mesh is up to {moved:.2f} cm from rest)")
    print(f"max vertex error over {len(frames)} frames: {worst:.5f} cm")


def main() -> None:
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    args = parse(argv)
    if args.reference:
        write_reference(args)
    else:
        blender_check(args)


if __name__ == "__main__":
    main()
