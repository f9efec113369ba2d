"""Drive HACK's cervical spine from head orientations: ``python -m motion.head2neck``.

    python -m motion.head2neck input=rotations.npy out=theta.npy [checkpoint=runs/head2neck/<run>/checkpoints/last.pt]
    python -m motion.head2neck input=ypr.npy input_format=ypr head_units=deg out=theta.npy
    python -m motion.head2neck input=take.csv out=theta.npy recenter=true rig=hack_rig.npz  # Live Link Face / ARKit CSV

Settings: :class:`Head2NeckCli` (``configs/head2neck.yaml``).  ``checkpoint=default`` (the default) is the
shipped model (``models/pretrained``); the model holds nothing of a rig, so ``rig=`` (default: the built-in
rig) says whose bone frames theta is written in.

Output: theta ``[T,8,3]`` float32 (axis-angle radians per joint in its bone frame, ``models.rig``),
one row per input frame, written atomically.  A CSV is resampled to a uniform grid at its own rate from
its first timestamp (Live Link Face drops lost-tracking rows; their frames are interpolated), so row t
is time ``start + t / fps``; start and rate are printed.
The model's output is made exact by the correction step (``models.head2neck.predict_theta``); the
remaining head orientation error and any joints outside the limits are printed.

Inputs (``input_format=auto`` picks by suffix and shape):
- ``matrix``: ``.npy`` ``[T,3,3]`` head orientations in the rig's world frame (y up, face towards +z,
  x to the subject's left), relative to the rest pose: ``HeadNeckModel.head_rotation``'s definition.
- ``ypr``: ``.npy`` ``[T,3]`` yaw, pitch, roll in ``head_units`` (rad | deg | halfturn, 1 halfturn = 180 deg).
- ``csv``: an expression capture read by ``data.expressions.read_expressions`` with ``HeadYaw,
  HeadPitch, HeadRoll`` columns (its ``head_ypr``).

Yaw/pitch/roll convention (``base.rotations.ypr_to_matrix``), in the rig's world frame::

    R = Ry(yaw) @ Rx(pitch) @ Rz(roll)        (intrinsic: yaw, then pitch, then roll)

- yaw about +y (up): + turns the face towards the subject's left;
- pitch about +x (the subject's left): + is flexion, the face looks down;
- roll about +z (forward): + tilts the head towards the subject's right shoulder.
Each sign is the rig's joint convention (``base.rotations``) applied to the whole head.

ARKit / Live Link Face ``HeadYaw, HeadPitch, HeadRoll``: ARKit's face anchor frame is x towards the
face's own left, y up, z out of the face (Apple, ``ARFaceAnchor`` documentation), the rig's frame, so
a face anchor rotation relative to a neutral, camera-facing pose is directly a ``matrix`` input.
Unreal's ARKit face support (``AppleARKitFaceSupport``, ``ToBlendShapeMap``) converts that rotation to
Unreal's left-handed frame (``FAppleARKitConversion::ToFTransform``), takes its ``FRotator`` and, when
the face is not mirrored, negates yaw and roll.  Working that through, a head turn to the subject's
left gives ``HeadYaw > 0``, looking down ``HeadPitch > 0`` and a tilt to the right shoulder
``HeadRoll > 0``, and ``FRotator``'s yaw-pitch-roll order is the order above: the mapping is the
identity, ``(yaw, pitch, roll) = (HeadYaw, HeadPitch, HeadRoll)``.  Uncertain, hence the options:
- signs: a mirrored face (Unreal's ``FaceMirrored``) flips yaw and roll, and users report HeadPitch and
  HeadYaw inverted with the phone in landscape; ``yaw_sign``, ``pitch_sign``, ``roll_sign`` (+-1)
  flip them.  Check with a recording of a known turn, nod and tilt;
- units: Unreal's live stream divides degrees by 180 (``units=halfturn``); the Live Link Face CSVs we
  have (../shared/samples) hold radians: their eye yaw spans +-0.6, physiological only in radians
  (+-35 deg), and ``data.expressions`` reads head angles as radians.  Default ``head_units=rad``;
- neutral: the angles are relative to the phone, so a subject not facing the camera squarely has an
  offset C: the captured orientation is M_t = C H_t, H_t the head's turn relative to the body.
  ``recenter=true`` takes the first frame as the rest pose (H_0 = I, so C = M_0) and feeds
  H_t = M_0^T M_t.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from omegaconf import DictConfig

from base.cli import REQUIRED, register_config, to_dataclass
from base.files import save_npy
from data.joint_limits import within_limits
from models.head2neck import head_error_deg, predict_theta
from motion.head2neck.inputs import INPUT_FORMATS, UNITS, read_head_rotations, recentered
from motion.head2neck.loading import load_head2neck


@dataclass
class Head2NeckCli:
    """``python -m motion.head2neck``: head orientations -> theta [T,8,3] (see the module docstring)."""

    input: str = REQUIRED              # .npy [T,3,3] head orientations, .npy [T,3] yaw/pitch/roll, or a capture .csv
    out: str = REQUIRED                # theta .npy [T,8,3], bone frames of ``rig``
    checkpoint: str = "default"        # default (the shipped model) | a head2neck checkpoint from train.py
    input_format: str = "auto"         # auto | matrix | ypr | csv
    head_units: str = "rad"            # yaw/pitch/roll units: rad | deg | halfturn (Unreal's live values, 1 = 180 deg)
    yaw_sign: float = 1.0              # flip HeadYaw/Pitch/Roll (mirrored capture, landscape phone): +1 or -1
    pitch_sign: float = 1.0
    roll_sign: float = 1.0
    recenter: bool = False             # make the first frame the rest pose (orientations relative to it)
    fps: float | None = None        # frame rate of a CSV without a time column
    timecode_fps: float | None = None  # Live Link Face timecode rate, for takes under a second
    rig: str | None = None          # rig file (python -m data.assets) whose bone frames theta is in; null = built-in
    iterations: int = 3                # at most this many Gauss-Newton steps of the exact correction
    threads: int = 1                   # enough for a capture; more threads only pay on an idle machine

    def __post_init__(self) -> None:
        if self.input_format not in INPUT_FORMATS:
            raise ValueError(f"input_format={self.input_format}: expected one of {', '.join(INPUT_FORMATS)}")
        if self.head_units not in UNITS:
            raise ValueError(f"head_units={self.head_units}: expected one of {', '.join(UNITS)}")
        for name in ("yaw_sign", "pitch_sign", "roll_sign"):
            if float(getattr(self, name)) not in (1.0, -1.0):
                raise ValueError(f"{name}={getattr(self, name)}: expected +1 or -1")
        if self.iterations < 0:
            raise ValueError(f"iterations={self.iterations}: expected a non-negative number of steps")


register_config("head2neck_cli_schema", Head2NeckCli)


def run(cfg: DictConfig) -> np.ndarray:
    """The CLI's work: returns theta [T,J,3] and writes it to ``cfg.out``."""
    cfg = to_dataclass(cfg, Head2NeckCli, where="configs/head2neck.yaml")
    model, rig = load_head2neck(cfg.checkpoint, cfg.rig)
    signs = (float(cfg.yaw_sign), float(cfg.pitch_sign), float(cfg.roll_sign))
    head, description = read_head_rotations(cfg.input, cfg.input_format, cfg.head_units, signs, cfg.fps,
                                            cfg.timecode_fps)
    if cfg.recenter:
        head = recentered(head)
    theta = predict_theta(model, rig, head, int(cfg.iterations))
    anatomical = rig.to_anatomical(theta)
    error = head_error_deg(anatomical, head, rig)
    outside = ~within_limits(anatomical)
    save_npy(cfg.out, theta.numpy().astype(np.float32))
    print(f"{cfg.input}: {description} -> {cfg.out} theta {list(theta.shape)}")
    print(f"head orientation residual: max {float(error.max()):.4f} deg, mean {float(error.mean()):.5f} deg")
    if outside.any():
        frames = torch.nonzero(outside.any(-1)).reshape(-1)
        print(f"joints outside the limits: {int(outside.sum())} in {len(frames)} frames (first: frame "
              f"{int(frames[0])})")
    else:
        print("joints outside the limits: none")
    return theta.numpy()
