"""Retarget head-and-neck motion from one character to another: ``python -m motion.retarget``.

- :mod:`motion.retarget.transfer`: theta carried over in the anatomical frames, gains and limits;
- :mod:`motion.retarget.posing`: the target posed per frame (LBS or DQS) and written as meshes;
- :mod:`motion.retarget.picture`: the reference poses picture, source beside target;
- :mod:`motion.retarget.cli`: the command line (its docstring: the transfer, the giraffe's gains, outputs).
"""

from motion.retarget.cli import MODES, RetargetConfig, resolve_gains, run, source_rig
from motion.retarget.picture import POSE_VIEWS, REFERENCE_POSES, pose_picture, reference_theta
from motion.retarget.posing import MESH_FORMATS, SKINNINGS, pose, supports_skinning, write_meshes
from motion.retarget.transfer import (
    FULCRUM_GAINS,
    GAIN_CHOICES,
    GIRAFFE_GAINS,
    character_limits,
    default_gains,
    giraffe_limits,
    retarget_params,
    retarget_theta,
)

__all__ = [
    "FULCRUM_GAINS",
    "GAIN_CHOICES",
    "GIRAFFE_GAINS",
    "MESH_FORMATS",
    "MODES",
    "POSE_VIEWS",
    "REFERENCE_POSES",
    "RetargetConfig",
    "SKINNINGS",
    "character_limits",
    "default_gains",
    "giraffe_limits",
    "pose",
    "pose_picture",
    "reference_theta",
    "resolve_gains",
    "retarget_params",
    "retarget_theta",
    "run",
    "source_rig",
    "supports_skinning",
    "write_meshes",
]
