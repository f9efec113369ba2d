"""The HACK head-and-neck model in torch: one pure function per step, and the module around them.

    G = LBS(T + B_S(beta) + B_E(psi) + B_P(theta) + L(eta, tau), J, theta, W)

Conventions (the project's, owned here):
- Mesh in cm, y up, face towards +z; x points to the subject's left.
- theta ``[B,J,3]``: axis-angle radians per joint, the rotation of each bone in
  its own rest frame (the frame its rest transform places relative to its
  parent).  Joints run root to head: c7t1, c6c7, c5c6, c4c5, c3c4, c2c3, c1c2,
  oc1.  This is the release's layout; what each axis means anatomically is
  given by the joint's anatomical frame (below).
- psi ``[B,E]``: expression blendshape weights (E = 55, ``expression_names``).
- tau ``[B]``: vertical slide of the larynx in UV units of the larynx map,
  positive = up the neck (the map is sampled at image row ``(1 - v) + tau``).
  On the HACK template one unit is about 33 cm along the neck (0.03 ~ 1 cm).
- eta ``[B]``: larynx size; 0 = no larynx, 1 = the generic larynx (default).
- Larynx maps ``[K,H,W]``: ``L = eta * (sum_k w_k Lc_k)(u, v + tau) * ts``
  with identity weights ``w [B,K]`` (default: the first map alone), sampled
  bilinearly with ``align_corners=True`` and border padding as the release.
- "Head orientation" is ``head_rotation(theta)``: the world rotation of the
  oc1 bone relative to its rest, ``G_oc1(theta)[:3,:3] @ G_oc1(0)[:3,:3]^T``.
- Anatomical joint frames: a bone's own axes need not be anatomical (the
  release's oc1 bone points into the face, so its y axis is forward).  Each
  joint's anatomical frame (x lateral to the subject's left, y up the spine,
  z forward; so +x rotation is flexion, +y axial rotation towards the
  subject's left, +z lateral bending to the right) is its bone frame turned by the quarter-turn rotation that best
  aligns it with the world axes at rest (``anatomical_axes`` [J,3,3], the
  anatomical axes as columns in bone coordinates).  Joint limits and priors
  (``models.joint_limits``) speak anatomical frames: convert with
  ``to_anatomical(theta)`` / ``from_anatomical(theta_anatomical)``.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from data.assets import RigData
from data.procedural_rig import build_procedural_rig
from models.rotations import axis_angle_to_matrix

# ----------------------------------------------------------------------------- pure steps


def blend_shapes(coefficients: torch.Tensor, basis: torch.Tensor, template: torch.Tensor) -> torch.Tensor:
    """Template plus linear blendshapes, vertex-major.

    coefficients [B,K], basis [N*3,K], template [N*3] -> rest shape [N,3,B].
    """
    return torch.addmm(template[:, None], basis, coefficients.T).reshape(-1, 3, coefficients.shape[0])


def pose_features(rotations: torch.Tensor) -> torch.Tensor:
    """SMPL-style pose-corrective features: (R - I) per joint, the root's zeroed (the release's rule).

    rotations [B,J,3,3] -> features [B,J*9].
    """
    eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
    features = rotations - eye
    features = torch.cat([torch.zeros_like(features[:, :1]), features[:, 1:]], dim=1)
    return features.reshape(rotations.shape[0], -1)


def larynx_scalar(tau: torch.Tensor, maps: torch.Tensor, map_weights: torch.Tensor,
                  grid: torch.Tensor) -> torch.Tensor:
    """Larynx displacement magnitude at vertices, the maps slid vertically by tau.

    tau [B] (UV units, + = up), maps [K,H,W], map_weights [B,K],
    grid [N,2] vertex UVs in grid_sample coordinates ((2u - 1, 2(1 - v) - 1)) -> [B,N].
    All frames sample the K maps as channels of one image (sampling is linear, so the identity
    weights apply afterwards): no per-frame copy of the maps.
    """
    shifted = grid[None].expand(tau.shape[0], -1, -1) + torch.stack([torch.zeros_like(tau), 2.0 * tau], dim=-1)[:, None]
    sampled = F.grid_sample(maps[None], shifted[None], mode="bilinear", padding_mode="border", align_corners=True)
    return torch.einsum("kbn,bk->bn", sampled[0], map_weights)


def forward_kinematics(rotations: torch.Tensor, rest_local: torch.Tensor, parents: Sequence[int]) -> torch.Tensor:
    """World transforms of the bones.  G_j = G_parent(j) @ L2P_j @ [R_j 0; 0 1].

    rotations [B,J,3,3], rest_local [J,4,4] -> [B,J,4,4].
    """
    batch, joints = rotations.shape[:2]
    local = rest_local[None].expand(batch, -1, -1, -1)
    posed_local = torch.cat([local[..., :3, :3] @ rotations, local[..., :3, 3:]], dim=-1)
    bottom = torch.zeros(batch, joints, 1, 4, dtype=rotations.dtype, device=rotations.device)
    bottom[..., 3] = 1.0
    posed_local = torch.cat([posed_local, bottom], dim=-2)
    world: list[torch.Tensor] = []
    for j, parent in enumerate(parents):
        world.append(posed_local[:, j] if parent < 0 else world[parent] @ posed_local[:, j])
    return torch.stack(world, dim=1)


def nearest_axis_permutation(rotation: torch.Tensor) -> torch.Tensor:
    """The signed permutation matrix (a proper rotation by quarter turns) nearest to ``rotation`` [3,3]."""
    remaining = rotation.abs().clone()
    out = torch.zeros_like(rotation)
    for _ in range(3):
        row, column = divmod(int(torch.argmax(remaining)), 3)
        out[row, column] = torch.sign(rotation[row, column])
        remaining[row, :] = -1.0
        remaining[:, column] = -1.0
    return out


def skinning_transforms(world: torch.Tensor, rest_world_inverse: torch.Tensor) -> torch.Tensor:
    """Per-bone transforms from rest to posed space: G_j(theta) @ G_j(0)^-1, top 3 rows.

    world [B,J,4,4], rest_world_inverse [J,4,4] -> [B,J,3,4].
    """
    return (world @ rest_world_inverse)[..., :3, :]


def linear_blend_skinning(rest: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """v'_n = sum_j w_nj (R_j v_n + t_j), vertex-major.

    rest [N,3,B], weights [N,J], transforms [B,J,3,4] -> posed [N,3,B].
    Blends the 3x4 matrices per vertex with one [N,J] x [J,12B] product, then
    applies them with three fused multiply-adds over contiguous batch rows
    (the release blends a dense 4x4 per vertex and multiplies it, ~20x slower).
    """
    batch, joints = transforms.shape[:2]
    by_column = transforms.permute(1, 3, 2, 0).reshape(joints, 12 * batch)  # [J, (column d, row c, b)]
    blended = (weights @ by_column).reshape(-1, 4, 3, batch)
    posed = blended[:, 3].addcmul(blended[:, 0], rest[:, 0:1])
    return posed.addcmul_(blended[:, 1], rest[:, 1:2]).addcmul_(blended[:, 2], rest[:, 2:3])


# ----------------------------------------------------------------------------- module


class HeadNeckModel(nn.Module):
    """A HACK-style head-and-neck rig (the real release via ``load``, the procedural one via ``builtin``).

    Call: ``model(theta [B,J,3], psi [B,E]=None, tau [B]=None, eta [B]=None,
    beta [B,S]=None, larynx_weights [B,K]=None) -> vertices [B,N,3]`` (cm).
    Missing inputs take their rest value (zero; eta = 1; the first larynx map).
    """

    def __init__(self, rig: RigData):
        super().__init__()
        self.rig = rig
        dtype = torch.float32
        self.joint_names: list[str] = [str(n) for n in rig.joint_names]
        self.expression_names: list[str] = [str(n) for n in rig.expression_names]
        self.parents: list[int] = [int(p) for p in rig.parents]
        self.faces = torch.tensor(rig.faces.astype(np.int64))
        n = len(rig.template)
        self.register_buffer("template", torch.tensor(rig.template, dtype=dtype))
        self.register_buffer("skin_weights", torch.tensor(rig.skin_weights, dtype=dtype))
        # One vertex-major basis [N*3, E + S + P] for expressions, identity shape and pose correctives:
        # B_E(psi) + B_S(beta) + B_P(theta) is a single product with the concatenated coefficients.
        bases = [rig.expression_deltas.reshape(-1, n * 3), rig.shape_deltas.reshape(-1, n * 3),
                 rig.pose_correctives.reshape(-1, n * 3)]
        self.num_expressions, self.num_shapes, self.num_pose_features = (len(b) for b in bases)
        self.register_buffer("blend_basis", torch.tensor(np.concatenate(bases).T, dtype=dtype).contiguous())
        self.register_buffer("rest_local", torch.tensor(rig.joint_rest_local, dtype=dtype))
        rest_world = forward_kinematics(torch.eye(3, dtype=torch.float64).expand(1, len(self.parents), 3, 3),
                                        torch.tensor(rig.joint_rest_local, dtype=torch.float64), self.parents)[0]
        self.register_buffer("rest_world", rest_world.to(dtype))
        self.register_buffer("rest_world_inverse", torch.linalg.inv(rest_world).to(dtype))
        # Columns: world x, y, z in each bone's coordinates, snapped to the nearest quarter turns.
        axes = torch.stack([nearest_axis_permutation(r[:3, :3].T) for r in rest_world])
        self.register_buffer("anatomical_axes", axes.to(dtype))
        self.register_buffer("larynx_maps", torch.tensor(rig.larynx_maps, dtype=dtype))
        self.register_buffer("larynx_direction", torch.tensor(rig.larynx_direction, dtype=dtype))
        # Only vertices whose map column (or its bilinear neighbour) holds a non-zero value can
        # ever be displaced, as tau slides along v only: sampling just those is exact.
        uv = torch.tensor(rig.vertex_uv, dtype=torch.float64)
        grid = torch.stack([2 * uv[:, 0] - 1, 2 * (1 - uv[:, 1]) - 1], dim=-1)
        width = rig.larynx_maps.shape[2]
        column = np.floor((grid[:, 0].clamp(-1, 1).numpy() + 1) / 2 * (width - 1)).astype(int)
        occupied = np.abs(rig.larynx_maps).max(axis=(0, 1)) > 0
        near = occupied[np.clip(column, 0, width - 1)] | occupied[np.clip(column + 1, 0, width - 1)]
        self.register_buffer("larynx_vertices", torch.tensor(np.flatnonzero(near)))
        self.register_buffer("larynx_grid", grid[self.larynx_vertices].to(dtype))
        self._chunk_plans: dict[tuple[int, torch.device], list] = {}

    # ------------------------------------------------------------------ constructors

    @classmethod
    def load(cls, path: str | os.PathLike) -> "HeadNeckModel":
        """A rig file written by ``python -m data.assets`` (the real HACK release)."""
        return cls(RigData.load(path))

    @classmethod
    def builtin(cls) -> "HeadNeckModel":
        """The built-in procedural rig (no download)."""
        return cls(build_procedural_rig())

    @classmethod
    def from_config(cls, path: str | os.PathLike | None) -> "HeadNeckModel":
        """``path`` to a rig file, or None / "" / "builtin" for the procedural rig."""
        if path in (None, "", "builtin"):
            return cls.builtin()
        return cls.load(Path(path))

    # ------------------------------------------------------------------ sizes

    @property
    def num_vertices(self) -> int:
        return self.template.shape[0]

    @property
    def num_joints(self) -> int:
        return len(self.parents)

    @property
    def num_larynx_maps(self) -> int:
        return self.larynx_maps.shape[0]

    # ------------------------------------------------------------------ kinematics

    def rotations(self, theta: torch.Tensor) -> torch.Tensor:
        """theta [B,J,3] -> [B,J,3,3]."""
        self._check(theta, (self.num_joints, 3), "theta")
        return axis_angle_to_matrix(theta.to(self.template.dtype))

    def joint_transforms(self, theta: torch.Tensor) -> torch.Tensor:
        """World transforms of the bones (bone frame -> world) [B,J,4,4] for theta [B,J,3]."""
        return forward_kinematics(self.rotations(theta), self.rest_local, self.parents)

    def head_rotation(self, theta: torch.Tensor) -> torch.Tensor:
        """Head orientation [B,3,3]: oc1's world rotation relative to rest."""
        world = self.joint_transforms(theta)
        return world[:, -1, :3, :3] @ self.rest_world[-1, :3, :3].T

    def to_anatomical(self, theta: torch.Tensor) -> torch.Tensor:
        """theta [...,J,3] in bone frames -> the same rotations in anatomical joint frames."""
        return torch.einsum("jab,...ja->...jb", self.anatomical_axes.to(theta), theta)

    def from_anatomical(self, theta: torch.Tensor) -> torch.Tensor:
        """theta [...,J,3] in anatomical joint frames -> bone frames (the model's input)."""
        return torch.einsum("jab,...jb->...ja", self.anatomical_axes.to(theta), theta)

    @property
    def anatomical_rest_rotations(self) -> torch.Tensor:
        """[J,3,3] rest world rotations of the anatomical joint frames (bone rest rotation @ axes)."""
        return self.rest_world[:, :3, :3] @ self.anatomical_axes

    # ------------------------------------------------------------------ geometry

    def larynx_region_offsets(self, tau: torch.Tensor, eta: torch.Tensor,
                              larynx_weights: torch.Tensor | None = None) -> torch.Tensor:
        """L(eta, tau) [B,M,3] at ``larynx_vertices`` [M], the only vertices it can move."""
        batch = tau.shape[0]
        self._check(tau, (), "tau", batch)
        self._check(eta, (), "eta", batch)
        tau, eta = tau.to(self.template.dtype), eta.to(self.template.dtype)
        if larynx_weights is None:
            larynx_weights = tau.new_zeros(batch, self.num_larynx_maps)
            larynx_weights[:, 0] = 1.0
        self._check(larynx_weights, (self.num_larynx_maps,), "larynx_weights", batch)
        larynx_weights = larynx_weights.to(self.template.dtype)
        scalar = larynx_scalar(tau, self.larynx_maps, larynx_weights, self.larynx_grid)
        return (eta[:, None] * scalar)[..., None] * self.larynx_direction

    def larynx_offsets(self, tau: torch.Tensor, eta: torch.Tensor,
                       larynx_weights: torch.Tensor | None = None) -> torch.Tensor:
        """L(eta, tau) at every vertex [B,N,3] (zero outside ``larynx_vertices``)."""
        out = self.template.new_zeros(tau.shape[0], self.num_vertices, 3)
        return out.index_add(1, self.larynx_vertices, self.larynx_region_offsets(tau, eta, larynx_weights))

    @property
    def expression_deltas(self) -> torch.Tensor:
        """[E,N,3] expression blendshape offsets (cm)."""
        return self.blend_basis[:, : self.num_expressions].T.reshape(self.num_expressions, -1, 3)

    def blend_coefficients(self, batch: int, psi=None, beta=None, rotations=None) -> torch.Tensor:
        """[B, E+S+P]: psi, beta and pose-corrective features, zero where not given."""
        parts = []
        for value, size, name in ((psi, self.num_expressions, "psi"), (beta, self.num_shapes, "beta")):
            if value is None:
                parts.append(self.template.new_zeros(batch, size))
            else:
                self._check(value, (size,), name, batch)
                parts.append(value.to(self.template.dtype))
        if self.num_pose_features:
            parts.append(pose_features(rotations) if rotations is not None
                         else self.template.new_zeros(batch, self.num_pose_features))
        return torch.cat(parts, dim=1)

    def rest_shape(self, psi=None, tau=None, eta=None, beta=None, larynx_weights=None,
                   rotations: torch.Tensor | None = None) -> torch.Tensor:
        """The unposed shape T + B_S + B_E + B_P + L, [B,N,3]: psi [B,E], tau [B], eta [B], beta [B,S],
        larynx_weights [B,K], rotations [B,J,3,3] (for the pose correctives), each optional; B is the
        inputs' batch (1 when none is given)."""
        given = [x for x in (psi, tau, eta, beta, larynx_weights, rotations) if x is not None]
        batch = given[0].shape[0] if given else 1
        coefficients = self.blend_coefficients(batch, psi, beta, rotations)
        shape = blend_shapes(coefficients, self.blend_basis, self.template.reshape(-1)).permute(2, 0, 1)
        tau, eta = self._larynx_inputs(batch, tau, eta)
        return shape.index_add(1, self.larynx_vertices, self.larynx_region_offsets(tau, eta, larynx_weights))

    def forward(self, theta: torch.Tensor, psi: torch.Tensor | None = None, tau: torch.Tensor | None = None,
                eta: torch.Tensor | None = None, beta: torch.Tensor | None = None,
                larynx_weights: torch.Tensor | None = None) -> torch.Tensor:
        rotations = self.rotations(theta)
        batch = theta.shape[0]
        coefficients = self.blend_coefficients(batch, psi, beta, rotations)
        tau, eta = self._larynx_inputs(batch, tau, eta)
        larynx = self.larynx_region_offsets(tau, eta, larynx_weights).permute(1, 2, 0).contiguous()  # [M,3,B]
        transforms = skinning_transforms(forward_kinematics(rotations, self.rest_local, self.parents),
                                         self.rest_world_inverse)
        template = self.template.reshape(-1)
        # Vertex chunks keep each step's working set in cache (~2x faster than whole-mesh passes).
        posed = template.new_empty(batch, self.num_vertices, 3)
        for start, stop, local, in_region in self._chunk_plan(max(256, 65536 // batch)):
            rest = blend_shapes(coefficients, self.blend_basis[3 * start: 3 * stop], template[3 * start: 3 * stop])
            if len(local):
                rest.index_add_(0, local, larynx[in_region])
            chunk = linear_blend_skinning(rest, self.skin_weights[start:stop], transforms)
            posed[:, start:stop] = chunk.permute(2, 0, 1)  # written while the chunk is in cache
        return posed

    # ------------------------------------------------------------------ helpers

    def _chunk_plan(self, size: int) -> list:
        """Vertex ranges of ``size`` with the larynx-region vertices each holds (local index, region index),
        on the device of the buffers (cached per size and device, so ``.to(device)`` gets its own)."""
        key = (size, self.larynx_vertices.device)
        if key not in self._chunk_plans:
            plan, region = [], self.larynx_vertices
            for start in range(0, self.num_vertices, size):
                stop = min(start + size, self.num_vertices)
                inside = torch.nonzero((region >= start) & (region < stop)).reshape(-1)
                plan.append((start, stop, region[inside] - start, inside))
            self._chunk_plans[key] = plan
        return self._chunk_plans[key]

    def _larynx_inputs(self, batch: int, tau, eta) -> tuple[torch.Tensor, torch.Tensor]:
        tau = self.template.new_zeros(batch) if tau is None else tau
        eta = self.template.new_ones(batch) if eta is None else eta
        self._check(tau, (), "tau", batch)
        self._check(eta, (), "eta", batch)
        return tau, eta

    @staticmethod
    def _check(value: torch.Tensor, trailing: tuple[int, ...], name: str, batch: int | None = None) -> None:
        if tuple(value.shape[1:]) != trailing or (batch is not None and value.shape[0] != batch):
            expected = f"[{batch if batch is not None else 'B'}" + "".join(f",{d}" for d in trailing) + "]"
            raise ValueError(f"{name} has shape {list(value.shape)}, expected {expected}")

    def neutral(self, batch: int = 1) -> torch.Tensor:
        """The rest pose theta = 0 [B,J,3]."""
        return self.template.new_zeros(batch, self.num_joints, 3)
