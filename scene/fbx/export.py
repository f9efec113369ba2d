"""``anim.fbx``: the validated GLB converted by headless Blender into one FBX take.

What the file holds (``blender_side.py`` writes it): the mesh with its UVs, the 8-joint skeleton as
skin clusters, the expressions and the larynx as blend-shape channels named as in the GLB (the larynx as
``larynx_tau+<node>`` targets, see ``scene.gltf``), and one take (named after the clip) in which the
joints' rotations and the channels' weights are keyed at every frame from time 0 at the clip's rate.
Axes: the file's axis setting is y up, the face towards +z (as glTF and the rig); the mesh and the bones
are stored in Blender's z-up frame under the root transform that turns them so (Blender's exporter does
not bake it into the data), which FBX readers apply.  Units
(``fbx_units``): ``cm`` (the FBX unit scale 1 cm; Unreal's and Maya's default) or ``m``.
"""
from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from base.files import atomic_path
from data.params import AnimationParams
from models.rig import HeadNeckModel
from scene.fbx.blender import blender_executable, run_blender
from scene.gltf import DEFAULT_LARYNX_ERROR_CM, build_glb

FBX_UNITS = ("cm", "m")


@dataclass
class FbxReport:
    """What ``export_fbx`` wrote and how long it took."""

    path: Path
    frames: int
    fps: float
    units: str
    seconds: float

    def summary(self) -> str:
        size = self.path.stat().st_size / 1e6
        return (f"{self.path}: FBX, one take of {self.frames} frames at {self.fps:g} fps, units {self.units}, "
                f"{size:.1f} MB in {self.seconds:.1f} s")


def export_fbx(params: AnimationParams, rig: HeadNeckModel, path: str | os.PathLike, units: str = "cm",
               glb: bytes | str | os.PathLike | None = None, take: str = "hackneck", max_influences: int = 8,
               larynx_error_cm: float = DEFAULT_LARYNX_ERROR_CM) -> FbxReport:
    """Write the clip ``params`` on ``rig`` as ``path`` (.fbx, atomically) through Blender.

    Args:
        params, rig: the clip and the rig it drives (as for ``scene.gltf.build_glb``).
        units: ``cm`` or ``m`` (the FBX's unit scale and the numbers it stores).
        glb: the clip's GLB when already built (its bytes, ``scene.gltf.build_glb``, or a written file),
            converted as it is; None: one is built here without morph normals (Blender recomputes normals).
        take: the take's name.
        max_influences, larynx_error_cm: for the GLB built here (``scene.gltf.build_glb``).
    Raises:
        BlenderMissing (an InputError) before anything is written when Blender is not installed.
    """
    if units not in FBX_UNITS:
        raise ValueError(f"fbx_units={units}: expected one of {', '.join(FBX_UNITS)}")
    blender_executable()
    started = time.perf_counter()
    path = Path(path)
    if glb is None:
        glb = build_glb(params, rig, max_influences, larynx_error_cm, check=False, morph_normals=False).raw
    with tempfile.TemporaryDirectory() as folder:
        if isinstance(glb, (bytes, bytearray)):   # Blender reads files: the bytes go to a scratch file
            scratch = Path(folder) / "clip.glb"
            scratch.write_bytes(glb)
            glb = scratch
        with atomic_path(path) as tmp:
            run_blender("convert", str(Path(glb).resolve()), str(tmp.resolve()), repr(float(params.fps)), units,
                        take)
    return FbxReport(path, len(params), float(params.fps), units, time.perf_counter() - started)
