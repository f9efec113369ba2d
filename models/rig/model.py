"""``HeadNeckModel``, the HACK head-and-neck rig as a torch module: it holds the rig's buffers and calls the
steps (``models.rig.skinning``) through the chunked engine (``models.rig.engine``); conventions owned here.

    G = LBS(T + B_S(beta) + B_E(psi) + B_P(theta) + L(eta, tau), J, theta, W)

(or DQS in place of LBS: ``skinning="dqs"``, dual-quaternion skinning, Kavan et al. 2008).

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
  (``data.joint_limits``) speak anatomical frames: convert with
  ``to_anatomical(theta)`` / ``from_anatomical(theta_anatomical)``.
- Skinning: ``"lbs"`` (the release's linear blend skinning, the default) or ``"dqs"`` (dual quaternions:
  no volume loss under twist), per model (``HeadNeckModel(rig, skinning=...)``) or per call
  (``model(..., skinning=...)``).

The forward pass, step by step, is ``models.rig.skinning.pose_vertices`` (``HeadNeckModel.pose_reference``
calls it with the model's buffers); ``forward`` computes the same through the threaded engine.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import nn

from base.rotations import axis_angle_to_matrix
from base.threads import single_thread
from data.assets import RigData
from data.procedural_rig import build_procedural_rig
from models.rig.engine import ChunkPlan, chunk_plan, larynx_reach, pose_in_chunks, schedule
from models.rig.skinning import (
    SKINNINGS,
    blend_shapes,
    dual_quaternion_columns,
    dual_quaternion_pivots,
    forward_kinematics,
    larynx_offsets,
    larynx_scalar,
    nearest_axis_permutation,
    pivot_usage,
    pose_features,
    pose_vertices,
    rigid_to_dual_quaternion,
    skinning_transforms,
    transform_columns,
)


class HeadNeckModel(nn.Module):
    """A HACK-style head-and-neck rig (the real release via ``load``, the procedural one via ``builtin``).

    Call: ``model(theta [B,J,3], psi [B,E]=None, tau [B]=None, eta [B]=None,
    beta [B,S]=None, larynx_weights [B,K]=None, skinning=None) -> vertices [B,N,3]`` (cm).
    Missing inputs take their rest value (zero; eta = 1; the first larynx map); ``skinning`` is
    ``"lbs"`` or ``"dqs"`` (default: the model's ``skinning`` attribute, ``"lbs"`` unless given).
    """

    def __init__(self, rig: RigData, skinning: str = "lbs"):
        super().__init__()
        self.rig = rig
        self.skinning = _skinning_name(skinning)
        dtype = torch.float32
        self.joint_names: list[str] = [str(n) for n in rig.joint_names]
        self.expression_names: list[str] = [str(n) for n in rig.expression_names]
        self.parents: list[int] = [int(p) for p in rig.parents]
        self.faces = torch.tensor(rig.faces.astype(np.int64))
        n = len(rig.template)
        self.register_buffer("template", torch.tensor(rig.template, dtype=dtype))
        self.register_buffer("skin_weights", torch.tensor(rig.skin_weights, dtype=dtype))
        # One planar basis [E + S + P + 1, 3, N] (per shape the x, y and z offsets of all vertices as rows) for
        # expressions, identity shapes, pose correctives and the template: T + B_E(psi) + B_S(beta) + B_P(theta)
        # is a single product with (psi, beta, pose features, 1).
        bases = [rig.expression_deltas, rig.shape_deltas, rig.pose_correctives.reshape(-1, n, 3),
                 rig.template.reshape(1, n, 3)]
        self.num_expressions, self.num_shapes, self.num_pose_features = (len(b) for b in bases[:3])
        basis = np.concatenate([np.asarray(b, np.float64).reshape(-1, n, 3) for b in bases]).transpose(0, 2, 1)
        self.register_buffer("shape_basis", torch.tensor(np.ascontiguousarray(basis), dtype=dtype))
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
        self._init_larynx_region(rig)
        pivots = dual_quaternion_pivots(self.skin_weights)
        self.register_buffer("dqs_pivots", pivots)
        self.register_buffer("dqs_usage", pivot_usage(self.skin_weights, pivots))
        self._plans: dict = {}

    def _init_larynx_region(self, rig: RigData) -> None:
        """``larynx_vertices`` [M]: the vertices whose map columns (or bilinear neighbours) hold a non-zero
        value, the only ones L can move as tau slides along v; ``larynx_grid`` [M,2] their sampling points;
        per vertex the unshifted sampling row ``larynx_row`` and the rows ``larynx_rows`` [M,2] (first,
        last; widened by 2 rows for rounding) between which its columns are non-zero: a frame displaces the
        vertex only if its shifted row falls between them (``_larynx_active``)."""
        uv = torch.tensor(rig.vertex_uv, dtype=torch.float64)
        grid = torch.stack([2 * uv[:, 0] - 1, 2 * (1 - uv[:, 1]) - 1], dim=-1)
        _, height, width = rig.larynx_maps.shape
        column = np.floor((grid[:, 0].clamp(-1, 1).numpy() + 1) / 2 * (width - 1)).astype(int)
        columns = np.stack([np.clip(column, 0, width - 1), np.clip(column + 1, 0, width - 1)])  # [2, N]
        occupied = np.abs(rig.larynx_maps).max(axis=0) > 0  # [H, W]
        vertices = np.flatnonzero(occupied[:, columns].any(axis=(0, 1)))
        self.register_buffer("larynx_vertices", torch.tensor(vertices))
        self.register_buffer("larynx_grid", grid[vertices].to(torch.float32))
        rows = occupied[:, columns[:, vertices]].any(axis=1)  # [H, M]
        index = np.arange(height)[:, None]
        first = np.where(rows, index, height).min(axis=0) - 2.0
        last = np.where(rows, index, -1).max(axis=0) + 2.0
        row = (self.larynx_grid[:, 1].double() + 1) / 2 * (height - 1)
        self.register_buffer("larynx_row", row.to(torch.float32))
        self.register_buffer("larynx_rows", torch.tensor(np.stack([first, last], axis=1), dtype=torch.float32))

    # ------------------------------------------------------------------ constructors

    @classmethod
    def load(cls, path: str | os.PathLike, skinning: str = "lbs") -> HeadNeckModel:
        """A rig file written by ``python -m data.assets`` (the real HACK release)."""
        return cls(RigData.load(path), skinning=skinning)

    @classmethod
    def builtin(cls, skinning: str = "lbs") -> HeadNeckModel:
        """The built-in procedural rig (no download)."""
        return cls(build_procedural_rig(), skinning=skinning)

    @classmethod
    def from_config(cls, path: str | os.PathLike | None, skinning: str = "lbs") -> HeadNeckModel:
        """``path`` to a rig file, or None / "" / "builtin" for the procedural rig."""
        if path in (None, "", "builtin"):
            return cls.builtin(skinning=skinning)
        return cls.load(Path(path), skinning=skinning)

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
        tau, eta, larynx_weights = self._larynx_arguments(tau, eta, larynx_weights)
        return larynx_offsets(tau, eta, self.larynx_maps, larynx_weights, self.larynx_grid, self.larynx_direction)

    def larynx_offsets(self, tau: torch.Tensor, eta: torch.Tensor,
                       larynx_weights: torch.Tensor | None = None) -> torch.Tensor:
        """L(eta, tau) at every vertex [B,N,3] (zero outside ``larynx_vertices``)."""
        out = self.template.new_zeros(tau.shape[0], self.num_vertices, 3)
        return out.index_add(1, self.larynx_vertices, self.larynx_region_offsets(tau, eta, larynx_weights))

    @property
    def expression_deltas(self) -> torch.Tensor:
        """[E,N,3] expression blendshape offsets (cm), a view of ``shape_basis``."""
        return self.shape_basis[: self.num_expressions].transpose(1, 2)

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
        coefficients = torch.cat([coefficients, coefficients.new_ones(batch, 1)], dim=1)
        shape = blend_shapes(coefficients, self.shape_basis).transpose(1, 2)
        tau, eta = self._larynx_inputs(batch, tau, eta)
        return shape.index_add(1, self.larynx_vertices, self.larynx_region_offsets(tau, eta, larynx_weights))

    def forward(self, theta: torch.Tensor, psi: torch.Tensor | None = None, tau: torch.Tensor | None = None,
                eta: torch.Tensor | None = None, beta: torch.Tensor | None = None,
                larynx_weights: torch.Tensor | None = None, skinning: str | None = None) -> torch.Tensor:
        """Posed vertices [B,N,3] (cm).

        Args:
            theta: [B,J,3] axis-angle per joint in its bone frame.
            psi: [B,E] expression weights; beta [B,S] identity shape; tau [B], eta [B] the larynx;
                larynx_weights [B,K] identity weights of the larynx maps (each optional, see the class).
            skinning: "lbs" or "dqs"; None takes the model's ``skinning``.

        Returns:
            [B,N,3] vertices; differentiable in every input.  Computed by ``models.rig.engine`` (chunks, threads).
        """
        skinning = _skinning_name(self.skinning if skinning is None else skinning)
        threads = torch.get_num_threads()
        with single_thread():
            return self._pose(theta, psi, tau, eta, beta, larynx_weights, skinning, threads)

    def pose_reference(self, theta: torch.Tensor, psi: torch.Tensor | None = None, tau: torch.Tensor | None = None,
                       eta: torch.Tensor | None = None, beta: torch.Tensor | None = None,
                       larynx_weights: torch.Tensor | None = None, skinning: str | None = None) -> torch.Tensor:
        """``forward``'s result computed step by step (``models.rig.skinning.pose_vertices``): plain batched
        torch over the whole mesh, no chunks or threads.  Same arguments and result [B,N,3]."""
        skinning = _skinning_name(self.skinning if skinning is None else skinning)
        self._check(theta, (self.num_joints, 3), "theta")
        batch = theta.shape[0]
        shape_coefficients = self.blend_coefficients(batch, psi, beta)[:, : self.num_expressions + self.num_shapes]
        tau, eta = self._larynx_inputs(batch, tau, eta)
        tau, eta, larynx_weights = self._larynx_arguments(tau, eta, larynx_weights)
        return pose_vertices(theta.to(self.template.dtype), shape_coefficients, tau, eta, larynx_weights,
                             shape_basis=self.shape_basis, rest_local=self.rest_local, parents=self.parents,
                             rest_world_inverse=self.rest_world_inverse, skin_weights=self.skin_weights,
                             larynx_maps=self.larynx_maps, larynx_grid=self.larynx_grid,
                             larynx_vertices=self.larynx_vertices, larynx_direction=self.larynx_direction,
                             skinning=skinning, pivots=self.dqs_pivots)

    # ------------------------------------------------------------------ the forward pass (engine)

    def _pose(self, theta, psi, tau, eta, beta, larynx_weights, skinning: str, threads: int,
              size: int | None = None) -> torch.Tensor:
        """``forward`` on ``threads`` threads in chunks of ``size`` vertices (default: ``engine.schedule``'s).
        Call under ``single_thread``."""
        rotations = self.rotations(theta)
        batch = theta.shape[0]
        coefficients = self.blend_coefficients(batch, psi, beta, rotations)
        tau, eta = self._larynx_inputs(batch, tau, eta)
        if batch == 0:
            return self.template.new_zeros(0, self.num_vertices, 3)
        # [B, E+S+P+1]: the last column multiplies the template, the last shape of ``shape_basis``.
        coefficients = torch.cat([coefficients, coefficients.new_ones(batch, 1)], dim=1)
        region, larynx = self._larynx_active(tau, eta, larynx_weights)  # [A], [3,B,A]
        transforms = skinning_transforms(forward_kinematics(rotations, self.rest_local, self.parents),
                                         self.rest_world_inverse)
        if skinning == "lbs":
            tables = (transform_columns(transforms), None)
        else:
            tables = dual_quaternion_columns(rigid_to_dual_quaternion(transforms), self.dqs_usage)
        scheduled, threads = schedule(self.num_vertices, batch, 1 if torch.compiler.is_compiling() else threads)
        return pose_in_chunks(self._plan(size or scheduled), skinning, region, threads, coefficients, larynx,
                              self.shape_basis, self.skin_weights, *tables)

    def _plan(self, size: int) -> ChunkPlan:
        """The mesh in chunks of ``size`` vertices (cached per size; ``.to()``, ``.double()`` clear it)."""
        if size not in self._plans:
            self._plans[size] = chunk_plan(self.shape_basis, self.skin_weights, self.dqs_pivots, size)
        return self._plans[size]

    def _apply(self, fn, *args, **kwargs):
        self._plans = {}
        return super()._apply(fn, *args, **kwargs)

    def _larynx_active(self, tau: torch.Tensor, eta: torch.Tensor,
                       larynx_weights: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The larynx vertices some frame of the batch displaces (sorted) [A], and L there [3,B,A].

        Exact: a vertex outside it has all four bilinear neighbours zero in every frame (so zero value and
        gradient), from the batch's tau range and the vertex's non-zero rows (``_init_larynx_region``)."""
        tau, eta, larynx_weights = self._larynx_arguments(tau, eta, larynx_weights)
        keep = larynx_reach(tau, self.larynx_row, self.larynx_rows, self.larynx_maps.shape[1] - 1)
        region = self.larynx_vertices if keep is None else self.larynx_vertices[keep]
        grid = self.larynx_grid if keep is None else self.larynx_grid[keep]
        scalar = larynx_scalar(tau, self.larynx_maps, larynx_weights, grid)  # [B, A]
        return region, (eta[:, None] * scalar)[None] * self.larynx_direction[:, None, None]

    # ------------------------------------------------------------------ helpers

    def _larynx_arguments(self, tau, eta, larynx_weights) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        batch = tau.shape[0]
        self._check(tau, (), "tau", batch)
        self._check(eta, (), "eta", batch)
        tau, eta = tau.to(self.template.dtype), eta.to(self.template.dtype)
        if larynx_weights is None:
            larynx_weights = tau.new_zeros(batch, self.num_larynx_maps)
            larynx_weights[:, 0] = 1.0
        self._check(larynx_weights, (self.num_larynx_maps,), "larynx_weights", batch)
        return tau, eta, larynx_weights.to(self.template.dtype)

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


def _skinning_name(skinning: str) -> str:
    if skinning not in SKINNINGS:
        raise ValueError(f"skinning={skinning!r}: expected one of {', '.join(SKINNINGS)}")
    return skinning
