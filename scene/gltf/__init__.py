"""Animated glTF 2.0 (``.glb``) export of a rig driven by a ``params.npz``: Blender, Unity, three.js.

    python -m scene.gltf source=params.npz out=anim.glb [rig=rig.npz] [character=giraffe] [max_influences=8|4]

What the file holds: :mod:`scene.gltf.cli`.  The modules:

- :mod:`scene.gltf.mesh`: the mesh split at UV seams, shape normals, skin influences;
- :mod:`scene.gltf.morphs`: the larynx slide and pose correctives as morph targets;
- :mod:`scene.gltf.clip`: the arrays an export writes (:class:`ExportData`) and their check against the rig;
- :mod:`scene.gltf.document`: the binary glTF file, built in memory once per clip (:func:`build_glb`) and
  written (:func:`write_glb`, :func:`export_glb`), and its report;
- :mod:`scene.gltf.cli`: the command line.  :func:`resolve_rig` is ``scene.characters.resolve_rig``.
"""
from scene.characters import resolve_rig
from scene.gltf.clip import (
    ZERO_DELTA_CM,
    ZERO_NORMAL_DELTA,
    ExportData,
    check_params,
    evaluate_export,
    export_data,
    export_error_cm,
    joint_rotations,
    local_rotations,
    rig_vertices,
)
from scene.gltf.document import (
    SKIN_COLOUR,
    ExportReport,
    Glb,
    build_glb,
    build_gltf,
    export_glb,
    write_glb,
)
from scene.gltf.mesh import (
    INFLUENCE_CHOICES,
    METRES_PER_CM,
    Influences,
    SeamSplit,
    shape_normals,
    skin_influences,
    split_uv_seams,
)
from scene.gltf.morphs import (
    DEFAULT_LARYNX_ERROR_CM,
    MAX_LARYNX_TARGETS,
    LarynxTargets,
    corrective_features,
    corrective_weights,
    hat_weights,
    larynx_region,
    larynx_targets,
)

__all__ = [
    "DEFAULT_LARYNX_ERROR_CM", "INFLUENCE_CHOICES", "MAX_LARYNX_TARGETS", "METRES_PER_CM", "SKIN_COLOUR",
    "ZERO_DELTA_CM", "ZERO_NORMAL_DELTA", "ExportData", "ExportReport", "Glb", "Influences", "LarynxTargets",
    "SeamSplit", "build_glb", "build_gltf", "check_params", "corrective_features", "corrective_weights",
    "evaluate_export", "export_data", "export_error_cm", "export_glb", "hat_weights", "joint_rotations",
    "larynx_region", "larynx_targets", "local_rotations", "resolve_rig", "rig_vertices", "shape_normals",
    "skin_influences", "split_uv_seams", "write_glb",
]
