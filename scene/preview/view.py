"""How a preview frame sees the posed rig: the views about the vertical axis, a camera framing the whole
clip, and the shading (Lambert or the normal map).
"""
from __future__ import annotations

import numpy as np
import torch

from base.errors import InputError
from data.normals import encode_normals
from data.params import AnimationParams
from models.rig import HeadNeckModel
from scene.render import Camera

# Camera azimuth about the world's y axis, degrees; the camera moves from the front (+z) towards the
# subject's left (+x).
VIEWS = {"front": 0.0, "three_quarter": 45.0, "side": 90.0}
SHADINGS = ("shaded", "normals")
MARGIN = 1.08                  # frame the posed meshes with 8 % to spare
LIGHT = np.array([-0.35, 0.45, 0.82])   # camera space: from the upper left, in front
AMBIENT = 0.22
ALBEDO_BGR = np.array([0.52, 0.62, 0.80])  # the GLB's skin colour (scene.gltf.SKIN_COLOUR), BGR
BACKGROUND_BGR = (38, 34, 30)


def view_rotation(view: str) -> np.ndarray:
    """World -> camera rotation [3,3] (rows: camera x right, y up, z towards the camera) of a named view."""
    if view not in VIEWS:
        raise InputError(f"view={view}: expected one of {', '.join(VIEWS)}")
    a = np.radians(VIEWS[view])
    towards_camera = np.array([np.sin(a), 0.0, np.cos(a)])
    up = np.array([0.0, 1.0, 0.0])
    return np.stack([np.cross(up, towards_camera), up, towards_camera])


@torch.no_grad()
def posed_vertices(rig: HeadNeckModel, params: AnimationParams, frames: np.ndarray) -> torch.Tensor:
    """``rig(theta, psi, tau, eta)`` at ``frames`` of the clip [B,N,3] cm."""
    return rig(torch.as_tensor(params.theta[frames]), torch.as_tensor(params.psi[frames]),
               torch.as_tensor(params.tau[frames]), torch.as_tensor(params.eta[frames]))


def framing_camera(rig: HeadNeckModel, params: AnimationParams, view: str = "front", size: int = 256,
                   samples: int = 24) -> Camera:
    """An orthographic camera of the named view holding the clip's posed meshes (``samples`` frames spread
    over the clip) in a ``size`` x ``size`` image with a margin."""
    rotation = view_rotation(view)
    frames = np.unique(np.linspace(0, len(params) - 1, min(samples, len(params))).round().astype(int))
    points = posed_vertices(rig, params, frames).double().numpy().reshape(-1, 3) @ rotation.T   # camera axes
    low, high = points.min(0), points.max(0)
    centre_camera = (low + high) / 2
    extent = float(max(high[0] - low[0], high[1] - low[1])) * MARGIN
    centre = rotation.T @ centre_camera
    depth = float(high[2] - low[2])
    return Camera(centre=tuple(float(c) for c in centre), width=int(size), height=int(size),
                  cm_per_px=extent / size, rotation=tuple(tuple(float(v) for v in row) for row in rotation),
                  distance=depth + 50.0, perspective=False)


def shade(normals: np.ndarray, mask: np.ndarray, shading: str = "shaded") -> np.ndarray:
    """Camera-space normals [B,H,W,3] and mask [B,H,W] -> BGR images [B,H,W,3] uint8.

    shaded: albedo * (ambient + (1 - ambient) * max(n . light, 0)); normals: the RGB encoding (n + 1) / 2.
    """
    if shading not in SHADINGS:
        raise InputError(f"shading={shading}: expected one of {', '.join(SHADINGS)}")
    normals = np.asarray(normals, np.float32)
    if shading == "normals":
        image = encode_normals(normals)[..., ::-1] * np.float32(255.0)
    else:
        light = (LIGHT / np.linalg.norm(LIGHT)).astype(np.float32)
        lambert = np.maximum(normals @ light, np.float32(0.0))
        image = ALBEDO_BGR.astype(np.float32) * (np.float32(AMBIENT) + np.float32(1.0 - AMBIENT) * lambert)[..., None]
        image *= np.float32(255.0)
    image = np.where(mask[..., None], image + np.float32(0.5), np.array(BACKGROUND_BGR, np.float32))
    return image.astype(np.uint8)
