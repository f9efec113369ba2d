"""The target posed by a clip, frame by frame (linear blend or dual quaternion skinning), and written as meshes."""
from __future__ import annotations

import inspect
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from base.errors import InputError
from data.mesh_io import write_obj, write_ply
from data.params import AnimationParams
from models.rig import HeadNeckModel
from scene.characters import person_rig

SKINNINGS = ("lbs", "dqs")
MESH_FORMATS = ("ply", "obj")


def supports_skinning(rig: HeadNeckModel, skinning: str) -> bool:
    """Whether ``rig``'s forward pass takes ``skinning=`` (dual quaternions are added to models.rig
    separately); plain LBS always works."""
    return skinning == "lbs" or "skinning" in inspect.signature(rig.forward).parameters


@torch.no_grad()
def pose(rig: HeadNeckModel, params: AnimationParams, skinning: str = "lbs", batch: int = 64,
         frames: np.ndarray | None = None) -> Iterator[tuple[int, torch.Tensor]]:
    """Posed vertices of ``params`` on ``rig`` in batches: yields (first frame, vertices [B,N,3] cm).

    rig: the base rig (a fitted ``params.shape_offset`` is added to its template here, ``person_rig``);
    skinning: lbs | dqs (InputError if the rig has no dual-quaternion skinning).
    """
    if skinning not in SKINNINGS:
        raise InputError(f"skinning={skinning}: expected one of {', '.join(SKINNINGS)}")
    if not supports_skinning(rig, skinning):
        raise InputError(f"skinning={skinning}: this version of models.rig has no dual-quaternion skinning yet")
    rig = person_rig(rig, params)
    extra = {"skinning": skinning} if "skinning" in inspect.signature(rig.forward).parameters else {}
    frames = np.arange(len(params)) if frames is None else np.asarray(frames)
    for start in range(0, len(frames), batch):
        index = frames[start:start + batch]
        yield start, rig(torch.as_tensor(params.theta[index]), torch.as_tensor(params.psi[index]),
                         torch.as_tensor(params.tau[index]), torch.as_tensor(params.eta[index]), **extra)


def write_meshes(folder: Path, rig: HeadNeckModel, params: AnimationParams, skinning: str = "lbs",
                 mesh_format: str = "ply", batch: int = 64) -> int:
    """``folder/frame_00000.<mesh_format>`` ... one posed mesh per frame (OBJ with the rig's UVs); returns
    the count."""
    if mesh_format not in MESH_FORMATS:
        raise InputError(f"mesh_format={mesh_format}: expected one of {', '.join(MESH_FORMATS)}")
    faces = rig.rig.faces
    uv = (rig.rig.uv_coords, rig.rig.faces_uv) if len(rig.rig.uv_coords) else (None, None)
    count = 0
    for start, vertices in pose(rig, params, skinning, batch):
        for k, frame in enumerate(vertices.numpy()):
            path = folder / f"frame_{start + k:05d}.{mesh_format}"
            if mesh_format == "ply":
                write_ply(path, frame, faces)
            else:
                write_obj(path, frame, faces, *uv)
            count += 1
    return count
