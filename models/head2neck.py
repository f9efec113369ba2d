"""Head orientation -> the 8 cervical joint rotations: the MLP, analytic baselines, and the exact correction.

Facial trackers give one head orientation ``H`` (``[B,3,3]``, the rig's world
frame, the definition of ``HeadNeckModel.head_rotation``); HACK needs theta
``[B,8,3]`` (axis-angle per joint in its bone frame).  Everything here works in
the joints' *anatomical* frames (``HeadNeckModel.to_anatomical``), where the
joint limits are written; :func:`predict_theta` returns bone-frame theta for
the rig.  With ``C_j`` the rest world rotation of joint j's anatomical frame
(``HeadNeckModel.anatomical_rest_rotations``) and ``R_j = exp(theta_j)``, the chain's head
orientation is ``H(theta) = prod_j C_j R_j C_j^T`` (root first), so joint j
contributes the world rotation vector ``C_j theta_j`` when the joints rotate
about one axis.

Baselines (``split_head_rotation``): the head's rotation vector ``v = log(H)``
expressed in each joint's anatomical frame, ``C_j^T v``, is split per axis by
shares that sum to 1 over the joints: ``theta_j = s_j * (C_j^T v)`` (component-wise).
- *uniform*: ``s_j = 1/8`` on every axis.  Every joint then rotates by
  ``v / 8`` in the world, so the chain reproduces H exactly.
- *rom*: each joint's share of the chain's range of motion on that axis
  (``data.joint_limits.range_of_motion_shares``: flexion or extension by the
  sign of the x component, axial rotation for y, lateral bending for z).
- *invivo*: the in-vivo prior's measured shares (``data.cervical_prior``),
  which change with the size of the motion (:func:`invivo_shares`): a small
  yaw goes mostly to C1-C2, flexion spreads down the neck as it grows.  It
  has none of the prior's coupling.
The joint frames are not parallel, so the last two reproduce H only
approximately; :func:`correct_to_head` makes them exact.

Model (:class:`Head2NeckMLP`, sizes in :class:`Head2NeckConfig`): an MLP (2
hidden layers of 512 by default) on the 6D representation of H
(``base.rotations.matrix_to_rot6d``, minus the identity's, times
``input_scale``) whose output is added to a split,
``theta = split(H) + residual_scale * MLP(H)`` (``base``: the in-vivo split by
default); the last layer starts at zero, so an untrained model is that
split.  The model holds no rig: the rest frames C_j are an argument of
``forward`` (read from the rig in use by :func:`predict_theta`), so one
checkpoint serves the built-in rig and the real release alike.

Correction (:func:`correct_to_head`), making the chain reproduce H: damped
Gauss-Newton steps on the residual rotation ``rho = log(H H(theta)^T)`` (world
frame), taken on the joints' Euler angles ``e_j`` (the angles the limits are
written in, so keeping them is a clamp).  A change ``de_j`` turns joint j by
``E_j de_j`` in its parent-side frame (``E_j``: Euler-rate axes) and the head
by ``M_j E_j de_j``, with ``M_j`` joint j's posed world frame before its own
rotation; so ``rho = J de`` with J ``[3, 3*8]``.  The step is the weighted
minimum-norm solution ``de = W J^T (J W J^T + damping I)^-1 rho``, W the
remaining range of each Euler angle in the direction the step moves it (the
sign of ``J^T rho``): the residual is spread over the joints in proportion to
the range they have left, and joints at a limit take none.  The angles are
clamped into the limits after each step.  From the MLP's output (residual
< 1 degree) one step leaves ~1e-4 degrees; from the ROM split (~10 degrees)
two steps; the loop stops once every residual is below ``tolerance_deg``.  A
target outside the chain's range keeps the residual the limits impose
(:func:`head_error_deg` reports it).  The chain's head orientation for training's losses is the
rig's forward kinematics on rotations alone (:func:`chain_head_rotation`), ``HeadNeckModel.head_rotation``
without the translations.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np
import torch
from torch import nn

from base.errors import InputError
from base.rotations import (
    axis_angle_to_euler_np,
    axis_angle_to_matrix,
    euler_to_axis_angle_np,
    euler_to_matrix_np,
    matrix_to_axis_angle,
    matrix_to_axis_angle_np,
    matrix_to_rot6d,
    relative_angle,
)
from data.cervical_prior import AXIAL, EXT, FLEX, FULL_SHARES, HEAD_RANGE_DEG, LAT, START_SHARES
from data.joint_limits import JOINT_LEVELS, euler_limits, range_of_motion_shares
from models.rig import forward_kinematics

NUM_JOINTS = len(JOINT_LEVELS)
SPLITS = ("uniform", "rom", "invivo")
BASES = ("rom", "invivo")
# In place where torch offers it: the same values and gradients, and ~1.4x faster inference on CPU
# (no fresh [B,512] buffers to fault in).
ACTIVATIONS = {"silu": lambda: nn.SiLU(inplace=True), "relu": lambda: nn.ReLU(inplace=True), "gelu": nn.GELU,
               "tanh": nn.Tanh}


# ----------------------------------------------------------------------------- baselines


def split_head_rotation(head_rotations: torch.Tensor, rest: torch.Tensor, split: str) -> torch.Tensor:
    """Analytic baseline: the head's rotation vector split over the joints by shares per axis.

    head_rotations [B,3,3], rest [J,3,3] (C_j, ``rig.anatomical_rest_rotations``) -> anatomical
    theta [B,J,3].  ``split``: "uniform" or "rom".
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split '{split}', expected one of {', '.join(SPLITS)}")
    v = matrix_to_axis_angle(head_rotations)                                   # [B,3] world
    in_joint_frames = torch.einsum("jkc,bk->bjc", rest.to(v), v)              # C_j^T v  [B,J,3]
    if split == "uniform":
        return in_joint_frames / rest.shape[0]
    if split == "invivo":
        return in_joint_frames * invivo_shares(in_joint_frames)
    positive, negative = range_of_motion_shares()
    return in_joint_frames * torch.where(in_joint_frames >= 0, positive.to(v), negative.to(v))


@functools.lru_cache(maxsize=8)
def _invivo_constants(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, ...]:
    """The in-vivo prior's start shares and half their change to the end shares [4 directions, J], the head
    range [4] (radians) and each direction's axis [4] (x: flexion and extension, y: axial, z: lateral), built
    once per dtype and device."""
    start = torch.tensor(START_SHARES, dtype=dtype, device=device)
    half_change = torch.tensor(FULL_SHARES, dtype=dtype, device=device) - start  # (end - start) / 2
    axis = torch.zeros(4, dtype=torch.long, device=device)
    axis[AXIAL], axis[LAT] = 1, 2
    return start, half_change, torch.deg2rad(torch.tensor(HEAD_RANGE_DEG, dtype=dtype, device=device)), axis


def invivo_shares(components: torch.Tensor) -> torch.Tensor:
    """The in-vivo prior's mean shares (``data.cervical_prior``: measured segmental contributions that change
    with the size of the motion) for the head's rotation in the joints' frames.

    components [B,J,3] (``C_j^T v``) -> shares [B,J,3] summing to 1 over J per axis: for axis c (x: flexion
    or extension by the sign, y: axial rotation, z: lateral bending) the share of a motion of size
    ``m = mean_j |u_jc| / T_c`` (T the default head range) is ``s0 + (s1 - s0) min(m, 1) / 2``.
    """
    start, half_change, head_range, axis = _invivo_constants(components.dtype, components.device)
    size = components.abs().mean(1)                                               # [B,3]
    # All four directions at once (one frame of the live receiver is a few dozen such calls).
    shares = start + half_change * (size[:, axis] / head_range).clamp(max=1.0)[..., None]   # [B,4,J]
    sagittal = torch.where(components[..., 0] >= 0, shares[:, FLEX], shares[:, EXT])
    return torch.stack([sagittal, shares[:, AXIAL], shares[:, LAT]], dim=-1)


# ----------------------------------------------------------------------------- the MLP


@dataclass
class Head2NeckConfig:
    """Sizes of :class:`Head2NeckMLP` (the ``model`` group of ``python train.py task=head2neck``).

    Nothing here depends on a rig: the model reads the rig's joint rest frames when it runs.
    """

    hidden: list[int] = field(default_factory=lambda: [512, 512])  # widths of the hidden layers
    activation: str = "silu"          # silu | relu | gelu | tanh
    residual_scale: float = 0.1       # theta = base split + residual_scale * MLP(rot6d(H)), radians
    base: str = "invivo"              # the split the MLP corrects: invivo (the prior's measured shares) | rom
    # The MLP sees (rot6d(H) - rot6d(I)) * input_scale: head rotations of a few degrees at unit scale, so it
    # resolves how the shares change with the size of small motions (measured: 0.90 -> 0.73 deg on the
    # prior with hidden [128,128] after 400 steps, input_scale 1 -> 10).
    input_scale: float = 10.0

    def __post_init__(self) -> None:
        """ValueError naming the field out of range."""
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation={self.activation}: expected one of {', '.join(ACTIVATIONS)}")
        if not list(self.hidden) or any(int(width) < 1 for width in self.hidden):
            raise ValueError(f"hidden={list(self.hidden)}: expected one or more positive layer widths")
        if not float(self.residual_scale) > 0:
            raise ValueError(f"residual_scale={self.residual_scale}: expected a positive scale")
        if not float(self.input_scale) > 0:
            raise ValueError(f"input_scale={self.input_scale}: expected a positive scale")
        if self.base not in BASES:
            raise ValueError(f"base={self.base}: expected one of {', '.join(BASES)}")


class Head2NeckMLP(nn.Module):
    """Head orientation [B,3,3] -> anatomical theta [B,J,3]: ROM split + residual_scale * MLP(rot6d(H)).

    Rig-independent: the joints' rest frames C_j (``rig.anatomical_rest_rotations``, [J,3,3]) are an input
    of :meth:`forward`, so one trained model serves every rig with the 8 cervical joints.
    """

    def __init__(self, config: Head2NeckConfig | None = None, num_joints: int = NUM_JOINTS):
        super().__init__()
        self.config = Head2NeckConfig() if config is None else config
        self.num_joints = int(num_joints)
        self.residual_scale = float(self.config.residual_scale)
        self.input_scale = float(self.config.input_scale)
        self.register_buffer("identity", matrix_to_rot6d(torch.eye(3)), persistent=False)
        layers: list[nn.Module] = []
        width = 6
        for size in self.config.hidden:
            layers += [nn.Linear(width, int(size)), ACTIVATIONS[self.config.activation]()]
            width = int(size)
        last = nn.Linear(width, self.num_joints * 3)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(*layers, last)

    def forward(self, head_rotations: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
        """head_rotations [B,3,3] (world frame, relative to rest), rest [J,3,3] (the rig's C_j) ->
        anatomical theta [B,J,3] (axis-angle radians), before the exact correction."""
        base = split_head_rotation(head_rotations, rest, self.config.base)
        features = (matrix_to_rot6d(head_rotations) - self.identity.to(head_rotations)) * self.input_scale
        residual = self.mlp(features).reshape(-1, self.num_joints, 3)
        return base + self.residual_scale * residual


def build_model(model_config: dict) -> Head2NeckMLP:
    """The model of a checkpoint's ``model_config`` (the fields of :class:`Head2NeckConfig`); unknown or
    missing keys, or values out of range, are a ValueError."""
    names = {f.name for f in fields(Head2NeckConfig)}
    unknown, missing = sorted(set(model_config) - names), sorted(names - set(model_config))
    if unknown or missing:
        raise ValueError(f"head2neck model config: unknown keys {unknown}, missing {missing}; expected "
                         f"{sorted(names)}")
    return Head2NeckMLP(Head2NeckConfig(**{k: (list(v) if k == "hidden" else v) for k, v in model_config.items()}))


def model_config(model: Head2NeckMLP) -> dict:
    """What :func:`build_model` needs to rebuild ``model`` (plain values, for a checkpoint)."""
    return {"hidden": [int(w) for w in model.config.hidden], "activation": str(model.config.activation),
            "residual_scale": float(model.config.residual_scale), "base": str(model.config.base),
            "input_scale": float(model.config.input_scale)}


# ----------------------------------------------------------------------------- kinematics and correction


def chain_to(parents: Sequence[int], joint: int) -> list[int]:
    """Indices of ``joint`` and its ancestors, root first."""
    chain = []
    while joint >= 0:
        chain.append(joint)
        joint = parents[joint]
    return chain[::-1]


def chain_head_rotation(theta: torch.Tensor, rig) -> torch.Tensor:
    """Head orientation [B,3,3] of anatomical theta [B,J,3]: ``rig.head_rotation(rig.from_anatomical(theta))``
    by the rig's forward kinematics on rotations alone (``models.rig.forward_kinematics``), in the anatomical
    frames.  With the rest rotations ``C_parent^T C_j`` between them the world frame of joint j is ``Q_j C_j``
    (``Q_j = Q_parent C_j R_j C_j^T``), so the head is ``G_oc1 C_oc1^T``.  Reads the rig's ``parents`` and
    ``anatomical_rest_rotations`` only; differentiable."""
    rest = rig.anatomical_rest_rotations.to(theta)
    between = torch.stack([rest[j] if p < 0 else rest[p].T @ rest[j] for j, p in enumerate(rig.parents)])
    return forward_kinematics(axis_angle_to_matrix(theta), between, rig.parents)[:, -1] @ rest[-1].T


def euler_rate_axes(euler: np.ndarray) -> np.ndarray:
    """Columns mapping Euler-angle rates to the spatial angular velocity of ``R = Rz Ry Rx``.

    euler [...,3] (ax, ay, az) -> [...,3,3] with columns Rz Ry e_x, Rz e_y, e_z.
    """
    cy, sy = np.cos(euler[..., 1]), np.sin(euler[..., 1])
    cz, sz = np.cos(euler[..., 2]), np.sin(euler[..., 2])
    axes = np.zeros((*euler.shape[:-1], 3, 3))
    axes[..., 0, 0], axes[..., 1, 0], axes[..., 2, 0] = cz * cy, sz * cy, -sy
    axes[..., 0, 1], axes[..., 1, 1], axes[..., 2, 2] = -sz, cz, 1.0
    return axes


@functools.lru_cache(maxsize=8)
def _euler_limits_np(margin: float) -> tuple[np.ndarray, np.ndarray]:
    """``data.joint_limits.euler_limits(margin)`` as float64 arrays, built once per margin."""
    return tuple(x.numpy().astype(np.float64) for x in euler_limits(margin))


def correct_to_head(theta: torch.Tensor, head_rotations: torch.Tensor, rig, iterations: int = 3,
                    tolerance_deg: float = 1e-3, damping: float = 1e-8, margin: float = 1.0,
                    rest: torch.Tensor | None = None) -> torch.Tensor:
    """Spread the residual between the chain's head orientation and the target over the joints.

    theta [B,J,3] (anatomical frames), head_rotations [B,3,3] (target) -> theta [B,J,3] (anatomical
    frames, theta's dtype) inside the joint limits (``margin`` scales them) whose head orientation matches
    the target (see the module docstring).  At most ``iterations`` steps, fewer once every residual is below
    ``tolerance_deg``.  The steps are taken on the joints' Euler angles, so the limits are a clamp: with E_j
    the Euler-rate axes (:func:`euler_rate_axes`) the Jacobian of the head's world rotation vector is
    ``M_j E_j``.  Computed in float64 numpy on 3x3 matrices: a step is a few dozen small array operations,
    where torch's per-call cost made one frame take ~5 ms (the live receiver's budget; bench_live.py).
    ``rest``: ``rig.anatomical_rest_rotations`` when the caller has them.  Not differentiable (training's losses
    use :func:`chain_head_rotation`).
    """
    chain = chain_to(rig.parents, len(rig.parents) - 1)
    rest = rig.anatomical_rest_rotations if rest is None else rest
    rest = rest[chain].detach().cpu().numpy().astype(np.float64)                               # C_j [K,3,3]
    lower, upper = (limit[chain] for limit in _euler_limits_np(margin))
    target = head_rotations.detach().cpu().numpy().astype(np.float64)                          # [B,3,3]
    out = theta.detach().cpu().numpy().astype(np.float64)
    euler = np.clip(axis_angle_to_euler_np(out[:, chain]), lower, upper)                        # [B,K,3]
    eye = damping * np.eye(3)
    identity = np.repeat(np.eye(3)[None], len(target), axis=0)
    tolerance = math.radians(tolerance_deg)
    for step in range(iterations + 1):
        world = rest @ euler_to_matrix_np(euler) @ rest.transpose(0, 2, 1)                      # C_j R_j C_j^T
        prefix = [identity]                                                                     # Q_parent(j)
        for k in range(len(chain)):
            prefix.append(prefix[-1] @ world[:, k])
        # rho: the world rotation taking the chain's head to the target, log(H Q^T)
        rho = matrix_to_axis_angle_np(target @ prefix[-1].transpose(0, 2, 1))                   # [B,3]
        if step == iterations or float(np.linalg.norm(rho, axis=-1).max(initial=0.0)) < tolerance:
            break
        frames = np.stack(prefix[:-1], axis=1) @ rest                                         # M_j [B,K,3,3]
        jacobian = frames @ euler_rate_axes(euler)                                              # [B,K,3(i),3(c)]
        gradient = np.einsum("bkic,bi->bkc", jacobian, rho)                                     # J^T rho
        weight = np.maximum(np.where(gradient >= 0, upper - euler, euler - lower), 1e-6)
        normal = np.einsum("bkic,bkc,bkjc->bij", jacobian, weight, jacobian) + eye
        multiplier = np.linalg.solve(normal, rho[..., None])[..., 0]
        update = weight * np.einsum("bkic,bi->bkc", jacobian, multiplier)                       # W J^T lambda
        euler = np.clip(euler + update, lower, upper)
    out[:, chain] = euler_to_axis_angle_np(euler)
    return torch.as_tensor(out, dtype=theta.dtype, device=theta.device)


def head_error_deg(theta: torch.Tensor, head_rotations: torch.Tensor, rig) -> torch.Tensor:
    """Angle (degrees) between the head orientation of anatomical theta [B,J,3] (``rig.head_rotation``,
    the full forward kinematics) and the target [B,3,3].  -> [B]."""
    head = rig.head_rotation(rig.from_anatomical(theta))
    return torch.rad2deg(relative_angle(head, head_rotations.to(head)))


def check_rig(model: Head2NeckMLP, rig) -> None:
    """InputError unless ``rig`` has the model's cervical chain: ``num_joints`` joints, each the child of the
    one before (root c7t1 to head oc1)."""
    chain = list(range(-1, model.num_joints - 1))
    if list(rig.parents) != chain:
        raise InputError(f"the rig's skeleton (parents {list(rig.parents)}) is not the {model.num_joints}-joint "
                         f"cervical chain the head2neck model drives (parents {chain})")


@torch.no_grad()
def predict_theta(model: Head2NeckMLP, rig, head_rotations: torch.Tensor, iterations: int = 3,
                  chunk: int = 4096) -> torch.Tensor:
    """Head orientations [T,3,3] -> bone-frame theta [T,J,3] for ``rig``: the MLP, then the exact
    correction, in chunks."""
    check_rig(model, rig)
    head_rotations = torch.as_tensor(head_rotations, dtype=torch.float32)
    if head_rotations.ndim != 3 or head_rotations.shape[1:] != (3, 3):
        raise InputError(f"head_rotations has shape {list(head_rotations.shape)}, expected [T,3,3]")
    rest = rig.anatomical_rest_rotations
    out = [correct_to_head(model(part, rest), part, rig, iterations, rest=rest)
           for part in head_rotations.split(chunk)]
    return rig.from_anatomical(torch.cat(out)) if out else head_rotations.new_zeros(0, model.num_joints, 3)
