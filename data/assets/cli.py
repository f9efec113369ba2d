"""Rig assets: the compact rig file, and its conversion from the HACK release and ICT-FaceKit.

    python -m data.assets hack_dir=PATH/HACK-Model ict_dir=PATH/ICT-FaceKit out=rig.npz

reads the official release (``model/000_generic_neutral_mesh_newuv.obj``,
``bones_neutral.json``, ``weight_map_smooth.npy``, ``Lc_mid.png``,
``ts_larynx.npy``; optionally ``P.npy`` pose correctives) and ICT-FaceKit's
``FaceXModel/`` OBJs, and writes one ``.npz`` that loads in a fraction of a
second.  The release is third-party data: keep the rig file outside the
repository and point the tools at it (``rig=...``).

Conventions (shared with ``models.rig``): mesh in cm, y up, face towards +z.
Bones follow the release's Blender layout: a bone's rest transform relative
to its parent ("local to parent", L2P) is ``[matrix | head + (0, parent
length, 0)]``, i.e. the bone's origin sits at its ``head`` offset from the
parent's *tail*, and its y axis runs along the bone.  The 55 expressions are
ICT's shapes except ``PupilDilate_L/R``, in sorted name order, taken over the
first N (template) vertices as deltas from ICT's neutral mesh.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from base.cli import REQUIRED, register_config
from data.assets.release import convert
from data.assets.rig_data import RigData


@dataclass
class AssetsCli:
    """``python -m data.assets``: the release and ICT-FaceKit folders, and the rig file to write."""

    hack_dir: str = REQUIRED
    ict_dir: str = REQUIRED
    out: str = "rig.npz"


register_config("assets_schema", AssetsCli)


def run(cfg) -> RigData:
    """``python -m data.assets``: convert and report."""
    started = time.perf_counter()
    rig = convert(cfg.hack_dir, cfg.ict_dir, cfg.out)
    print(f"wrote {cfg.out}: {len(rig.template)} vertices, {len(rig.faces)} faces, "
          f"{len(rig.joint_names)} joints, {len(rig.expression_names)} expressions, "
          f"{len(rig.larynx_maps)} larynx map(s) in {time.perf_counter() - started:.1f} s")
    return rig
