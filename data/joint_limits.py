"""Anatomical joint limits of the cervical spine, the paper's pose priors, and a clamp.

Angles are Euler angles of each joint's rotation in its *anatomical* frame
(``HeadNeckModel.to_anatomical``; on the built-in rig the bone frames are
anatomical already, on the release oc1's is not), with
``R = Rz(az) Ry(ay) Rx(ax)`` (``base.rotations``): ``ax`` flexion (+) /
extension (-), ``ay`` axial rotation (+ = to the subject's left), ``az``
lateral bending (+ = to the subject's right).

Ranges per motion segment, degrees.  Representative values from White &
Panjabi, *Clinical Biomechanics of the Spine*, 2nd ed., Lippincott 1990,
tables 2-1 (occipito-atlanto-axial complex) and 2-3 (lower cervical spine):
combined flexion+extension, lateral bending to one side, axial rotation to
one side.  The flexion/extension split at O-C1 and C1-C2 follows Panjabi et
al., "Three-dimensional movements of the upper cervical spine", Spine
13(7):726-730, 1988 (O-C1 flexion 3.5, extension 21.0; C1-C2 flexion 11.5,
extension 10.9); below C2 the sagittal range is split evenly, as in vivo
mid-cervical motion is close to symmetric about neutral (our assumption).

    level   flex  ext  lat(one side)  axial(one side)
    C7-T1    4.5  4.5   4              2
    C6-C7    8.5  8.5   7              6
    C5-C6   10   10     8              7
    C4-C5   10   10    11              7
    C3-C4    7.5  7.5  11              7
    C2-C3    5    5    10              3
    C1-C2   11.5 10.9   5             40
    O-C1     3.5 21.0   5              5
"""
from __future__ import annotations

import numpy as np
import torch

from base.rotations import axis_angle_to_euler, euler_to_axis_angle

JOINT_LEVELS = ("C7-T1", "C6-C7", "C5-C6", "C4-C5", "C3-C4", "C2-C3", "C1-C2", "O-C1")  # root to head

# [J, 4]: flexion, extension, lateral bending (one side), axial rotation (one side), degrees.
RANGES_DEG = np.array([
    [4.5, 4.5, 4.0, 2.0],
    [8.5, 8.5, 7.0, 6.0],
    [10.0, 10.0, 8.0, 7.0],
    [10.0, 10.0, 11.0, 7.0],
    [7.5, 7.5, 11.0, 7.0],
    [5.0, 5.0, 10.0, 3.0],
    [11.5, 10.9, 5.0, 40.0],
    [3.5, 21.0, 5.0, 5.0],
])


def euler_limits(margin: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper Euler limits [J,3] in radians, (ax, ay, az) order, ranges scaled by ``margin``."""
    flexion, extension, lateral, axial = np.radians(RANGES_DEG).T * margin
    lower = np.stack([-extension, -axial, -lateral], axis=1)
    upper = np.stack([flexion, axial, lateral], axis=1)
    return torch.tensor(lower, dtype=torch.float32), torch.tensor(upper, dtype=torch.float32)


def range_of_motion_shares() -> tuple[torch.Tensor, torch.Tensor]:
    """Each joint's share of the chain's range per Euler axis (ax, ay, az), for positive and negative
    motion: [J,3] each, columns summing to 1.

    Positive: flexion, axial rotation, lateral bending; negative: extension, axial, lateral.
    """
    flexion, extension, lateral, axial = torch.tensor(RANGES_DEG, dtype=torch.float32).T
    positive = torch.stack([flexion, axial, lateral], dim=1)
    negative = torch.stack([extension, axial, lateral], dim=1)
    return positive / positive.sum(0), negative / negative.sum(0)


def rotation_limit_energy(theta: torch.Tensor, margin: float = 1.0) -> torch.Tensor:
    """The paper's E_rot: squared excess of each joint's Euler angles over its limits.

    theta [B,J,3] axis-angle in anatomical frames -> [B] (radians^2).
    """
    lower, upper = (x.to(theta) for x in euler_limits(margin))
    euler = axis_angle_to_euler(theta)
    excess = torch.relu(euler - upper) + torch.relu(lower - euler)
    return (excess**2).sum(dim=(1, 2))


def adjacent_similarity_energy(theta: torch.Tensor, parents: list[int] | None = None) -> torch.Tensor:
    """The paper's E_sim: squared difference of each joint's rotation from its parent's.

    theta [B,J,3] axis-angle -> [B].  ``parents`` defaults to a chain.
    """
    parents = list(range(-1, theta.shape[1] - 1)) if parents is None else parents
    children = [j for j, p in enumerate(parents) if p >= 0]
    return ((theta[:, children] - theta[:, [parents[j] for j in children]]) ** 2).sum(dim=(1, 2))


def clamp_to_limits(theta: torch.Tensor, margin: float = 1.0) -> torch.Tensor:
    """Clamp each joint's Euler angles into its limits.  theta [B,J,3] (anatomical frames) -> [B,J,3]."""
    lower, upper = (x.to(theta) for x in euler_limits(margin))
    euler = axis_angle_to_euler(theta)
    return euler_to_axis_angle(torch.clamp(euler, lower, upper))


def within_limits(theta: torch.Tensor, margin: float = 1.0, tolerance: float = 1e-4) -> torch.Tensor:
    """[B,J] True where a joint's Euler angles (anatomical frames) lie inside its limits (+ ``tolerance`` rad)."""
    lower, upper = (x.to(theta) for x in euler_limits(margin))
    euler = axis_angle_to_euler(theta)
    return ((euler >= lower - tolerance) & (euler <= upper + tolerance)).all(dim=-1)
