"""Import an exported GLB or FBX into Blender with its animation and compare the mesh with the rig's.

    python benchmarks/blender_check.py anim.glb|anim.fbx params.npz [--frames 0,10,20|all] [--rig rig.npz]

Blender (``scene.fbx.blender``: ``$BLENDER`` or ``blender`` on the PATH, with numpy in its Python; Debian:
``apt-get install blender python3-numpy``) imports the file in the background, plays its animation from
frame 0 at the clip's rate and evaluates the skinned, shape-keyed mesh at each frame of ``--frames``
(default: first, middle, last; ``all``: every frame).  This prints the largest and mean vertex distance
(cm) from the rig's own mesh at the same frames (a fitted person's: with the params' ``shape_offset``),
after Blender's axes (z up) are turned back into the rig's (y up): Blender (x, y, z) = rig (x, -z, y), in
metres.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.params import load_params  # noqa: E402
from scene.characters import person_rig, resolve_rig  # noqa: E402
from scene.gltf import METRES_PER_CM, rig_vertices  # noqa: E402
from scene.gltf.mesh import split_uv_seams  # noqa: E402
from tests.blender_sampling import blender_vertices  # noqa: E402


def choose_frames(spec: str | None, count: int) -> np.ndarray:
    if spec == "all":
        return np.arange(count)
    if spec:
        frames = np.array([int(f) for f in spec.split(",")])
        if (frames < 0).any() or (frames >= count).any():
            raise SystemExit(f"--frames {spec}: the clip has frames 0..{count - 1}")
        return frames
    return np.unique([0, count // 2, count - 1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file", help="anim.glb or anim.fbx")
    parser.add_argument("params")
    parser.add_argument("--frames", default=None, help="comma-separated frame indices, or all (default: first, "
                                                       "middle, last)")
    parser.add_argument("--rig", default=None, help="rig file overriding the one recorded in params")
    args = parser.parse_args()
    params = load_params(args.params)
    rig = person_rig(resolve_rig(params, args.params, args.rig), params, args.params)   # a fit's shape_offset
    frames = choose_frames(args.frames, len(params))
    index = split_uv_seams(rig).rig_index          # Blender keeps the GLB's (and so the FBX's) vertex order
    expected = rig_vertices(rig, params, frames)[:, index] * METRES_PER_CM
    rest = rig_vertices(rig, params, frames[:1])[0, index] * METRES_PER_CM
    got = blender_vertices(args.file, params.fps, frames)
    vertices = got["vertices"]
    print(f"{args.file}: {vertices.shape[1]} vertices, {len(got['shape_keys'])} shape keys, {len(got['bones'])} bones")
    if vertices.shape[1] != expected.shape[1]:
        raise SystemExit(f"Blender has {vertices.shape[1]} vertices, the rig's GLB layout {expected.shape[1]}")
    rig_axes = np.stack([vertices[..., 0], vertices[..., 2], -vertices[..., 1]], axis=-1)
    error = np.linalg.norm(rig_axes - expected, axis=-1) / METRES_PER_CM
    moved = np.linalg.norm(expected - rest, axis=-1).max() / METRES_PER_CM
    for frame, row in zip(frames, error):
        print(f"frame {int(frame)} (t = {params.time[frame]:.4f} s): vertex error max {row.max():.5f} cm, "
              f"mean {row.mean():.5f} cm")
    print(f"max vertex error over {len(frames)} frames: {error.max():.5f} cm (the mesh moves up to {moved:.2f} cm "
          f"from frame {int(frames[0])})")


if __name__ == "__main__":
    main()
