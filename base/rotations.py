"""Rotation conversions: the project's one place for them (kornia underneath).

Conventions owned here:
- torch tensors through kornia; numpy float64 arrays (``*_np``, for few-frame work where torch's per-call
  cost dominates) through scipy's ``Rotation``, in the same conventions.
- Axis-angle ("rotation vector") ``[..., 3]`` in radians, right-handed.
- Quaternions ``[..., 4]`` as ``(w, x, y, z)``; ``quaternion_multiply(a, b)`` is the rotation b
  followed by a (Hamilton product).
- 6D representation ``[..., 6]``: the first two *columns* of the rotation
  matrix, concatenated (Zhou et al., "On the Continuity of Rotation
  Representations in Neural Networks", CVPR 2019).
- Euler angles ``[..., 3]`` as ``(ax, ay, az)`` about x, y and z of the frame
  the rotation acts in, composed ``R = Rz(az) @ Ry(ay) @ Rx(ax)``.  In a
  joint's anatomical frame (``HeadNeckModel.to_anatomical``: x lateral to the
  subject's left, y up the spine, z forward) ``ax`` is flexion (+) / extension (-), ``ay`` axial rotation
  (+ = towards the subject's left) and ``az`` lateral bending (+ = towards the
  subject's right); ``ay`` stays far from the +-90 degree singularity in any
  physiological pose.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry import conversions as kc
from scipy.spatial.transform import Rotation


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """[..., 3] radians -> [..., 3, 3]."""
    shape = axis_angle.shape[:-1]
    return kc.axis_angle_to_rotation_matrix(axis_angle.reshape(-1, 3)).reshape(*shape, 3, 3)


# The log map from the skew part of R: w = vee((R - R^T) / 2) = sin(angle) axis, cos(angle) = (trace - 1) / 2.
# Exact and a dozen operations away from angle pi; within NEAR_PI of it, where w vanishes, the conversion
# through the quaternion (kornia; scipy for numpy) takes over.
NEAR_PI = 0.1


def _skew_vector(matrix):
    return 0.5 * (matrix[..., [2, 0, 1], [1, 2, 0]] - matrix[..., [1, 2, 0], [2, 0, 1]])


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation matrices -> [..., 3] radians, angle in [0, pi] (differentiable, finite gradients
    at the identity)."""
    skew = _skew_vector(matrix)
    sine = torch.sqrt((skew * skew).sum(-1).clamp_min(1e-30))
    angle = torch.atan2(sine, 0.5 * (matrix.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0))
    out = skew * (angle / sine)[..., None]                        # angle / sin(angle) -> 1 at the identity
    near_pi = angle > torch.pi - NEAR_PI
    if not matrix.is_meta and bool(near_pi.any()):  # (meta tensors carry shapes only: nothing to choose)
        through_quaternion = kc.rotation_matrix_to_axis_angle(matrix.reshape(-1, 3, 3)).reshape(out.shape)
        out = torch.where(near_pi[..., None], through_quaternion, out)
    return out


def matrix_to_quaternion(matrix: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] -> [..., 4] (w, x, y, z) with w >= 0."""
    shape = matrix.shape[:-2]
    q = kc.rotation_matrix_to_quaternion(matrix.reshape(-1, 3, 3))
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(*shape, 4)


def quaternion_to_matrix(quaternion: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z), normalised here -> [..., 3, 3]."""
    shape = quaternion.shape[:-1]
    q = F.normalize(quaternion.reshape(-1, 4), dim=-1)
    return kc.quaternion_to_rotation_matrix(q).reshape(*shape, 3, 3)


def axis_angle_to_quaternion(axis_angle: torch.Tensor) -> torch.Tensor:
    """[..., 3] radians -> [..., 4] (w, x, y, z)."""
    return kc.axis_angle_to_quaternion(axis_angle)


def quaternion_to_axis_angle(quaternion: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z), unit -> [..., 3] radians, angle in [0, pi]."""
    return kc.quaternion_to_axis_angle(quaternion)


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b`` of (w, x, y, z) quaternions [..., 4] (the rotation b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def matrix_to_rot6d(matrix: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] -> [..., 6]: first two columns."""
    return torch.cat([matrix[..., :, 0], matrix[..., :, 1]], dim=-1)


def quaternion_to_euler(quaternion: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z), unit -> [..., 3] (ax, ay, az) with ``R = Rz(az) Ry(ay) Rx(ax)``."""
    roll, pitch, yaw = kc.euler_from_quaternion(*quaternion.unbind(-1))
    return torch.stack([roll, pitch, yaw], dim=-1)


def euler_to_quaternion(euler: torch.Tensor) -> torch.Tensor:
    """[..., 3] (ax, ay, az) -> [..., 4] (w, x, y, z) of ``Rz(az) Ry(ay) Rx(ax)``."""
    return torch.stack(kc.quaternion_from_euler(euler[..., 0], euler[..., 1], euler[..., 2]), dim=-1)


def matrix_to_euler(matrix: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] -> [..., 3] (ax, ay, az) with ``R = Rz(az) Ry(ay) Rx(ax)``."""
    return quaternion_to_euler(matrix_to_quaternion(matrix))


def euler_to_matrix(euler: torch.Tensor) -> torch.Tensor:
    """[..., 3] (ax, ay, az) -> [..., 3, 3] ``Rz(az) Ry(ay) Rx(ax)``."""
    return quaternion_to_matrix(euler_to_quaternion(euler))


# Through quaternions, not matrices: the same values (to float rounding), ~5x faster.
def axis_angle_to_euler(axis_angle: torch.Tensor) -> torch.Tensor:
    return quaternion_to_euler(axis_angle_to_quaternion(axis_angle))


def euler_to_axis_angle(euler: torch.Tensor) -> torch.Tensor:
    return quaternion_to_axis_angle(euler_to_quaternion(euler))


def ypr_to_matrix(ypr: torch.Tensor) -> torch.Tensor:
    """Head yaw, pitch, roll [...,3] radians -> [...,3,3] ``Ry(yaw) @ Rx(pitch) @ Rz(roll)`` (intrinsic: yaw,
    then pitch, then roll; in the rig's frame + yaw turns the face to the subject's left, + pitch looks
    down, + roll tilts towards the right shoulder; ``motion.head2neck`` maps tracker angles onto it)."""
    cos, sin = torch.cos(ypr), torch.sin(ypr)
    cy, cp, cr = cos.unbind(-1)
    sy, sp, sr = sin.unbind(-1)
    # Ry(yaw) @ Rx(pitch) @ Rz(roll) multiplied out
    return torch.stack([torch.stack([cy * cr + sy * sp * sr, -cy * sr + sy * sp * cr, sy * cp], -1),
                        torch.stack([cp * sr, cp * cr, -sp], -1),
                        torch.stack([-sy * cr + cy * sp * sr, sy * sr + cy * sp * cr, cy * cp], -1)], -2)


def relative_angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Geodesic angle in radians between rotation matrices [..., 3, 3] (stable near 0 and pi)."""
    r = a.transpose(-1, -2) @ b
    skew = torch.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    return torch.atan2(0.5 * skew.norm(dim=-1), 0.5 * (trace - 1.0))


# ----------------------------------------------------------------------------- numpy (scipy), same conventions
# scipy's lower-case "xyz" is extrinsic: x, then y, then z about the fixed axes, i.e. Rz(az) Ry(ay) Rx(ax).


def euler_to_matrix_np(euler: np.ndarray) -> np.ndarray:
    """[..., 3] (ax, ay, az) -> [..., 3, 3] ``Rz(az) Ry(ay) Rx(ax)``, multiplied out."""
    euler = np.asarray(euler, dtype=np.float64)
    cos, sin = np.cos(euler), np.sin(euler)
    cx, cy, cz, sx, sy, sz = cos[..., 0], cos[..., 1], cos[..., 2], sin[..., 0], sin[..., 1], sin[..., 2]
    out = np.empty((*euler.shape[:-1], 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx
    out[..., 2, 0], out[..., 2, 1], out[..., 2, 2] = -sy, cy * sx, cy * cx
    return out


def euler_to_axis_angle_np(euler: np.ndarray) -> np.ndarray:
    """[..., 3] (ax, ay, az) -> [..., 3] radians, angle in [0, pi]."""
    euler = np.asarray(euler, dtype=np.float64)
    return Rotation.from_euler("xyz", euler.reshape(-1, 3)).as_rotvec().reshape(euler.shape)


def axis_angle_to_euler_np(axis_angle: np.ndarray) -> np.ndarray:
    """[..., 3] radians -> [..., 3] (ax, ay, az) with ``R = Rz(az) Ry(ay) Rx(ax)``, ay in [-pi/2, pi/2]."""
    axis_angle = np.asarray(axis_angle, dtype=np.float64)
    return Rotation.from_rotvec(axis_angle.reshape(-1, 3)).as_euler("xyz").reshape(axis_angle.shape)


def matrix_to_axis_angle_np(matrix: np.ndarray) -> np.ndarray:
    """[..., 3, 3] rotation matrices -> [..., 3] radians, angle in [0, pi] (as :func:`matrix_to_axis_angle`)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    skew = _skew_vector(matrix)
    sine = np.sqrt((skew * skew).sum(-1))
    angle = np.arctan2(sine, 0.5 * (np.trace(matrix, axis1=-2, axis2=-1) - 1.0))
    out = skew * np.where(sine > 1e-12, angle / np.maximum(sine, 1e-300), 1.0)[..., None]
    near_pi = angle > np.pi - NEAR_PI
    if near_pi.any():
        out[near_pi] = Rotation.from_matrix(matrix[near_pi]).as_rotvec()
    return out


def matrix_to_ypr_np(matrix: np.ndarray) -> np.ndarray:
    """Head orientations [..., 3, 3] -> yaw, pitch, roll [..., 3] radians: the inverse of :func:`ypr_to_matrix`
    (``R = Ry(yaw) Rx(pitch) Rz(roll)``, |pitch| < 90 degrees)."""
    r = np.asarray(matrix, dtype=np.float64)
    return np.stack([np.arctan2(r[..., 0, 2], r[..., 2, 2]), np.arcsin(-np.clip(r[..., 1, 2], -1.0, 1.0)),
                     np.arctan2(r[..., 1, 0], r[..., 1, 1])], axis=-1)


def nearest_rotation_np(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest to a roughly orthonormal [..., 3, 3] (scipy's orthonormalisation)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    return Rotation.from_matrix(matrix.reshape(-1, 3, 3)).as_matrix().reshape(matrix.shape)
