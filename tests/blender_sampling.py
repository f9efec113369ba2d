"""Blender as an evaluator, for the tests and benchmarks that compare an exported GLB or FBX with the rig
(``tests/test_fbx.py``, ``benchmarks/blender_check.py``): Blender imports the file with its animation and
gives the skinned, shape-keyed mesh at chosen frames (the ``sample`` half of ``scene/fbx/blender_side.py``,
which shares the exporter's import and playback steps)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from scene.fbx.blender import run_blender


def blender_vertices(path: str | os.PathLike, fps: float, frames) -> dict:
    """The skinned, shape-keyed mesh Blender makes of the GLB or FBX at ``path`` at each of ``frames``
    (frame k at time k / fps): ``vertices [F,V,3]`` in Blender's world (metres, z up), ``shape_keys``,
    ``bones``."""
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "sample.npz"
        run_blender("sample", str(Path(path).resolve()), str(out), repr(float(fps)),
                    ",".join(str(int(f)) for f in frames), purpose=f"sampling {path}")
        with np.load(out) as z:
            return {key: z[key] for key in z.files}
