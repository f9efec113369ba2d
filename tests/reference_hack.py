"""An independent re-implementation of the HACK release's forward pass, for testing and benchmarking.

It follows the release's own algorithm step by step, in float64, and shares
no code with ``models.rig`` or ``data.assets``: it parses the raw release
files itself, chains the bones recursively from ``[matrix | head + (0,
parent length, 0)]``, normalises the weights per vertex, blends a dense 4x4
matrix per vertex, and samples the larynx map with a per-vertex grid taken
from the first face corner that mentions each vertex (align_corners=True,
border padding).
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F


def _parse_obj(path: Path, with_faces: bool):
    vertices, uvs, faces, faces_uv = [], [], [], []
    for line in Path(path).read_text().splitlines():
        if line.startswith("v "):
            vertices.append([float(t) for t in line.split()[1:4]])
        elif with_faces and line.startswith("vt "):
            uvs.append([float(t) for t in line.split()[1:3]])
        elif with_faces and line.startswith("f "):
            corners = [c.split("/") for c in line.split()[1:]]
            faces.append([int(c[0]) - 1 for c in corners])
            faces_uv.append([int(c[1]) - 1 for c in corners])
    return np.array(vertices), np.array(uvs), faces, faces_uv


def _rodrigues(axis_angle: torch.Tensor) -> torch.Tensor:
    angle = axis_angle.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    k = axis_angle / angle
    kx, ky, kz = k.unbind(-1)
    zero = torch.zeros_like(kx)
    K = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], -1).reshape(*k.shape[:-1], 3, 3)
    s, c = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    return torch.eye(3, dtype=axis_angle.dtype) + s * K + (1 - c) * (K @ K)


class ReleaseReference:
    def __init__(self, hack_dir: Path, ict_dir: Path, expressions: list[str], dtype=torch.float64):
        self.dtype = dtype
        model = Path(hack_dir) / "model"
        self.bones = json.loads((model / "bones_neutral.json").read_text())
        self.names = list(self.bones)
        vertices, uvs, faces, faces_uv = _parse_obj(model / "000_generic_neutral_mesh_newuv.obj", True)
        self.template = torch.tensor(vertices)
        n = len(vertices)
        w = torch.tensor(np.load(model / "weight_map_smooth.npy"), dtype=torch.float64)
        self.weights = w / w.sum(0, keepdim=True)  # [J,N]
        grid = np.full((n, 2), 2.0)
        flipped = uvs.copy()
        flipped[:, 1] = 1 - flipped[:, 1]
        flipped = flipped * 2 - 1
        for fv, ft in zip(faces, faces_uv):
            for vi, ti in zip(fv, ft):
                if grid[vi, 0] == 2:
                    grid[vi] = flipped[ti]
        self.grid = torch.tensor(grid)
        self.larynx = torch.tensor(cv2.imread(str(model / "Lc_mid.png"), cv2.IMREAD_GRAYSCALE) / 255.0)[None, None]
        self.ts = torch.tensor(np.load(model / "ts_larynx.npy"), dtype=torch.float64)
        neutral = _parse_obj(Path(ict_dir) / "FaceXModel" / "generic_neutral_mesh.obj", False)[0][:n]
        self.expressions = expressions
        self.deltas = torch.tensor(np.stack([
            _parse_obj(Path(ict_dir) / "FaceXModel" / f"{name}.obj", False)[0][:n] - neutral for name in expressions
        ]))
        self.l2p = []
        for name in self.names:
            bone = self.bones[name]
            m = torch.eye(4, dtype=torch.float64)
            m[:3, :3] = torch.tensor(bone["matrix"], dtype=torch.float64)
            head = torch.tensor(bone["head"], dtype=torch.float64)
            if bone["parent"] is not None:
                head = head + torch.tensor([0.0, self.bones[bone["parent"]]["length"], 0.0], dtype=torch.float64)
            m[:3, 3] = head
            self.l2p.append(m)
        rest = self._chain([torch.eye(3, dtype=torch.float64)[None]] * len(self.names))  # float64 until the end
        self.rest_inverse = torch.linalg.inv(rest)
        for name in ("template", "weights", "grid", "larynx", "ts", "deltas", "rest_inverse"):
            setattr(self, name, getattr(self, name).to(dtype))
        self.l2p = [m.to(dtype) for m in self.l2p]

    def _chain(self, local_rotations):
        world = {}

        def get(i):
            if i in world:
                return world[i]
            local = torch.eye(4, dtype=local_rotations[i].dtype).repeat(local_rotations[i].shape[0], 1, 1)
            local[:, :3, :3] = local_rotations[i]
            transform = self.l2p[i] @ local
            parent = self.bones[self.names[i]]["parent"]
            if parent is not None:
                transform = get(self.names.index(parent)) @ transform
            world[i] = transform
            return transform

        return torch.stack([get(i) for i in range(len(self.names))], dim=1)

    def __call__(self, theta: torch.Tensor, psi_subset: torch.Tensor, tau: torch.Tensor, eta: torch.Tensor):
        """theta [B,8,3], psi_subset [B,len(expressions)], tau [B], eta [B] -> [B,N,3]."""
        theta = theta.to(self.dtype)
        rotations = _rodrigues(theta)
        world = self._chain([rotations[:, i] for i in range(rotations.shape[1])])
        per_bone = world @ self.rest_inverse  # [B,J,4,4]
        per_vertex = (per_bone[:, :, None] * self.weights[None, :, :, None, None]).sum(1)  # [B,N,4,4]
        grid = self.grid[None].repeat(theta.shape[0], 1, 1)
        grid[..., 1] = grid[..., 1] + 2 * tau.to(self.dtype)[:, None]
        sampled = F.grid_sample(self.larynx.expand(theta.shape[0], -1, -1, -1), grid[:, None],
                                mode="bilinear", padding_mode="border", align_corners=True)[:, 0, 0]
        shape = (self.template + (psi_subset.to(self.dtype)[:, :, None, None] * self.deltas).sum(1)
                 + sampled[..., None] * self.ts * eta.to(self.dtype)[:, None, None])
        homogeneous = F.pad(shape, [0, 1], value=1.0)
        return (per_vertex @ homogeneous[..., None])[..., :3, 0]
