"""Rig assets: the compact rig file, and its conversion from the HACK release and ICT-FaceKit.

- :mod:`data.assets.rig_data`: :class:`RigData`, the rig file; :func:`with_shape_offset`, a person's rig
  (the template plus a fitted ``shape_offset``);
- :mod:`data.assets.release`: :func:`convert`, the release and ICT-FaceKit read into a :class:`RigData`;
- :mod:`data.assets.cli`: ``python -m data.assets``.
"""

from data.assets.cli import AssetsCli, run
from data.assets.release import (
    convert,
    per_vertex_uv,
    read_ict_expressions,
    read_larynx_map,
    rest_transforms_from_bones,
)
from data.assets.rig_data import JOINT_NAMES, NO_UV, RIG_FORMAT_VERSION, RigData, with_shape_offset

__all__ = [
    "AssetsCli",
    "JOINT_NAMES",
    "NO_UV",
    "RIG_FORMAT_VERSION",
    "RigData",
    "convert",
    "per_vertex_uv",
    "read_ict_expressions",
    "read_larynx_map",
    "rest_transforms_from_bones",
    "run",
    "with_shape_offset",
]
