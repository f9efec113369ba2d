"""Joint rotations carried from a source rig to a target through their anatomical frames: per joint and
axis gains (the giraffe's: :data:`GIRAFFE_GAINS`, explained in ``motion.retarget.cli``), the target's limits.
"""
from __future__ import annotations

import numpy as np
import torch

from base.errors import InputError
from base.rotations import axis_angle_to_euler, euler_to_axis_angle
from data.joint_limits import RANGES_DEG, euler_limits
from data.params import AnimationParams, fit_fields, rig_checksum
from models.rig import HeadNeckModel
from scene.characters import character_kind

GAIN_CHOICES = ("auto", "unit", "giraffe")


# Gains at c7t1 (the giraffe's fulcrum, standing in for T1-T2), per anatomical Euler axis
# (flexion/extension ax, axial rotation ay, lateral bend az): see the docstring of motion.retarget.cli.
FULCRUM_GAINS = np.array([3.0, 1.0, 2.0])


def _giraffe_gains() -> np.ndarray:
    flexion, extension, lateral, axial = RANGES_DEG.T
    ranges = np.stack([flexion + extension, axial, lateral], axis=1)       # [J,3] per Euler axis
    gains = np.ones_like(ranges)
    gains[0] = FULCRUM_GAINS
    # The other joints share what keeps sum_j gain_j * range_j = sum_j range_j per axis.
    rest = (ranges.sum(0) - FULCRUM_GAINS * ranges[0]) / (ranges.sum(0) - ranges[0])
    gains[1:] = rest
    return gains


GIRAFFE_GAINS = _giraffe_gains()   # [8,3]: c7t1 (3, 1, 2), the others (0.860, 1, 0.930)


def giraffe_limits(margin: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The giraffe's Euler limits [J,3] (radians, (ax, ay, az)): the human's (``euler_limits``) times the
    default gains where they exceed 1 (c7t1: sagittal x3, lateral x2)."""
    lower, upper = euler_limits(margin)
    scale = torch.tensor(np.maximum(GIRAFFE_GAINS, 1.0), dtype=lower.dtype)
    return lower * scale, upper * scale


def character_limits(rig: HeadNeckModel, margin: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Euler limits [J,3] of a character: the giraffe's for a built giraffe, the human's otherwise."""
    return giraffe_limits(margin) if character_kind(rig.rig) == "giraffe" else euler_limits(margin)


def default_gains(target: HeadNeckModel, choice: str = "auto") -> np.ndarray | None:
    """Gains [J,3] for ``choice`` (auto: the giraffe's on a giraffe, none otherwise; unit: none)."""
    if choice not in GAIN_CHOICES:
        raise InputError(f"gains={choice}: expected one of {', '.join(GAIN_CHOICES)}")
    if choice == "giraffe" or (choice == "auto" and character_kind(target.rig) == "giraffe"):
        return GIRAFFE_GAINS.copy()
    return None


def retarget_theta(theta: torch.Tensor, source: HeadNeckModel, target: HeadNeckModel,
                   gains: np.ndarray | torch.Tensor | None = None,
                   limits: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Carry joint rotations from ``source``'s bone frames to ``target``'s through the anatomical frames.

    Args:
        theta: [T,J,3] axis-angle radians in the source's bone frames.
        source, target: the rigs (same joint names).
        gains: [J,3] or [J] factors on each joint's anatomical Euler angles (flexion, axial, lateral), or None.
        limits: (lower, upper) [J,3] Euler limits (radians) of the target to clamp to, or None.
    Returns:
        [T,J,3] axis-angle in the target's bone frames.  Without gains and limits,
        ``target.to_anatomical(result) == source.to_anatomical(theta)`` exactly.
    """
    if source.joint_names != target.joint_names:
        raise InputError(f"joints differ: source {source.joint_names}, target {target.joint_names}")
    anatomical = source.to_anatomical(theta)
    if gains is not None or limits is not None:
        euler = axis_angle_to_euler(anatomical)
        if gains is not None:
            gains = torch.as_tensor(gains, dtype=euler.dtype)
            euler = euler * (gains[:, None] if gains.ndim == 1 else gains)
        if limits is not None:
            euler = torch.maximum(torch.minimum(euler, limits[1].to(euler)), limits[0].to(euler))
        anatomical = euler_to_axis_angle(euler)
    return target.from_anatomical(anatomical)


def retarget_params(params: AnimationParams, source: HeadNeckModel, target: HeadNeckModel, rig_label: str,
                    gains: np.ndarray | None = None, clamp: bool | None = None, margin: float = 1.0,
                    source_name: str = "params") -> AnimationParams:
    """``params`` (in ``source``'s bone frames) for ``target``: theta retargeted (:func:`retarget_theta`),
    clamped to the target's limits when ``clamp`` (None: when gains are given), psi by expression name,
    tau and eta as they are; ``rig_label`` names the target's rig in the result (with its checksum).  A fit's
    placement and residual carry over; its ``shape_offset`` (the person's rest mesh) only onto the same rig
    (``character=human``): another character has its own rest shape."""
    clamp = gains is not None if clamp is None else clamp
    limits = character_limits(target, margin) if clamp else None
    with torch.no_grad():
        # float64 through the Euler angles (the bone <-> anatomical turns are exact signed permutations)
        theta64 = torch.as_tensor(params.theta, dtype=torch.float64)
        theta = retarget_theta(theta64, source, target, gains, limits).float()
        head = target.head_rotation(theta).numpy()
    missing = [n for n in target.expression_names if n not in params.expression_names]
    if missing:
        raise InputError(f"{source_name}: no psi for the character's expressions {missing[:5]}")
    order = [params.expression_names.index(n) for n in target.expression_names]
    producers = dict(params.producers)
    producers.update({"tool": "motion.retarget", "retargeted_from": params.rig})
    checksum = rig_checksum(target.rig)
    same_rig = checksum == rig_checksum(source.rig)
    if params.shape_offset is not None and not same_rig:
        producers["shape_offset_dropped"] = "the fitted person's shape belongs to the source rig"
    return AnimationParams(time=params.time, fps=params.fps, psi=params.psi[:, order], tau=params.tau, eta=params.eta,
                           theta=theta.numpy(), head_rotation=head, joint_names=target.joint_names,
                           expression_names=target.expression_names, rig=rig_label,
                           rig_checksum=checksum, producers=producers, f0=params.f0,
                           tau_voice=params.tau_voice, **fit_fields(params, shape=same_rig))
