"""The HACK head-and-neck model in torch: one pure function per step, and the module around them.

    G = LBS(T + B_S(beta) + B_E(psi) + B_P(theta) + L(eta, tau), J, theta, W)

(or DQS in place of LBS: ``skinning="dqs"``, dual-quaternion skinning, Kavan et al. 2008).

- ``models.rig.model``: ``HeadNeckModel``, the rig's buffers and the conventions of its inputs (theta, psi,
  tau, eta, anatomical joint frames, head orientation, units).
- ``models.rig.skinning``: the pure batched steps (blend shapes, pose features, larynx, forward kinematics,
  LBS, DQS) and ``pose_vertices``, the whole forward pass composed from them in plain torch.
- ``models.rig.engine``: the same forward (and backward) pass in vertex chunks on threads, the one
  ``HeadNeckModel.forward`` runs; ``models.rig.workers``: the threads it hands chunks to.
"""
from __future__ import annotations

from models.rig.model import HeadNeckModel
from models.rig.skinning import (
    SKINNINGS,
    blend_shapes,
    dual_quaternion_pivots,
    dual_quaternion_skinning,
    forward_kinematics,
    larynx_offsets,
    larynx_scalar,
    linear_blend_skinning,
    nearest_axis_permutation,
    pose_features,
    pose_vertices,
    rigid_to_dual_quaternion,
    skinning_transforms,
)

__all__ = [
    "SKINNINGS",
    "HeadNeckModel",
    "blend_shapes",
    "dual_quaternion_pivots",
    "dual_quaternion_skinning",
    "forward_kinematics",
    "larynx_offsets",
    "larynx_scalar",
    "linear_blend_skinning",
    "nearest_axis_permutation",
    "pose_features",
    "pose_vertices",
    "rigid_to_dual_quaternion",
    "skinning_transforms",
]
